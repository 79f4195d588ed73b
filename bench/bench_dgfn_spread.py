"""Why DGFN's fused network spreads over seeds more than its single-sensor SSDs (docs/recipes.md#detection_cpu):
its rows trained over several seeds with their inner state traced (``trace.every``, :mod:`ablate.jobs.trace`).

    PYTHONPATH=. python bench/bench_dgfn_spread.py [--seeds 5] [--rows dgfn ssd_rgb ssd_dhi]
        [--store /tmp/ablate-dgfn-spread] [--jobs 2] [--read-only] [--set model.key=value ...]

Trains each row (``dgfn``, ``dgfn_clean`` and ``dgfn_baseline`` of dgfn_table1 / its follow-up, ``ssd_rgb`` and
``ssd_dhi`` of dgfn_table2) for seeds 0..N-1 through ``python -m ablate``, ``--jobs`` at a time, in a scratch folder
and MLflow store (``--store``; never the project's), with the rows' own cpu recipe and ``trace.every=10``; the
robustness severities are left out of the test (``task.eval_severities=[]``): only the normal input is read here.
``--set`` adds overrides to every row (a stabiliser under trial: a recipe is every row's); ``--read-only`` prints from a store.

Prints, per row: each seed's test Car easy / moderate on the normal input with the std over seeds (the target of
docs/recipes.md: the fused row's at most the larger SSD's); validation Car moderate per epoch; the training loss
at a few steps; Adam's second moment per part at the last step (from ``last.ckpt``); and, where traced, each fusion point's mean weight map and its share shut (< 0.05) at a few
steps, and the gradient norm of each part (trunks, fusion, head) over the fit.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from mlflow.tracking import MlflowClient

REPO = Path(__file__).resolve().parents[1]
TABLE = {
    "dgfn": "dgfn_table1",
    "dgfn_baseline": "dgfn_table1",
    "dgfn_clean": "dgfn_table2_followup",
    "ssd_rgb": "dgfn_table2",
    "ssd_dhi": "dgfn_table2",
}
STEPS = (0, 20, 50, 100, 200, 400, 670)
TEST = ("normal/car_easy", "normal/car_moderate")


def launch(store: Path, rows: list[str], seeds: int, jobs: int, extra: list[str]) -> None:
    env = {**os.environ, "MLFLOW_TRACKING_URI": f"sqlite:///{store / 'mlflow.db'}", "PYTHONPATH": str(REPO)}
    if (REPO / "data").is_dir() and not (store / "data").exists():  # the generated frames, not generated again
        (store / "data").symlink_to(REPO / "data", target_is_directory=True)
    common = ["trace.every=10", "task.eval_severities=[]", "comp_time.after_sweep=false"]

    def one(row: str, seed: int) -> int:
        cmd = [f"experiment={TABLE[row]}", f"row={row}", f"seed={seed}", *common]
        cmd += extra
        with open(store / f"{row}-{seed}.log", "w") as log:
            return subprocess.call(
                [sys.executable, "-m", "ablate", *cmd], cwd=store, env=env, stdout=log, stderr=subprocess.STDOUT
            )

    order = [(row, seed) for seed in range(seeds) for row in rows]
    with ThreadPoolExecutor(jobs) as pool:
        codes = list(pool.map(lambda job: one(*job), order))
    if any(codes):
        print(f"failed jobs (logs under {store}):", [job for job, c in zip(order, codes) if c])


def history(client: MlflowClient, run_id: str, key: str) -> dict[int, float]:
    return {m.step: m.value for m in client.get_metric_history(run_id, key)}


def near(values: dict[int, float], step: int) -> float | None:
    """The value logged at the step nearest ``step``."""
    if not values:
        return None
    return values[min(values, key=lambda s: abs(s - step))]


def adam_moments(ckpt: Path) -> dict[str, float]:
    """{part: mean over its parameters of sqrt(mean exp_avg_sq)} from a Lightning checkpoint's Adam state; parts as
    :func:`ablate.jobs.trace.parts` names them (``branches.rgb``, ``fuse``, ``head``)."""
    import torch

    state = torch.load(ckpt, map_location="cpu", weights_only=False)
    names = [n for n in state["state_dict"] if not n.endswith(("running_mean", "running_var", "num_batches_tracked"))]
    parts: dict[str, list[float]] = {}
    for index, moments in state["optimizer_states"][0]["state"].items():
        path = names[index].split(".")[1:]  # without the task's "model."
        part = ".".join(path[:2]) if path[0] == "branches" else path[0]
        parts.setdefault(part, []).append(float(moments["exp_avg_sq"].float().mean().sqrt()))
    return {k: statistics.fmean(v) for k, v in parts.items()}


def fmt(values: list[float | None], digits: int = 2) -> str:
    return " ".join("     —" if v is None else f"{v:6.{digits}f}" for v in values)


def report(store: Path, rows: list[str], by: list[str]) -> None:
    client = MlflowClient(f"sqlite:///{store / 'mlflow.db'}")
    for row in rows:
        exp = client.get_experiment_by_name(TABLE[row])
        runs = (
            []
            if exp is None
            else client.search_runs([exp.experiment_id], f"tags.row = '{row}' and attributes.status = 'FINISHED'")
        )
        runs = sorted(runs, key=lambda r: int(r.data.tags.get("seed", 0)))
        if not runs:
            print(f"\n{row}: no finished run in {store}")
            continue
        groups: dict[str, list] = {}
        for r in runs:  # the variants of a row: the values of the --by params (absent: the row as configured)
            groups.setdefault(" ".join(f"{k}={r.data.params.get(k, '-')}" for k in by), []).append(r)
        for variant, members in groups.items():
            show(client, store, row, variant, members)


def show(client: MlflowClient, store: Path, row: str, variant: str, runs: list) -> None:
    """One row's (one variant's) seeds: test figures, validation curves, loss and trace."""
    tags = runs[0].data.tags
    print(f"\n## {row} {variant} ({TABLE[row]}; {tags.get('cpu')}, {tags.get('precision')}, 1 thread)")
    for key in TEST:
        values = [r.data.metrics.get(key) for r in runs]
        ok = [v for v in values if v is not None]
        sd = statistics.stdev(ok) if len(ok) > 1 else float("nan")
        print(f"  test {key:22s} {fmt(values)}   mean {statistics.fmean(ok):6.2f}  std {sd:5.2f}  (n={len(ok)})")
    print("  val car_moderate per epoch, per seed:")
    for r in runs:
        curve = history(client, r.info.run_id, "val/car_moderate")
        print(f"    seed {r.data.tags.get('seed')}: {fmt([curve[s] for s in sorted(curve)], 1)}")
    print(f"  train loss at steps {STEPS}:")
    for r in runs:
        loss = history(client, r.info.run_id, "train/loss")
        print(f"    seed {r.data.tags.get('seed')}: {fmt([near(loss, s) for s in STEPS])}")
    print("  Adam's sqrt(second moment) at the last step, mean over each part's parameters:")
    for r in runs:
        ckpt = store / "checkpoints" / TABLE[row] / r.data.tags.get("config_hash", "") / "last.ckpt"
        moments = adam_moments(ckpt) if ckpt.is_file() else {}
        print(f"    seed {r.data.tags.get('seed')}: " + "  ".join(f"{k} {v:.3g}" for k, v in moments.items()))
    keys = sorted(k for k in runs[0].data.metrics if k.startswith("trace/"))
    if not keys:
        return
    print(f"  trace at steps {STEPS} (per seed):")
    for key in keys:
        print(f"   {key}")
        for r in runs:
            values = history(client, r.info.run_id, key)
            print(f"    seed {r.data.tags.get('seed')}: {fmt([near(values, s) for s in STEPS])}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--rows", nargs="+", default=["dgfn", "ssd_rgb", "ssd_dhi"], choices=sorted(TABLE))
    parser.add_argument("--store", type=Path, default=Path("/tmp/ablate-dgfn-spread"))
    parser.add_argument("--jobs", type=int, default=2, help="jobs at once (each on 1 thread)")
    parser.add_argument("--read-only", action="store_true")
    parser.add_argument("--set", nargs="*", default=[], help="more overrides for every row")
    parser.add_argument(
        "--by", nargs="*", default=None, help="params that tell a row's variants apart (default: --set's)"
    )
    args = parser.parse_args()
    args.store.mkdir(parents=True, exist_ok=True)
    if not args.read_only:
        launch(args.store, args.rows, args.seeds, args.jobs, args.set)
    by = args.by if args.by is not None else [s.lstrip("+").split("=")[0] for s in args.set]
    report(args.store, args.rows, by)


if __name__ == "__main__":
    main()
