"""A job the store already holds: skipped where its config hash has a FINISHED run in its table (``force=true``
reruns it), copied where one finished in another table (tables share rows), and an expert copied from the tuning
trial that trained it, with that trial's best checkpoint (stage 2 of a tuning phase, :mod:`ablate.sweep.tuning`).
The job (:mod:`ablate.jobs.job`) asks :func:`already_done` before it starts a run; the sweep's plan counts such a job
as done with :func:`done_in_store`.
"""

from __future__ import annotations

import logging
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

from mlflow.entities import Run

from ablate.jobs.spec import JobSpec, checkpoint_dir
from ablate.jobs.tags import run_tags
from ablate.store import KIND_EXPERT, KIND_JOB, KIND_TRIAL, Tracker

log = logging.getLogger(__name__)


@dataclass
class Outcome:
    """What a job ended as: FINISHED or SKIPPED, its run, and its checkpoint directory."""

    status: str
    run_id: str
    ckpt_dir: Path


def copy_source(tracker: Tracker, chash: str, kind: str) -> Run | None:
    """The FINISHED run of another table that a job of this config hash and kind copies (:func:`reuse`), or None:
    for a raced or swept job the same row of another table, for an expert the tuning trial that trained it (stage 2
    of a tuning phase); a tuning trial copies nothing."""
    if kind == KIND_JOB:
        return tracker.finished_elsewhere(chash)
    if kind == KIND_EXPERT:
        return tracker.finished_elsewhere(chash, KIND_TRIAL, "expert_hash")
    return None


def done_in_store(tracker: Tracker, exp: str, chash: str, kind: str) -> bool:
    """Whether :func:`already_done` will skip a job of this config hash and kind: a FINISHED run of it in this
    table, or one it copies from another (:func:`copy_source`). The sweep's plan counts it so."""
    return tracker.finished_run(exp, chash) is not None or copy_source(tracker, chash, kind) is not None


def already_done(spec: JobSpec, tracker: Tracker, exp: str) -> Outcome | None:
    """SKIPPED where the store holds a FINISHED run of this config (in this table, or copied from another), else
    None (``force=true``: always None)."""
    if spec.cfg.force:
        return None
    done = tracker.finished_run(exp, spec.config_hash)
    if done is not None:
        log.info(
            "Skipping %s (seed %s): run %s with config hash %s is FINISHED (force=true reruns it)",
            spec.row,
            spec.seed,
            done.info.run_id,
            spec.config_hash,
        )
        return Outcome("SKIPPED", done.info.run_id, spec.ckpt_dir)
    source = copy_source(tracker, spec.config_hash, spec.kind)
    return reuse(spec, tracker, exp, source) if source is not None else None


#: A trial's tags that an expert copied from it does not keep: it is no trial, of no table's race or sweep.
TRIAL_TAGS = ("trial", "trial_config", "tune_search", "expert_hash", "race_plan", "job_num")


def reuse(spec: JobSpec, tracker: Tracker, exp: str, source: Run) -> Outcome | None:
    """Copy a FINISHED run of the same config from another table into this one (tables share rows). An expert is
    copied from the tuning trial that trained it, with the trial's best checkpoint into the expert's own folder,
    where every later job finds it; None (train it) where that checkpoint is gone."""
    code = ("git_commit", "ablate_version", "launch_commit")
    tags = {k: v for k, v in run_tags(spec).items() if k not in code}
    where = checkpoint_dir(source.data.tags.get("table", ""), source.data.tags.get("config_hash", ""))
    if spec.kind == KIND_EXPERT:
        if not copy_checkpoint(where / "best.ckpt", spec.ckpt_dir / "best.ckpt"):
            return None
        where = spec.ckpt_dir
    run_id = tracker.copy_run(source, exp, tags, drop=TRIAL_TAGS if spec.kind == KIND_EXPERT else ())
    log.info(
        "Reusing %s (seed %s): the same config finished as %s run %s of %s; copied as %s",
        spec.row,
        spec.seed,
        source.data.tags.get("kind", "a"),
        source.info.run_id,
        source.data.tags.get("table", "another table"),
        run_id,
    )
    return Outcome("SKIPPED", run_id, where)


def copy_checkpoint(source: Path, target: Path) -> bool:
    """Copy a checkpoint file (a hard link where the file system allows), whole or not at all; False where
    ``source`` is gone."""
    if not source.is_file():
        return False
    target.parent.mkdir(parents=True, exist_ok=True)
    partial = target.with_suffix(".part")
    partial.unlink(missing_ok=True)
    try:
        os.link(source, partial)
    except OSError:
        shutil.copyfile(source, partial)
    partial.replace(target)
    return True
