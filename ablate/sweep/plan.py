"""A sweep's plan, logged before its first job starts: the jobs, the experts they will train first (SMoE §4.3), and an
estimated wall time.

Each job's config is composed from its overrides, as the sweep will launch it (the first look of a race: its rows x
the look's seeds). An expert is planned once per config hash, as :func:`ablate.jobs.experts.ensure_expert` trains
it; one whose best checkpoint exists is not trained again, nor is one of a tuning phase's stage 2 (its trials copy
their experts from the experts' chosen trials, :func:`ablate.jobs.reuse.reuse`), and a job whose config has a FINISHED
run in the store, in its table or (a raced or swept job) in another that it copies, is skipped (``done``,
:func:`ablate.jobs.reuse.done_in_store`, by the hash its job will have: a trial's draws applied,
:func:`ablate.jobs.spec.resolved_config`). A resumed tuning phase's stage-2 trials and raced jobs are composed on what
it chose from the trials in the store (:func:`ablate.sweep.tuning.choices`), so that they are found done too. Every
other job and expert is estimated from the recipe's steps (epochs x training batches, or ``trainer.max_steps``) at a
step time measured here, now (:func:`ablate.jobs.steptime.step_times`): one row key (the job's overrides but the
seed; an expert's modality) at a time, until ``plan.measure_s`` seconds have gone by (the first of each kind whatever
the time: the first measurement generates the dataset where it is missing, which the first job would do); a job or
expert not measured by then is timed at the mean step times of those measured of its kind (:func:`measured_as`): a
single-modal network of one modality trained alone (an expert, an expert's tuning trial), or a fusion network (whose
first epoch runs its frozen experts and the later ones read their cached features).

The wall time schedules the items on the sweep's workers in order, as its launcher does, each on the worker free
first, and each of a tuning phase's launches (trial k of every row) after the one before has ended: the experts
first (each fused job trains whichever expert no other job is training, :func:`ablate.jobs.experts.prepare`), and a
job no earlier than the experts it needs are trained. The estimate leaves out the start of each job's interpreter and
the sweep's end (row timing, the table); progress lines (:mod:`ablate.sweep.progress`) update it from the jobs' real
durations as they finish.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from ablate.config import composer
from ablate.jobs.experts import expert_config, job_config, needed
from ablate.jobs.reuse import done_in_store
from ablate.jobs.rungs import stop_epoch
from ablate.jobs.spec import best_checkpoint, resolved_config
from ablate.jobs.spec import job_kind as run_kind
from ablate.jobs.steptime import StepTimes, step_times
from ablate.store import Tracker, config_hash, row_name
from ablate.sweep.launches import SweepPlan
from ablate.sweep.progress import estimated, experts_planned, job_kind, workers
from ablate.tables.tuning import trial_objectives

log = logging.getLogger(__name__)

#: Seconds a sweep spends timing its jobs' steps before it launches them, where the config does not say.
MEASURE_S = 30.0


@dataclass
class Item:
    """One job or expert of the plan: its name, the items it waits for, and its estimated seconds (None: not
    estimated; 0 where it is done already)."""

    name: str
    key: str  # what it is measured as: its overrides but the seed, or "expert <modality>"
    config: DictConfig
    done: bool = False
    needs: list[str] = field(default_factory=list)  # the names of the experts it waits for
    seconds: float | None = None
    how: str = ""
    kind: str = "expert"  # a job's kind (ablate.sweep.progress.job_kind); an expert trains within a job
    row: str = ""  # a job's row


def swept_keys(jobs: list[list[str]]) -> set[str]:
    """The keys whose value differs between ``jobs``: what names their rows."""
    values: dict[str, set[str]] = {}
    for job in jobs:
        for item in job:
            key, _, value = item.lstrip("+~").partition("=")
            values.setdefault(key, set()).add(value)
    return {key for key, seen in values.items() if len(seen) > 1 or len(jobs) == 1}


def items(
    config: DictConfig,
    done: Callable[[DictConfig], bool] = lambda cfg: False,
    objectives: Mapping[str, Mapping[int, float]] | None = None,
    jobs: list[list[str]] | None = None,
) -> list[Item]:
    """The experts, then the jobs, of the sweep of ``config`` (``done``: whether a job's config, as it runs and is
    hashed, has a FINISHED run), or of its ``jobs``: those its sweeper launches before the first look ends
    (:meth:`ablate.sweep.launches.SweepPlan.jobs`, with ``objectives``: the tuning trials' in the store, where a
    resumed sweep has them), or a race's later look."""
    jobs = SweepPlan.of_config(config).jobs(objectives) if jobs is None else jobs
    compose = composer(config)  # with the sweep's own config folders (hydra.searchpath), as its jobs compose
    swept = swept_keys(jobs)
    experts: dict[str, Item] = {}
    planned: list[Item] = []
    for overrides in jobs:
        # an expert's tuning trial: the expert's config; a trial's draws applied, as the job hashes it
        ran, named = job_config(compose(overrides))
        cfg, _, base = resolved_config(ran)
        row = named or row_name(overrides, swept)  # an expert's trial: "expert <modality>"
        key = " ".join(sorted(o for o in overrides if not o.lstrip("+~").startswith("seed=")))
        trial = cfg.get("trial")  # every trial trains at one seed: named by its number
        label = f"trial {trial}" if trial is not None else f"seed {cfg.seed}"
        job = Item(f"{row} {label}", key or row, cfg, done=done(cfg), kind=job_kind(overrides), row=row)
        from_trials = trial is not None and bool((cfg.table.get("tune") or {}).get("experts", True))
        for modality in needed(cfg) if cfg.get("experts") and not job.done else []:
            ecfg = expert_config(base or cfg, modality)  # the experts of every trial of a row: without its draws
            chash = config_hash(ecfg)
            name = f"expert {modality} seed {cfg.seed}"
            if chash not in experts:  # stage 2's trials copy their experts from the experts' chosen trials
                trained = from_trials or best_checkpoint(str(ecfg.table.name), chash).exists()
                experts[chash] = Item(name, f"expert {modality}", ecfg, done=trained)
            if not experts[chash].done:
                job.needs.append(experts[chash].name)
        planned.append(job)
    return [*experts.values(), *planned]


