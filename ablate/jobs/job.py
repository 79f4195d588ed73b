"""One job: one resolved config -> train, test, and one MLflow run.

A job whose config hash already has a FINISHED run is skipped unless ``force=true``. A job that crashed or was
killed is recorded FAILED or KILLED and runs again next time, resuming from its last checkpoint
(``checkpoints/<table>/<config hash>/last.ckpt``) when one exists and loads, else from ``best.ckpt``, else from
scratch (:mod:`ablate.jobs.checkpoint`, which also writes every checkpoint atomically). SIGTERM or SIGINT stops a job
after the batch in progress with its checkpoint saved, its run KILLED with the reason, and exit status 143 (130)
(:mod:`ablate.jobs.preempt`). A full disk fails the job with one message naming the file.

A tracking server that does not answer never stops training: the run's metrics wait in the job's outbox
(``outbox.jsonl`` beside its checkpoints, :mod:`ablate.store.outbox`) and are delivered once it answers. Where the
job needs the server (to start, to upload, to end its run) it waits up to ``logger.outage_s``; past that it fails
with one message naming the server, its checkpoint and outbox kept, and the same command again delivers the outbox
(the earlier run then ends FAILED) and resumes from the checkpoint.

A job runs in the launch directory, whichever process runs it, so that its relative paths (``checkpoints/``,
``data/``, the SQLite store, the artifact root) are the ones the sweep was launched with.
"""

from __future__ import annotations

import json
import logging
import multiprocessing
import os
import re
import shutil
import socket
import sys
import time
import traceback
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import lightning as L
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.utils import instantiate
from lightning.pytorch.callbacks import Callback, ModelCheckpoint
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException, ValidationError

from ablate import hardware
from ablate.jobs import fingerprint
from ablate.jobs.checkpoint import AtomicCheckpointIO, resume_point
from ablate.jobs.experts import attach as attach_experts
from ablate.jobs.experts import feature_cache
from ablate.jobs.experts import prepare as prepare_experts
from ablate.jobs.preempt import SETTLE_S, STOP, SaveOnStop, Stopped, exit_status, loky_worker
from ablate.jobs.record import deliver_earlier, kept_for_later, record_end, unreachable
from ablate.store import (
    KIND_JOB,
    SKIPPED_FRAMES,
    AccessDenied,
    Outbox,
    RunLogger,
    ServerUnreachable,
    Tracker,
    config_hash,
    flatten,
    launch_dir,
    parent_run_id,
    provenance_tags,
    record_failure,
    sweep_dir,
    swept_keys,
)
from ablate.store.outbox import FILE as OUTBOX_FILE

log = logging.getLogger(__name__)
warnings.filterwarnings("ignore", ".*does not have many workers.*")
warnings.filterwarnings("ignore", ".*GPU available but not used.*")


class JobFailed(RuntimeError):
    """A job ended in error; its run is recorded FAILED."""


def row_name(cfg: DictConfig) -> str:
    """The table row a job belongs to: the `row` choice; else, in a sweep, the values of the swept keys
    (``fusion=sum``); else the job's own overrides; else ``default``."""
    if not HydraConfig.initialized():
        return "default"
    hc = HydraConfig.get()
    if hc.runtime.choices.get("row"):
        return str(hc.runtime.choices["row"])
    swept = swept_keys()
    skip = ("seed", "scale", "force", "experiment", "hydra", "logger", "trainer.enable_progress_bar")
    own = []
    for override in hc.overrides.task:
        key = override.split("=", 1)[0].lstrip("+~")
        if (key in swept and key != "seed") if swept is not None else not key.startswith(skip):
            own.append(override.lstrip("+~"))
    return " ".join(sorted(own)) or "default"


@dataclass
class Outcome:
    """What a job ended as: FINISHED or SKIPPED, its run, and its checkpoint directory."""

    status: str
    run_id: str
    ckpt_dir: Path


def check_stage(cfg: DictConfig) -> None:
    """Every option of ``stage`` but its name must be one the model's config reads (``${stage.<option>}`` or
    ``${oc.select:stage.<option>,...}``, conf/model/): a misspelt or misplaced option (``+stage.spcae=shpl``, or
    ``stage.space`` on a model without space transforms) raises a ValidationError naming it, instead of the
    model silently taking its default."""
    model = OmegaConf.to_yaml(OmegaConf.to_container(cfg.get("model") or {}, resolve=False))
    reads = sorted(set(re.findall(r"stage\.(\w+)", model)) - {"name"})
    for option in cfg.get("stage") or {}:
        if option != "name" and option not in reads:
            raise ValidationError(
                f"stage.{option}: not an option of model {cfg.model.get('_target_', '?')!r}, "
                f"which reads stage.{{{', '.join(['name', *reads])}}}"
            )


