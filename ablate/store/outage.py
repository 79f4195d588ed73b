"""A tracking store that does not answer: how it is recognised, how long a job waits for it, and what it fails as.

An ``mlflow server`` that is stopped, restarting or unreachable (or the database behind it, or a database store
itself) refuses connections, times out or answers HTTP 5xx. MLflow's own HTTP client retries each request 7 times
with a backoff of 2 s doubling (``MLFLOW_HTTP_REQUEST_MAX_RETRIES``, ``..._BACKOFF_FACTOR``; 120 s per try,
``MLFLOW_HTTP_REQUEST_TIMEOUT``), so one call could block for minutes. Against a server each process makes those
short instead (:func:`short_http_retries`, where the variables are unset), and the waiting is done by
:func:`ablate.store.tracker.retry`, bounded by the outage budget ``logger.outage_s`` (:data:`DEFAULT_OUTAGE_S`)
and ending in one :class:`ServerUnreachable` naming the store and how long it was waited for. A job does not wait
while it trains: its metrics wait in an outbox on disk (:mod:`ablate.store.outbox`).
"""

from __future__ import annotations

import os
import random
import re
from urllib.parse import urlsplit, urlunsplit

import requests

#: Seconds a process waits for a tracking store that does not answer before it gives up (``logger.outage_s``).
DEFAULT_OUTAGE_S = 300.0
#: Seconds the health check of a server may take while a job trains: a server that needs longer counts as down.
PROBE_TIMEOUT_S = 5
#: MLflow's HTTP settings against a server, where the environment does not set them: one quick retry of each
#: request (a stale pooled connection), and 30 s for an answer.
HTTP_DEFAULTS = {
    "MLFLOW_HTTP_REQUEST_MAX_RETRIES": "1",
    "MLFLOW_HTTP_REQUEST_BACKOFF_FACTOR": "1",
    "MLFLOW_HTTP_REQUEST_TIMEOUT": "30",
}
#: Phrases of the errors of a store that does not answer (requests, urllib3, MLflow, SQLAlchemy's drivers), each
#: with the words a message gives it.
SYMPTOMS = (
    ("connection refused", "connection refused"),
    ("failed to establish a new connection", "connection refused"),
    ("name or service not known", "unknown host"),
    ("temporary failure in name resolution", "unknown host"),
    ("no route to host", "no route to host"),
    ("network is unreachable", "network unreachable"),
    ("connection aborted", "connection dropped"),
    ("connection reset", "connection dropped"),
    ("remotedisconnected", "connection dropped"),
    ("remote end closed connection", "connection dropped"),
    ("connection broken", "connection dropped"),  # killed while it sent its answer (urllib3's IncompleteRead)
    ("response ended prematurely", "connection dropped"),
    ("server closed the connection unexpectedly", "connection dropped"),
    ("timeout exception", "timed out"),
    ("timed out", "timed out"),
    ("too many 429 error responses", "HTTP 429"),
    ("too many 500 error responses", "HTTP 500"),
    ("too many 502 error responses", "HTTP 502"),
    ("too many 503 error responses", "HTTP 503"),
    ("too many 504 error responses", "HTTP 504"),
    ("502 server error", "HTTP 502"),
    ("503 server error", "HTTP 503"),
    ("504 server error", "HTTP 504"),
    ("max retries exceeded", "no answer"),
)


def symptom(err: BaseException) -> str | None:
    """What ``err`` says of a store that does not answer (``connection refused``, ``HTTP 503``, ...), or None when
    it is another error (a bad request, a missing run, a refused credential)."""
    text = str(err).lower()
    for phrase, words in SYMPTOMS:
        if phrase in text:
            return words
    network = (
        requests.exceptions.ConnectionError,
        requests.exceptions.Timeout,
        requests.exceptions.ChunkedEncodingError,
    )
    return "connection error" if isinstance(err, network) else None


def server_of(err: BaseException) -> str | None:
    """The server address an MLflow request error names (``API request to http://host:5000/api/...``), or None."""
    found = re.search(r"https?://[^/\s'\"]+", str(err))
    return found.group(0) if found else None


def shown(uri: str) -> str:
    """``uri`` without a user name or password (``postgresql://user:secret@host/db`` -> ``postgresql://host/db``)."""
    parts = urlsplit(uri)
    if "@" not in parts.netloc:
        return uri
    return urlunsplit(parts._replace(netloc=parts.netloc.rsplit("@", 1)[1]))


class ServerUnreachable(RuntimeError):
    """The tracking store did not answer for the whole outage budget. The message names the store, the seconds
    waited, the budget (``logger.outage_s``) and the last symptom."""

    def __init__(self, uri: str | None, waited_s: float, budget_s: float, what: str) -> None:
        self.uri, self.waited_s, self.budget_s, self.what = uri, waited_s, budget_s, what
        store = f"the tracking server {shown(uri)}" if uri else "the tracking server"
        if budget_s <= 0:  # not waited for
            super().__init__(f"{store} does not answer ({what})")
        else:
            super().__init__(
                f"{store} did not answer for {waited_s:.0f} s ({what}; logger.outage_s={budget_s:g} is the longest "
                "a job waits for it)"
            )


def backoff(attempt: int, cap: float = 5.0) -> float:
    """Seconds to wait before try ``attempt + 1`` of a store that does not answer: 0.5 s doubling up to ``cap``,
    times a random 0.5 to 1.5, so that parallel jobs do not all call again at the same moment."""
    return min(0.5 * 2**attempt, cap) * (0.5 + random.random())


def short_http_retries() -> None:
    """Set :data:`HTTP_DEFAULTS` in this process's environment where they are unset (MLflow reads them at every
    request; a job's worker processes inherit them): the waiting for a server is then :func:`retry`'s, bounded by
    the outage budget, instead of minutes inside one request."""
    for key, value in HTTP_DEFAULTS.items():
        os.environ.setdefault(key, value)


def answers(uri: str, timeout_s: float = PROBE_TIMEOUT_S) -> bool:
    """Whether the server ``uri`` answers its health check (``GET /health``) within ``timeout_s``, with the
    client's credentials and TLS settings: any answer but a gateway's 502-504 counts."""
    from mlflow.utils.credentials import get_default_host_creds
    from mlflow.utils.rest_utils import http_request

    try:
        response = http_request(
            get_default_host_creds(uri), "/health", "GET", max_retries=0, timeout=timeout_s, raise_on_status=False
        )
    except Exception:
        return False
    return response.status_code not in (502, 503, 504)
