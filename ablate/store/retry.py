"""Every call to the store goes through :func:`retry`: SQLite's "database is locked" is waited out, a store that does
not answer is waited for up to the outage budget (``logger.outage_s``) and then named in one
:class:`~ablate.store.outage.ServerUnreachable`, and refused credentials are :class:`~ablate.store.errors.AccessDenied`
at once. :class:`ablate.store.tracker.Tracker` calls it with its own budget and server name."""

from __future__ import annotations

import logging
import random
import time
from collections.abc import Callable
from typing import Any, TypeVar

from mlflow.exceptions import MlflowException

from ablate.store.errors import refusal
from ablate.store.outage import DEFAULT_OUTAGE_S, ServerUnreachable, backoff, server_of, shown, symptom

log = logging.getLogger(__name__)
T = TypeVar("T")
#: How long a call waits out a SQLite store that other jobs keep locked ("database is locked"), whatever the outage
#: budget: a lock means the store answers and is busy, and a job never fails for its neighbours' writes
#: (:mod:`ablate.store.sqlite`).
LOCKED_S = 600.0


def retry(
    fn: Callable[..., T],
    *args: Any,
    locked_s: float | None = None,
    outage_s: float | None = None,
    server: str | None = None,
    **kwargs: Any,
) -> T:
    """Call ``fn``, retrying with jittered backoff while SQLite says the database is locked or busy (for up to
    ``locked_s`` seconds, default :data:`LOCKED_S`, then its error is raised), and while the
    tracking store does not answer (:func:`~ablate.store.outage.symptom`: a refused connection, a timeout, HTTP
    5xx) for up to ``outage_s`` seconds (default :data:`~ablate.store.outage.DEFAULT_OUTAGE_S`; 0: not at all),
    after which it raises :class:`~ablate.store.outage.ServerUnreachable` naming ``server`` (else the address in
    the error). A refused credential is :class:`AccessDenied` at once."""
    budget = DEFAULT_OUTAGE_S if outage_s is None else float(outage_s)
    locked = down = 0
    down_since: float | None = None
    locked_since: float | None = None
    where = server
    while True:
        try:
            result = fn(*args, **kwargs)
        except Exception as err:  # sqlalchemy's OperationalError arrives wrapped in MlflowException
            if isinstance(err, MlflowException) and (denied := refusal(err)) is not None:
                raise denied from None
            what = symptom(err)
            if what is not None:
                now = time.monotonic()
                down_since = now if down_since is None else down_since
                where = server or server_of(err)
                named = f"The tracking server {shown(where)}" if where else "The tracking server"
                if now - down_since >= budget:
                    raise ServerUnreachable(where, now - down_since, budget, what) from err
                if down == 0:
                    log.warning(
                        "%s does not answer (%s): waiting up to %.0f s for it (logger.outage_s)", named, what, budget
                    )
                time.sleep(min(backoff(down), max(budget - (now - down_since), 0.0)))
                down += 1
                continue
            text = str(err).lower()
            if not ("locked" in text or "busy" in text):
                raise
            now = time.monotonic()
            locked_since = now if locked_since is None else locked_since
            if now - locked_since >= (LOCKED_S if locked_s is None else locked_s):
                raise
            time.sleep(min(0.05 * 2**locked, 1.0) * (0.5 + random.random()))
            locked += 1
            continue
        if down_since is not None:
            named = f"The tracking server {shown(where)}" if where else "The tracking server"
            log.warning("%s answers again after %.0f s of waiting", named, time.monotonic() - down_since)
        return result
