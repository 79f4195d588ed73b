"""Training and testing one job with Lightning: its run's metrics, checkpoint and figures.

:func:`fit_and_test` is read top to bottom: the experts a two-stage job starts from (SMoE §4.3), the data, model and
task built from the job's config under its seed, a Lightning ``Trainer`` logging into the job's run
(:class:`~ablate.store.RunLogger`, through the job's outbox while the server does not answer), the fit (resumed from
the job's checkpoint where there is one, :func:`ablate.jobs.checkpoint.resume_point`), and the test of the best
checkpoint. The order of these steps is the order of the seeded random draws: it is part of every result.
"""

from __future__ import annotations

import hashlib
import json
import logging
import shutil
import tempfile
import warnings
from pathlib import Path
from typing import Any, cast

import lightning as L
import pandas as pd
import torch
from hydra.utils import instantiate
from lightning.pytorch.callbacks import Callback, LearningRateMonitor, ModelCheckpoint
from lightning.pytorch.utilities import rank_zero_only
from omegaconf import DictConfig, OmegaConf

from ablate import hardware
from ablate.jobs.checkpoint import AtomicCheckpointIO, resume_point
from ablate.jobs.experts import attach as attach_experts
from ablate.jobs.experts import feature_cache
from ablate.jobs.generators import GlobalGenerators
from ablate.jobs.preempt import STOP, SaveOnStop, Stopped
from ablate.jobs.progress_lines import ProgressLines, progress_bar
from ablate.jobs.rung_callbacks import StopAtRung, ValCurve
from ablate.jobs.rungs import stop_epoch
from ablate.jobs.spec import JobSpec
from ablate.jobs.trace import Trace
from ablate.store import FRAME_COUNTS, FRAME_DETECTIONS, KIND_TRIAL, SKIPPED_FRAMES, RunLogger, Tracker

log = logging.getLogger(__name__)
# torchmetrics warns when a metric is computed before its first update: a validation epoch whose batches held no
# object of a class (the tiny smoke scale), where the metric is defined (ablate.metrics) and nothing is to be done
warnings.filterwarnings("ignore", ".*compute.*method of metric .* was called before the .*update.* method.*")


def fit_and_test(
    spec: JobSpec, tracker: Tracker, run_id: str, experts: dict[str, tuple[Path, str]]
) -> dict[str, float]:
    """Train with Lightning, test the best checkpoint, and log metrics, checkpoint and figures to ``run_id``.
    Metrics logged while the tracking server does not answer wait in the job's outbox, and are all delivered before
    the test's results are logged.

    With ``experts`` set (SMoE §4.3), a fused model first gets its frozen single-modal experts (``experts``:
    {modality: (best checkpoint, run id)}, trained before the job's run started, :func:`ablate.jobs.job.prepare_experts`;
    their features per frame are computed once and cached for the fit with
    ``experts.cache_features``), and a single-modal job *is* the expert: it is tested from the expert's checkpoint,
    never trained twice.
    """
    cfg = spec.cfg
    if cfg.trainer.get("threads"):
        torch.set_num_threads(int(cfg.trainer.threads))
    L.seed_everything(cfg.seed, workers=True)
    datamodule = instantiate(cfg.data)
    model = instantiate(cfg.model)
    task = instantiate(cfg.task, model=model)
    checkpoint = ModelCheckpoint(
        dirpath=spec.ckpt_dir, filename="best", monitor=task.monitor, mode="max", save_last=True, save_top_k=1
    )
    on_stop = SaveOnStop(spec.ckpt_dir / "last.ckpt")
    logger = RunLogger(tracker, run_id, spec.outbox)
    rate = LearningRateMonitor(logging_interval="step")  # the learning rate per step, as a metric of the run
    callbacks: list[Callback] = [checkpoint, on_stop, DataCount(logger), rate, GlobalGenerators()]  # exact resumes
    curve = ValCurve(task.monitor)  # a tuning trial's validation value per epoch (ablate.sweep.halving replays it)
    if spec.kind == KIND_TRIAL:
        callbacks.append(curve)
    if (every := OmegaConf.select(cfg, "trace.every")) is not None:  # gates and gradients over training
        callbacks.append(Trace(every))
    if (epoch := stop_epoch(cfg)) is not None:  # a trial at a rung of successive halving stops there
        callbacks.append(StopAtRung(epoch))
    trainer = build_trainer(cfg, logger, callbacks, spec.ckpt_dir)
    best = attach_experts(cfg, model, experts, tracker, run_id) if cfg.get("experts") else None
    prepare_model(cfg, model)
    if best is None:
        fit(spec, tracker, run_id, trainer, task, datamodule, on_stop)
        best = checkpoint.best_model_path or None
    if spec.kind == KIND_TRIAL:  # a tuning trial: validation only, never the test split
        tracker.set_tags(run_id, curve.tag())
        return validated(tracker, run_id, checkpoint, task, trainer, logger)
    return test(spec, tracker, run_id, trainer, task, datamodule, best, logger)


