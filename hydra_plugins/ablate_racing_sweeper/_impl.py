"""The racing sweeper: a table's rows x seeds launched look by look, seeds added only where a comparison is open.

Shaped like hydra-optuna-sweeper: :class:`RacingSweeperImpl` builds the job overrides and hands each batch to
whatever launcher is configured (``self.launcher.launch(overrides, initial_job_idx=...)``), so the parallel,
basic, SLURM and Ray launchers all race alike. Each look is one batch of (row, seed) jobs; after it, the rows'
primary metric is read back from the store with the tables' own code (:func:`ablate.tables.racing.table_values`)
and the race is replayed (:func:`ablate.tables.racing.race`), which says which rows need seeds at the next look.

Without a plan (``table.seeds`` null: ad-hoc sweeps) or with ``seed`` given on the command line, it launches every
combination of the swept values at once, as Hydra's basic sweeper does.

A paper table lists its rows once (``table.rows``): unless the command line names ``row``, the sweeper sweeps
``row`` over the rows the table runs (:func:`ablate.tables.spec.sweep_params`). Rows are named as the jobs name them
(:func:`ablate.store.row_name`), from the keys this sweeper records as swept (its ``params`` and the command line's).
"""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd
from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.plugins import Plugins
from hydra.core.utils import JobReturn
from hydra.plugins.launcher import Launcher
from hydra.types import HydraContext, TaskFunction
from omegaconf import DictConfig, OmegaConf

from ablate.config import composer
from ablate.store import AccessDenied, ServerUnreachable, SweepContext, Tracker, row_name
from ablate.store.context import SWEPT_FILE
from ablate.sweep import progress
from ablate.sweep.tuning import Experts, TuneSpec, expert_row, tune
from ablate.tables import table_spec
from ablate.tables.collect import earlier_wall, job_runs, row_seconds
from ablate.tables.columns import kernels_sd
from ablate.tables.racing import RacePlan, RaceState, race, table_values
from ablate.tables.spec import LOWER_IS_BETTER, sweep_params
from ablate.tables.tuning import from_store as tuning_trials
from ablate.tables.tuning import last_trials, phase_wall, trial_objectives
from ablate.tables.twolevel import store_frames

log = logging.getLogger(__name__)


#: What a job returns (``ablate.jobs.job.main``) when the store already held its run and nothing trained.
SKIPPED = "SKIPPED"


def look_estimate(elapsed: float, trained: list[float], batch: list[float]) -> float:
    """Seconds the next look should take: the wall time so far, scaled from the jobs that trained to the next look's
    jobs by their costs (``trained``: one per job that trained in this command; ``batch``: one per job of the next
    look; each its row's job seconds, :func:`job_costs`). With every row of one cost this is the wall time per
    trained job times the look's jobs; a row twice as costly counts twice. A job the store already held (skipped,
    or copied from another table: ``ablate.jobs.job``) took seconds, so it is not among ``trained``; until one job
    has trained there is nothing to go by (0). Jobs of the next look that the store holds make this an
    overestimate, which stops a race early rather than past its budget."""
    return elapsed * sum(batch) / sum(trained) if sum(trained) > 0 else 0.0


def job_costs(seconds: dict[str, float]) -> Callable[[str], float]:
    """A row's cost for :func:`look_estimate`: its job seconds in the store (:func:`ablate.tables.collect.row_seconds`),
    else the mean of the known rows' (1 where none is known: every row alike)."""
    known = [s for s in seconds.values() if s > 0]
    default = sum(known) / len(known) if known else 1.0
    return lambda row: seconds[row] if seconds.get(row, 0) > 0 else default


