"""An empty MLflow SQLite store with its schema made, and the tests' generated dataset, copied where a test's
command would otherwise make them.

MLflow creates a new SQLite file's schema on first use (its alembic migrations): about 2 s for every test that
runs ``python -m ablate`` or opens a Tracker in a fresh folder. The copy is the same file a first use makes, made
once per test process. Tests of first use itself (``tests/test_tracking_race.py``, the submitit test) keep a fresh
store.

A job generates its dataset on first use too (``data/synth-<hash>``, :func:`ablate.data.datamodule.ensure_synth`;
about a second at ``data.synth.frames=20``, in two worker processes). The first command of a test process that
generates the smoke dataset of :data:`tests.scaleout.TINY` keeps a copy (:func:`keep_data`); later commands find
it in their folder (:func:`seed_data`), the same files.
"""

from __future__ import annotations

import atexit
import json
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


#: The generator parameters of the dataset of :data:`tests.scaleout.TINY` (scale=smoke, data.synth.frames=20): the
#: one dataset kept and copied.
SMOKE_DATA = {"frames": 20, "seed": 0, "height": 64, "width": 208}
_datasets: dict[str, Path] = {}


@cache
def _data_cache() -> Path:
    folder = Path(tempfile.mkdtemp(prefix="ablate-test-data-"))
    atexit.register(shutil.rmtree, folder, ignore_errors=True)
    return folder


def keep_data(cwd: Path) -> None:
    """Keep a copy of the smoke dataset a command generated in ``cwd/data`` (once per test process)."""
    if _datasets:
        return
    for made in Path(cwd).glob("data/synth-*/synth.json"):  # written last: the dataset is whole
        params = json.loads(made.read_text())
        if {k: params.get(k) for k in SMOKE_DATA} == SMOKE_DATA:
            copy = _data_cache() / made.parent.name
            shutil.copytree(made.parent, copy)
            _datasets[made.parent.name] = copy


def seed_data(cwd: Path) -> None:
    """Put the kept smoke dataset in ``cwd/data`` unless it is there."""
    for name, source in _datasets.items():
        target = Path(cwd) / "data" / name
        if not target.exists():
            shutil.copytree(source, target)
