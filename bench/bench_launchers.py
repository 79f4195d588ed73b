"""Launchers on this machine: a table sweep with 1 vs 2 parallel workers, and each launcher's start-up cost per job.

    PYTHONPATH=. python bench/bench_launchers.py [--seeds 2] [--frames 30] [--launchers basic,joblib,submitit_local,ray]

1. Wall time of ``python -m ablate -m experiment=chinet_table2 scale=smoke seed=0..S-1`` (3 rows x S seeds) with
   ``hydra/launcher=joblib hydra.launcher.n_jobs=1`` and then ``=2``, each on a fresh SQLite store, both reading one
   dataset generated beforehand; and their ratio.
2. Start-up cost of each launcher: the same sweep again in the first store, where every job is FINISHED and so
   skipped, with 1 job and with all 3 x S jobs, one job at a time (joblib n_jobs=1, submitit max_batch_size=1, a
   local Ray of 1 CPU). A sweep of N such jobs takes a + b N: b is what a job costs the launcher (a process to start,
   the task to ship, ablate to import, the skip check), a the one-off (the driver, the launcher's own start, the
   table). b = (T(N) - T(1)) / (N - 1).

Prints seconds, and the load average: the machine is shared, and anything else running stretches every figure.
"""

from __future__ import annotations

import argparse
import os
import secrets
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
TOKEN = secrets.token_hex(16)
ONE_AT_A_TIME = {
    "basic": [],
    "joblib": ["hydra/launcher=joblib", "hydra.launcher.n_jobs=1"],
    "submitit_local": ["hydra/launcher=submitit_local", "hydra.sweeper.max_batch_size=1"],
    "ray": ["hydra/launcher=ray", "+hydra.launcher.ray.init.num_cpus=1"],
}


def sweep(cwd: Path, *args: str) -> float:
    """Seconds one ``python -m ablate -m ARGS`` takes in ``cwd``; it must succeed."""
    # a token of its own for the local Ray, which otherwise writes one to ~/.ray/auth_token (Ray >= 2.59)
    env = {**os.environ, "PYTHONPATH": str(REPO), "RAY_USAGE_STATS_ENABLED": "0", "RAY_AUTH_TOKEN": TOKEN}
    env.pop("MLFLOW_TRACKING_URI", None)
    start = time.perf_counter()
    out = subprocess.run(
        [sys.executable, "-m", "ablate", "-m", *args], cwd=cwd, env=env, capture_output=True, text=True
    )
    seconds = time.perf_counter() - start
    if out.returncode != 0:
        raise SystemExit(f"failed: {' '.join(args)}\n{out.stdout[-3000:]}\n{out.stderr[-3000:]}")
    return seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--launchers", default=",".join(ONE_AT_A_TIME))
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-launchers-") as tmp:
        tmp = Path(tmp)
        seeds = ",".join(str(s) for s in range(args.seeds))
        table = [
            "experiment=chinet_table2",
            "scale=smoke",
            f"seed={seeds}",
            f"data.synth.frames={args.frames}",
            f"data.data_dir={tmp / 'data'}",
            "trainer.enable_progress_bar=false",
            "comp_time.repeats=2",
        ]
        n_jobs = 3 * args.seeds
        print(
            f"chinet_table2 at scale=smoke, {n_jobs} jobs; {os.cpu_count()} cores; load average at start "
            f"{os.getloadavg()[0]:.1f}"
        )
        sweep(tmp, *table[:2], "row=unet", "seed=0", *table[3:])  # generates the dataset once, for every sweep
        walls = {}
        for workers in (1, 2):
            (tmp / f"w{workers}").mkdir()
            walls[workers] = sweep(
                tmp / f"w{workers}", *table, "hydra/launcher=joblib", f"hydra.launcher.n_jobs={workers}"
            )
            print(f"  {workers} worker(s): {walls[workers]:7.1f} s")
        print(f"  1 / 2 workers: {walls[1] / walls[2]:.2f}x   (load average now {os.getloadavg()[0]:.1f})")
        print(f"\nstart-up per job (all {n_jobs} jobs FINISHED, so skipped; one at a time):")
        print(f"  {'launcher':16s} {'T(1) s':>8s} {f'T({n_jobs}) s':>8s} {'per job s':>10s} {'one-off s':>10s}")
        for name in args.launchers.split(","):
            one = sweep(tmp / "w1", *table[:2], "row=unet", "seed=0", *table[3:], *ONE_AT_A_TIME[name])
            every = sweep(tmp / "w1", *table, *ONE_AT_A_TIME[name])
            per_job = (every - one) / (n_jobs - 1)
            print(f"  {name:16s} {one:8.1f} {every:8.1f} {per_job:10.2f} {one - per_job:10.1f}")
        print(f"load average at the end {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
