"""Where the store is: its tracking URI and artifact location, relative paths resolved against the launch directory
(the directory the command was started in, passed in by the caller), and links into the MLflow UI."""

from __future__ import annotations

import os
from pathlib import Path
from urllib.parse import urlparse

from omegaconf import DictConfig

from ablate.store.identity import resolve_path

#: The MLflow UI's shared views: an experiment tag ``mlflow.sharedViewState.<key>`` holding the runs table's state as
#: JSON, opened by ``#/experiments/<id>/runs?viewStateShareKey=<key>`` (MLflow 3.17's "Share" button writes the same
#: tag; its reader also takes plain JSON, and keeps only the keys it shares: ``selectedColumns``, ``orderByKey``, ...).
SHARED_VIEW_TAG, SHARED_VIEW_KEY = "mlflow.sharedViewState.", "ablate-table"


def resolve_uri(uri: str, base: Path | None = None) -> str:
    """A tracking URI whose local path (``sqlite:///REL``, or a plain folder: MLflow's file store) is made absolute
    against ``base`` (the launch directory; default the current one); server and database URIs are returned as they
    are."""
    if uri.startswith("sqlite:///"):
        rest = uri[len("sqlite:///") :]
        return (
            uri if rest.startswith("/") or rest.startswith(":memory:") else "sqlite:///" + str(resolve_path(rest, base))
        )
    if not urlparse(uri).scheme:
        return str(resolve_path(uri, base))
    return uri


def is_server(uri: str) -> bool:
    """Whether ``uri`` names a tracking server (``http://``, ``https://``) rather than a store MLflow opens itself."""
    return urlparse(uri).scheme in ("http", "https")


def tracking_uri(cfg_logger: DictConfig | dict | None = None, base: Path | None = None) -> str:
    """The tracking URI: ``MLFLOW_TRACKING_URI`` if set, else the config's, else ``sqlite:///mlflow.db``; relative
    paths resolved against ``base`` (the launch directory; default the current one)."""
    uri = os.environ.get("MLFLOW_TRACKING_URI")
    if not uri and cfg_logger is not None and cfg_logger.get("tracking_uri"):
        uri = str(cfg_logger["tracking_uri"])
    return resolve_uri(uri or "sqlite:///mlflow.db", base)


def artifact_location(uri: str, root: str | None, base: Path | None = None) -> str | None:
    """Where new experiments keep their artifacts (``logger.artifact_root``), as a URI, or None for the server's.

    With a tracking server (``http(s)://``) the default is None: the experiment is created without a location, so
    ``mlflow server`` gives it ``mlflow-artifacts:/...`` and clients upload through the server, which stores the
    files under its ``--artifacts-destination`` (``mlflow server --help``: "By default, data will be logged to the
    mlflow-artifacts:/ uri proxy if the --serve-artifacts option is enabled", which it is by default; MLflow docs,
    https://mlflow.org/docs/latest/ml/tracking/server). A remote URI given explicitly (``s3://...``) is kept. A
    local path is an error there: every worker would write its own disk. With any other store the default is
    ``mlartifacts`` in the launch directory ``base`` (default the current one), and a relative path resolves against
    it.
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
    return resolve_path(local, base).as_uri()


def runs_link(uri: str, experiment_id: str) -> str:
    """Where the MLflow UI shows ``experiment_id``'s runs with the view of :meth:`Tracker.share_table_view`: on the
    tracking server itself when ``uri`` is one, else on ``mlflow ui``'s default address (127.0.0.1:5000)."""
    base = uri.rstrip("/") if is_server(uri) else "http://127.0.0.1:5000"
    return (
        f"{base}/#/experiments/{experiment_id}/runs?viewStateShareKey={SHARED_VIEW_KEY}&workflowType=machine_learning"
    )
