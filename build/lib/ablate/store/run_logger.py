"""The Lightning logger of a job: its metrics into the job's MLflow run, kept in the job's outbox while the tracking
server does not answer (:mod:`ablate.store.outbox`, :mod:`ablate.store.outage`)."""

from __future__ import annotations

import logging
import time
from typing import Any

from lightning.pytorch.loggers.logger import Logger
from lightning.pytorch.utilities import rank_zero_only

from ablate.store.outage import ServerUnreachable, answers, backoff, shown
from ablate.store.outbox import Outbox, Row
from ablate.store.tracker import Tracker, rows
from ablate.store.uris import is_server

log = logging.getLogger(__name__)
#: The prefix of a test epoch's metrics, as the tasks log them.
TEST_PREFIX = "test/"


class RunLogger(Logger):
    """A Lightning logger writing metrics into an existing MLflow run, through :func:`retry`.

    Unlike Lightning's ``MLFlowLogger`` it never ends the run: the job ends it once testing and artifact logging
    are done, so a run is FINISHED only when everything it should hold is there.

    With an ``outbox`` (:mod:`ablate.store.outbox`), a tracking server that does not answer never stops training:
    the metrics go to the outbox, and each later call (no sooner than a backoff of 0.5 s doubling up to 10 s after
    the last try, and only once the server answers its health check) delivers what waits there, in order. The job
    then calls :meth:`deliver`, which waits up to the outage budget for the rest. Without one, every call waits for
    the server as :class:`Tracker`'s do.
    """

    #: The longest pause between two tries of a server that does not answer, while training.
    MAX_PAUSE_S = 10.0

    def __init__(self, tracker: Tracker, run_id: str, outbox: Outbox | None = None) -> None:
        super().__init__()
        self.tracker, self.run_id, self.outbox = tracker, run_id, outbox
        self.down_since: float | None = None  # time.monotonic() of the first call the server did not answer
        self.tries = 0
        self.next_try = 0.0
        self.kept = 0  # metric values put in the outbox since then

    @property
    def name(self) -> str:
        return "mlflow"

    @property
    def version(self) -> str:
        return self.run_id

    @rank_zero_only
    def log_hyperparams(self, params: Any, *args: Any, **kwargs: Any) -> None:
        """Params are logged once by the job, from the resolved config."""

    @rank_zero_only
    def log_metrics(self, metrics: dict[str, float], step: int | None = None) -> None:
        """Log training and validation metrics; the test epoch's (``test/...``) are left to the job, which logs them
        once, under their plain names, with the model's size (:func:`ablate.jobs.train.test`)."""
        kept = {k: v for k, v in metrics.items() if not k.startswith(TEST_PREFIX)}
        if kept:
            self.log_rows(rows(kept, step or 0))

    def log_rows(self, items: list[Row]) -> None:
        """Log metric rows now, or keep them in the outbox while the server does not answer."""
        if self.outbox is None:
            self.tracker.log_rows(self.run_id, items)
            return
        if self.down_since is None and not self.outbox.pending:
            try:
                self.tracker.log_rows(self.run_id, items, outage_s=0)
                return
            except ServerUnreachable as err:
                self.went_down(err)
        self.outbox.add(self.run_id, items)
        self.kept += len(items)
        self.try_delivery()

    def went_down(self, err: ServerUnreachable) -> None:
        self.down_since, self.tries, self.kept = time.monotonic(), 0, 0
        self.next_try = self.down_since + backoff(0, self.MAX_PAUSE_S)
        log.warning(
            "The tracking server %s does not answer (%s): training goes on, and the metrics of run %s wait in %s "
            "until it does",
            shown(self.tracker.uri),
            err.what,
            self.run_id,
            self.outbox.path if self.outbox is not None else None,
        )

    def try_delivery(self) -> None:
        """Deliver the outbox if the last try is long enough ago and the server answers; else try again later."""
        if self.outbox is None or time.monotonic() < self.next_try:
            return
        try:
            if is_server(self.tracker.uri) and not answers(self.tracker.uri):
                raise ServerUnreachable(self.tracker.uri, 0.0, 0.0, "no answer to its health check")
            self.outbox.deliver(lambda batch: self.tracker.send(batch, outage_s=0))
        except ServerUnreachable:
            self.tries += 1
            self.next_try = time.monotonic() + backoff(self.tries, self.MAX_PAUSE_S)
            return
        self.delivered()

    def deliver(self) -> None:
        """Deliver everything in the outbox, waiting up to the outage budget for the server; raise
        :class:`ServerUnreachable` if it does not answer in that time (the outbox then keeps the rest)."""
        if self.outbox is not None and self.outbox.pending:
            self.outbox.deliver(self.tracker.send)
            self.delivered()

    def delivered(self) -> None:
        """Note that the outbox is delivered: the server answers again."""
        if self.down_since is not None:
            log.warning(
                "The tracking server %s answers again, %.0f s after it stopped answering; training went on, and the "
                "%d metric value(s) logged meanwhile are delivered to run %s",
                shown(self.tracker.uri),
                time.monotonic() - self.down_since,
                self.kept,
                self.run_id,
            )
        self.down_since, self.tries, self.next_try, self.kept = None, 0, 0.0, 0

    @rank_zero_only
    def finalize(self, status: str) -> None:
        """At the end of a fit or a test, deliver what the outbox holds if the server answers (never waiting)."""
        if self.outbox is not None and self.outbox.pending:
            self.next_try = 0.0
            self.try_delivery()
