"""The store: where runs are recorded, and what identifies them. It imports nothing of the orchestration
(:mod:`ablate.jobs` and above) or of the tables (:mod:`ablate.tables`).

- :mod:`~ablate.store.tracker`: the MLflow :class:`Tracker`, the store's URI and artifact root, :func:`retry` and
  :func:`file_lock`; :mod:`~ablate.store.run_logger`: the Lightning :class:`RunLogger` of a job;
- :mod:`~ablate.store.identity`: the config hash, params, the launch directory and the code's version;
- :mod:`~ablate.store.sweepdir`: the store and parent run a running multirun recorded in its sweep directory;
- :mod:`~ablate.store.outage` and :mod:`~ablate.store.outbox`: a tracking server that does not answer (how long a
  job waits for it, :class:`ServerUnreachable`), and the outbox that keeps a job's metrics meanwhile.
"""

from typing import TYPE_CHECKING

from ablate.store.identity import (
    UNHASHED,
    code_version,
    config_hash,
    flatten,
    git_commit,
    launch_dir,
    provenance_tags,
    resolve_path,
)
from ablate.store.outage import DEFAULT_OUTAGE_S, ServerUnreachable
from ablate.store.outbox import Outbox
from ablate.store.sweepdir import parent_run_id, record_failure, sweep_dir, sweep_store, swept_keys
from ablate.store.tracker import (
    KIND_JOB,
    KIND_SWEEP,
    SKIPPED_FRAMES,
    AccessDenied,
    DiskFull,
    Tracker,
    file_lock,
    is_server,
    retry,
    runs_link,
    tracking_uri,
)

if TYPE_CHECKING:
    from ablate.store.run_logger import RunLogger


def __getattr__(name: str) -> object:
    """:class:`RunLogger` on first use: it subclasses Lightning's logger, and importing Lightning takes seconds that
    a process reading or writing the store without training (a report, a sweep's launcher) need not spend."""
    if name == "RunLogger":
        from ablate.store.run_logger import RunLogger

        return RunLogger
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "DEFAULT_OUTAGE_S",
    "KIND_JOB",
    "KIND_SWEEP",
    "SKIPPED_FRAMES",
    "AccessDenied",
    "DiskFull",
    "UNHASHED",
    "Outbox",
    "RunLogger",
    "ServerUnreachable",
    "Tracker",
    "code_version",
    "config_hash",
    "file_lock",
    "flatten",
    "git_commit",
    "is_server",
    "launch_dir",
    "parent_run_id",
    "provenance_tags",
    "record_failure",
    "resolve_path",
    "retry",
    "runs_link",
    "sweep_dir",
    "sweep_store",
    "swept_keys",
    "tracking_uri",
]
