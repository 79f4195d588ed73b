"""The tuning phase before a race: every row of a table gets the same tuning budget, on validation only.

An ablation table whose rows got unequal tuning measures tuning effort, not design, and one recipe for every row is
unequal tuning in disguise (Melis et al. 2018; Lucic et al. 2018; Dodge et al. 2019). With ``table.tune`` set, the
racing sweeper (``hydra_plugins.ablate_racing_sweeper``) runs this phase first and races each row on the config it
chose:

* **Draws** (:mod:`ablate.sweep.draws`): N trials per row, the same N for every row; trial k's value of each
  parameter of ``table.tune.space`` depends only on the tuning seed, the table, the parameter's name and k (common
  random numbers, as DomainBed), so every row gets the same draws; trial 0 is the recipe.
* **Trials** are jobs of their own kind (``trial=k`` on the command line: ``kind=trial`` runs under the sweep's
  parent run, tagged with their row and trial): they train and validate and never test; their objective is the
  best value of the task's validation monitor over the epochs (``val_best``). They train at ``table.tune.job_seed``
  (1000 by default), a seed no race reaches, the same for every trial and row: the trials differ by their draws
  alone.
* **Order and budget**: trial k of every row is one batch, k = 0, 1, ...; ``table.tune.budget_min`` stops the phase
  only between two batches (every row has then had the same trials), where the next batch would end past it. A
  failed trial counts as spent: it has no objective and is never chosen.
* **Resuming**: the same command draws the same configs; a trial whose config has a FINISHED run is skipped by the
  jobs' config hash, and its objective read back from the store. The budget counts the time earlier sweeps spent on
  the phase (each sweep's span of its trials, :func:`ablate.tables.tuning.phase_wall`), as the race's does.
* **Draws as config**: a trial's values go under ``draws`` (``++draws.task.optimizer.lr=...``), which the job applies
  over its config (:func:`ablate.jobs.spec.apply_draws`); its experts (SMoE §4.3, BiFNet's frozen experts) are
  derived from the config without them, so every trial of a row shares one pair of experts, trained at the trials'
  seed on their own values (below), and only stage 2 is tuned.
* **Experts' own recipe** (SMoE §4.3, BiFNet's frozen experts): where rows sit on single-modal experts, each expert
  is tuned first, once, as a row of its own (``expert <modality>``: ``experts.tune=<modality>`` makes a trial of it,
  :func:`ablate.jobs.experts.trial_config`), with the same N and draws; its chosen values go under
  ``experts.draws.<modality>`` of every later job, so the experts stay fixed while stage 2 is tuned (its trials sit
  on the chosen experts, trained at the trials' seed: the chosen expert trials, copied, :func:`ablate.jobs.reuse.reuse`),
  and a single-modal row, which *is* its expert, races on its
  expert's choice. A budget that stops the experts' trials leaves the rest of it to stage 2.
* **Successive halving** (``table.tune.halving``, :mod:`ablate.sweep.halving`): every trial trains to the first
  rung, the top 1/η of each row's go on, resumed, to the next, and so on to the full budget; the rows' trials at a
  rung launch as the trials of a full-budget phase do (the i-th trial alive of every row one batch).
* **Choice**: each row races on its trial with the best objective (the first such trial where several tie: the
  recipe before any draw). The raced jobs carry ``tuned=k`` and record the tuned parameters' values
  (``tuned_config``); a table refuses to mix runs of one row tuned to different configs.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from ablate.sweep.draws import draw, parse_space
from ablate.sweep.halving import Halving, promote, rung_batches

log = logging.getLogger(__name__)

#: The training seed of every tuning trial: disjoint from any race's seeds (0 .. the last look's).
JOB_SEED = 1000


@dataclass(frozen=True)
class TuneSpec:
    """``table.tune``: ``trials`` per row (N, trial 0 the recipe), the draws' ``seed``, the ``space`` (parameter ->
    Hydra sweep), the phase's ``budget_min`` (None: none), the trials' training ``job_seed``, and whether rows on
    experts have their ``experts`` tuned first."""

    trials: int
    space: dict[str, str]
    seed: int = 0
    budget_min: float | None = None
    job_seed: int = JOB_SEED
    experts: bool = True  # tune the experts' own recipe first, where rows sit on experts
    halving: Halving | None = None  # successive halving (ablate.sweep.halving); None: every trial to the full budget

    @classmethod
    def from_config(cls, tune: Mapping[str, Any] | None) -> TuneSpec | None:
        """The spec of ``table.tune``; None where the table does not tune. One clear error per bad option."""
        if not tune:
            return None
        unknown = set(tune) - {"trials", "space", "seed", "budget_min", "job_seed", "experts", "halving"}
        if unknown:
            raise ValueError(f"table.tune: unknown option(s) {', '.join(sorted(unknown))}")
        trials = tune.get("trials")
        if not isinstance(trials, int) or isinstance(trials, bool) or trials < 1:
            raise ValueError(f"table.tune.trials: {trials!r} must be a positive integer (trial 0 is the recipe)")
        space = dict(tune.get("space") or {})
        if not space:
            raise ValueError("table.tune.space: empty; give at least one parameter, e.g. the learning rate")
        parse_space(space)  # every parameter parses, or one error naming it
        budget = tune.get("budget_min")
        if budget is not None and not float(budget) > 0:
            raise ValueError(f"table.tune.budget_min: {budget} must be positive (or null: no budget)")
        experts = tune.get("experts", True)
        if not isinstance(experts, bool):
            raise ValueError(f"table.tune.experts: {experts!r} must be true or false")
        return cls(
            trials,
            {str(k): str(v) for k, v in space.items()},
            int(tune.get("seed", 0)),
            None if budget is None else float(budget),
            int(tune.get("job_seed", JOB_SEED)),
            experts,
            Halving.from_config(tune.get("halving")),
        )

    def drawn(self, table: str, trial: int, under: str = "draws") -> list[str]:
        """Trial ``trial``'s draws as overrides under ``under`` (added where the config lacks the key); none for
        trial 0, the recipe."""
        return [f"++{under}.{name}={value}" for name, value in draw(self.space, table, self.seed, trial).items()]

    def overrides(self, table: str, trial: int, rung: int | None = None) -> list[str]:
        """Trial ``trial``'s overrides: its draws, its seed, its number, and where the phase halves, its ``rung``
        (none at the last, the full budget)."""
        at = self.halving.override(rung) if self.halving is not None and rung is not None else []
        return [*self.drawn(table, trial), f"seed={self.job_seed}", f"trial={trial}", *at]

    def batch(self, table: str, jobs: Mapping[str, list[str]], trial: int) -> list[list[str]]:
        """Trial ``trial`` of every row of ``jobs`` (row -> overrides), one launch: the phase launches it, and the
        sweep's plan counts it (:class:`ablate.sweep.launches.SweepPlan`)."""
        return [[*overrides, *self.overrides(table, trial)] for overrides in jobs.values()]


