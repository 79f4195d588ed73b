"""How many epochs the cpu-scale detection recipe should train: the learning curves of the single-sensor SSDs and of
DGFN's baseline without GFU, before any GFU row is trained (docs/recipes.md#detection_cpu records the decision).

    PYTHONPATH=. python bench/bench_detection_schedule.py [--epochs 8] [--seed 0] [--store /tmp/schedule]
        [--read-only] [--set trainer.precision=auto ...]

Trains ``ssd_rgb`` and ``ssd_dhi`` (dgfn_table2's rows: clean training data) one after the other beside
``dgfn_baseline`` (dgfn_table1's: the corruption training, weight maps fixed to one), each for ``--epochs`` epochs
under one poly schedule, in a scratch folder and MLflow store (``--store``; never the project's, so no table under
``results/`` is touched), through ``python -m ablate``
with the rows' own cpu recipe but the epochs. Their test pass is cut to 20 frames: only validation is read here.
Then prints, per row and epoch, Car moderate (KITTI 11-point, %) on the 100 validation frames, the logged step, and
the minutes of training per epoch, from the runs' metric histories. ``--read-only`` prints from an existing store.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

from mlflow.tracking import MlflowClient

REPO = Path(__file__).resolve().parents[1]
ROWS = {"dgfn_baseline": "dgfn_table1", "ssd_rgb": "dgfn_table2", "ssd_dhi": "dgfn_table2"}
KEY = "val/car_moderate"


def launch(store: Path, epochs: int, seed: int, extra: list[str]) -> None:
    """dgfn_baseline on one core, the two SSDs one after the other on the other."""
    env = {**os.environ, "MLFLOW_TRACKING_URI": f"sqlite:///{store / 'mlflow.db'}", "PYTHONPATH": str(REPO)}
    if (REPO / "data").is_dir() and not (store / "data").exists():  # the generated frames, not generated again
        (store / "data").symlink_to(REPO / "data", target_is_directory=True)
    common = [f"trainer.max_epochs={epochs}", f"seed={seed}", "data.limit_frames.test=20", "table.seeds=null"]
    common += ["hydra/sweeper=basic", "hydra/launcher=basic"]
    common += ["comp_time.after_sweep=false", *extra]
    cmds = [
        ["-m", "experiment=dgfn_table1", "row=dgfn_baseline"],
        ["-m", "experiment=dgfn_table2", "row=ssd_rgb,ssd_dhi"],
    ]
    procs = []
    for cmd in cmds:
        log = open(store / f"{cmd[2].split('=')[1]}.log", "w")
        procs.append(
            subprocess.Popen(
                [sys.executable, "-m", "ablate", *cmd, *common],
                cwd=store,
                env=env,
                stdout=log,
                stderr=subprocess.STDOUT,
            )
        )
    codes = [p.wait() for p in procs]
    if any(codes):
        raise SystemExit(f"a training failed (exit {codes}); logs under {store}")


def curves(store: Path) -> None:
    client = MlflowClient(f"sqlite:///{store / 'mlflow.db'}")
    for row, table in ROWS.items():
        exp = client.get_experiment_by_name(table)
        runs = (
            []
            if exp is None
            else client.search_runs([exp.experiment_id], f"tags.row = '{row}' and attributes.status = 'FINISHED'")
        )
        if not runs:
            print(f"{row}: no finished run in {store}")
            continue
        run = runs[0]
        history = sorted(client.get_metric_history(run.info.run_id, KEY), key=lambda m: m.step)
        print(
            f"\n{row} (seed {run.data.tags.get('seed')}, {run.data.tags.get('precision')}, "
            f"{run.data.tags.get('cpu')}, {run.data.tags.get('threads')} thread(s))"
        )
        print("  epoch     step  Car moderate  min/epoch")
        last = run.info.start_time
        for epoch, m in enumerate(history, 1):
            print(f"  {epoch:>5}  {m.step:>7}  {m.value:>12.2f}  {(m.timestamp - last) / 60000:>9.1f}")
            last = m.timestamp
        total = ((run.info.end_time or last) - run.info.start_time) / 60000
        print(f"  whole job {total:.1f} min (test on 20 frames included)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--epochs", type=int, default=8)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--store", type=Path, default=Path("/tmp/ablate-detection-schedule"))
    parser.add_argument("--read-only", action="store_true")
    parser.add_argument("--set", nargs="*", default=[], help="more overrides for every job")
    args = parser.parse_args()
    args.store.mkdir(parents=True, exist_ok=True)
    if not args.read_only:
        launch(args.store, args.epochs, args.seed, args.set)
    curves(args.store)


if __name__ == "__main__":
    main()
