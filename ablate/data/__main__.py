"""Command line: ``python -m ablate.data synth --out DIR --frames N --seed S`` and
``python -m ablate.data prepare --root KITTI_DIR``."""
from __future__ import annotations

import argparse
import os

from ablate.data import DEFAULT_SYNTH


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m ablate.data")
    sub = parser.add_subparsers(dest="command", required=True)
    syn = sub.add_parser("synth", help="generate a KITTI-format dataset")
    syn.add_argument("--out", required=True)
    syn.add_argument("--frames", type=int, default=DEFAULT_SYNTH["frames"])
    syn.add_argument("--seed", type=int, default=DEFAULT_SYNTH["seed"])
    syn.add_argument("--height", type=int, default=DEFAULT_SYNTH["height"])
    syn.add_argument("--width", type=int, default=DEFAULT_SYNTH["width"])
    syn.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1))
    prep = sub.add_parser("prepare", help="precompute the cache of derived LiDAR modalities")
    prep.add_argument("--root", required=True)
    prep.add_argument("--data-dir", default="data")
    prep.add_argument("--modalities", default="sparse_depth,dense_depth,dhi,bev")
    prep.add_argument("--max-depth", type=float, default=80.0)
    args = parser.parse_args(argv)
    if args.command == "synth":
        from ablate.data.generate import generate

        generate(args.out, args.frames, args.seed, args.height, args.width, workers=args.workers)
    else:
        from ablate.data.datamodule import prepare

        prepare(args.root, args.data_dir, args.modalities.split(","), args.max_depth)


if __name__ == "__main__":
    main()