#: A reader of the trials' objectives in the store (row -> trial -> value): at the full budget, or at the rung of
#: successive halving given as its fraction of the recipe's epochs.
Objectives = Callable[..., Mapping[str, Mapping[int, float]]]


@dataclass
class Phase:
    """A tuning phase in progress: the trials launched per row (all rows alike), why it stopped early, the seconds
    it took; where it halves, the trials that reached each rung (per row, all rows alike) and the last rung every
    row's trials completed (None: the full budget)."""

    spec: TuneSpec
    rows: list[str]
    done: int = 0
    stopped: str = ""
    started: float = field(default_factory=time.monotonic)
    reached: list[int] = field(default_factory=list)
    rung: float | None = None


def _over_budget(
    spec: TuneSpec, phase: Phase, spent: float, elapsed: float, per_batch: float, what: str, unit: str = "batch"
) -> bool:
    """Whether the next batch (about ``per_batch`` seconds) would end past the phase's budget; if so, why, in
    ``phase.stopped`` (``what`` it stopped after, and what a ``unit`` costs)."""
    if not spec.budget_min or spent + elapsed + per_batch <= spec.budget_min * 60:
        return False
    phase.stopped = (
        f"the tuning budget of {spec.budget_min:g} min stopped the phase after {what} "
        f"({(spent + elapsed) / 60:.1f} min spent, about {per_batch / 60:.1f} more a {unit})"
    )
    return True