def estimate(
    plan: list[Item],
    measure_s: float = MEASURE_S,
    measure: Callable[[DictConfig], StepTimes] = step_times,
    clock: Callable[[], float] = time.monotonic,
) -> None:
    """Set each item's :attr:`Item.seconds` and :attr:`Item.how` (see the module)."""
    start = clock()
    times: dict[str, StepTimes] = {}
    kinds: dict[str, str] = {}  # measured key -> what it was measured as (measured_as)
    for item in plan:
        if item.done:
            item.seconds, item.how = 0.0, "done"
            continue
        first = measured_as(item) not in kinds.values()
        if item.key not in times and measure_s > 0 and (first or clock() - start < measure_s):
            try:
                times[item.key], kinds[item.key] = measure(item.config), measured_as(item)
            except Exception as err:  # an estimate is a convenience: the job will say what is wrong
                log.warning("Could not time the steps of %s for the sweep's plan: %s", item.name, err)
        if item.key in times:
            item.seconds, item.how = seconds(item.config, times[item.key]), "measured"
    for item in (i for i in plan if i.seconds is None):  # the rest: at the mean step times of their kind's measured
        mates = [times[key] for key, kind in kinds.items() if kind == measured_as(item)]
        mates = mates or [times[key] for key, kind in kinds.items() if kind.startswith("alone") == trains_alone(item)]
        if mates:
            item.seconds, item.how = seconds(item.config, StepTimes.mean(mates)), "as the measured"


def measured_as(item: Item) -> str:
    """What ``item``'s steps are timed as: ``alone <modality>`` for a single-modal network trained alone
    (:func:`trains_alone`; a camera expert's step can take three times a BEV one's), else ``fused``."""
    return f"alone {item.config.stage.get('modality', '')}" if trains_alone(item) else "fused"


