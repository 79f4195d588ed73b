"""A job's outbox: the metrics, tags and end of its run that the tracking server could not take when they were
logged, kept on disk until it answers, then delivered in order, each once.

The outbox is a JSON-lines file (``outbox.jsonl`` in the job's checkpoint folder), only appended to, each line
flushed and fsynced: so nothing in it is lost when the process dies. A line per batch logged,
``{"seq": 3, "run": ID, "metrics": [[key, value, timestamp_ms, step], ...], "tags": {...}, "status": "FAILED"}``,
and a line per batch delivered, ``{"sent": 3}``; once every batch is delivered the file is removed. A batch keeps
the timestamps its metrics were logged with, and MLflow holds a metric as the row (key, timestamp, step, value)
whose SQL stores ignore a row they already hold: a batch sent again because the process died between sending it
and marking it changes nothing on the server. A last line a crash cut short is skipped.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

#: The outbox's name in a job's checkpoint folder.
FILE = "outbox.jsonl"

#: One metric value as MLflow stores it: key, value, timestamp (ms since the epoch), step.
Row = tuple[str, float, int, int]


@dataclass
class Batch:
    """What one call logged to run ``run``: metric rows, tags, and the status that ends the run (or None)."""

    seq: int
    run: str
    metrics: list[Row] = field(default_factory=list)
    tags: dict[str, str] = field(default_factory=dict)
    status: str | None = None


class Outbox:
    """The outbox file ``path``: :meth:`add` a batch, :meth:`deliver` the pending ones in order."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._next: int | None = None
        self._pending: int | None = None

    def __repr__(self) -> str:
        return f"Outbox({str(self.path)!r})"

    def __getstate__(self) -> dict[str, str]:
        return {"path": str(self.path)}

    def __setstate__(self, state: dict[str, str]) -> None:
        Outbox.__init__(self, state["path"])

    def read(self) -> list[Batch]:
        """The batches not yet delivered, in the order they were added."""
        if not self.path.exists():
            self._next, self._pending = 1, 0
            return []
        batches: dict[int, Batch] = {}
        sent = last = 0
        for line in self.path.read_text().splitlines():
            try:
                item = json.loads(line)
            except json.JSONDecodeError:  # a line a crash cut short
                continue
            if "sent" in item:
                sent = max(sent, int(item["sent"]))
            elif "seq" in item:
                seq = int(item["seq"])
                last = max(last, seq)
                rows = [(str(k), float(v), int(t), int(s)) for k, v, t, s in item.get("metrics", [])]
                batches[seq] = Batch(seq, str(item["run"]), rows, dict(item.get("tags", {})), item.get("status"))
        pending = [batches[s] for s in sorted(batches) if s > sent]
        self._next, self._pending = last + 1, len(pending)
        return pending

    @property
    def pending(self) -> int:
        """How many batches wait to be delivered."""
        if self._pending is None:
            self.read()
        return int(self._pending or 0)

    def values(self) -> int:
        """How many metric values wait to be delivered."""
        return sum(len(b.metrics) for b in self.read())

    def add(
        self, run_id: str, metrics: Iterable[Row] = (), tags: dict[str, str] | None = None, status: str | None = None
    ) -> Batch:
        """Append a batch for ``run_id`` (on disk before this returns) and return it."""
        if self._next is None:
            self.read()
        batch = Batch(int(self._next or 1), run_id, list(metrics), dict(tags or {}), status)
        self._append({"seq": batch.seq, "run": run_id, "metrics": batch.metrics, "tags": batch.tags, "status": status})
        self._next, self._pending = batch.seq + 1, self.pending + 1
        return batch

    def mark(self, seq: int) -> None:
        """Record that every batch up to ``seq`` is delivered."""
        self._append({"sent": seq})
        self._pending = None

    def deliver(self, send: Callable[[Batch], None]) -> Sequence[Batch]:
        """Call ``send`` on each pending batch in order, marking each once it returns; remove the file when all are
        delivered. An error of ``send`` stops the delivery there (that batch and those after it stay) and is raised.
        Returns the batches delivered."""
        done: list[Batch] = []
        for batch in self.read():
            send(batch)
            self.mark(batch.seq)
            done.append(batch)
        if self.path.exists() and not self.read():
            self.path.unlink()
            self._next, self._pending = 1, 0
        return done

    def _append(self, item: dict) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with open(self.path, "ab") as handle:
            if handle.tell() > 0:  # a last line a crash cut short must not swallow this one
                with open(self.path, "rb") as back:
                    back.seek(-1, os.SEEK_END)
                    if back.read(1) != b"\n":
                        handle.write(b"\n")
            handle.write((json.dumps(item) + "\n").encode())
            handle.flush()
            os.fsync(handle.fileno())