def run_phase(
    spec: TuneSpec,
    table: str,
    jobs: Mapping[str, list[str]],
    launch: Callable[[list[list[str]]], None],
    clock: Callable[[], float] = time.monotonic,
    spent: float = 0.0,
) -> Phase:
    """Launch trial k of every row as one batch, k = 0 .. N-1, stopping between batches where the budget would be
    passed (the mean batch so far taken for the next); ``launch`` runs a batch of jobs' overrides. ``spent``: the
    seconds of the phase's budget spent before this part (the experts' trials, earlier sweeps)."""
    phase = Phase(spec, list(jobs), started=clock())
    for k in range(spec.trials):
        elapsed = clock() - phase.started
        per_batch = elapsed / k if k else 0.0
        if k and _over_budget(spec, phase, spent, elapsed, per_batch, f"trial {k - 1} of every row", "trial"):
            break
        log.info("Tuning trial %d of %d for %d row(s)%s", k, spec.trials, len(jobs), _eta(k, spec.trials, elapsed))
        launch(spec.batch(table, jobs, k))
        phase.done = k + 1
    if phase.stopped:
        log.info("Tuning stopped: %s", phase.stopped)
    return phase


def run_halving(
    spec: TuneSpec,
    table: str,
    jobs: Mapping[str, list[str]],
    launch: Callable[[list[list[str]]], None],
    objectives: Objectives,
    higher_is_better: bool = True,
    clock: Callable[[], float] = time.monotonic,
    spent: float = 0.0,
) -> Phase:
    """Successive halving (:mod:`ablate.sweep.halving`): every row's N trials to the first rung, then per row the top
    ``ceil(n / η)`` of the rung before, by their objectives there (``objectives(rung)``), resumed to the next, to the
    full budget. A rung's i-th trial alive of every row is one batch; the budget stops the phase only between two
    batches, each at the mean of its rung's batches so far (the rung before's, scaled by the rungs' spans, at a
    rung's first)."""
    assert spec.halving is not None
    halving, rows = spec.halving, list(jobs)
    phase = Phase(spec, rows, started=clock(), rung=halving.rungs[0])
    alive = {row: list(range(spec.trials)) for row in rows}
    spans = [b - a for a, b in zip((0.0, *halving.rungs), halving.rungs)]
    per_batch = 0.0
    for r, keep in enumerate(halving.counts(spec.trials)):
        if r:
            at = objectives(halving.rungs[r - 1])
            alive = {
                row: promote({k: at.get(row, {}).get(k, math.nan) for k in alive[row]}, keep, higher_is_better)
                for row in rows
            }
            per_batch *= spans[r] / spans[r - 1]
        started, batches = clock(), rung_batches(rows, alive)
        for i, batch in enumerate(batches):
            elapsed = clock() - phase.started
            what = f"rung {r - 1}" if not i else f"{i} trial(s) of every row at rung {r}"
            if (r or i) and _over_budget(spec, phase, spent, elapsed, per_batch, what):
                log.info("Tuning stopped: %s", phase.stopped)
                return phase
            log.info("Tuning rung %d of %d (%.3g of the epochs): trial(s) %s", r, len(halving.rungs),
                     halving.rungs[r], ", ".join(f"{row} {k}" for row, k in batch))  # fmt: skip
            launch([[*jobs[row], *spec.overrides(table, k, r)] for row, k in batch])
            per_batch = (clock() - started) / (i + 1)
            phase.done = max(phase.done, i + 1)  # the trials per row started: all of them after rung 0
        phase.reached.append(keep)
        phase.rung = None if r == len(halving.rungs) - 1 else halving.rungs[r]
    return phase


def _eta(k: int, trials: int, elapsed: float) -> str:
    """The phase's progress before trial ``k``: the minutes spent, and the phase's own ETA (the sweep's progress line
    gives the whole sweep's), taking the mean trial index so far for each one to go (this one included); nothing
    before the first has ended."""
    if not k:
        return ""
    per = elapsed / k
    left = per * (trials - k) / 60
    return f"; {elapsed / 60:.1f} min spent, tuning ETA {left:.1f} min ({per / 60:.1f} min a trial index)"


