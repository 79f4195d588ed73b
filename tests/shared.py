"""Results that several test files need, made once a test session (across pytest-xdist's worker processes) and
copied for each: :func:`smoke_table2`, ChiNet Table II swept at scale=smoke (tests/test_cli.py,
tests/test_mlflow_ui.py).

The first worker to ask makes it in a folder the workers share (under a file lock; the others wait for it). Each
test file gets a copy of that launch directory of its own (:func:`relocated_copy`), its store's and files' paths
moved with it, so that what a test adds to its copy is seen by no other.
"""

from __future__ import annotations

import fcntl
import json
import os
import shutil
import sqlite3
import subprocess
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from tests.scaleout import FIGURES, SERIAL, TINY, ablate

#: Files of a launch directory that may name its absolute path (configs, sweep records, tables, logs).
TEXT = {".yaml", ".json", ".md", ".txt", ".log", ".csv"}


def session_folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder of this test session that every pytest-xdist worker of it sees (the workers' base folders'
    parent), or this process's base folder without xdist."""
    base = tmp_path_factory.getbasetemp()
    return base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base


@contextmanager
def locked(path: Path) -> Iterator[None]:
    """Hold an exclusive lock on the file ``path`` (made if need be)."""
    with open(path, "a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def shared_run(
    tmp_path_factory: pytest.TempPathFactory, name: str, *args: str
) -> tuple[Path, subprocess.CompletedProcess]:
    """The launch directory where ``python -m ablate ARGS`` ran (:func:`tests.scaleout.ablate`) once this session,
    and what it returned. The command runs on the first call of the session; every call waits for it."""
    root = session_folder(tmp_path_factory) / f"shared-{name}"
    root.mkdir(exist_ok=True)
    cwd, done = root / "cwd", root / "done.json"
    with locked(root / "lock"):
        if not done.exists():
            cwd.mkdir(exist_ok=True)
            out = ablate(cwd, *args)
            done.write_text(json.dumps({"args": out.args, "returncode": out.returncode, "stdout": out.stdout,
                                        "stderr": out.stderr}))  # fmt: skip
    made = json.loads(done.read_text())
    return cwd, subprocess.CompletedProcess(made["args"], made["returncode"], made["stdout"], made["stderr"])


def relocated_copy(source: Path, target: Path) -> Path:
    """A copy at ``target`` of the launch directory ``source``, with ``source``'s absolute path replaced by
    ``target``'s wherever it is written down: the store's experiments' and runs' artifact locations and tags
    (every text column of ``mlflow.db``) and the text files (Hydra's configs, the sweep's records)."""
    old, new = str(source), str(target)
    shutil.copytree(source, target, dirs_exist_ok=True)
    for path in target.rglob("*"):
        if path.suffix in TEXT and path.is_file():
            text = path.read_text(errors="surrogateescape")
            if old in text:
                path.write_text(text.replace(old, new), errors="surrogateescape")
    if (target / "mlflow.db").exists():
        with sqlite3.connect(target / "mlflow.db") as db:
            for (table,) in db.execute("SELECT name FROM sqlite_master WHERE type = 'table'").fetchall():
                for column in [c[1] for c in db.execute(f'PRAGMA table_info("{table}")') if "CHAR" in c[2].upper()
                               or "TEXT" in c[2].upper()]:  # fmt: skip
                    db.execute(
                        f'UPDATE "{table}" SET "{column}" = replace("{column}", ?, ?) WHERE "{column}" LIKE ?',
                        (old, new, f"%{old}%"),
                    )
        db.close()
    return target


def smoke_table2(tmp_path_factory: pytest.TempPathFactory, name: str) -> tuple[Path, subprocess.CompletedProcess]:
    """A copy of its own (folder ``name``) of ChiNet Table II swept at scale=smoke, one job after the other
    (``python -m ablate -m experiment=chinet_table2``), and what the sweep returned, its paths those of the copy."""
    shared, out = shared_run(
        tmp_path_factory, "chinet_table2", "-m", "experiment=chinet_table2", SERIAL, *TINY, FIGURES
    )
    cwd = relocated_copy(shared, tmp_path_factory.mktemp(name))
    moved = [text.replace(str(shared), str(cwd)) for text in (out.stdout, out.stderr)]
    return cwd, subprocess.CompletedProcess(out.args, out.returncode, *moved)