@dataclass
class Race:
    """A race in progress: the rows' jobs (their overrides but the seed), the seeds each row has, the race's state,
    the jobs launched and the row of each that trained (not skipped), and why it stopped early, if it did."""

    plan: RacePlan
    jobs: dict[str, list[str]]
    reference: str | list[str]
    higher: bool
    state: RaceState
    have: dict[str, int]
    started: float = field(default_factory=lambda: time.monotonic())
    launched: int = 0
    trained: list[str] = field(default_factory=list)
    returns: list[list[JobReturn]] = field(default_factory=list)
    stopped: str = ""
    cost: Callable[[str], float] = field(default_factory=lambda: job_costs({}))
    earlier: float = 0.0  # seconds the race spent in earlier sweeps (the same command, resumed)

    def next_look(self) -> tuple[int, int, list[list[str]], list[str]]:
        """The next look's number, its seeds per row, and its jobs' overrides and rows."""
        look, n = self.state.looks_done + 1, self.plan.looks[self.state.looks_done]
        rows = [r for r in self.state.racing for _ in range(self.have[r], n)]
        batch = [self.jobs[r] + [f"seed={s}"] for r in self.state.racing for s in range(self.have[r], n)]
        return look, n, batch, rows

    def over_budget(self, look: int, rows: list[str], timed: float | None = None) -> bool:
        """Whether the next look would end past the wall-time budget (then :attr:`stopped` says so): this command's
        time since the race began, and the race's time in earlier sweeps where the command resumed it
        (:attr:`earlier`), as the table's footer counts its wall time. The look's time is the larger of two
        estimates: :func:`look_estimate` from the rows' costs, and ``timed``, the look's jobs and the experts they
        train timed apart (:func:`ablate.sweep.progress.look_seconds`); each misses what the other sees."""
        elapsed = time.monotonic() - self.started
        needed = look_estimate(elapsed, [self.cost(r) for r in self.trained], [self.cost(r) for r in rows])
        needed = max(needed, timed or 0.0)
        spent = elapsed + self.earlier
        if self.plan.budget_min and spent + needed > self.plan.budget_min * 60:
            before = f", {self.earlier / 60:.1f} of them in earlier sweeps" if self.earlier else ""
            self.stopped = (
                f"the wall-time budget of {self.plan.budget_min:g} min stopped the race before look {look} "
                f"({spent / 60:.1f} min spent{before}, about {needed / 60:.1f} more needed)"
            )
            return True
        return False

    def outcome(self) -> str:
        open_ = [f"{c.a} vs {c.b}" for c in self.state.undecided() if c.n >= 2]
        unseen = [f"{c.a} vs {c.b}" for c in self.state.undecided() if c.n < 2]
        said = [f"left undecided after the last look: {', '.join(open_)}"] if open_ else []
        said += [f"no verdict, fewer than 2 paired seeds: {', '.join(unseen)}"] if unseen else []
        return self.stopped or ("; ".join(said) or "all decided")