def choose(objectives: Mapping[str, Mapping[int, float]], trials: int, higher_is_better: bool = True) -> dict[str, int]:
    """Per row, the trial (of 0 .. ``trials``-1) with the best objective, the first of several that tie; a failed
    trial (no objective, or NaN) is never chosen; a row none of whose trials has one races on the recipe (0)."""
    out = {}
    for row, values in objectives.items():
        scored = {k: v for k, v in values.items() if k < trials and not math.isnan(v)}
        out[row] = promote(scored, 1, higher_is_better)[0] if scored else 0  # halving's rule: of equals, the first
    return out


def tuned_overrides(spec: TuneSpec, table: str, trial: int) -> list[str]:
    """What a raced job of a row tuned to ``trial`` adds to its overrides: the trial's draws and ``tuned=trial``."""
    return [*spec.drawn(table, trial), f"tuned={trial}"]


def expert_overrides(spec: TuneSpec, table: str, chosen: Mapping[str, int]) -> list[str]:
    """What every job of a table on experts adds once its experts' trials have chosen (``chosen``: modality ->
    trial): each expert's chosen draws under ``experts.draws.<modality>`` (none for the recipe, trial 0)."""
    return [o for modality, trial in chosen.items() for o in spec.drawn(table, trial, f"experts.draws.{modality}")]


def expert_row(modality: str) -> str:
    """The tuning row of ``modality``'s expert, as its trials' runs name it (:func:`ablate.jobs.experts.trial_config`)."""
    return f"expert {modality}"


@dataclass(frozen=True)
class Experts:
    """Where a table's rows sit on experts: per modality, the overrides of a row its expert is derived from
    (``base``), and the single-modal rows, each its modality's expert (``single``: row -> modality)."""

    base: dict[str, list[str]] = field(default_factory=dict)
    single: dict[str, str] = field(default_factory=dict)

    @classmethod
    def of(cls, jobs: Mapping[str, list[str]], compose: Callable[[list[str]], Any]) -> Experts:
        """From the rows' overrides, each composed with ``compose`` (:func:`ablate.config.compose`)."""
        from ablate.jobs.experts import needed  # torch: the sweeper plans the experts anyway

        base: dict[str, list[str]] = {}
        single: dict[str, str] = {}
        for row, overrides in jobs.items():
            cfg = compose(list(overrides))
            if not cfg.get("experts"):
                continue
            for modality in needed(cfg):
                base.setdefault(str(modality), list(overrides))
            if cfg.stage.name == "single":
                single[row] = str(cfg.stage.modality)
        return cls(base, single)

    def trials(self) -> dict[str, list[str]]:
        """The experts' tuning rows and their jobs' overrides (but the trial's)."""
        return {expert_row(m): [*o, f"++experts.tune={m}"] for m, o in self.base.items()}


@dataclass
class Tuned:
    """What a tuning phase chose: per row, what its raced jobs add (``overrides``) and its chosen trial (``chosen``,
    the experts' rows too); what every stage-2 job adds, the experts' chosen draws (``fixed``); the trials run per row
    of stage 2 and of the experts; why a phase stopped early; the trials' objectives as last read (row -> trial ->
    value)."""

    overrides: dict[str, list[str]]
    chosen: dict[str, int]
    done: int
    experts_done: int = 0
    stopped: list[str] = field(default_factory=list)
    objectives: Mapping[str, Mapping[int, float]] = field(default_factory=dict)
    fixed: list[str] = field(default_factory=list)
    reached: list[list[int]] = field(default_factory=list)  # halving: per part, the trials per row at each rung


