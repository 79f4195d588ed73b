"""Recording a job's end in its run, whether or not the tracking server answers, and delivering what an earlier
job of the same config kept for it.

A run's end (its status and the tags that say why) normally goes to the server at once. Where the server does not
answer, the end goes to the job's outbox (:mod:`ablate.store.outbox`) beside the metrics that wait there, and the
next job of the same config delivers both before it starts (:func:`deliver_earlier`): a run recorded on the server
is never left without its metrics or its end, whatever the outage.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

from mlflow.exceptions import MlflowException

from ablate.store import Outbox, ServerUnreachable, Tracker

log = logging.getLogger(__name__)


def record_end(
    tracker: Tracker,
    run_id: str,
    status: str,
    tags: dict[str, str],
    error: str | None = None,
    outbox: Outbox | None = None,
) -> None:
    """End ``run_id`` as ``status`` with ``tags`` (and ``error.txt``): each step tried on its own, so that a tag or
    an artifact the store cannot take (a full disk) never keeps the status from being recorded. Where the tracking
    server does not answer (the outbox still holds metrics it did not take, or a step waited for it in vain), the
    tags and the status go to the ``outbox``, for the next run of the job to deliver."""
    if outbox is not None and outbox.pending:  # the server did not answer lately: one try, no waiting
        try:
            outbox.deliver(lambda batch: tracker.send(batch, outage_s=0))
        except ServerUnreachable as err:
            log.error(
                "Could not record the end of run %s: %s; %s",
                run_id,
                err,
                kept_for_later(outbox, run_id, None, str(err), status, tags),
            )
            return
    for step, call in (
        ("tags", lambda: tracker.set_tags(run_id, tags)),
        ("error.txt", lambda: tracker.log_text(run_id, error, "error.txt") if error else None),
        ("status", lambda: tracker.end(run_id, status)),
    ):
        try:
            call()
        except ServerUnreachable as err:
            kept = "" if outbox is None else "; " + kept_for_later(outbox, run_id, None, str(err), status, tags)
            log.error("Could not record the %s of run %s (%s): %s%s", step, run_id, status, err, kept)
            return
        except Exception as err:
            log.error("Could not record the %s of run %s (%s): %s", step, run_id, status, err)


def unreachable(err: BaseException) -> ServerUnreachable | None:
    """The :class:`ServerUnreachable` that ``err`` is or was raised from, or None."""
    seen: set[int] = set()
    cause: BaseException | None = err
    while cause is not None and id(cause) not in seen:
        if isinstance(cause, ServerUnreachable):
            return cause
        seen.add(id(cause))
        cause = cause.__cause__ or cause.__context__
    return None


def kept_for_later(
    outbox: Outbox,
    run_id: str,
    ckpt_dir: Path | None,
    error: str,
    status: str = "FAILED",
    tags: dict[str, str] | None = None,
) -> str:
    """Put the end of ``run_id`` (``status``, ``tags`` or the ``error``) in the outbox, and say what is kept where,
    and how it reaches the server."""
    outbox.add(run_id, tags=tags if tags is not None else {"error": error[:5000]}, status=status)
    kept = f"its end ({status}) and {outbox.values()} metric value(s) wait in {outbox.path}"
    if ckpt_dir is not None:
        last = ckpt_dir / "last.ckpt"
        kept += f", its checkpoint {last} is kept" if last.exists() else " (no checkpoint was written yet)"
    return (
        f"run {run_id} stays RUNNING on the server for now: {kept}; once the server answers, the same command again "
        "delivers them and resumes"
    )


def deliver_earlier(tracker: Tracker, outbox: Outbox) -> None:
    """Deliver what an earlier job of this config left in its outbox (metrics, the end of its run) because the
    tracking server did not answer, waiting for the server up to the outage budget. A batch the server refuses
    (its run was deleted) leaves the outbox aside as ``outbox.jsonl.undelivered``, named in a warning."""
    if not outbox.pending:
        return
    try:
        done = outbox.deliver(tracker.send)
    except MlflowException as err:
        aside = outbox.path.with_name(outbox.path.name + ".undelivered")
        os.replace(outbox.path, aside)
        log.warning("The tracking server refused the outbox of an earlier job (%s); it is moved to %s", err, aside)
        return
    ends = ", ".join(f"run {b.run} {b.status}" for b in done if b.status)
    log.info(
        "Delivered what an earlier job of this config kept while the tracking server did not answer: %d metric "
        "value(s) to run(s) %s%s",
        sum(len(b.metrics) for b in done),
        ", ".join(sorted({b.run for b in done})),
        f"; {ends}" if ends else "",
    )
