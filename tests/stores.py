"""An empty MLflow SQLite store with its schema made, copied where a test's command would otherwise make one.

MLflow creates a new SQLite file's schema on first use (its alembic migrations): about 2 s for every test that
runs ``python -m ablate`` or opens a Tracker in a fresh folder. The copy is the same file a first use makes, made
once per test process. Tests of first use itself (``tests/test_tracking_race.py``, the submitit test) keep a fresh
store.
"""

from __future__ import annotations

import atexit
import shutil
import tempfile
from functools import cache
from pathlib import Path


@cache
def template() -> Path:
    """The empty store this test process copies (removed at its exit)."""
    from mlflow.tracking import MlflowClient

    folder = Path(tempfile.mkdtemp(prefix="ablate-test-store-"))
    atexit.register(shutil.rmtree, folder, ignore_errors=True)
    MlflowClient(f"sqlite:///{folder / 'mlflow.db'}").search_experiments()
    return folder / "mlflow.db"


def seed_store(cwd: Path) -> None:
    """Put the empty store at ``cwd/mlflow.db`` (the default tracking URI's file) unless one is there."""
    target = Path(cwd) / "mlflow.db"
    if not target.exists():
        shutil.copyfile(template(), target)


def sqlite_uri(folder: Path) -> str:
    """The URI of ``folder/mlflow.db``, the empty store put there first (``folder`` made if need be)."""
    Path(folder).mkdir(parents=True, exist_ok=True)
    seed_store(folder)
    return f"sqlite:///{Path(folder) / 'mlflow.db'}"
