"""The racing sweeper: a table's rows x seeds launched look by look, seeds added only where a comparison is open; it
owns the sweep's life, from its parent run to its table.

Shaped like hydra-optuna-sweeper: :class:`RacingSweeperImpl` builds the sweep's plan once
(:class:`ablate.sweep.launches.SweepPlan`) and hands each batch of it to whatever launcher is configured
(``self.launcher.launch(overrides, initial_job_idx=...)``), so the parallel, basic, SLURM and Ray launchers all race
alike. :meth:`RacingSweeperImpl.sweep` opens the sweep's parent run and records what its jobs need and what its
progress counts in the sweep's one state file (:mod:`ablate.sweep.parent`, :mod:`ablate.sweep.state`), runs the
phases (the tuning phase where the table has one, :mod:`ablate.sweep.tuning`, then the race), and writes the table
at the end (:mod:`ablate.sweep.finish`). Each look is one batch of (row, seed) jobs; after it, the rows' primary
metric is read back from the store with the tables' own code (:func:`ablate.tables.racing.table_values`) and the race
is replayed (:func:`ablate.tables.racing.race`), which says which rows need seeds at the next look.

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
from pathlib import Path
from typing import Any

import pandas as pd
from hydra.core.plugins import Plugins
from hydra.core.utils import JobReturn
from hydra.plugins.launcher import Launcher
from hydra.types import HydraContext, TaskFunction
from omegaconf import DictConfig, OmegaConf

from ablate.options import check_sweep
from ablate.store import AccessDenied, ServerUnreachable, SweepContext, Tracker, row_name
from ablate.sweep import progress, state
from ablate.sweep.finish import finish
from ablate.sweep.launches import SweepPlan
from ablate.sweep.parent import STORE_ERRORS, check_launcher, open_parent, ray_driver_auth
from ablate.sweep.tuning import expert_row, tune
from ablate.tables import table_spec
from ablate.tables.collect import earlier_wall, job_runs, row_seconds
from ablate.tables.columns import kernels
from ablate.tables.racing import race, table_values
from ablate.tables.tuning import from_store as tuning_trials
from ablate.tables.tuning import phase_wall, rung_runs, trial_objectives
from ablate.tables.twolevel import store_frames

from ._race import SKIPPED, Race, job_costs

log = logging.getLogger(__name__)


def one_line(err: BaseException) -> SystemExit:
    """Say ``err`` in one line (a bad option, a store that does not answer) and end the sweep with status 1."""
    print(f"error: {err}", file=sys.stderr)
    return SystemExit(1)


class RacingSweeperImpl:
    def __init__(self, params: dict[str, Any] | None, max_batch_size: int | None = None) -> None:
        self.params = dict(params or {})
        self.max_batch_size = max_batch_size
        self.config: DictConfig | None = None
        self.hydra_context: HydraContext | None = None
        self.launcher: Launcher | None = None

    def setup(self, *, hydra_context: HydraContext, task_function: TaskFunction, config: DictConfig) -> None:
        """Check the launcher (one line naming its extra where its plugin is missing), then build it."""
        self.hydra_context, self.config = hydra_context, config
        try:
            check_launcher(config)
        except ValueError as err:
            raise one_line(err) from None
        ray_driver_auth(config)
        self.launcher = Plugins.instance().instantiate_launcher(
            hydra_context=hydra_context, task_function=task_function, config=config
        )

    def _context(self) -> SweepContext:
        """The sweep's context: its directories from the multirun's config, its store and parent run from its state
        file (:class:`ablate.store.SweepContext`)."""
        assert self.config is not None
        launch = Path(str(self.config.hydra.runtime.cwd))
        return SweepContext.of_sweep(launch / str(self.config.hydra.sweep.dir), launch)

    def sweep(self, arguments: list[str]) -> list[list[JobReturn]]:
        """The whole sweep: its plan (a bad option is one line, before anything runs), its start, its phases, and
        its end (the table; status 1 where a job failed)."""
        assert self.config is not None and self.launcher is not None and self.hydra_context is not None
        try:
            check_sweep(self.config, arguments, self.params)  # every option a user gives (ablate.options)
            plan = SweepPlan.of(self.config, arguments, self.params, self.hydra_context.config_loader)
        except ValueError as err:  # a bad plan is one line naming the option, before any job runs
            raise one_line(err) from None
        sdir = self._start(plan)
        if plan.race is None:
            if plan.seeded:
                log.info("seed given on the command line: no racing, every job launched at once")
            returns = [self._launch(plan.jobs(), 0)]
        else:
            returns = self._race(plan, sdir)
        finish(self.config)
        return returns

    def _start(self, plan: SweepPlan) -> Path:
        """Record what the jobs need and what the progress counts (the keys that name the rows, the planned jobs) in
        the sweep's state file, then open the parent run and log the plan's estimate (:meth:`_open`)."""
        assert self.config is not None
        sdir = self._context().sweep_dir
        assert sdir is not None
        sdir.mkdir(parents=True, exist_ok=True)
        OmegaConf.save(self.config, sdir / "multirun.yaml")
        state.record(sdir, swept=sorted(plan.swept))  # the jobs name their rows from these (row_name)
        progress.start(sdir, plan.jobs())
        self._open(plan, sdir)
        return sdir

    def _open(self, plan: SweepPlan, sdir: Path) -> None:
        """Open the sweep's parent run (a store that cannot be reached, or refuses this client, is one line), then
        compose, estimate and log the plan, and record its estimates for the progress lines."""
        assert self.config is not None
        try:
            tracker, _ = open_parent(self.config)
        except (*STORE_ERRORS, ValueError) as err:  # a sweep that cannot start says why in one line
            raise one_line(err) from None
        try:
            from ablate.sweep.plan import log_sweep  # torch, Lightning: the jobs' configs and step times

            log_sweep(self.config, plan, tracker, sdir)
        except Exception as err:  # composes and times every job's config: whatever fails, the jobs will say it
            log.warning("Could not plan the sweep: %s", err)
            log.info("Sweep of %d job(s), %s at a time", len(plan.jobs()), progress.workers(self.config))

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

    def _race(self, plan: SweepPlan, sdir: Path) -> list[list[JobReturn]]:
        """Launch look after look until every comparison is decided, the looks run out or the budget stops it."""
        assert self.config is not None and plan.race is not None
        race_, workers = Race.start(plan), progress.workers(self.config)
        self._tune(race_, plan)
        while not race_.state.over:
            look, n, batch, rows = race_.next_look()
            experts = self._look_experts(batch) if look > 1 else {}  # the first look's are in the sweep's plan
            if race_.over_budget(look, rows, self._look_seconds(sdir, len(batch), experts, workers)):
                break
            racing = ", ".join(race_.state.racing)
            log.info(
                "Look %d of %d: %d job(s), seeds up to %d for %s", look, len(plan.race.looks), len(batch), n, racing
            )
            progress.replan(sdir, race_.launched + len(batch))
            if experts:
                progress.experts_planned(sdir, experts)
            race_.returns.append(self._launch(batch, race_.launched))
            race_.launched += len(batch)
            race_.trained += [
                row_name(r.overrides or [], plan.swept) for r in race_.returns[-1] if r.return_value != SKIPPED
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
    def _look_seconds(sdir: Path, jobs: int, experts: dict[str, int], workers: int) -> float | None:
        try:
            return progress.look_seconds(sdir, jobs, experts, workers)
        except (OSError, ValueError, KeyError) as err:  # a state file that cannot be read: the rows' costs alone
            log.warning("Could not time the look from the sweep's progress: %s", err)
            return None

    def _look_experts(self, batch: list[list[str]]) -> dict[str, int]:
        """The experts of each modality a later look's jobs will train first (its new seeds'), for the look's
        estimate and the sweep's ETA (:mod:`ablate.sweep.progress`); none where they cannot be counted."""
        assert self.config is not None
        try:
            from ablate.sweep.plan import expert_seconds, items  # torch: the experts' configs and hashes

            return expert_seconds(items(self.config, jobs=batch))[0]
        except Exception as err:  # composes the look's configs: whatever fails, its jobs will say it
            log.warning("Could not count the experts of the look: %s", err)
            return {}

    def _tune(self, race_: Race, plan: SweepPlan) -> None:
        """The tuning phase where the table has one (``table.tune``, :mod:`ablate.sweep.tuning`): the experts' trials
        where rows sit on experts, then every other row's, one trial index a batch; then each row's jobs race on its
        chosen trial's config; the race's own budget counts from there."""
        spec, name, experts = plan.tune, plan.table, plan.experts
        if spec is None:
            return

        def launch(batch: list[list[str]]) -> None:  # the sweep's plan counts every trial: its progress stays whole
            race_.returns.append(self._launch(batch, race_.launched))
            race_.launched += len(batch)

        def objectives(rung: float | None = None) -> dict[str, dict[int, float]]:  # at a rung where it halves
            try:
                return trial_objectives(self._tracker(), name, rung)
            except (ServerUnreachable, AccessDenied) as err:
                print(f"error: {err}; the tuning phase stopped: the same command resumes it", file=sys.stderr)
                raise SystemExit(1) from None

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
        reached = ";".join(",".join(map(str, part)) for part in tuned.reached)  # halving: trials per row per rung
        self._tag_parent(
            {"tune_trials": str(tuned.done), "tune_chosen": chosen, **({"tune_rungs": reached} if reached else {})}
        )
        race_.started = time.monotonic()

    def _earlier_trials(self, name: str) -> float:
        """Seconds that earlier sweeps of the same command spent on the table's tuning phase (before this phase
        launches, every trial in the store is theirs): each sweep's span (:func:`ablate.tables.tuning.phase_wall`),
        counted against the phase's budget as :attr:`Race.earlier` is against the race's."""
        try:
            trials = rung_runs(tuning_trials(self._tracker(), name))  # every rung's run: each took its time
        except (ServerUnreachable, AccessDenied) as err:
            print(f"error: {err}; the tuning phase did not start: the same command resumes it", file=sys.stderr)
            raise SystemExit(1) from None
        return 60 * phase_wall(trials)[0] if len(trials) else 0.0

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
            kernels=kernels(table),
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
        except (*STORE_ERRORS, KeyError, ValueError) as err:  # an estimate: never the reason a sweep fails
            log.warning("Could not read the rows' job times (every row counted alike): %s", err)
            return job_costs({})

    def _tag_parent(self, tags: dict[str, str]) -> None:
        context = self._context()
        if context.parent_run is None:
            return
        try:
            self._tracker().set_tags(context.parent_run, tags)
        except STORE_ERRORS as err:  # a convenience: never the reason a sweep fails
            log.warning("Could not tag the sweep's run with the race's outcome: %s", err)
