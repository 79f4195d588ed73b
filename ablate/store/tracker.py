"""MLflow tracking: one experiment per table, one parent run per sweep, one child run per job.

The store defaults to ``sqlite:///mlflow.db`` in the launch directory (where ``python -m ablate`` was started), so
``mlflow ui`` there finds it; ``MLFLOW_TRACKING_URI`` in the environment wins over the config. Relative paths in the
URI and the artifact root resolve against the launch directory, never against the directory a job happens to run
in (a Ray job runs where its cluster was started). Two set-ups are supported: a SQLite file (one machine) and an
``mlflow server`` on PostgreSQL (many machines; ``scripts/tracking_server.py`` starts one), whose artifacts go
through the server. Several processes (``hydra/launcher=joblib``, ``submitit_local``) write one SQLite file: the
first use of the store (where MLflow creates and migrates its schema, which two processes cannot do at once) is
serialised by a file lock beside it, every write goes through :func:`retry`, which waits out "database is locked",
and experiment creation tolerates a concurrent creator. A store that does not answer (a server stopped or
restarting) is waited for up to ``logger.outage_s`` (:mod:`ablate.store.outage`), except by :class:`RunLogger` while
a job trains: its metrics wait in the job's outbox meanwhile (:mod:`ablate.store.outbox`).
"""

from __future__ import annotations

import errno
import fcntl
import json
import logging
import os
import random
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, TypeVar
from urllib.parse import urlparse

from matplotlib.figure import Figure
from mlflow.entities import Metric, Param, Run, RunTag
from mlflow.exceptions import MlflowException
from mlflow.tracking import MlflowClient
from omegaconf import DictConfig

from ablate.store.identity import resolve_path
from ablate.store.outage import (
    DEFAULT_OUTAGE_S,
    ServerUnreachable,
    backoff,
    server_of,
    short_http_retries,
    shown,
    symptom,
)
from ablate.store.outbox import Batch, Row
from ablate.store.sweepdir import sweep_store

log = logging.getLogger(__name__)
T = TypeVar("T")

#: Tags every job run carries; the report reads them.
KIND_JOB, KIND_SWEEP = "job", "sweep"
#: The metric a job logs once its data module is set up: the bad frames it left out (``data.on_bad_frame=skip``).
SKIPPED_FRAMES = "data/skipped_frames"
#: Every experiment's kind (model training, not GenAI). MLflow 3.17's UI still opens on its GenAI view until the
#: browser's "Model training" switch is set (a per-browser setting, default GenAI), so a sweep also prints
#: :func:`runs_link`, which sets it.
EXPERIMENT_KIND = {"mlflow.experimentKind": "custom_model_development"}
#: The MLflow UI's shared views: an experiment tag ``mlflow.sharedViewState.<key>`` holding the runs table's state as
#: JSON, opened by ``#/experiments/<id>/runs?viewStateShareKey=<key>`` (MLflow 3.17's "Share" button writes the same
#: tag; its reader also takes plain JSON, and keeps only the keys it shares: ``selectedColumns``, ``orderByKey``, ...).
SHARED_VIEW_TAG, SHARED_VIEW_KEY = "mlflow.sharedViewState.", "ablate-table"