def validated(
    tracker: Tracker, run_id: str, checkpoint: ModelCheckpoint, task: Any, trainer: L.Trainer, logger: RunLogger
) -> dict[str, float]:
    """A tuning trial's objective (ablate.sweep.tuning): the best value of the task's validation monitor over the
    epochs, logged as ``val_best``; NaN where no validation ran."""
    logger.deliver()
    score = checkpoint.best_model_score
    metrics = {"val_best": float(score) if score is not None else float("nan")}
    tracker.log_metrics(run_id, metrics, step=trainer.global_step)
    return metrics


def build_trainer(cfg: DictConfig, logger: RunLogger, callbacks: list[Callback], ckpt_dir: Path) -> L.Trainer:
    """The Lightning ``Trainer`` of ``cfg.trainer`` (but the options :mod:`ablate.hardware` reads), writing its
    checkpoints atomically (:class:`~ablate.jobs.checkpoint.AtomicCheckpointIO`); its progress bar only on a
    terminal (``enable_progress_bar: auto``), progress lines elsewhere (:mod:`ablate.jobs.progress_lines`)."""
    trainer = cast("dict[str, Any]", OmegaConf.to_container(cfg.trainer, resolve=True))
    options = {k: v for k, v in trainer.items() if k not in hardware.OPTIONS}
    options["enable_progress_bar"] = progress_bar(options.get("enable_progress_bar", "auto"))
    if not options["enable_progress_bar"]:  # not a terminal: a line a person can read, every 30 s at most
        callbacks = [*callbacks, ProgressLines()]
    return instantiate(
        options, logger=logger, callbacks=callbacks, plugins=[AtomicCheckpointIO()], default_root_dir=str(ckpt_dir)
    )


def prepare_model(cfg: DictConfig, model: torch.nn.Module) -> None:
    """The model's memory format and compilation (``trainer.channels_last``, ``trainer.compile``), after the
    experts' weights are in; compiled in place, so that the state dict, and the checkpoints, keep their keys."""
    if cfg.trainer.get("channels_last"):
        model.to(memory_format=torch.channels_last)
    if cfg.trainer.get("compile"):
        backend = cfg.trainer.compile
        model.compile(**({"backend": backend} if isinstance(backend, str) else {}))


def fit(
    spec: JobSpec,
    tracker: Tracker,
    run_id: str,
    trainer: L.Trainer,
    task: Any,
    datamodule: Any,
    on_stop: SaveOnStop,
) -> None:
    """Fit the task, resumed from the job's last (else best) checkpoint where one loads; a forced rerun trains
    afresh. A stop saves a checkpoint first (:class:`~ablate.jobs.preempt.SaveOnStop`), named in the
    :class:`~ablate.jobs.preempt.Stopped` it raises."""
    if spec.cfg.force and spec.ckpt_dir.exists():
        shutil.rmtree(spec.ckpt_dir)
    start = resume_point(spec.ckpt_dir)
    if start.path is not None:
        log.info("Resuming from %s (step %d, epoch %d)", start.path, start.step, start.epoch)
    tracker.set_tags(run_id, start.tags)
    task.feature_cache = feature_cache(spec.cfg, task.model)
    if torch.cuda.is_available():  # a sweep's worker process runs job after job: each job's peak is its own
        torch.cuda.reset_peak_memory_stats()
    try:
        with STOP.training(trainer):
            trainer.fit(task, datamodule=datamodule, ckpt_path=str(start.path) if start.path else None)
    except Stopped as stop:
        if on_stop.saved_step is not None:
            stop.checkpoint = (on_stop.path, on_stop.saved_step)
        raise
    if task.feature_cache is not None:
        cache = task.feature_cache
        log.info("Expert feature cache: %d frames, %.0f MiB", len(cache.frames), cache.nbytes / 2**20)
        task.feature_cache = None  # testing runs the whole model, whatever its data


def test(
    spec: JobSpec,
    tracker: Tracker,
    run_id: str,
    trainer: L.Trainer,
    task: Any,
    datamodule: Any,
    best: str | None,
    logger: RunLogger,
) -> dict[str, float]:
    """Test ``best`` and log the test metrics (after what waits in the outbox), the model's size, where it ran, its
    figures and its checkpoint; the test metrics."""
    with STOP.training(trainer):
        results = trainer.test(task, datamodule=datamodule, ckpt_path=best, verbose=False)[0]
    logger.deliver()  # what waits in the outbox first, waiting for the server up to logger.outage_s
    metrics = {k.split("/", 1)[-1]: float(v) for k, v in results.items() if k.startswith("test/")}
    metrics["params_m"] = sum(p.numel() for p in task.model.parameters()) / 1e6
    tracker.log_metrics(run_id, metrics, step=trainer.global_step)
    device = trainer.strategy.root_device  # the model's parameters are back on the CPU once the test ends
    tracker.set_tags(run_id, {"device": str(device), "threads_used": str(torch.get_num_threads())})
    if memory := gpu_memory(device):
        tracker.log_metrics(run_id, memory, step=trainer.global_step)
    tracker.set_tags(run_id, {"evaluator": task.evaluator} if getattr(task, "evaluator", None) else {})
    # the figures' forward pass where the job ran, not on one CPU thread: ChiNet at the paper's size takes 35 s a
    # frame there, and drew its 4 frames for most of a GPU job's 95 s test
    if spec.cfg.logger.get("log_figures", True):
        task.to(device)
        figures = task.figures(next(iter(datamodule.test_dataloader())))
        import matplotlib.pyplot as plt  # after the tasks' figure modules, which choose the Agg backend

        for name, figure in figures.items():
            tracker.log_figure(run_id, figure, name)
            plt.close(figure)  # pyplot keeps every figure it made: the jobs of one process would pile them up
    log_frame_counts(tracker, run_id, getattr(task, "frame_counts", []))
    log_frame_detections(tracker, run_id, getattr(task, "frame_detections", []))
    if best and spec.cfg.logger.get("log_checkpoint", True) and Path(best).resolve().parent == spec.ckpt_dir.resolve():
        tracker.log_artifact(run_id, best, "checkpoints")
    return metrics


