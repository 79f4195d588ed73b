"""One job: one resolved config -> train, test, and one MLflow run.

A job whose config hash already has a FINISHED run is skipped unless ``force=true``, and one that finished in another
table is copied from there (:mod:`ablate.jobs.reuse`); a job's run records its params and tags
(:mod:`ablate.jobs.tags`). A job that crashed or was killed is recorded FAILED or KILLED and runs again next time,
resuming from its last checkpoint (``checkpoints/<table>/<config hash>/last.ckpt``) when one exists and loads, else from
``best.ckpt``, else from scratch (:mod:`ablate.jobs.checkpoint`, which also writes every checkpoint atomically). SIGTERM
or SIGINT stops a job after the batch in progress with its checkpoint saved, its run KILLED with the reason, and exit
status 143 (130) (:mod:`ablate.jobs.preempt`). A full disk fails the job with one message naming the file.

A tracking server that does not answer never stops training: the run's metrics wait in the job's outbox
(``outbox.jsonl`` beside its checkpoints, :mod:`ablate.store.outbox`) and are delivered once it answers. Where the
job needs the server (to start, to upload, to end its run) it waits up to ``logger.outage_s``; past that it fails
with one message naming the server, its checkpoint and outbox kept, and the same command again delivers the outbox
(the earlier run then ends FAILED) and resumes from the checkpoint.

A job runs in the launch directory, whichever process runs it, so that its relative paths (``checkpoints/``,
``data/``, the SQLite store, the artifact root) are the ones the sweep was launched with.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import re
import socket
import sys
import time
import traceback
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException, ValidationError

from ablate.jobs import stage1
from ablate.jobs.preempt import SETTLE_S, STOP, Stopped, exit_status, loky_worker
from ablate.jobs.record import deliver_earlier, kept_for_later, record_end, unreachable
from ablate.jobs.reuse import Outcome, already_done
from ablate.jobs.spec import JobSpec
from ablate.jobs.tags import params_of, run_tags
from ablate.store import AccessDenied, ServerUnreachable, SweepContext, Tracker
from ablate.tasks.quiet import silence

log = logging.getLogger(__name__)
silence()


class JobFailed(RuntimeError):
    """A job ended in error; its run is recorded FAILED."""


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


def run(spec: JobSpec, spent: stage1.StageOne | None = None) -> Outcome:
    """Run one job tracked as an MLflow run of its table; raise :class:`JobFailed` after recording a FAILED run, and
    re-raise an interrupt after recording KILLED. A config whose stage options no model reads fails first
    (:func:`check_stage`). A job whose config hash has a FINISHED run is skipped (``force=true`` reruns it), and one
    that finished in another table is copied from there."""
    check_stage(spec.cfg)
    tracker = Tracker.from_config(spec.cfg, spec.context)
    exp = tracker.experiment_id(spec.table)
    deliver_earlier(tracker, spec.outbox)
    done = already_done(spec, tracker, exp)
    if done is not None:
        return done
    if stale := tracker.close_stale(exp, spec.config_hash):
        log.info("Marked %d stale RUNNING run(s) of config %s as KILLED", stale, spec.config_hash)
    began = str(int(time.time() * 1000))  # the job's own start, before the experts it trains or waits for
    experts = prepare_experts(spec, tracker, exp, spent)  # before the job's run: no RUNNING run while it waits for one
    run_id = tracker.start(exp, f"{spec.row} seed={spec.seed}", run_tags(spec) | {"job_started": began})
    log.info("MLflow run %s: %s, seed %s, config %s", run_id, spec.row, spec.seed, spec.config_hash)
    log.info("Numerics: %s; %s intra-op thread(s)", spec.numerics, spec.cfg.trainer.get("threads") or "all")
    metrics = train(spec, tracker, run_id, experts)
    attach_logs(spec, tracker, run_id)
    tracker.end(run_id, "FINISHED")
    described = ", ".join(f"{k}={v:.4g}" for k, v in sorted(metrics.items()))
    log.info("FINISHED %s seed %s: %s", spec.row, spec.seed, described)
    return Outcome("FINISHED", run_id, spec.ckpt_dir)


def prepare_experts(
    spec: JobSpec, tracker: Tracker, exp: str, spent: stage1.StageOne | None = None
) -> dict[str, tuple[Path, str]]:
    """Stage 1 (SMoE §4.3): the experts the job starts from, trained first where missing, each as a job of its own
    (:func:`ablate.jobs.experts.prepare`), before the job's own run starts. An expert that fails fails the job: its
    run is recorded FAILED, naming the expert. What it takes is added to ``spent`` (:mod:`ablate.jobs.stage1`)."""
    if not spec.cfg.get("experts"):
        return {}
    from ablate.jobs.experts import prepare  # torch: imported once a job trains

    began = time.monotonic()

    def timed(ecfg: DictConfig, kind: str, row: str) -> Outcome:  # each expert trained now timed for the ETA
        start = time.monotonic()
        outcome = run(JobSpec.of(ecfg, spec.context, kind, row))
        if outcome.status == "FINISHED" and spent is not None:
            spent.trained[str(ecfg.stage.modality)] = time.monotonic() - start
        return outcome

    try:
        return prepare(spec.experts_cfg, timed)
    except JobFailed as err:
        run_id = tracker.start(exp, f"{spec.row} seed={spec.seed}", run_tags(spec))
        message = f"an expert failed: {err}"
        record_end(tracker, run_id, "FAILED", {"error": message[:5000]}, outbox=spec.outbox)
        log.error("%s (seed %s) FAILED: %s", named(spec), spec.seed, message)
        raise JobFailed(message) from err
    finally:
        if spent is not None:
            spent.seconds += time.monotonic() - began


def train(spec: JobSpec, tracker: Tracker, run_id: str, experts: dict[str, tuple[Path, str]]) -> dict[str, float]:
    """Record the job's params, config and fingerprint, then train and test it (:func:`ablate.jobs.train.fit_and_test`);
    an interrupt ends the run KILLED, an error FAILED (or waits in the outbox where the server is down)."""
    from ablate.jobs.train import fit_and_test  # torch and Lightning: imported once a job trains

    cfg, outbox = spec.cfg, spec.outbox
    try:
        tracker.log_params(run_id, params_of(cfg))
        tracker.log_text(run_id, OmegaConf.to_yaml(cfg, resolve=True), "config.yaml")
        record_fingerprint(cfg, tracker, run_id)
        with tracker.system_metrics(run_id, bool(cfg.logger.get("system_metrics"))):
            return fit_and_test(spec, tracker, run_id, experts)
    except Stopped as stop:
        stop.reason = stopped_reason(stop, spec.ckpt_dir)
        record_end(tracker, run_id, "KILLED", {"killed_by": stop.signame, "kill_reason": stop.reason}, outbox=outbox)
        log.warning("%s (seed %s) KILLED: %s", named(spec), spec.seed, stop.reason)
        raise
    except (KeyboardInterrupt, SystemExit) as err:  # Lightning turns Ctrl+C inside fit into sys.exit(1)
        record_end(tracker, run_id, "KILLED", {"killed_by": type(err).__name__}, outbox=outbox)
        raise
    except Exception as err:
        if (down := unreachable(err)) is not None:  # the server is not there to take the end: the outbox keeps it
            message = f"{down}; {kept_for_later(outbox, run_id, spec.ckpt_dir, str(down))}"
        else:
            message = f"{type(err).__name__}: {err}"
            record_end(tracker, run_id, "FAILED", {"error": message[:5000]}, traceback.format_exc(), outbox)
        log.error("%s (seed %s) FAILED: %s", named(spec), spec.seed, message)
        raise JobFailed(message) from err


#: What of a job's output folder its run keeps: its log (``hydra.job.name`` is ``ablate``) and its overrides.
LOGS = ("ablate.log", ".hydra/overrides.yaml")


def attach_logs(spec: JobSpec, tracker: Tracker, run_id: str) -> None:
    """Attach the job's log and Hydra's ``overrides.yaml`` to its run (under ``logs/``), where the job has an output
    folder; a file that cannot be attached is one warning, never the job's failure."""
    folder = spec.context.output_dir
    if folder is None:
        return
    for name in LOGS:
        path = folder / name
        if path.is_file():
            try:
                tracker.log_artifact(run_id, path, "logs")
            except Exception as err:  # a convenience: the run's numbers are what matters
                log.warning("Could not attach %s to run %s: %s", path, run_id, err)