def run(cfg: DictConfig, kind: str = KIND_JOB, row: str | None = None) -> Outcome:
    """Run one job tracked as an MLflow run of ``cfg.table.name``; raise :class:`JobFailed` after recording a
    FAILED run, and re-raise an interrupt after recording KILLED. A config whose stage options no model reads
    fails first (:func:`check_stage`)."""
    check_stage(cfg)
    numerics = hardware.resolve(cfg)  # before the hash: the resolved precision is what the hash holds
    tracker = Tracker.from_config(cfg)
    exp = tracker.experiment_id(cfg.table.name)
    chash = config_hash(cfg)
    row = row or row_name(cfg)
    ckpt_dir = Path("checkpoints") / cfg.table.name / chash
    outbox = Outbox(ckpt_dir / OUTBOX_FILE)
    deliver_earlier(tracker, outbox)
    done = None if cfg.force else tracker.finished_run(exp, chash)
    if done is not None:
        log.info(
            "Skipping %s (seed %s): run %s with config hash %s is FINISHED (force=true reruns it)",
            row,
            cfg.seed,
            done.info.run_id,
            chash,
        )
        return Outcome("SKIPPED", done.info.run_id, ckpt_dir)
    parent = parent_run_id() if kind == KIND_JOB else None
    tags = {
        "kind": kind,
        "table": cfg.table.name,
        "row": row,
        "seed": str(cfg.seed),
        "config_hash": chash,
        **provenance_tags(),
        "scale": cfg.scale.name,
        **hardware.tags(cfg),
    }
    if cfg.table.get("seeds"):  # the race this run belongs to: its table replays that race (ablate.tables.racing)
        tags["race_plan"] = json.dumps(OmegaConf.to_container(cfg.table.seeds, resolve=True), sort_keys=True)
    if parent:
        tags.update({"mlflow.parentRunId": parent, "sweep_id": parent, "job_num": str(HydraConfig.get().job.num)})
    source = None if cfg.force or kind != KIND_JOB else tracker.finished_elsewhere(chash)
    if source is not None:
        run_id = tracker.copy_run(
            source, exp, {k: v for k, v in tags.items() if k not in ("git_commit", "ablate_version", "launch_commit")}
        )
        log.info(
            "Reusing %s (seed %s): the same config finished as run %s of another table; copied as %s",
            row,
            cfg.seed,
            source.info.run_id,
            run_id,
        )
        return Outcome("SKIPPED", run_id, Path("checkpoints") / source.data.tags.get("table", "") / chash)
    if stale := tracker.close_stale(exp, chash):
        log.info("Marked %d stale RUNNING run(s) of config %s as KILLED", stale, chash)
    run_id = tracker.start(exp, f"{row} seed={cfg.seed}", tags)
    log.info("MLflow run %s: %s, seed %s, config %s", run_id, row, cfg.seed, chash)
    log.info("Numerics: %s; %s intra-op thread(s)", numerics, cfg.trainer.get("threads") or "all")
    try:
        tracker.log_params(run_id, flatten(OmegaConf.to_container(cfg, resolve=True)))
        tracker.log_text(run_id, OmegaConf.to_yaml(cfg, resolve=True), "config.yaml")
        record_fingerprint(cfg, tracker, run_id)
        metrics = fit_and_test(cfg, tracker, run_id, ckpt_dir, outbox)
    except Stopped as stop:
        stop.reason = stopped_reason(stop, ckpt_dir)
        record_end(tracker, run_id, "KILLED", {"killed_by": stop.signame, "kill_reason": stop.reason}, outbox=outbox)
        log.warning("%s %s (seed %s) KILLED: %s", kind, row, cfg.seed, stop.reason)
        raise
    except (KeyboardInterrupt, SystemExit) as err:  # Lightning turns Ctrl+C inside fit into sys.exit(1)
        record_end(tracker, run_id, "KILLED", {"killed_by": type(err).__name__}, outbox=outbox)
        raise
    except Exception as err:
        if (down := unreachable(err)) is not None:  # the server is not there to take the end: the outbox keeps it
            message = f"{down}; {kept_for_later(outbox, run_id, ckpt_dir, str(down))}"
        else:
            message = f"{type(err).__name__}: {err}"
            record_end(tracker, run_id, "FAILED", {"error": message[:5000]}, traceback.format_exc(), outbox)
        log.error("%s %s (seed %s) FAILED: %s", kind, row, cfg.seed, message)
        raise JobFailed(message) from err
    tracker.end(run_id, "FINISHED")
    log.info("FINISHED %s seed %s: %s", row, cfg.seed, ", ".join(f"{k}={v:.4g}" for k, v in sorted(metrics.items())))
    return Outcome("FINISHED", run_id, ckpt_dir)


