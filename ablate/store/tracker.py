"""MLflow tracking: one experiment per table, one parent run per sweep, one child run per job. :class:`Tracker` is
the only code that talks to MLflow: the tables, the report, latency, the reproduction check and the diagnosis use
its public methods, each under the configured outage budget (``logger.outage_s``) and naming the server.

The store defaults to ``sqlite:///mlflow.db`` in the launch directory (where ``python -m ablate`` was started), so
``mlflow ui`` there finds it; ``MLFLOW_TRACKING_URI`` in the environment wins over the config; inside a multirun the
store its sweep recorded wins over both (:class:`~ablate.store.context.SweepContext`, passed in). Relative paths
resolve against the launch directory (:mod:`ablate.store.uris`). Two set-ups are supported: a SQLite file (one
machine) and an ``mlflow server`` on PostgreSQL (many machines; ``scripts/tracking_server.py`` starts one), whose
artifacts go through the server. Several processes (``hydra/launcher=joblib``, ``submitit_local``) write one SQLite
file: the first use of the store (where MLflow creates and migrates its schema, which two processes cannot do at
once) is serialised by a file lock beside it (:mod:`ablate.store.locks`), every call goes through
:func:`~ablate.store.retry.retry`, which waits out "database is locked", and experiment creation tolerates a
concurrent creator. A store that does not answer is waited for up to ``logger.outage_s``
(:mod:`ablate.store.outage`), except by :class:`RunLogger` while a job trains: its metrics wait in the job's outbox
(:mod:`ablate.store.outbox`).
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from matplotlib.figure import Figure
from mlflow.entities import Dataset, DatasetInput, InputTag, Metric, Param, Run, RunTag
from mlflow.exceptions import MlflowException
from mlflow.tracking import MlflowClient
from omegaconf import DictConfig

from ablate.store.errors import AccessDenied, naming_full_disk
from ablate.store.locks import file_lock
from ablate.store.outage import DEFAULT_OUTAGE_S, short_http_retries
from ablate.store.outbox import Batch, Row
from ablate.store.retry import retry
from ablate.store.sqlite import db_path, needs_schema, write_ahead
from ablate.store.uris import SHARED_VIEW_KEY, SHARED_VIEW_TAG, artifact_location, is_server, runs_link, tracking_uri

if TYPE_CHECKING:
    from ablate.store.context import SweepContext

log = logging.getLogger(__name__)
T = TypeVar("T")

#: Tags every job run carries; the report reads them.
KIND_JOB, KIND_SWEEP = "job", "sweep"
#: A tuning trial's run (ablate.sweep.tuning): it trains and validates, never tests, and is no table's row.
KIND_TRIAL = "trial"
#: A tuning trial's tag of its validation value per epoch of its run ({epoch: value}, ablate.jobs.rungs).
VAL_CURVE = "val_curve"
#: A single-modal expert's run (ablate.jobs.experts, SMoE §4.3 stage 1), in the experiment ``experts``.
KIND_EXPERT = "expert"
#: The metric a job logs once its data module is set up: the bad frames it left out (``data.on_bad_frame=skip``).
SKIPPED_FRAMES = "data/skipped_frames"
#: A run's artifact of its test metric's counts per test frame (ablate.tables.frames).
FRAME_COUNTS = "frames/test_counts.csv"
#: A run's artifact of its AP metric's scored detections per test frame (ablate.metrics.accumulate).
FRAME_DETECTIONS = "frames/test_detections.csv.gz"
#: Every experiment's kind (model training, not GenAI). MLflow 3.17's UI still opens on its GenAI view until the
#: browser's "Model training" switch is set (a per-browser setting, default GenAI), so a sweep also prints
#: :func:`runs_link`, which sets it.
EXPERIMENT_KIND = {"mlflow.experimentKind": "custom_model_development"}


class Tracker:
    """The store: a retrying wrapper over :class:`MlflowClient`, the only one in the project, for the run lifecycle of
    a table and for reading runs back.

    ``uri`` is used as given (:func:`~ablate.store.uris.tracking_uri` resolves the configured one);
    ``artifact_root`` is turned into :attr:`artifact_location` by :func:`~ablate.store.uris.artifact_location`,
    relative to ``base`` (the launch directory). Every call waits up to ``outage_s`` seconds
    (``logger.outage_s``) for a store that does not answer (:func:`retry`); against a server, MLflow's own HTTP
    retries are made short (:func:`~ablate.store.outage.short_http_retries`). A Tracker pickles as its URI,
    artifact location and budget, so that Lightning's ``ddp_spawn`` can hand the run's logger to its processes,
    each opening its own client.
    """

    def __init__(
        self, uri: str, artifact_root: str | None = None, outage_s: float = DEFAULT_OUTAGE_S, base: Path | None = None
    ) -> None:
        self.uri = uri
        self.outage_s = float(outage_s)
        self.artifact_location = artifact_location(uri, artifact_root, base)
        if (db := db_path(uri)) is not None:  # many jobs of one machine on one file (ablate.store.sqlite)
            if needs_schema(db):  # MLflow creates the schema on first use: one process at a time
                with file_lock(db.with_name(db.name + "-lock")):
                    self._client = MlflowClient(tracking_uri=uri)
                    self.call(self._client.search_experiments, max_results=1)
            else:
                self._client = MlflowClient(tracking_uri=uri)
            write_ahead(db)
        else:
            self._client = MlflowClient(tracking_uri=uri)
            if is_server(uri):  # credentials the server refuses stop here, with the server's name
                short_http_retries()
                try:
                    self.call(self._client.search_experiments, max_results=1)
                except AccessDenied as err:
                    raise AccessDenied(err.code, uri) from None

    def __getstate__(self) -> dict[str, Any]:
        return {"uri": self.uri, "artifact_location": self.artifact_location, "outage_s": self.outage_s}

    def __setstate__(self, state: dict[str, Any]) -> None:
        Tracker.__init__(self, state["uri"], state["artifact_location"], state.get("outage_s", DEFAULT_OUTAGE_S))

    @classmethod
    def from_config(cls, cfg: DictConfig, context: SweepContext | None = None) -> Tracker:
        """The store of ``cfg`` (``logger.tracking_uri``, ``MLFLOW_TRACKING_URI`` first), relative paths against
        ``context``'s launch directory; inside a multirun (``context.store``), the store its sweep recorded, where
        its parent run is, whatever this process's environment says. The outage budget is ``logger.outage_s``."""
        lg = cfg.get("logger") or {}
        budget = float(lg.get("outage_s", DEFAULT_OUTAGE_S))
        if context is not None and context.store is not None:
            return cls(str(context.store["uri"]), context.store["artifact_location"], budget)
        base = context.launch_dir if context is not None else None
        root = lg.get("artifact_root")
        return cls(tracking_uri(lg, base), None if root is None else str(root), budget, base)

    def call(self, fn: Callable[..., T], *args: Any, outage_s: float | None = None, **kwargs: Any) -> T:
        """``fn(*args, **kwargs)`` through :func:`retry`, waiting up to ``outage_s`` (default :attr:`outage_s`)
        for a store that does not answer, which is then named in :class:`ServerUnreachable`."""
        budget = self.outage_s if outage_s is None else outage_s
        return retry(fn, *args, outage_s=budget, server=self.uri, **kwargs)

    def experiment_id(self, name: str) -> str:
        """The id of experiment ``name``, created if missing (tagged :data:`EXPERIMENT_KIND`, with its artifacts
        under :attr:`artifact_location`, or the server's when that is None); safe when another process creates it
        too. An existing experiment without the tag gets it."""
        exp = self.call(self._client.get_experiment_by_name, name)
        if exp is not None:
            if any(exp.tags.get(k) != v for k, v in EXPERIMENT_KIND.items()):
                for key, value in EXPERIMENT_KIND.items():
                    self.call(self._client.set_experiment_tag, exp.experiment_id, key, value)
            return exp.experiment_id
        try:
            location = None if self.artifact_location is None else f"{self.artifact_location.rstrip('/')}/{name}"
            return self.call(self._client.create_experiment, name, artifact_location=location, tags=EXPERIMENT_KIND)
        except MlflowException:
            exp = self.call(self._client.get_experiment_by_name, name)
            if exp is None:
                raise
            return exp.experiment_id

    def runs(self, experiment_id: str, filter_string: str = "") -> list[Run]:
        """All runs of an experiment matching ``filter_string``, every page."""
        out: list[Run] = []
        token = None
        while True:
            page = self.call(
                self._client.search_runs, [experiment_id], filter_string, max_results=1000, page_token=token
            )
            out.extend(page)
            token = page.token
            if not token:
                return out

    def find_experiment(self, name: str) -> str | None:
        """The id of experiment ``name``, or None where the store has none (nothing is created)."""
        exp = self.call(self._client.get_experiment_by_name, name)
        return None if exp is None else str(exp.experiment_id)

    def experiment_tags(self, experiment_id: str) -> dict[str, str]:
        """The tags of an experiment."""
        return dict(self.call(self._client.get_experiment, experiment_id).tags)

    def get_run(self, run_id: str) -> Run:
        """One run: its info, params, final metrics and tags."""
        return self.call(self._client.get_run, run_id)

    def metric_history(self, run_id: str, key: str) -> list[Metric]:
        """Every logged value of metric ``key`` of a run, step by step."""
        return list(self.call(self._client.get_metric_history, run_id, key))

    def list_artifacts(self, run_id: str, path: str | None = None) -> list[str]:
        """The paths of a run's artifacts under ``path`` (its top level by default)."""
        return [a.path for a in self.call(self._client.list_artifacts, run_id, path)]

    def download_artifact(self, run_id: str, path: str, dst: str | Path) -> Path:
        """Download a run's artifact ``path`` into the folder ``dst``; the local file. Without MLflow's progress bar
        (``MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR``, unless set): a table reads one small file per run, whose bars
        were most of a sweep's closing output."""
        os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")
        return Path(self.call(self._client.download_artifacts, run_id, path, str(dst)))

    def finished_run(self, experiment_id: str, chash: str) -> Run | None:
        """A FINISHED job run with this config hash, or None."""
        runs = self.runs(experiment_id, f"tags.config_hash = '{chash}' and attributes.status = 'FINISHED'")
        return runs[0] if runs else None

    def finished_elsewhere(self, chash: str, kind: str = KIND_JOB, tag: str = "config_hash") -> Run | None:
        """A FINISHED run of ``kind`` whose tag ``tag`` is this config hash, in any experiment, or None: a job run of
        the same config (tables share rows: ChiNet Tables II-V all hold the ChiNet row), or an expert's tuning
        trial that trained the expert of this hash (``kind=trial``, ``tag=expert_hash``)."""
        ids = [e.experiment_id for e in self.call(self._client.search_experiments)]
        runs = (
            self.call(
                self._client.search_runs,
                ids,
                f"tags.{tag} = '{chash}' and attributes.status = 'FINISHED' and tags.kind = '{kind}'",
                max_results=1,
            )
            if ids
            else []
        )
        return runs[0] if runs else None

    def copy_run(self, source: Run, experiment_id: str, tags: dict[str, str], drop: tuple[str, ...] = ()) -> str:
        """A FINISHED copy of ``source`` (params, final metrics, tags but ``drop``) in ``experiment_id``, tagged
        ``reused_from``; artifacts stay with the source run."""
        own = ("sweep_id", "job_started", *drop)  # the copy belongs to its own sweep and starts when it is made
        keep = {k: v for k, v in source.data.tags.items() if not k.startswith("mlflow.") and k not in own}
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
            self.call(self._client.set_terminated, run.info.run_id, "KILLED")
        return len(stale)

    def start(self, experiment_id: str, name: str, tags: dict[str, str]) -> str:
        run = self.call(self._client.create_run, experiment_id, tags=tags, run_name=name)
        return run.info.run_id

    def start_at(self, experiment_id: str, name: str, tags: dict[str, str], start: int) -> str:
        """A RUNNING run that started at ``start`` (ms): a job made elsewhere, loaded from its record."""
        run = self.call(self._client.create_run, experiment_id, start_time=start, tags=tags, run_name=name)
        return str(run.info.run_id)

    def end_at(self, run_id: str, status: str, end: int) -> None:
        """End a run with ``status`` at ``end`` (ms)."""
        self.call(self._client.set_terminated, run_id, status, end_time=end)

    def import_run(
        self, experiment_id: str, name: str, tags: dict[str, str], metrics: dict[str, float], start: int, end: int
    ) -> str:
        """A FINISHED run made elsewhere (a published record), with its own start and end (ms) and final metrics."""
        run = self.call(self._client.create_run, experiment_id, start_time=start, tags=tags, run_name=name)
        self.log_rows(run.info.run_id, [(k, float(v), end, 0) for k, v in sorted(metrics.items())])
        self.call(self._client.set_terminated, run.info.run_id, "FINISHED", end_time=end)
        return str(run.info.run_id)

    def end(self, run_id: str, status: str) -> None:
        self.call(self._client.set_terminated, run_id, status)

    def log_params(self, run_id: str, params: dict[str, str]) -> None:
        items = [Param(k[:250], v[:6000]) for k, v in sorted(params.items())]
        for i in range(0, len(items), 100):
            self.call(self._client.log_batch, run_id, params=items[i : i + 100])

    def log_metrics(self, run_id: str, metrics: dict[str, float], step: int = 0) -> None:
        self.log_rows(run_id, rows(metrics, step))

    def log_rows(self, run_id: str, items: list[Row], outage_s: float | None = None) -> None:
        """Log metric rows (key, value, timestamp, step) as they are: a batch sent twice adds no row twice."""
        metrics = [Metric(k, v, t, s) for k, v, t, s in items]
        for i in range(0, len(metrics), 500):
            self.call(self._client.log_batch, run_id, metrics=metrics[i : i + 500], outage_s=outage_s)

    def send(self, batch: Batch, outage_s: float | None = None) -> None:
        """Deliver an outbox batch: its metric rows, its tags, then its status."""
        self.log_rows(batch.run, batch.metrics, outage_s)
        if batch.tags:
            tags = [RunTag(k, str(v)) for k, v in batch.tags.items()]
            self.call(self._client.log_batch, batch.run, tags=tags, outage_s=outage_s)
        if batch.status:
            self.call(self._client.set_terminated, batch.run, batch.status, outage_s=outage_s)

    def set_tags(self, run_id: str, tags: dict[str, str]) -> None:
        self.call(self._client.log_batch, run_id, tags=[RunTag(k, str(v)) for k, v in tags.items()])

    def artifact_uri(self, run_id: str) -> str:
        """Where ``run_id`` keeps its artifacts."""
        return str(self.call(self._client.get_run, run_id).info.artifact_uri)

    def log_artifact(self, run_id: str, path: str | Path, artifact_path: str | None = None) -> None:
        """Upload the file ``path``; a full disk is one :class:`DiskFull` naming it and the run's artifact store."""
        with naming_full_disk(f"the artifact {path}", lambda: self.artifact_uri(run_id)):
            self.call(self._client.log_artifact, run_id, str(path), artifact_path)

    def log_figure(self, run_id: str, figure: Figure, name: str) -> None:
        with naming_full_disk(f"the artifact {name}", lambda: self.artifact_uri(run_id)):
            self.call(self._client.log_figure, run_id, figure, name)

    def log_text(self, run_id: str, text: str, name: str) -> None:
        with naming_full_disk(f"the artifact {name}", lambda: self.artifact_uri(run_id)):
            self.call(self._client.log_text, run_id, text, name)

    def log_dataset(self, run_id: str, name: str, digest: str, source: str, frames: dict[str, int]) -> None:
        """Record the data a run trained and was tested on as an MLflow dataset input: its ``name``, a content
        ``digest``, where it lies (``source``) and its frames per split (the dataset's profile)."""
        dataset = Dataset(name, digest, "local", json.dumps({"uri": source}), None, json.dumps({"frames": frames}))
        context = InputTag("mlflow.data.context", "training")
        inputs = [DatasetInput(dataset, tags=[context])]
        try:
            self.call(self._client.log_inputs, run_id, datasets=inputs)
        except Exception as err:
            if not inserted_beside(err):
                raise
            # two jobs of a sweep recorded the same new dataset at once: MLflow's store looks it up, finds none, and
            # the second insert breaks the unique key; now it exists, and the run is linked to it
            self.call(self._client.log_inputs, run_id, datasets=inputs)

    @contextmanager
    def system_metrics(self, run_id: str, on: bool, interval_s: float = 10.0) -> Iterator[None]:
        """Record the machine's CPU, memory, disk and network (GPU where present) as ``system/*`` metrics of
        ``run_id`` every ``interval_s`` seconds while the block runs, where ``on`` or MLflow's own switch
        (``MLFLOW_ENABLE_SYSTEM_METRICS_LOGGING=true``) says so (MLflow's ``SystemMetricsMonitor``; psutil)."""
        switched = os.environ.get("MLFLOW_ENABLE_SYSTEM_METRICS_LOGGING", "").lower() in ("true", "1")
        if not (on or switched):
            yield
            return
        from mlflow.system_metrics.system_metrics_monitor import SystemMetricsMonitor

        monitor = SystemMetricsMonitor(run_id, sampling_interval=interval_s, tracking_uri=self.uri)
        monitor.start()
        try:
            yield
        finally:
            monitor.finish()

    def share_table_view(self, experiment_id: str, metrics: list[str]) -> str:
        """Store the runs table view of a table's experiment, with each run's row and the table's ``metrics`` as columns and the
        newest runs first, under :data:`SHARED_VIEW_KEY`, and return its address in the MLflow UI
        (:func:`runs_link`). A sweep's jobs stay folded under its parent run until its [+] is clicked: the UI does
        not take which runs are expanded from a shared view."""
        state = {
            "selectedColumns": ["tags.`row`", *(f"metrics.`{m}`" for m in metrics)],  # each run's row, its metrics
            "orderByKey": "attributes.start_time",
            "orderByAsc": False,
        }
        self.call(self._client.set_experiment_tag, experiment_id, SHARED_VIEW_TAG + SHARED_VIEW_KEY, json.dumps(state))
        return runs_link(self.uri, experiment_id)


def rows(metrics: dict[str, float], step: int = 0) -> list[Row]:
    """``metrics`` at ``step`` as metric rows stamped now (ms), sorted by key."""
    now = int(time.time() * 1000)
    return [(k, float(v), now, int(step)) for k, v in sorted(metrics.items())]


def inserted_beside(err: Exception) -> bool:
    """Whether ``err`` is a unique key broken by another writer's insert of the same row (SQLite's and PostgreSQL's
    words for it, as SQLAlchemy and MLflow pass them on)."""
    text = str(err)
    return "UNIQUE constraint failed" in text or "duplicate key value violates unique constraint" in text