def trains_alone(item: Item) -> bool:
    """Whether ``item`` trains a single-modal network alone (an expert, an expert's tuning trial, a single-modal row
    not on experts): its steps are timed apart from a fusion network's, whose later epochs read cached features."""
    cfg = item.config
    return item.key.startswith("expert") or (cfg.stage.name == "single" and not cfg.get("experts"))


def seconds(cfg: DictConfig, times: StepTimes) -> float:
    """A job's or expert's estimated seconds: its fit (none for a single-modal row of two-stage training, which is
    tested from its expert) and its test."""
    conditions = len(cfg.task.get("eval_conditions") or {}) if "task" in cfg else 0
    test = times.test_seconds(conditions or 1) if cfg.get("trial") is None else 0.0  # a tuning trial never tests
    if cfg.get("experts") and cfg.stage.name == "single":
        return test
    epochs = stop_epoch(cfg) or int(cfg.trainer.get("max_epochs") or -1)  # a trial at a rung stops there
    steps = cfg.trainer.get("max_steps")
    return times.fit_seconds(epochs, int(steps) if steps is not None else None, cached=True) + test


def batch(item: Item) -> tuple[str, object, object] | None:
    """The launch a job belongs to: a tuning phase launches trial k of every row at once, and waits for them all
    before trial k + 1 (the experts' trials, then stage 2's); the first look is one more launch. An expert trains
    within a job: None."""
    return None if item.kind == "expert" else (item.kind, item.config.get("trial"), item.config.get("rung"))


def wall_seconds(plan: list[Item], parallel: int) -> float | None:
    """The plan's wall time on ``parallel`` workers (see the module); None where an item has no estimate. A launch
    (:func:`batch`) starts when the one before has ended, as the sweeper waits for it: a tuned table of three rows
    on two workers takes two rounds a trial index."""
    if any(item.seconds is None for item in plan):
        return None
    free = [0.0] * max(parallel, 1)
    ends: dict[str, float] = {}
    launch, after = None, 0.0
    for item in plan:
        this = batch(item)
        if this is not None and this != launch:  # the first launch waits for no other
            after = max(ends.values()) if launch is not None else 0.0
            launch = this
        worker = min(range(len(free)), key=free.__getitem__)
        begin = max([free[worker], after, *(ends.get(name, 0.0) for name in item.needs)])
        ends[item.name] = free[worker] = begin + float(item.seconds or 0.0)
    return max(free)


def expert_seconds(plan: list[Item]) -> tuple[dict[str, int], dict[str, float]]:
    """How many experts of each modality the plan's jobs will train within them, and each modality's mean estimated
    seconds where estimated (for the progress lines' ETA, :mod:`ablate.sweep.progress`)."""
    count: dict[str, int] = {}
    timed: dict[str, list[float]] = {}
    for item in (i for i in plan if i.kind == "expert" and not i.done):
        modality = str(item.config.stage.modality)
        count[modality] = count.get(modality, 0) + 1
        if item.seconds is not None:
            timed.setdefault(modality, []).append(float(item.seconds))
    return count, {m: sum(s) / len(s) for m, s in timed.items()}


def row_jobs(plan: list[Item]) -> dict[str, list[float]]:
    """Each row's raced jobs in the plan, done ones included, and the mean estimated seconds of those to run (0
    where none is): ``{row: [jobs, seconds]}``, for the progress lines' ETA (:mod:`ablate.sweep.progress`), whose
    rows can differ twentyfold (a single-modal row that only tests its expert against a fused row that trains)."""
    rows: dict[str, list[float]] = {}
    timed: dict[str, list[float]] = {}
    for item in plan:
        if item.kind == "job" and item.row:
            rows.setdefault(item.row, [0, 0.0])[0] += 1
            if not item.done and item.seconds is not None:
                timed.setdefault(item.row, []).append(float(item.seconds))
    for row, seconds in timed.items():
        rows[row][1] = sum(seconds) / len(seconds)
    return rows