def stopped_reason(stop: Stopped, ckpt_dir: Path) -> str:
    """What a stopped job tells its run and its user: the signal, and where a rerun resumes."""
    saved = stop.checkpoint
    if saved is not None:
        where = f"checkpoint {saved[0]} saved at step {saved[1]}"
    elif (ckpt_dir / "last.ckpt").exists():
        where = f"not training; {ckpt_dir / 'last.ckpt'} is kept"
    else:
        where = "stopped before training"
    return f"stopped by {stop.signame} (preemption or interrupt); {where}; the same command again resumes it"


def record_fingerprint(cfg: DictConfig, tracker: Tracker, run_id: str) -> None:
    """Tag the run with its config's fingerprint (:mod:`ablate.jobs.fingerprint`) and the seconds it took."""
    numbers, seconds = fingerprint.timed(cfg)
    tracker.set_tags(run_id, {fingerprint.TAG: fingerprint.encode(numbers), "fingerprint_s": f"{seconds:.2f}"})
    log.info("Fingerprint in %.1f s", seconds)


def fit_and_test(
    cfg: DictConfig, tracker: Tracker, run_id: str, ckpt_dir: Path, outbox: Outbox | None = None
) -> dict[str, float]:
    """Train with Lightning, test the best checkpoint, and log metrics, checkpoint and figures to ``run_id``.
    Metrics logged while the tracking server does not answer wait in ``outbox``, and are all delivered before the
    test's results are logged.

    With ``experts`` set (SMoE §4.3), a fused model first gets its frozen single-modal experts (whose features
    per frame are computed once and cached for the fit with ``experts.cache_features``), and a single-modal job
    *is* the expert: it is tested from the expert's checkpoint, never trained twice.
    """
    experts = prepare_experts(cfg, run) if cfg.get("experts") else {}
    if cfg.trainer.get("threads"):
        torch.set_num_threads(int(cfg.trainer.threads))
    L.seed_everything(cfg.seed, workers=True)
    datamodule = instantiate(cfg.data)
    model = instantiate(cfg.model)
    task = instantiate(cfg.task, model=model)
    checkpoint = ModelCheckpoint(
        dirpath=ckpt_dir, filename="best", monitor=task.monitor, mode="max", save_last=True, save_top_k=1
    )
    on_stop = SaveOnStop(ckpt_dir / "last.ckpt")
    lightning_options = {
        k: v for k, v in OmegaConf.to_container(cfg.trainer, resolve=True).items() if k not in hardware.OPTIONS
    }
    logger = RunLogger(tracker, run_id, outbox)
    trainer = instantiate(
        lightning_options,
        logger=logger,
        callbacks=[checkpoint, on_stop, DataCount(logger)],
        plugins=[AtomicCheckpointIO()],
        default_root_dir=str(ckpt_dir),
    )
    best = attach_experts(cfg, model, experts, tracker, run_id) if cfg.get("experts") else None
    if cfg.trainer.get("channels_last"):  # after the experts' weights are in
        model.to(memory_format=torch.channels_last)
    if cfg.trainer.get("compile"):  # in place: the state dict, and so the checkpoints, keep their keys
        backend = cfg.trainer.compile
        model.compile(**({"backend": backend} if isinstance(backend, str) else {}))
    if best is None:
        if cfg.force and ckpt_dir.exists():  # a forced rerun trains afresh
            shutil.rmtree(ckpt_dir)
        start = resume_point(ckpt_dir)
        if start.path is not None:
            log.info("Resuming from %s (step %d, epoch %d)", start.path, start.step, start.epoch)
        tracker.set_tags(run_id, start.tags)
        task.feature_cache = feature_cache(cfg, model)
        try:
            with STOP.training(trainer):
                trainer.fit(task, datamodule=datamodule, ckpt_path=str(start.path) if start.path else None)
        except Stopped as stop:
            if on_stop.saved_step is not None:
                stop.checkpoint = (on_stop.path, on_stop.saved_step)
            raise
        if task.feature_cache is not None:
            log.info(
                "Expert feature cache: %d frames, %.0f MiB",
                len(task.feature_cache.frames),
                task.feature_cache.nbytes / 2**20,
            )
            task.feature_cache = None  # testing runs the whole model, whatever its data
        best = checkpoint.best_model_path or None
    with STOP.training(trainer):
        results = trainer.test(task, datamodule=datamodule, ckpt_path=best, verbose=False)[0]
    logger.deliver()  # what waits in the outbox first, waiting for the server up to logger.outage_s
    metrics = {k.split("/", 1)[-1]: float(v) for k, v in results.items() if k.startswith("test/")}
    sample = next(iter(datamodule.test_dataloader()))
    metrics["params_m"] = sum(p.numel() for p in task.model.parameters()) / 1e6
    tracker.log_metrics(run_id, metrics, step=trainer.global_step)
    tracker.set_tags(
        run_id, {"device": str(next(task.model.parameters()).device), "threads_used": str(torch.get_num_threads())}
    )
    tracker.set_tags(run_id, {"evaluator": task.evaluator} if getattr(task, "evaluator", None) else {})
    for method, name in (("figure", "predictions.png"), ("gate_figure", "gates.png")):
        figure = getattr(task, method, lambda _: None)(sample)
        if figure is not None:
            tracker.log_figure(run_id, figure, name)
    if best and cfg.logger.get("log_checkpoint", True) and Path(best).resolve().parent == ckpt_dir.resolve():
        tracker.log_artifact(run_id, best, "checkpoints")
    return metrics


