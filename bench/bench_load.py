"""Many writers on one tracking store: N light jobs at once, each logging like a real job through the project's own
:class:`~ablate.store.tracker.Tracker`, :class:`~ablate.store.run_logger.RunLogger` and outbox, against the default
SQLite store and against the PostgreSQL-backed ``mlflow server`` (``scripts/tracking_server.py``).

    python bench/bench_load.py                                  # N = 2, 8, 16, 32 on both stores
    python bench/bench_load.py --writers 16 --stores server --outage 30   # the server killed for 30 s mid-run

A writer is a forked process that opens the store, starts a run (tags, 40 params, a dataset input), logs two
metrics every step for ``--steps`` steps (one call per step, ``--step-s`` of "training" between calls: Lightning's
``log_every_n_steps=1``), then an artifact, delivers its outbox and records its end (:func:`ablate.jobs.record
.record_end`), as a job does. Every writer starts logging at the same moment (a barrier): the worst case of a sweep
whose jobs start together.

What it counts, per N and store: the metric values acknowledged (a log call that returned: the value is in the store
or on disk in the job's outbox) against the values stored (read back, each (key, step) once: ``lost`` is acknowledged
but not stored, ``dup`` a (key, step) stored twice), the runs FINISHED, log calls per second over the whole load,
the p50 and p99 latency of a log call, and the errors by kind. With ``--outage S`` the server (not PostgreSQL) is
killed (SIGKILL) a third of the way into the run and started again S seconds later on the same port.

Name the CPU beside its figures (it is printed first): the store's cost is the client's and the database's CPU, and
on a 2-core machine 32 writers share two cores with the server.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SERVER = REPO / "scripts" / "tracking_server.py"
#: The metrics every step logs.
KEYS = ("train/loss", "train/lr")


@dataclass
class Load:
    """One load: ``writers`` jobs of ``steps`` steps each, ``step_s`` apart, on the store at ``uri``; the outbox
    files and the writers' reports go to ``folder``."""

    uri: str
    folder: Path
    writers: int
    steps: int = 300
    step_s: float = 0.02
    outage_s: float = 120.0
    experiment: str = "load"


@dataclass
class Outcome:
    """What a load left: per writer, the run, the values acknowledged, each call's latency (s) and errors."""

    store: str
    writers: int
    wall_s: float
    acknowledged: int = 0
    stored: int = 0
    lost: int = 0
    duplicated: int = 0
    finished: int = 0
    runs: int = 0
    calls: int = 0
    latencies: list[float] = field(default_factory=list)
    errors: Counter = field(default_factory=Counter)
    down_s: float = 0.0

    def row(self) -> str:
        lat = sorted(self.latencies) or [float("nan")]
        p99 = lat[min(len(lat) - 1, int(0.99 * len(lat)))]
        errors = ", ".join(f"{k} ×{n}" for k, n in self.errors.most_common()) or "none"
        return (
            f"| {self.store} | {self.writers} | {self.acknowledged} | {self.stored} | {self.lost} | {self.duplicated} "
            f"| {self.finished}/{self.writers} | {self.calls / self.wall_s:.0f} | {1000 * statistics.median(lat):.1f} "
            f"| {1000 * p99:.1f} | {errors} |"
        )


HEADER = (
    "| store | N | metrics acknowledged | stored | lost | stored twice | runs FINISHED | log calls/s | p50 ms | p99 ms "
    "| errors |\n|---|--:|--:|--:|--:|--:|--:|--:|--:|--:|---|"
)


def kind_of(err: BaseException) -> str:
    """A short name of what went wrong: the exception's class and the store's own words (a known phrase, else the
    message's first 300 characters)."""
    text = str(err).lower()
    for words in ("database is locked", "database is busy", "does not answer", "unique constraint", "timed out"):
        if words in text:
            return f"{type(err).__name__}: {words}"
    first = " ".join(str(err).split())[:300]
    return f"{type(err).__name__}: {first}" if first else type(err).__name__


def writer(load: Load, index: int, barrier) -> None:
    """One light job (see the module's docstring); its report goes to ``load.folder/writer-<index>.json``."""
    from ablate.jobs.record import record_end
    from ablate.store import Outbox, Tracker
    from ablate.store.run_logger import RunLogger

    report: dict = {"run": None, "acknowledged": 0, "latencies": [], "errors": []}
    out = load.folder / f"writer-{index}.json"
    try:
        tracker = Tracker(load.uri, outage_s=load.outage_s)
        experiment = tracker.experiment_id(load.experiment)
        run = tracker.start(experiment, f"writer {index}", {"kind": "load", "writer": str(index)})
        report["run"] = run
        tracker.log_params(run, {f"model.option_{i:02d}": str(i) for i in range(40)})
        tracker.log_dataset(run, "synth-load", "0" * 16, str(load.folder), {"train": 10, "test": 5})
        outbox = Outbox(load.folder / f"outbox-{index}.jsonl")
        logger = RunLogger(tracker, run, outbox)
        barrier.wait(timeout=600)
        for step in range(load.steps):
            began = time.perf_counter()
            try:
                logger.log_metrics({KEYS[0]: 1.0 / (step + 1), KEYS[1]: 0.01}, step)
            except Exception as err:  # counted by kind: the bench's figure
                report["errors"].append(kind_of(err))
            else:
                report["acknowledged"] += len(KEYS)
            report["latencies"].append(time.perf_counter() - began)
            time.sleep(load.step_s)
        logger.deliver()
        tracker.log_text(run, f"writer {index}: {load.steps} steps\n", "summary.txt")
        record_end(tracker, run, "FINISHED", {"steps": str(load.steps)}, outbox=outbox)
    except Exception as err:  # the writer's end: counted by kind
        report["errors"].append(kind_of(err))
    out.write_text(json.dumps(report))


