"""Command line: ``python -m ablate.data synth --out DIR --frames N --seed S``,
``python -m ablate.data prepare --root KITTI_DIR`` and
``python -m ablate.data masks --root KITTI_DIR --frame ID --out PNG`` (figure of ablate.data.masks.from_lidar);
``python -m ablate.data stats --root DIR --out results/NAME [--frames N]`` (ablate.data.stats)."""

from __future__ import annotations

import argparse

from ablate.config import RESULTS
from ablate.data import DEFAULT_SYNTH
from ablate.hardware import cores


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m ablate.data")
    sub = parser.add_subparsers(dest="command", required=True)
    syn = sub.add_parser("synth", help="generate a KITTI-format dataset")
    syn.add_argument("--out", required=True)
    syn.add_argument("--frames", type=int, default=DEFAULT_SYNTH["frames"])
    syn.add_argument("--seed", type=int, default=DEFAULT_SYNTH["seed"])
    syn.add_argument("--height", type=int, default=DEFAULT_SYNTH["height"])
    syn.add_argument("--width", type=int, default=DEFAULT_SYNTH["width"])
    syn.add_argument("--workers", type=int, default=cores(), help="processes (default: the cores it may use)")
    syn.add_argument("--furniture", action="store_true", help="street furniture in every scene")
    prep = sub.add_parser("prepare", help="precompute the cache of derived LiDAR modalities")
    prep.add_argument("--root", required=True)
    prep.add_argument("--data-dir", default="data")
    prep.add_argument("--modalities", default="sparse_depth,dense_depth,dhi,bev")
    prep.add_argument("--max-depth", type=float, default=80.0)
    fig = sub.add_parser("masks", help="figure of one frame's instance masks from LiDAR + 3D boxes")
    fig.add_argument("--root", required=True)
    fig.add_argument("--frame", required=True)
    fig.add_argument("--out", default=str(RESULTS / "kitti_masks_from_lidar.png"))
    stats = sub.add_parser("stats", help="camera/LiDAR complementarity report of a dataset (no model)")
    stats.add_argument("--root", required=True)
    stats.add_argument("--out", default=str(RESULTS / "complementarity"), help="writes OUT.md and OUT.png")
    stats.add_argument("--frames", type=int, default=None, help="the first N frames only")
    args = parser.parse_args(argv)
    if args.command == "synth":
        from ablate.data.generate import generate

        generate(
            args.out, args.frames, args.seed, args.height, args.width, workers=args.workers, furniture=args.furniture
        )
    elif args.command == "masks":
        from ablate.data.datamodule import resolve_split_dir
        from ablate.data.masks import figure

        figure(resolve_split_dir(args.root), args.frame, args.out)
    elif args.command == "stats":
        from ablate.data import DataError
        from ablate.data.stats import report

        try:
            print(*report(args.root, args.out, args.frames), sep="\n")
        except DataError as err:
            raise SystemExit(f"error: {err}") from None
    else:
        from ablate.data.datamodule import prepare

        prepare(args.root, args.data_dir, args.modalities.split(","), args.max_depth)


if __name__ == "__main__":
    main()