def named(spec: JobSpec) -> str:
    """A job as its log lines name it: ``job unet``; an expert's row already says it (``expert rgb``)."""
    return spec.row if spec.row.startswith(spec.kind) else f"{spec.kind} {spec.row}"


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
    from ablate.jobs import fingerprint

    numbers, seconds = fingerprint.timed(cfg)
    tracker.set_tags(run_id, {fingerprint.TAG: fingerprint.encode(numbers), "fingerprint_s": f"{seconds:.2f}"})
    log.info("Fingerprint in %.1f s", seconds)


@contextmanager
def in_launch_dir(target: Path) -> Iterator[Path]:
    """Run the block in the launch directory ``target`` (:attr:`ablate.store.SweepContext.launch_dir`), then go
    back.

    Workaround for ``hydra/launcher=ray``: a Ray task runs in the directory its cluster was started in, so the
    relative paths of a job (``checkpoints/``, ``data/``, the expert locks, ``mlflow.db``) would land there, beside
    another store. Every other launcher starts its jobs in the launch directory already, where this changes nothing.
    A launch directory missing on this machine is an error: a sweep over several machines needs it on a shared
    filesystem at the same path (submitit and Hydra's sweep directory need that too).
    """
    here = Path.cwd()
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


def no_row(cfg: DictConfig) -> None:
    """A job of a paper table names its row: without one it would train the root config's defaults (no row of the
    table: for DGFN's and BiFNet's tasks, a model they cannot build) into the table's experiment. Raise
    :class:`JobFailed` naming the rows and the two commands; an ad-hoc table (no ``table.rows``) needs none."""
    from ablate.tables.spec import run_rows

    rows = run_rows(cfg.table)
    if rows:
        name = cfg.table.name
        raise JobFailed(
            f"experiment={name} is a table of {len(rows)} rows ({', '.join(rows)}): name one with row=<row> "
            f"(python -m ablate experiment={name} row={rows[0]}), or race them all (python -m ablate -m "
            f"experiment={name})"
        )


def main(cfg: DictConfig) -> str:
    """Hydra task function: the job's context is read here, once (:meth:`SweepContext.current`), and the job runs in
    the launch directory. In a multirun a failed job is noted for the end-of-sweep summary and the other jobs go on;
    a failed single run exits with status 1 and one clear line."""
    standard_start_method()
    context = SweepContext.current()
    try:
        with STOP.installed(), in_launch_dir(context.launch_dir):
            from ablate.jobs.experts import job_config  # torch: the job trains

            cfg, row = job_config(cfg)  # an expert's tuning trial (table.tune) is the expert's config
            if row is None and context.row_choice is None:
                no_row(cfg)
            spent = stage1.StageOne()
            return stage1.Ended(run(JobSpec.of(cfg, context, row=row), spent).status, spent)
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
        if context.sweep_dir is None:
            print(f"error: {err}", file=sys.stderr)
            raise SystemExit(1) from None
        context.record_failure(str(err))
        return "FAILED"
