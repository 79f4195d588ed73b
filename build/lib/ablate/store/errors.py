"""What the store fails as, each in one message naming the file or the server: a full disk (:class:`DiskFull`) and
credentials the tracking server refuses (:class:`AccessDenied`). A server that does not answer is
:class:`ablate.store.outage.ServerUnreachable`."""

from __future__ import annotations

import errno
import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager


class DiskFull(OSError):
    """No space left on the device (or the quota is spent) while writing a checkpoint or an artifact; the message
    names the file and where it was going."""

    def __init__(self, message: str) -> None:
        super().__init__(errno.ENOSPC, message)
        self.message = message

    def __str__(self) -> str:
        return self.message


@contextmanager
def naming_full_disk(what: str, where: Callable[[], str]) -> Iterator[None]:
    """Turn ``ENOSPC`` / ``EDQUOT`` raised in the block into one :class:`DiskFull` naming ``what`` and ``where()``
    (called only then)."""
    try:
        yield
    except DiskFull:
        raise
    except OSError as err:
        if err.errno not in (errno.ENOSPC, errno.EDQUOT):
            raise
        try:
            dest = where()
        except Exception:
            dest = "the artifact store"
        raise DiskFull(f"no space left on the device writing {what} to {dest} ({err.strerror})") from err


class AccessDenied(RuntimeError):
    """The tracking server refused this client (HTTP 401 or 403): no, wrong or insufficient credentials. The
    message names the server (where known) and the variables that hold the credentials."""

    def __init__(self, code: int, uri: str | None = None) -> None:
        self.code, self.uri = code, uri
        user = os.environ.get("MLFLOW_TRACKING_USERNAME")
        who = f"as user {user!r}" if user else "without MLFLOW_TRACKING_USERNAME"
        meaning = "no credentials, or wrong ones" if code == 401 else "this user may not do that"
        server = f"the tracking server {uri}" if uri else "the tracking server"
        super().__init__(
            f"{server} refused this client {who} (HTTP {code}: {meaning}): set MLFLOW_TRACKING_USERNAME and "
            "MLFLOW_TRACKING_PASSWORD to an account of the server (scripts/tracking_server.py start --auth "
            "prints them)"
        )


def refusal(err: BaseException) -> AccessDenied | None:
    """An :class:`AccessDenied` if ``err`` is a request the tracking server refused (HTTP 401 or 403), else None."""
    for code in (401, 403):
        if f"error code {code}" in str(err):
            return AccessDenied(code)
    return None