def choices(
    spec: TuneSpec,
    table: str,
    jobs: Mapping[str, list[str]],
    experts: Experts,
    objectives: Mapping[str, Mapping[int, float]],
    done: tuple[int, int],
    higher_is_better: bool = True,
) -> Tuned:
    """What a tuning phase chooses from its trials' ``objectives`` (row -> trial -> value), ``done`` = (trials run
    per expert, per stage-2 row): each expert's trial and the draws every stage-2 job adds with it, then each row's
    trial and what its raced jobs add. Launches nothing: the phase (:func:`tune`) and the plan of a resumed sweep
    (:mod:`ablate.sweep.plan`, from the objectives in the store) choose alike."""
    experts_done, stage2_done = done
    experts = experts if spec.experts else Experts()
    chosen: dict[str, int] = {}
    fixed: list[str] = []
    if experts.base:
        got = choose(objectives, experts_done, higher_is_better)
        by_modality = {m: got.get(expert_row(m), 0) for m in experts.base}
        chosen |= {expert_row(m): k for m, k in by_modality.items()}
        fixed = expert_overrides(spec, table, by_modality)
    stage2 = [row for row in jobs if row not in experts.single]
    chosen |= choose({r: v for r, v in objectives.items() if r in stage2}, stage2_done, higher_is_better)
    overrides: dict[str, list[str]] = {}
    for row in jobs:
        if row in experts.single:
            chosen[row] = chosen.get(expert_row(experts.single[row]), 0)
            overrides[row] = [*fixed, f"tuned={chosen[row]}"]
        else:
            chosen.setdefault(row, 0)
            overrides[row] = [*fixed, *tuned_overrides(spec, table, chosen[row])]
    return Tuned(overrides, chosen, stage2_done, experts_done, objectives=objectives, fixed=fixed)


def stage2_rows(jobs: Mapping[str, list[str]], experts: Experts, fixed: list[str]) -> dict[str, list[str]]:
    """The rows stage 2 tunes and their jobs' overrides on the experts' chosen draws (``fixed``): every row but the
    single-modal rows on experts, which are tuned as their experts. The phase launches them, and the sweep's plan
    counts them (:class:`ablate.sweep.launches.SweepPlan`)."""
    return {row: [*overrides, *fixed] for row, overrides in jobs.items() if row not in experts.single}


def tune(
    spec: TuneSpec,
    table: str,
    jobs: Mapping[str, list[str]],
    experts: Experts,
    launch: Callable[[list[list[str]]], None],
    objectives: Objectives,
    higher_is_better: bool = True,
    clock: Callable[[], float] = time.monotonic,
    earlier: float = 0.0,
) -> Tuned:
    """The whole tuning phase of a table: its experts' trials first where rows sit on experts (and
    ``spec.experts``), then every other row's on the chosen experts; ``objectives`` reads the trials' objectives
    back (row -> trial -> value) after each part; :func:`choices` chooses. Single-modal rows on experts are tuned as
    their experts. ``earlier``: the seconds earlier sweeps spent on this phase (the same command, resumed), counted
    against ``spec.budget_min`` as this sweep's own."""
    started = clock() - earlier
    experts = experts if spec.experts else Experts()
    experts_done, done, stopped, reached = 0, 0, [], []
    values: dict[str, Mapping[int, float]] = {}

    def part(rows: Mapping[str, list[str]]) -> Phase:
        """One part of the phase (the experts' trials, or stage 2's), its objectives read into ``values``: at the full
        budget, or where halving stopped early at the last rung its rows completed."""
        if spec.halving is None:
            phase = run_phase(spec, table, rows, launch, clock, spent=clock() - started)
        else:
            phase = run_halving(spec, table, rows, launch, objectives, higher_is_better, clock, clock() - started)
            reached.append(phase.reached)
        at = objectives() if phase.rung is None else objectives(phase.rung)  # halving stopped early: the last rung's
        values.update({r: v for r, v in at.items() if r in rows})
        stopped.extend([phase.stopped] if phase.stopped else [])
        return phase

    if experts.base:
        experts_done = part(experts.trials()).done
    fixed = choices(spec, table, jobs, experts, values, (experts_done, 0), higher_is_better).fixed
    stage2 = stage2_rows(jobs, experts, fixed)
    if stage2:
        done = part(stage2).done
    out = choices(spec, table, jobs, experts, values, (experts_done, done), higher_is_better)
    out.stopped, out.reached = stopped, reached
    return out
