"""Helpers of the scale-out tests: run ``python -m ablate`` as a user does, read a store, find a free port."""

from __future__ import annotations

import importlib.util
import os
import socket
import subprocess
from pathlib import Path

import pytest
from mlflow.tracking import MlflowClient

from tests import forkserver
from tests.stores import keep_data, seed_data, seed_store

REPO = Path(__file__).resolve().parents[1]
# publish=true: these sweeps' tables are read under results/, as a publishing sweep writes them (a sweep that does not
# publish leaves results/ alone: tests/test_publish.py)
TINY = [
    "scale=smoke",
    "data.synth.frames=20",
    "trainer.enable_progress_bar=false",
    "comp_time.repeats=2",
    "publish=true",
    "logger.log_figures=false",  # 1-4 s a job; the tests about figures turn them on (FIGURES)
]
#: What a test about a job's figures adds after TINY.
FIGURES = "logger.log_figures=true"
# a sweep whose parallelism is not what a test is about runs its jobs in its own process: a parallel sweep's two
# worker processes would import torch and Lightning again (seconds each) for tiny jobs
SERIAL = "hydra/launcher=basic"


def ablate(
    cwd: Path,
    *args: str,
    module: str = "ablate",
    env: dict[str, str] | None = None,
    timeout: int = 600,
    fresh_store: bool = False,
) -> subprocess.CompletedProcess:
    """``python -m MODULE ARGS`` in ``cwd``, with ``env`` added to this environment (and no tracking URI unless
    ``env`` names one), forked from a warm interpreter (:mod:`tests.forkserver`). Without a tracking URI in ``env``
    the store is ``cwd/mlflow.db``, an empty one copied there (:func:`tests.stores.seed_store`) unless
    ``fresh_store``; the smoke dataset is copied into ``cwd/data`` once a command has made it
    (:func:`tests.stores.seed_data`)."""
    if not fresh_store and "MLFLOW_TRACKING_URI" not in (env or {}):
        seed_store(cwd)
    seed_data(cwd)
    full = {**os.environ, "PYTHONPATH": str(REPO), "HYDRA_FULL_ERROR": "0"}
    for key in ("MLFLOW_TRACKING_URI", "RAY_AUTH_MODE", "RAY_ADDRESS"):
        full.pop(key, None)
    full.update(env or {})
    done = forkserver.run(Path(cwd), module, list(args), full, timeout)
    keep_data(cwd)
    return done


def output(out: subprocess.CompletedProcess) -> str:
    """The tail of a command's stdout and stderr, for an assertion message."""
    return out.stdout[-4000:] + "\n---\n" + out.stderr[-4000:]


def runs(uri: str, experiment: str, kind: str = "job") -> tuple[MlflowClient, list]:
    """The client of ``uri`` and the runs of ``experiment`` tagged ``kind``."""
    client = MlflowClient(uri)
    exp = client.get_experiment_by_name(experiment)
    return client, client.search_runs([exp.experiment_id], f"tags.kind = '{kind}'") if exp else []


def most_at_once(runs_: list) -> int:
    """How many of the runs were running at the same moment, at most (from their start and end times)."""
    events = sorted([(r.info.start_time, 1) for r in runs_] + [(r.info.end_time, -1) for r in runs_])
    best = now = 0
    for _, step in events:
        now += step
        best = max(best, now)
    return best


def free_port() -> int:
    """A TCP port free on 127.0.0.1 now."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def need(*modules: str) -> None:
    """Skip the test, naming them, when ``modules`` are not installed (``pip install -e .[slurm,ray,server,browser]``)."""
    missing = [m for m in modules if importlib.util.find_spec(m) is None]
    if missing:
        pytest.skip(f"not installed: {', '.join(missing)} (pip install -e .[slurm,ray,server,browser])")