def count(load: Load, store: str, wall_s: float) -> Outcome:
    """Read back what the writers' runs hold and compare with what they were acknowledged."""
    from ablate.store import Tracker

    outcome = Outcome(store, load.writers, wall_s)
    tracker = Tracker(load.uri, outage_s=load.outage_s)
    for index in range(load.writers):
        path = load.folder / f"writer-{index}.json"
        report = json.loads(path.read_text()) if path.exists() else {"errors": ["no report (process died)"]}
        outcome.acknowledged += int(report.get("acknowledged", 0))
        outcome.calls += len(report.get("latencies", []))
        outcome.latencies += report.get("latencies", [])
        outcome.errors.update(report.get("errors", []))
        if not report.get("run"):
            continue
        outcome.runs += 1
        run = tracker.get_run(report["run"])
        outcome.finished += run.info.status == "FINISHED"
        for key in KEYS:
            steps = [m.step for m in tracker.metric_history(report["run"], key)]
            outcome.stored += len(set(steps))
            outcome.duplicated += len(steps) - len(set(steps))
    outcome.lost = max(outcome.acknowledged - outcome.stored, 0)
    return outcome


def run_load(load: Load, store: str, outage: tuple[Path, float] | None = None) -> Outcome:
    """Fork the writers, wait for them (killing the server for ``outage``'s seconds once a third of the steps are
    due), and count."""
    ctx = mp.get_context("fork")
    barrier = ctx.Barrier(load.writers + 1)
    procs = [ctx.Process(target=writer, args=(load, i, barrier)) for i in range(load.writers)]
    for proc in procs:
        proc.start()
    barrier.wait(timeout=600)
    began = time.monotonic()
    down_s = 0.0
    if outage is not None:
        folder, seconds = outage
        time.sleep(load.steps * load.step_s / 3)
        down_s = kill_and_restart(folder, seconds)
    for proc in procs:
        proc.join()
    outcome = count(load, store, time.monotonic() - began)
    outcome.down_s = down_s
    return outcome


def kill_and_restart(folder: Path, seconds: float) -> float:
    """SIGKILL the ``mlflow server`` started from ``folder`` (PostgreSQL stays up), start it again ``seconds`` later
    on its port; the seconds it did not answer."""
    state = json.loads((folder / "server.json").read_text())
    down = time.monotonic()
    os.killpg(int(state["mlflow_pid"]), signal.SIGKILL)
    time.sleep(seconds)
    start_server(folder, state["port"], state["pg_port"])
    return time.monotonic() - down


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def start_server(folder: Path, port: int, pg_port: int, workers: int = 2) -> str:
    """Start (or start again) the PostgreSQL-backed server in ``folder``; its tracking URI."""
    cmd = [sys.executable, str(SERVER), "start", str(folder), "--port", str(port), "--pg-port", str(pg_port)]
    done = subprocess.run([*cmd, "--workers", str(workers)], capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"{SERVER} start {folder}: {done.stderr.strip()}")
    return json.loads((folder / "server.json").read_text())["tracking_uri"]


def stop_server(folder: Path) -> None:
    subprocess.run([sys.executable, str(SERVER), "stop", str(folder)], capture_output=True, text=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--writers", type=int, nargs="+", default=[2, 8, 16, 32], help="N: jobs at once")
    parser.add_argument("--stores", nargs="+", choices=["sqlite", "server"], default=["sqlite", "server"])
    parser.add_argument("--steps", type=int, default=300, help="steps per job, each a log call of 2 metrics")
    parser.add_argument("--step-s", type=float, default=0.02, help="seconds of 'training' between two log calls")
    parser.add_argument("--outage", type=float, default=0.0, help="server only: seconds it is down mid-run")
    args = parser.parse_args(argv)
    import ablate.store  # noqa: F401  (imported once here: the writers fork with it)
    from ablate.hardware import cores, cpu

    machine = cpu()
    print(f"CPU: {machine.model}; {cores()} cores; bf16 in hardware: {machine.has_bf16}\n\n{HEADER}", flush=True)
    for store in args.stores:
        root = Path(tempfile.mkdtemp(prefix=f"ablate-load-{store}-", dir="/tmp"))
        root.chmod(0o755)  # PostgreSQL runs as the user postgres when we are root: it must reach its folder
        try:
            uri, outage = f"sqlite:///{root / 'mlflow.db'}", None
            if store == "server":
                uri = start_server(root / "server", free_port(), free_port())
                outage = (root / "server", args.outage) if args.outage > 0 else None
            for n in args.writers:
                folder = root / f"n{n}"
                folder.mkdir()
                load = Load(uri, folder, n, args.steps, args.step_s, experiment=f"load-{n}")
                outcome = run_load(load, store, outage)
                suffix = f" (server down {outcome.down_s:.0f} s)" if outage else ""
                print(outcome.row() + suffix, flush=True)
        finally:
            if store == "server":
                stop_server(root / "server")
            shutil.rmtree(root, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