def gpu_memory(device: torch.device) -> dict[str, float]:
    """Where the job ran on a CUDA device, the peak memory its tensors took there since its fit began, allocated and
    reserved by torch's caching allocator, in GiB (metrics ``gpu_peak_alloc_gib`` and ``gpu_peak_reserved_gib``);
    on the CPU, none."""
    if device.type != "cuda":
        return {}
    gib = 2**30
    return {
        "gpu_peak_alloc_gib": torch.cuda.max_memory_allocated(device) / gib,
        "gpu_peak_reserved_gib": torch.cuda.max_memory_reserved(device) / gib,
    }


def log_frame_counts(tracker: Tracker, run_id: str, counts: list[dict[str, Any]]) -> None:
    """The test metric's counts per test frame (:attr:`ablate.tasks.base.FusionTask.frame_counts`) as the run's
    artifact :data:`ablate.store.FRAME_COUNTS`, where the task keeps them: what a table resamples the test set
    from (:mod:`ablate.tables.frames`)."""
    if not counts:
        return
    width = len(counts[0]["counts"])
    rows = [[c["frame"], c["condition"], *c["counts"]] for c in counts]
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / Path(FRAME_COUNTS).name
        pd.DataFrame(rows, columns=["frame", "condition", *(f"c{i}" for i in range(width))]).to_csv(path, index=False)
        tracker.log_artifact(run_id, path, str(Path(FRAME_COUNTS).parent))


#: The columns of :data:`ablate.store.FRAME_DETECTIONS`: the frame, its condition, the metric, then the rows of
#: :mod:`ablate.metrics.accumulate`.
DETECTION_COLUMNS = ("frame", "condition", "metric", "index", "kind", "cls", "level", "score", "a", "b")


def log_frame_detections(tracker: Tracker, run_id: str, rows: list[dict[str, Any]]) -> None:
    """An AP metric's scored detections per test frame (:attr:`ablate.tasks.base.FusionTask.frame_detections`) as
    the run's artifact :data:`ablate.store.FRAME_DETECTIONS`, where the task keeps them: what a table resamples the
    test set of an AP task from (:mod:`ablate.tables.twolevel`)."""
    if not rows:
        return
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / Path(FRAME_DETECTIONS).name
        frame = pd.DataFrame([[r.get(c) for c in DETECTION_COLUMNS] for r in rows], columns=list(DETECTION_COLUMNS))
        frame.to_csv(path, index=False, compression={"method": "gzip", "mtime": 0})
        tracker.log_artifact(run_id, path, str(Path(FRAME_DETECTIONS).parent))


class DataCount(Callback):
    """Once the data module is set up, log how many bad frames it left out (``data.on_bad_frame=skip``) as the
    run's metric ``data/skipped_frames``, through the run's logger (so into its outbox while the server does not
    answer), and the data itself as the run's dataset input (:func:`log_dataset`)."""

    def __init__(self, logger: RunLogger) -> None:
        self.logger, self.logged = logger, False

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        count = getattr(trainer.datamodule, "skipped_frames", None)
        if count is not None and not self.logged:
            self.logger.log_metrics({SKIPPED_FRAMES: float(count)})
            log_dataset(self.logger, trainer.datamodule)
            self.logged = True


@rank_zero_only
def log_dataset(logger: RunLogger, datamodule: Any) -> None:
    """The run's dataset input: the data folder's name (``synth-<hash of the generator's parameters>`` for the
    generated data), a digest of it and of the frames of each split, its path and the frames per split. A
    convenience: where the store does not take it, one warning."""
    split_dir = Path(datamodule.split_dir())
    frames = {name: list(ds.frames) for name, ds in datamodule.datasets.items()}
    digest = hashlib.sha1(json.dumps([split_dir.name, frames], sort_keys=True).encode()).hexdigest()[:12]
    counts = {name: len(ids) for name, ids in frames.items()}
    try:
        logger.tracker.log_dataset(logger.run_id, split_dir.name, digest, str(split_dir.resolve()), counts)
    except Exception as err:
        log.warning("Could not record the run's dataset: %s", err)