class RacingSweeperImpl:
    def __init__(self, params: dict[str, Any] | None, max_batch_size: int | None = None) -> None:
        self.params = dict(params or {})
        self.max_batch_size = max_batch_size
        self.config: DictConfig | None = None
        self.hydra_context: HydraContext | None = None
        self.launcher: Launcher | None = None

    def setup(self, *, hydra_context: HydraContext, task_function: TaskFunction, config: DictConfig) -> None:
        self.hydra_context, self.config = hydra_context, config
        self.launcher = Plugins.instance().instantiate_launcher(
            hydra_context=hydra_context, task_function=task_function, config=config
        )

    def _context(self) -> SweepContext:
        """The sweep's context: its directories from the multirun's config, its store and parent run from the files
        the sweep callback wrote there (:class:`ablate.store.SweepContext`)."""
        assert self.config is not None
        launch = Path(str(self.config.hydra.runtime.cwd))
        return SweepContext.of_sweep(launch / str(self.config.hydra.sweep.dir), launch)

    def sweep(self, arguments: list[str]) -> list[list[JobReturn]]:
        assert self.config is not None and self.launcher is not None and self.hydra_context is not None
        parser = OverridesParser.create(config_loader=self.hydra_context.config_loader)
        params = sweep_params(self.params, list(arguments), self.config.table)
        overrides = parser.parse_overrides([f"{k}={v}" for k, v in params.items()] + list(arguments))
        combos = [list(c) for batch in BasicSweeper.split_arguments(overrides, None) for c in batch]
        swept = {o.get_key_element().lstrip("+~") for o in overrides if o.is_sweep_override()}
        context = self._context()
        context.record(SWEPT_FILE, " ".join(sorted(swept)))  # the jobs name their rows from these (row_name)
        assert context.sweep_dir is not None
        OmegaConf.save(self.config, context.sweep_dir / "multirun.yaml")
        try:
            plan = RacePlan.of_table(self.config)
        except ValueError as err:  # a bad plan is one line naming the option, before any job runs
            print(f"error: {err}", file=sys.stderr)
            raise SystemExit(1) from None
        given = any(o.get_key_element().lstrip("+~") == "seed" for o in overrides)
        if plan is None or given:
            if plan is not None:
                log.info("seed given on the command line: no racing, every job launched at once")
            return [self._launch(combos, 0)]
        return self._race(plan, combos, swept, context.sweep_dir)

    def _launch(self, batch: list[list[str]], first: int) -> list[JobReturn]:
        """Launch ``batch`` (in chunks of ``max_batch_size``), its jobs numbered from ``first``."""
        assert self.launcher is not None
        size = self.max_batch_size if self.max_batch_size and self.max_batch_size > 0 else max(len(batch), 1)
        results: list[JobReturn] = []
        for i in range(0, len(batch), size):
            results += list(self.launcher.launch(batch[i : i + size], initial_job_idx=first + i))
        for r in results:
            _ = r.return_value  # a job that raised stops the sweep, as with Hydra's basic sweeper
        return results

    def _race(self, plan: RacePlan, combos: list[list[str]], swept: set[str], sdir: Path) -> list[list[JobReturn]]:
        """Launch look after look until every comparison is decided, the looks run out or the budget stops it."""
        assert self.config is not None
        race_, workers = self._start_race(plan, combos, swept), progress.workers(self.config)
        self._tune(race_)
        while not race_.state.over:
            look, n, batch, rows = race_.next_look()
            experts = self._look_experts(batch) if look > 1 else 0  # the first look's are in the sweep's plan
            if race_.over_budget(look, rows, self._look_seconds(sdir, len(batch), experts, workers)):
                break
            racing = ", ".join(race_.state.racing)
            log.info("Look %d of %d: %d job(s), seeds up to %d for %s", look, len(plan.looks), len(batch), n, racing)
            progress.replan(sdir, race_.launched + len(batch))
            if experts:
                progress.experts_planned(sdir, experts)
            race_.returns.append(self._launch(batch, race_.launched))
            race_.launched += len(batch)
            race_.trained += [
                row_name(r.overrides or [], swept) for r in race_.returns[-1] if r.return_value != SKIPPED
            ]
            for r in race_.state.racing:
                race_.have[r] = n
            if not self._replay(race_, look):
                break
        outcome = race_.outcome()
        log.info("Race over after %d look(s) and %d job(s): %s", race_.state.looks_done, race_.launched, outcome)
        tags = {"race_looks": str(race_.state.looks_done), "race_jobs": str(race_.launched), "race": outcome}
        self._tag_parent(tags)
        return race_.returns

    @staticmethod
    def _look_seconds(sdir: Path, jobs: int, experts: int, workers: int) -> float | None:
        try:
            return progress.look_seconds(sdir, jobs, experts, workers)
        except Exception as err:  # an estimate: never the reason a sweep fails
            log.warning("Could not time the look from the sweep's progress: %s", err)
            return None

    def _look_experts(self, batch: list[list[str]]) -> int:
        """The experts a later look's jobs will train first (its new seeds'), for the look's estimate and the
        sweep's ETA (:mod:`ablate.sweep.progress`); 0 where they cannot be counted."""
        assert self.config is not None
        try:
            from ablate.sweep.plan import items  # torch: the experts' configs and hashes

            return sum(i.kind == "expert" and not i.done for i in items(self.config, jobs=batch))
        except Exception as err:  # an estimate: never the reason a look does not start
            log.warning("Could not count the experts of the look: %s", err)
            return 0

    def _tune(self, race_: Race) -> None:
        """The tuning phase where the table has one (``table.tune``, :mod:`ablate.sweep.tuning`): the experts' trials
        where rows sit on experts, then every other row's, one trial index a batch; then each row's jobs race on its
        chosen trial's config; the race's own budget counts from there."""
        assert self.config is not None
        table = table_spec(self.config)
        name = str(table.name)
        try:
            given = table.get("tune")
            spec = TuneSpec.from_config(OmegaConf.to_container(given, resolve=True) if given else None)  # type: ignore[arg-type]
        except ValueError as err:  # one line naming the option, before any job runs
            print(f"error: {err}", file=sys.stderr)
            raise SystemExit(1) from None
        if spec is None:
            return

        def launch(batch: list[list[str]]) -> None:  # the sweep's plan counts every trial: its progress stays whole
            race_.returns.append(self._launch(batch, race_.launched))
            race_.launched += len(batch)

        def objectives() -> dict[str, dict[int, float]]:
            try:
                return trial_objectives(self._tracker(), name)
            except (ServerUnreachable, AccessDenied) as err:
                print(f"error: {err}; the tuning phase stopped: the same command resumes it", file=sys.stderr)
                raise SystemExit(1) from None

        experts = Experts.of(race_.jobs, composer(self.config)) if spec.experts else Experts()
        earlier = self._earlier_trials(name) if spec.budget_min else 0.0
        tuned = tune(spec, name, race_.jobs, experts, launch, objectives, earlier=earlier)
        values = tuned.objectives
        for row, k in tuned.chosen.items():
            as_expert = expert_row(experts.single[row]) if row in experts.single else ""
            value = values.get(as_expert or row, {}).get(k, float("nan"))
            n = tuned.experts_done if row.startswith("expert ") or as_expert else tuned.done
            said = " (its expert's)" if as_expert else ""
            log.info("Tuned %s: trial %d of %d%s (validation %.4g)", row, k, n, said, value)
        for row in race_.jobs:
            race_.jobs[row] = [*race_.jobs[row], *tuned.overrides[row]]
        chosen = " ".join(f"{r}={k}" for r, k in tuned.chosen.items()).replace("expert ", "expert_")
        self._tag_parent({"tune_trials": str(tuned.done), "tune_chosen": chosen})
        race_.started = time.monotonic()

    def _earlier_trials(self, name: str) -> float:
        """Seconds that earlier sweeps of the same command spent on the table's tuning phase (before this phase
        launches, every trial in the store is theirs): each sweep's span (:func:`ablate.tables.tuning.phase_wall`),
        counted against the phase's budget as :attr:`Race.earlier` is against the race's."""
        try:
            trials = last_trials(tuning_trials(self._tracker(), name))
        except (ServerUnreachable, AccessDenied) as err:
            print(f"error: {err}; the tuning phase did not start: the same command resumes it", file=sys.stderr)
            raise SystemExit(1) from None
        return 60 * phase_wall(trials)[0] if len(trials) else 0.0

    def _start_race(self, plan: RacePlan, combos: list[list[str]], swept: set[str]) -> Race:
        """The race before its first look: every row racing, its reference the table's (or the first row)."""
        assert self.config is not None
        jobs = {row_name(c, swept): c for c in combos}
        rows = list(jobs)
        table = table_spec(self.config)
        named = table.get("reference")
        candidates = [named] if isinstance(named, str) else list(named or [])
        reference: str | list[str] = [r for r in candidates if r in rows] or rows[0]
        higher = table.primary not in LOWER_IS_BETTER
        return Race(plan, jobs, reference, higher, RaceState(plan, racing=rows), dict.fromkeys(rows, 0))

    def _replay(self, race_: Race, look: int) -> bool:
        """Read the rows' values back from the store and replay the race after ``look``; False where the look gave
        nothing to go on (its jobs failed). A store that does not answer ends the sweep in one line."""
        assert self.config is not None
        table = table_spec(self.config)
        try:
            tracker = self._tracker()
            runs = job_runs(tracker, str(table.name))
        except (ServerUnreachable, AccessDenied) as err:
            print(f"error: {err}; the race stopped after look {look}: the same command resumes it", file=sys.stderr)
            raise SystemExit(1) from None
        values = table_values(runs, table)
        race_.earlier = 60 * earlier_wall(runs, self._context().parent_run)
        if race_.trained:
            race_.cost = self._costs(tracker, runs)
        frames_var = store_frames(tracker, runs, str(table.primary), str(table.get("primary_condition") or ""))
        race_.state = race(
            values,
            list(race_.jobs),
            race_.reference,
            race_.plan,
            race_.higher,
            stop_after=look,
            frames_var=frames_var,
            kernels_sd=kernels_sd(table),
        )
        if race_.state.looks_done < look:
            race_.stopped = f"look {look} gave no values (its jobs failed): the race stopped there"
            return False
        for c in race_.state.comparisons.values():
            log.info("  %s vs %s (%s): %s", c.a, c.b, c.why, c.verdict())
        return True

    def _tracker(self) -> Tracker:
        """The store the sweep recorded (where its parent run is), else the config's."""
        assert self.config is not None
        return Tracker.from_config(self.config, self._context())

    @staticmethod
    def _costs(tracker: Tracker, runs: pd.DataFrame) -> Callable[[str], float]:
        try:
            return job_costs(row_seconds(tracker, runs))
        except Exception as err:  # an estimate: never the reason a sweep fails
            log.warning("Could not read the rows' job times (every row counted alike): %s", err)
            return job_costs({})

    def _tag_parent(self, tags: dict[str, str]) -> None:
        context = self._context()
        if context.parent_run is None:
            return
        try:
            self._tracker().set_tags(context.parent_run, tags)
        except Exception as err:  # a convenience: never the reason a sweep fails
            log.warning("Could not tag the sweep's run with the race's outcome: %s", err)
