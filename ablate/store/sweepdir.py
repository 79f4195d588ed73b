"""What a running multirun recorded in its sweep directory: the store its jobs log to, their parent run, the keys
it sweeps over, and the notes of failed jobs.

Jobs find the parent through a file in the sweep directory (``.parent_run``), and the store it lives in through
another (``.tracking.json``), which works for every launcher whose jobs see the sweep directory: the basic one,
joblib, submitit (local or SLURM, on a shared filesystem) and Ray (the sweep directory is absolute, under the launch
directory). A job so writes to its parent's store even where its own environment names no store (a Ray worker does
not inherit the driver's ``MLFLOW_TRACKING_URI``). The sweep callback (:mod:`ablate.sweep.callback`) writes these files;
this module only names and reads them, so the store never imports the orchestration.
"""

from __future__ import annotations

import json
from pathlib import Path

from hydra.core.hydra_config import HydraConfig

PARENT_FILE = ".parent_run"
SWEPT_FILE = ".swept_keys"
STORE_FILE = ".tracking.json"
FAILURES = "failures"


def sweep_dir() -> Path | None:
    """The sweep directory of the running multirun job (a relative one resolved against the launch directory,
    ``hydra.runtime.cwd``), or None for a single run."""
    if not HydraConfig.initialized():
        return None
    hc = HydraConfig.get()
    if hc.mode is None or hc.mode.name != "MULTIRUN":
        return None
    return Path(hc.runtime.cwd) / hc.sweep.dir


def sweep_store() -> dict[str, str | None] | None:
    """The tracking store the running multirun recorded (``uri``, ``artifact_location``), or None."""
    sdir = sweep_dir()
    path = sdir / STORE_FILE if sdir else None
    return json.loads(path.read_text()) if path and path.exists() else None


def parent_run_id() -> str | None:
    """The MLflow parent run of the running multirun job, if any."""
    sdir = sweep_dir()
    path = sdir / PARENT_FILE if sdir else None
    return path.read_text().strip() if path and path.exists() else None


def swept_keys() -> list[str] | None:
    """The config keys the running multirun sweeps over (``fusion`` in ``fusion=sum,max``), or None."""
    sdir = sweep_dir()
    path = sdir / SWEPT_FILE if sdir else None
    return path.read_text().split() if path and path.exists() else None


def record_failure(job: str, message: str) -> None:
    """Leave a note that ``job`` failed, for the end-of-sweep summary."""
    sdir = sweep_dir()
    if sdir is not None:
        (sdir / FAILURES).mkdir(parents=True, exist_ok=True)
        (sdir / FAILURES / f"{job}.txt").write_text(message)