def kind_seconds(plan: list[Item]) -> dict[str, float]:
    """Each job kind's mean estimated seconds over its jobs to run (for the progress lines' ETA,
    :mod:`ablate.sweep.progress`)."""
    seconds: dict[str, list[float]] = {}
    for item in plan:
        if item.kind != "expert" and not item.done and item.seconds is not None:
            seconds.setdefault(item.kind, []).append(item.seconds)
    return {kind: sum(s) / len(s) for kind, s in seconds.items()}


def lines(plan: list[Item], parallel: int, race: int) -> list[str]:
    """The plan as log lines: a header, one line per item, the estimated wall time; ``race``: the looks of the race
    whose first look the jobs are (0: no race)."""
    experts = [i for i in plan if i.key.startswith("expert") and not i.done]
    jobs = [i for i in plan if not i.key.startswith("expert")]
    skipped = sum(i.done for i in jobs)
    what = " (the first look of a race)" if race > 1 else " (a race of one look)" if race == 1 else ""
    header = f"Sweep plan: {len(jobs)} job(s){what}, {parallel} at a time"
    header += f"; {len(experts)} expert(s) to train first" if experts else ""
    header += f"; {skipped} done already (skipped)" if skipped else ""
    out = [header]
    for item in [*experts, *(i for i in jobs if not i.done)]:
        guess = f"~{_minutes(item.seconds)} ({item.how})" if item.seconds is not None else "not estimated"
        out.append(f"  {item.name}: {guess}")
    wall = wall_seconds(plan, parallel)
    more = "; later looks add seeds where rows are undecided" if race > 1 else ""
    out.append(f"Sweep ETA: {'~' + _minutes(wall) if wall is not None else 'unknown until a job ends'}{more}")
    return out


def _minutes(seconds: float | None) -> str:
    seconds = float(seconds or 0.0)
    return f"{seconds:.0f} s" if seconds < 90 else f"{seconds / 60:.1f} min"


def log_plan(
    config: DictConfig, jobs: list[list[str]], parallel: int, done: Callable[[DictConfig], bool], race: int
) -> list[Item]:
    """Compose, estimate and log the plan of a sweep's ``jobs`` (``plan.measure_s`` seconds of step timing at most; 0:
    none; ``race``: the looks of the race whose first look they are, 0 for none); return it."""
    measure_s = float(OmegaConf.select(config, "plan.measure_s", default=MEASURE_S))
    plan = items(config, done, jobs=jobs)
    said = lines(plan, parallel, race)
    if measure_s > 0:  # the plan at once; its estimates once the steps are timed (the dataset made first if missing)
        log.info("%s; timing their steps for an ETA (plan.measure_s = %g s)", said[0], measure_s)
    estimate(plan, measure_s)
    for line in lines(plan, parallel, race)[1 if measure_s > 0 else 0 :]:
        log.info(line)
    return plan


def log_sweep(config: DictConfig, sweep: SweepPlan, tracker: Tracker, sweep_dir: Path) -> None:
    """Log the plan of the jobs ``sweep`` launches before its first look ends (a resumed tuning phase's on what it
    chose from the trials in the store), each found done by the hash its job will have, and record the plan's
    estimates for the progress lines (:mod:`ablate.sweep.progress`)."""
    exp = tracker.experiment_id(sweep.table)
    objectives = trial_objectives(tracker, sweep.table) if sweep.tune is not None else None
    jobs = sweep.jobs(objectives)

    def done(cfg: DictConfig) -> bool:
        return done_in_store(tracker, exp, config_hash(cfg), run_kind(cfg))

    plan = log_plan(config, jobs, workers(config), done, race=len(sweep.race.looks) if sweep.race is not None else 0)
    estimated(sweep_dir, kind_seconds(plan), row_jobs(plan))
    experts_planned(sweep_dir, *expert_seconds(plan))