@contextmanager
def file_lock(path: Path) -> Iterator[None]:
    """An exclusive lock on ``path`` (created with its folder) across processes, held for the ``with`` block."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


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


def retry(
    fn: Callable[..., T],
    *args: Any,
    attempts: int = 12,
    outage_s: float | None = None,
    server: str | None = None,
    **kwargs: Any,
) -> T:
    """Call ``fn``, retrying with jittered backoff while SQLite says the database is locked or busy, and while the
    tracking store does not answer (:func:`~ablate.store.outage.symptom`: a refused connection, a timeout, HTTP
    5xx) for up to ``outage_s`` seconds (default :data:`~ablate.store.outage.DEFAULT_OUTAGE_S`; 0: not at all),
    after which it raises :class:`~ablate.store.outage.ServerUnreachable` naming ``server`` (else the address in
    the error). A refused credential is :class:`AccessDenied` at once."""
    budget = DEFAULT_OUTAGE_S if outage_s is None else float(outage_s)
    locked = down = 0
    down_since: float | None = None
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
            if locked >= attempts - 1 or not ("locked" in text or "busy" in text):
                raise
            time.sleep(min(0.1 * 2**locked, 5.0) * (0.5 + random.random()))
            locked += 1
            continue
        if down_since is not None:
            named = f"The tracking server {shown(where)}" if where else "The tracking server"
            log.warning("%s answers again after %.0f s of waiting", named, time.monotonic() - down_since)
        return result


def resolve_uri(uri: str) -> str:
    """A tracking URI whose local path (``sqlite:///REL``, or a plain folder: MLflow's file store) is made absolute
    against :func:`launch_dir`; server and database URIs are returned as they are."""
    if uri.startswith("sqlite:///"):
        rest = uri[len("sqlite:///") :]
        return uri if rest.startswith("/") or rest.startswith(":memory:") else "sqlite:///" + str(resolve_path(rest))
    if not urlparse(uri).scheme:
        return str(resolve_path(uri))
    return uri


def is_server(uri: str) -> bool:
    """Whether ``uri`` names a tracking server (``http://``, ``https://``) rather than a store MLflow opens itself."""
    return urlparse(uri).scheme in ("http", "https")


def tracking_uri(cfg_logger: DictConfig | dict | None = None) -> str:
    """The tracking URI: ``MLFLOW_TRACKING_URI`` if set, else the config's, else ``sqlite:///mlflow.db``; relative
    paths resolved against :func:`launch_dir`."""
    uri = os.environ.get("MLFLOW_TRACKING_URI")
    if not uri and cfg_logger is not None and cfg_logger.get("tracking_uri"):
        uri = str(cfg_logger["tracking_uri"])
    return resolve_uri(uri or "sqlite:///mlflow.db")


def artifact_location(uri: str, root: str | None) -> str | None:
    """Where new experiments keep their artifacts (``logger.artifact_root``), as a URI, or None for the server's.

    With a tracking server (``http(s)://``) the default is None: the experiment is created without a location, so
    ``mlflow server`` gives it ``mlflow-artifacts:/...`` and clients upload through the server, which stores the
    files under its ``--artifacts-destination`` (``mlflow server --help``: "By default, data will be logged to the
    mlflow-artifacts:/ uri proxy if the --serve-artifacts option is enabled", which it is by default; MLflow docs,
    https://mlflow.org/docs/latest/ml/tracking/server). A remote URI given explicitly (``s3://...``) is kept. A
    local path is an error there: every worker would write its own disk. With any other store the default is
    ``mlartifacts`` in the launch directory, and a relative path resolves against it.
    """
    scheme = urlparse(str(root)).scheme if root is not None else ""
    remote = len(scheme) > 1 and scheme != "file"  # a one-letter scheme is a Windows drive
    if is_server(uri):
        if root is None or remote:
            return None if root is None else str(root)
        raise ValueError(
            f"logger.artifact_root={root} is a local path, but the tracking store is the server {uri}: "
            "every worker would keep artifacts on its own disk. Leave it null (the server stores them) "
            "or give a URI every machine reaches (s3://..., mlflow-artifacts:/...)"
        )
    if remote:
        return str(root)
    local = urlparse(str(root)).path if scheme == "file" else (root or "mlartifacts")
    return resolve_path(local).as_uri()


class Tracker:
    """A thin, retrying wrapper over :class:`MlflowClient` for the run lifecycle of a table.

    ``uri`` is used as given (:func:`tracking_uri` resolves the configured one); ``artifact_root`` is turned into
    :attr:`artifact_location` by :func:`artifact_location`. Every call waits up to ``outage_s`` seconds
    (``logger.outage_s``) for a store that does not answer (:func:`retry`); against a server, MLflow's own HTTP
    retries are made short (:func:`~ablate.store.outage.short_http_retries`). A Tracker pickles as its URI,
    artifact location and budget, so that Lightning's ``ddp_spawn`` can hand the run's logger to its processes,
    each opening its own client.
    """

    def __init__(self, uri: str, artifact_root: str | None = None, outage_s: float = DEFAULT_OUTAGE_S) -> None:
        self.uri = uri
        self.outage_s = float(outage_s)
        self.artifact_location = artifact_location(uri, artifact_root)
        if uri.startswith("sqlite:///"):  # MLflow creates the schema on first use: one process at a time
            db = Path(uri[len("sqlite:///") :].split("?", 1)[0])
            with file_lock(db.with_name(db.name + "-lock")):
                self.client = MlflowClient(tracking_uri=uri)
                self.call(self.client.search_experiments, max_results=1)
        else:
            self.client = MlflowClient(tracking_uri=uri)
            if is_server(uri):  # credentials the server refuses stop here, with the server's name
                short_http_retries()
                try:
                    self.call(self.client.search_experiments, max_results=1)
                except AccessDenied as err:
                    raise AccessDenied(err.code, uri) from None

    def __getstate__(self) -> dict[str, Any]:
        return {"uri": self.uri, "artifact_location": self.artifact_location, "outage_s": self.outage_s}

    def __setstate__(self, state: dict[str, Any]) -> None:
        Tracker.__init__(self, state["uri"], state["artifact_location"], state.get("outage_s", DEFAULT_OUTAGE_S))

    @classmethod
    def from_config(cls, cfg: DictConfig) -> Tracker:
        """The store of ``cfg``; inside a multirun, the store its sweep recorded (where its parent run is), whatever
        this process's environment says. The outage budget is ``logger.outage_s``."""
        lg = cfg.get("logger") or {}
        budget = float(lg.get("outage_s", DEFAULT_OUTAGE_S))
        recorded = sweep_store()
        if recorded is not None:
            return cls(str(recorded["uri"]), recorded["artifact_location"], budget)
        root = lg.get("artifact_root")
        return cls(tracking_uri(lg), None if root is None else str(root), budget)

    def call(self, fn: Callable[..., T], *args: Any, outage_s: float | None = None, **kwargs: Any) -> T:
        """``fn(*args, **kwargs)`` through :func:`retry`, waiting up to ``outage_s`` (default :attr:`outage_s`)
        for a store that does not answer, which is then named in :class:`ServerUnreachable`."""
        budget = self.outage_s if outage_s is None else outage_s
        return retry(fn, *args, outage_s=budget, server=self.uri, **kwargs)

    def experiment_id(self, name: str) -> str:
        """The id of experiment ``name``, created if missing (tagged :data:`EXPERIMENT_KIND`, with its artifacts
        under :attr:`artifact_location`, or the server's when that is None); safe when another process creates it
        too. An existing experiment without the tag gets it."""
        exp = self.call(self.client.get_experiment_by_name, name)
        if exp is not None:
            if any(exp.tags.get(k) != v for k, v in EXPERIMENT_KIND.items()):
                for key, value in EXPERIMENT_KIND.items():
                    self.call(self.client.set_experiment_tag, exp.experiment_id, key, value)
            return exp.experiment_id
        try:
            location = None if self.artifact_location is None else f"{self.artifact_location.rstrip('/')}/{name}"
            return self.call(self.client.create_experiment, name, artifact_location=location, tags=EXPERIMENT_KIND)
        except MlflowException:
            exp = self.call(self.client.get_experiment_by_name, name)
            if exp is None:
                raise
            return exp.experiment_id

    def runs(self, experiment_id: str, filter_string: str = "") -> list[Run]:
        """All runs of an experiment matching ``filter_string``, every page."""
        out: list[Run] = []
        token = None
        while True:
            page = self.call(
                self.client.search_runs, [experiment_id], filter_string, max_results=1000, page_token=token
            )
            out.extend(page)
            token = page.token
            if not token:
                return out

    def finished_run(self, experiment_id: str, chash: str) -> Run | None:
        """A FINISHED job run with this config hash, or None."""
        runs = self.runs(experiment_id, f"tags.config_hash = '{chash}' and attributes.status = 'FINISHED'")
        return runs[0] if runs else None

    def finished_elsewhere(self, chash: str) -> Run | None:
        """A FINISHED job run with this config hash in any experiment, or None (tables share rows: ChiNet
        Tables II-V all hold the ChiNet row)."""
        ids = [e.experiment_id for e in self.call(self.client.search_experiments)]
        runs = (
            self.call(
                self.client.search_runs,
                ids,
                f"tags.config_hash = '{chash}' and attributes.status = 'FINISHED' and tags.kind = '{KIND_JOB}'",
                max_results=1,
            )
            if ids
            else []
        )
        return runs[0] if runs else None

    def copy_run(self, source: Run, experiment_id: str, tags: dict[str, str]) -> str:
        """A FINISHED copy of ``source`` (params, final metrics, tags) in ``experiment_id``, tagged
        ``reused_from``; artifacts stay with the source run."""
        keep = {k: v for k, v in source.data.tags.items() if not k.startswith("mlflow.") and k != "sweep_id"}
        origin = source.data.tags.get("reused_from", source.info.run_id)
        run_id = self.start(experiment_id, source.info.run_name or "reused", {**keep, **tags, "reused_from": origin})
        self.log_params(run_id, dict(source.data.params))
        self.log_metrics(run_id, dict(source.data.metrics))
        self.end(run_id, "FINISHED")
        return run_id

    def close_stale(self, experiment_id: str, chash: str) -> int:
        """Mark runs of this config hash still RUNNING (a killed process left them) as KILLED; return how many."""
        stale = self.runs(experiment_id, f"tags.config_hash = '{chash}' and attributes.status = 'RUNNING'")
        for run in stale:
            self.call(self.client.set_terminated, run.info.run_id, "KILLED")
        return len(stale)

    def start(self, experiment_id: str, name: str, tags: dict[str, str]) -> str:
        run = self.call(self.client.create_run, experiment_id, tags=tags, run_name=name)
        return run.info.run_id

    def end(self, run_id: str, status: str) -> None:
        self.call(self.client.set_terminated, run_id, status)

    def log_params(self, run_id: str, params: dict[str, str]) -> None:
        items = [Param(k[:250], v[:6000]) for k, v in sorted(params.items())]
        for i in range(0, len(items), 100):
            self.call(self.client.log_batch, run_id, params=items[i : i + 100])

    def log_metrics(self, run_id: str, metrics: dict[str, float], step: int = 0) -> None:
        self.log_rows(run_id, rows(metrics, step))

    def log_rows(self, run_id: str, items: list[Row], outage_s: float | None = None) -> None:
        """Log metric rows (key, value, timestamp, step) as they are: a batch sent twice adds no row twice."""
        metrics = [Metric(k, v, t, s) for k, v, t, s in items]
        for i in range(0, len(metrics), 500):
            self.call(self.client.log_batch, run_id, metrics=metrics[i : i + 500], outage_s=outage_s)

    def send(self, batch: Batch, outage_s: float | None = None) -> None:
        """Deliver an outbox batch: its metric rows, its tags, then its status."""
        self.log_rows(batch.run, batch.metrics, outage_s)
        if batch.tags:
            tags = [RunTag(k, str(v)) for k, v in batch.tags.items()]
            self.call(self.client.log_batch, batch.run, tags=tags, outage_s=outage_s)
        if batch.status:
            self.call(self.client.set_terminated, batch.run, batch.status, outage_s=outage_s)

    def set_tags(self, run_id: str, tags: dict[str, str]) -> None:
        self.call(self.client.log_batch, run_id, tags=[RunTag(k, str(v)) for k, v in tags.items()])

    def artifact_uri(self, run_id: str) -> str:
        """Where ``run_id`` keeps its artifacts."""
        return str(self.call(self.client.get_run, run_id).info.artifact_uri)

    def log_artifact(self, run_id: str, path: str | Path, artifact_path: str | None = None) -> None:
        """Upload the file ``path``; a full disk is one :class:`DiskFull` naming it and the run's artifact store."""
        with naming_full_disk(f"the artifact {path}", lambda: self.artifact_uri(run_id)):
            self.call(self.client.log_artifact, run_id, str(path), artifact_path)

    def log_figure(self, run_id: str, figure: Figure, name: str) -> None:
        with naming_full_disk(f"the artifact {name}", lambda: self.artifact_uri(run_id)):
            self.call(self.client.log_figure, run_id, figure, name)

    def log_text(self, run_id: str, text: str, name: str) -> None:
        with naming_full_disk(f"the artifact {name}", lambda: self.artifact_uri(run_id)):
            self.call(self.client.log_text, run_id, text, name)

    def share_table_view(self, experiment_id: str, metrics: list[str]) -> str:
        """Store the runs table view of a table's experiment, with the table's ``metrics`` as columns and the
        newest runs first, under :data:`SHARED_VIEW_KEY`, and return its address in the MLflow UI
        (:func:`runs_link`). A sweep's jobs stay folded under its parent run until its [+] is clicked: the UI does
        not take which runs are expanded from a shared view."""
        state = {
            "selectedColumns": [f"metrics.`{m}`" for m in metrics],
            "orderByKey": "attributes.start_time",
            "orderByAsc": False,
        }
        self.call(self.client.set_experiment_tag, experiment_id, SHARED_VIEW_TAG + SHARED_VIEW_KEY, json.dumps(state))
        return runs_link(self.uri, experiment_id)


def runs_link(uri: str, experiment_id: str) -> str:
    """Where the MLflow UI shows ``experiment_id``'s runs with the view of :meth:`Tracker.share_table_view`: on the
    tracking server itself when ``uri`` is one, else on ``mlflow ui``'s default address (127.0.0.1:5000)."""
    base = uri.rstrip("/") if is_server(uri) else "http://127.0.0.1:5000"
    return (
        f"{base}/#/experiments/{experiment_id}/runs?viewStateShareKey={SHARED_VIEW_KEY}&workflowType=machine_learning"
    )


def rows(metrics: dict[str, float], step: int = 0) -> list[Row]:
    """``metrics`` at ``step`` as metric rows stamped now (ms), sorted by key."""
    now = int(time.time() * 1000)
    return [(k, float(v), now, int(step)) for k, v in sorted(metrics.items())]
