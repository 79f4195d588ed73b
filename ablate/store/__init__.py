"""The store: where runs are recorded, and what identifies them. It imports nothing of the orchestration
(:mod:`ablate.jobs` and above) or of the tables (:mod:`ablate.tables`).

- :mod:`~ablate.store.tracker`: the MLflow :class:`Tracker`, the only code that calls MLflow;
  :mod:`~ablate.store.run_logger`: the Lightning :class:`RunLogger` of a job;
- :mod:`~ablate.store.uris`: the store's URI and artifact root, and links into the MLflow UI;
- :mod:`~ablate.store.identity`: the config hash, params, the row a job fills, and the code's version;
- :mod:`~ablate.store.context`: where a job or command runs, and the store and parent run its sweep recorded;
- :mod:`~ablate.store.retry`, :mod:`~ablate.store.outage`, :mod:`~ablate.store.errors`, :mod:`~ablate.store.locks`
  and :mod:`~ablate.store.outbox`: waiting for a store that is locked or does not answer, what the store fails as,
  locks across processes, and the outbox that keeps a job's metrics while the server does not answer.
"""

from typing import TYPE_CHECKING

from ablate.store.context import SweepContext
from ablate.store.errors import AccessDenied, DiskFull
from ablate.store.identity import (
    UNHASHED,
    code_version,
    config_hash,
    flatten,
    git_commit,
    provenance_tags,
    resolve_path,
    row_name,
    split_tuned_key,
    tuned_key,
)
from ablate.store.locks import file_lock
from ablate.store.outage import DEFAULT_OUTAGE_S, ServerUnreachable
from ablate.store.outbox import Outbox
from ablate.store.tracker import (
    FRAME_COUNTS,
    FRAME_DETECTIONS,
    KIND_EXPERT,
    KIND_JOB,
    KIND_SWEEP,
    KIND_TRIAL,
    SKIPPED_FRAMES,
    VAL_CURVE,
    Tracker,
)
from ablate.store.uris import is_server, runs_link, tracking_uri

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
    "KIND_EXPERT",
    "KIND_JOB",
    "KIND_TRIAL",
    "VAL_CURVE",
    "KIND_SWEEP",
    "SKIPPED_FRAMES",
    "FRAME_COUNTS",
    "FRAME_DETECTIONS",
    "AccessDenied",
    "DiskFull",
    "UNHASHED",
    "Outbox",
    "RunLogger",
    "ServerUnreachable",
    "SweepContext",
    "Tracker",
    "code_version",
    "config_hash",
    "file_lock",
    "flatten",
    "git_commit",
    "is_server",
    "provenance_tags",
    "resolve_path",
    "row_name",
    "runs_link",
    "split_tuned_key",
    "tracking_uri",
    "tuned_key",
]