class DataCount(Callback):
    """Once the data module is set up, log how many bad frames it left out (``data.on_bad_frame=skip``) as the
    run's metric ``data/skipped_frames``, through the run's logger (so into its outbox while the server does not
    answer)."""

    def __init__(self, logger: RunLogger) -> None:
        self.logger, self.logged = logger, False

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        count = getattr(trainer.datamodule, "skipped_frames", None)
        if count is not None and not self.logged:
            self.logger.log_metrics({SKIPPED_FRAMES: float(count)})
            self.logged = True


@contextmanager
def in_launch_dir() -> Iterator[Path]:
    """Run the block in the launch directory (:func:`ablate.store.launch_dir`), then go back.

    Workaround for ``hydra/launcher=ray``: a Ray task runs in the directory its cluster was started in, so the
    relative paths of a job (``checkpoints/``, ``data/``, the expert locks, ``mlflow.db``) would land there, beside
    another store. Every other launcher starts its jobs in the launch directory already, where this changes nothing.
    A launch directory missing on this machine is an error: a sweep over several machines needs it on a shared
    filesystem at the same path (submitit and Hydra's sweep directory need that too).
    """
    here, target = Path.cwd(), launch_dir()
    if here == target:
        yield target
        return
    if not target.is_dir():
        raise JobFailed(
            f"the launch directory {target} does not exist on {socket.gethostname()}: run the sweep "
            "from a directory every machine sees at the same path (a shared filesystem)"
        )
    os.chdir(target)
    try:
        yield target
    finally:
        os.chdir(here)


def standard_start_method() -> None:
    """Workaround for a job in a loky worker (``hydra/launcher=parallel``, joblib): loky makes its own start method
    the worker's default, and a process that the job spawns through multiprocessing (DDP, ``trainer=ddp_cpu``)
    then fails at start-up with "cannot find context for 'loky'". Such a job spawns with multiprocessing's own."""
    if multiprocessing.get_start_method(allow_none=True) not in (None, "fork", "spawn", "forkserver"):
        multiprocessing.set_start_method("spawn", force=True)


def main(cfg: DictConfig) -> str:
    """Hydra task function, run in the launch directory. In a multirun a failed job is noted for the end-of-sweep
    summary and the other jobs go on; a failed single run exits with status 1 and one clear line."""
    standard_start_method()
    try:
        with STOP.installed(), in_launch_dir():
            return run(cfg).status
    except Stopped as stop:
        reason = stop.reason
        if loky_worker():  # a sweep's worker goes with its parent, which is stopping too
            # when one loky worker exits, the executor kills the others at once: a sibling still recording its
            # KILLED status would be cut off, so a worker that has recorded its own waits a moment first
            time.sleep(SETTLE_S)
            logging.shutdown()
            os._exit(exit_status(stop.signame))
        print(f"stopped: {reason}", file=sys.stderr)
        raise SystemExit(exit_status(stop.signame)) from None
    # a config that does not resolve, or a server that refuses the credentials or does not answer, fails before any run
    except (JobFailed, OmegaConfBaseException, AccessDenied, ServerUnreachable) as err:
        if sweep_dir() is None:
            print(f"error: {err}", file=sys.stderr)
            raise SystemExit(1) from None
        record_failure(f"{HydraConfig.get().job.num}_{row_name(cfg).replace(' ', '_').replace('/', '-')}", str(err))
        return "FAILED"
