"""Many jobs of one machine writing one SQLite store (``sqlite:///mlflow.db``, the default) at once.

SQLite lets one writer in at a time (https://www.sqlite.org/lockingv3.html, https://www.sqlite.org/wal.html);
the others wait in its busy handler (MLflow sets 20 s), and a transaction that read before it writes is refused at
once ("database is locked") where another writer got in between: MLflow's log calls read (is the run active?) then
write. Two things keep that from losing work when 16 or 32 jobs log a metric every step:

- every call to the store waits a lock out for as long as the outage budget allows (:func:`ablate.store.retry
  .retry`), not a fixed number of tries: a job never fails for a lock held by its neighbours;
- the store is switched to write-ahead logging once (:func:`write_ahead`; the mode is kept in the file): readers
  (``mlflow ui``, ``python -m ablate.report``, the jobs' own reads) never block the writer, and a commit appends to
  ``mlflow.db-wal`` instead of writing and deleting a journal. WAL needs the store on a local disk, not a network
  file system (SQLite's own rule); past one machine, use the server (``scripts/tracking_server.py``).

A transaction begun ``BEGIN IMMEDIATE`` would take the write lock before reading and so never be refused, but MLflow
holds one session open while it opens another in places (its schema's first use, its managed sessions), and with
both asking for the write lock a process waits for itself: its transactions are left as MLflow begins them.

MLflow creates the schema on first use, which two processes cannot do at once: :func:`needs_schema` says whether a
file still lacks it, so that only then is that first use serialised by a file lock (:mod:`ablate.store.tracker`);
jobs opening a store that has its schema no longer wait for each other.

``bench/bench_load.py`` measures it (docs/guide.md, "Many jobs on one store").
"""

from __future__ import annotations

import sqlite3
from contextlib import closing
from pathlib import Path

#: How long this module's own statements wait for another process's write lock (ms).
BUSY_TIMEOUT_MS = 60_000


def db_path(uri: str) -> Path | None:
    """The file of a ``sqlite:///PATH`` URI (query dropped), or None for another store or an in-memory one."""
    if not uri.startswith("sqlite:///"):
        return None
    rest = uri[len("sqlite:///") :].split("?", 1)[0]
    return None if rest in ("", ":memory:") else Path(rest)


def needs_schema(db: Path) -> bool:
    """Whether MLflow has yet to create its schema in ``db`` (no file, an empty one, or no ``alembic_version``)."""
    if not db.exists() or db.stat().st_size == 0:
        return True
    try:
        with closing(sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=BUSY_TIMEOUT_MS / 1000)) as conn:
            found = conn.execute("SELECT 1 FROM sqlite_master WHERE type='table' AND name='alembic_version'")
            return found.fetchone() is None
    except sqlite3.DatabaseError:  # not a database (yet): MLflow's first use says what it is
        return True


def write_ahead(db: Path) -> None:
    """Put ``db`` in write-ahead-logging mode (kept in the file; a no-op where it already is)."""
    with closing(sqlite3.connect(str(db), timeout=BUSY_TIMEOUT_MS / 1000)) as conn:
        if conn.execute("PRAGMA journal_mode").fetchone()[0].lower() != "wal":
            conn.execute("PRAGMA journal_mode=WAL")
