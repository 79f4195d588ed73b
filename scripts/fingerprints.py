"""The fingerprint of every row of every table, and of the experts its fused rows start from: a refactor's check
that no number moved.

    python scripts/fingerprints.py OUT.json [--scale cpu]       # write {table/row: fingerprint}
    python scripts/fingerprints.py NEW.json --compare OLD.json   # write, then name every entry that differs

A row's fingerprint (:mod:`ablate.jobs.fingerprint`) is what its job config computes on a tiny fixed input; the
experts' (``<table>/<row>/expert <modality>``) are those of the stage-1 configs a fused row's experts train with.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from ablate import hardware
from ablate.capacity.rows import needed_experts
from ablate.config import CONF, compose
from ablate.jobs import fingerprint
from ablate.jobs.experts import expert_config
from ablate.store import config_hash
from ablate.store.fingerprint import decode, differs


def configs(scale: str):
    """(name, job config) of every row of every table at ``scale``, and of each expert a fused row needs."""
    for table in sorted(p.stem for p in (CONF / "experiment").glob("*.yaml")):
        rows = compose([f"experiment={table}", f"scale={scale}"]).table.rows
        for row in [str(r["row"]) for r in rows if not r.get("paper_only")]:
            cfg = compose([f"experiment={table}", f"row={row}", f"scale={scale}"])
            hardware.resolve(cfg)
            yield f"{table}/{row}", cfg
            for modality in needed_experts(cfg):
                yield f"{table}/{row}/expert {modality}", expert_config(cfg, modality)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out", type=Path)
    parser.add_argument("--scale", default="cpu")
    parser.add_argument("--compare", type=Path)
    args = parser.parse_args(argv)
    out = {}
    for name, cfg in configs(args.scale):
        start = time.perf_counter()
        out[name] = {"fingerprint": fingerprint.encode(fingerprint.compute(cfg)), "config_hash": config_hash(cfg)}
        print(f"{name}: {time.perf_counter() - start:.1f} s", file=sys.stderr, flush=True)
    args.out.write_text(json.dumps(out, indent=1, sort_keys=True) + "\n")
    if args.compare is None:
        return 0
    old = json.loads(args.compare.read_text())
    moved = [
        f"{name}: {differs(decode(old[name]['fingerprint']), decode(new['fingerprint'])) or 'same'}"
        for name, new in out.items()
        if name not in old or differs(decode(old[name]["fingerprint"]), decode(new["fingerprint"]))
    ]
    moved += [f"{name}: gone" for name in old if name not in out]
    print("\n".join(moved) or f"all {len(out)} fingerprints unchanged")
    return 1 if moved else 0


if __name__ == "__main__":
    raise SystemExit(main())
