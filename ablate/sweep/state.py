"""A sweep's one state file, ``<sweep dir>/sweep.json`` (:data:`ablate.store.context.STATE_FILE`).

The racing sweeper writes what its jobs need before it launches them (``store``: the store's URI and artifact
location; ``parent_run``: the sweep's MLflow run; ``swept``: the keys that name the rows, which
:class:`ablate.store.SweepContext` reads back in every job, whichever launcher runs it) and what its progress lines
count (``progress``: the jobs it plans, and the estimates of its plan, :mod:`ablate.sweep.progress`); each job adds
its end to ``ended`` as it finishes, in whichever process runs it. The file is always whole: every change is made
under a lock across processes (``sweep.lock`` beside it, which holds nothing) and written beside the file, then
renamed over it, so that a job starting while another ends reads the one or the other. A sweep killed and run again
starts a sweep folder of its own; its jobs find the runs of the first in the store, not here.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

from ablate.store import file_lock
from ablate.store.context import STATE_FILE

T = TypeVar("T")

#: The lock every change of the state file is made under (it holds nothing).
LOCK_FILE = "sweep.lock"


def read(sweep_dir: Path) -> dict[str, Any]:
    """The sweep's state (empty before the sweeper wrote it)."""
    path = sweep_dir / STATE_FILE
    return json.loads(path.read_text()) if path.exists() else {}


def change(sweep_dir: Path, edit: Callable[[dict[str, Any]], T]) -> T:
    """Apply ``edit`` to the sweep's state in place, under the lock, and write the state whole; ``edit``'s answer."""
    with file_lock(sweep_dir / LOCK_FILE):
        state = read(sweep_dir)
        answer = edit(state)
        temporary = sweep_dir / f".{STATE_FILE}.{os.getpid()}"
        temporary.write_text(json.dumps(state, indent=1))
        os.replace(temporary, sweep_dir / STATE_FILE)
    return answer


def record(sweep_dir: Path, **values: Any) -> None:
    """Set ``values`` in the sweep's state (``store``, ``parent_run``, ``swept``, ...)."""
    change(sweep_dir, lambda state: state.update(values))
