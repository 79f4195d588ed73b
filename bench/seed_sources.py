"""What a seed randomises, measured: ChiNet Table II's U-Net row trained at seeds 0 .. n-1 twice, once with the
training frames' order fixed (``data.order_seed=0``, as every job trained before ``order_seed`` existed) and once
with it following the seed (the default, ``data.order_seed: ${seed}``); each seed's detection rate and the spread
over the seeds of each, on a reduced cpu scale (``--frames`` generated frames, ``--epochs`` epochs).

Usage: ``python bench/seed_sources.py [--seeds 5] [--frames 300] [--epochs 2]`` (about a minute a job on a 2-core
AMD EPYC; the jobs run one at a time, each on one thread). Prints the CPU, then one line per seed and the spreads.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def sweep(folder: Path, seeds: int, frames: int, epochs: int, fixed: bool) -> dict[int, float]:
    """Run the row's seeds in ``folder`` and return each seed's test detection rate."""
    overrides = [
        "experiment=chinet_table2",
        "row=unet",
        f"seed={','.join(map(str, range(seeds)))}",
        f"data.synth.frames={frames}",
        f"trainer.max_epochs={epochs}",
        "trainer.threads=1",
        "hydra/launcher=basic",
        "comp_time.after_sweep=false",
        "plan.measure_s=0",
        *(["data.order_seed=0"] if fixed else []),
    ]
    env = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}
    out = subprocess.run(
        [sys.executable, "-m", "ablate", "-m", *overrides], cwd=folder, env=env, capture_output=True, text=True
    )
    if out.returncode != 0:
        raise SystemExit(f"the sweep failed:\n{out.stderr[-3000:]}")
    from ablate.store import Tracker
    from ablate.tables.collect import collect

    runs = collect(Tracker(f"sqlite:///{folder / 'mlflow.db'}", str(folder / "mlartifacts")), "chinet_table2")
    return {int(s): float(v) for s, v in zip(runs["seed"], runs["det_rate"])}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--epochs", type=int, default=2)
    args = parser.parse_args()
    from ablate import hardware

    machine = hardware.cpu()
    print(f"CPU: {machine.model} ({machine.isa}); {args.seeds} seeds, {args.frames} frames, {args.epochs} epochs")
    results = {}
    for fixed in (True, False):
        with tempfile.TemporaryDirectory() as folder:
            results[fixed] = sweep(Path(folder), args.seeds, args.frames, args.epochs, fixed)
    print("seed  order fixed  order follows the seed")
    for seed in range(args.seeds):
        print(
            f"{seed:4d}  {results[True].get(seed, float('nan')):11.2f}  {results[False].get(seed, float('nan')):22.2f}"
        )
    for fixed, name in ((True, "order fixed"), (False, "order follows the seed")):
        values = list(results[fixed].values())
        print(f"{name}: mean {statistics.mean(values):.2f}, std over seeds {statistics.stdev(values):.2f}")


if __name__ == "__main__":
    main()
