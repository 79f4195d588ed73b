"""The racing sweeper: a table's rows x seeds launched look by look, seeds added only where a comparison is open.

Shaped like hydra-optuna-sweeper: :class:`RacingSweeperImpl` builds the job overrides and hands each batch to
whatever launcher is configured (``self.launcher.launch(overrides, initial_job_idx=...)``), so the parallel,
basic, SLURM and Ray launchers all race alike. Each look is one batch of (row, seed) jobs; after it, the rows'
primary metric is read back from the store with the tables' own code (:func:`ablate.tables.racing.table_values`)
and the race is replayed (:func:`ablate.tables.racing.race`), which says which rows need seeds at the next look.

Without a plan (``table.seeds`` null: ad-hoc sweeps) or with ``seed`` given on the command line, it launches every
combination of the swept values at once, as Hydra's basic sweeper does.
"""

from __future__ import annotations

import json
import logging
import sys
import time
from collections.abc import Callable
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

from ablate.store import AccessDenied, ServerUnreachable, Tracker
from ablate.store.sweepdir import PARENT_FILE, STORE_FILE
from ablate.sweep import progress
from ablate.tables import table_spec
from ablate.tables.collect import job_runs, row_seconds
from ablate.tables.racing import RacePlan, RaceState, race, table_values
from ablate.tables.spec import LOWER_IS_BETTER

log = logging.getLogger(__name__)

#: What a job returns (``ablate.jobs.job.main``) when the store already held its run and nothing trained.
SKIPPED = "SKIPPED"


def row_key(combo: list[str], swept: set[str]) -> str:
    """The ``row`` tag the job of ``combo`` records (:func:`ablate.jobs.job.row_name`): its ``row`` choice, else
    its swept overrides, sorted."""
    for item in combo:
        key, _, value = item.lstrip("+~").partition("=")
        if key == "row":
            return value
    own = sorted(item.lstrip("+~") for item in combo if item.split("=", 1)[0].lstrip("+~") in swept)
    return " ".join(own) or "default"


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

    def sweep(self, arguments: list[str]) -> list[list[JobReturn]]:
        assert self.config is not None and self.launcher is not None and self.hydra_context is not None
        parser = OverridesParser.create(config_loader=self.hydra_context.config_loader)
        overrides = parser.parse_overrides([f"{k}={v}" for k, v in self.params.items()] + list(arguments))
        combos = [list(c) for batch in BasicSweeper.split_arguments(overrides, None) for c in batch]
        swept = {o.get_key_element().lstrip("+~") for o in overrides if o.is_sweep_override()}
        sdir = Path(str(self.config.hydra.runtime.cwd)) / str(self.config.hydra.sweep.dir)
        sdir.mkdir(parents=True, exist_ok=True)
        OmegaConf.save(self.config, sdir / "multirun.yaml")
        seeds = self.config.table.get("seeds")
        try:
            plan = RacePlan.from_config(OmegaConf.to_container(seeds, resolve=True) if seeds is not None else None)
        except ValueError as err:  # a bad plan is one line naming the option, before any job runs
            print(f"error: {err}", file=sys.stderr)
            raise SystemExit(1) from None
        given = any(o.get_key_element().lstrip("+~") == "seed" for o in overrides)
        if plan is None or given:
            if plan is not None:
                log.info("seed given on the command line: no racing, every job launched at once")
            return [self._launch(combos, 0)]
        return self._race(plan, combos, swept, sdir)

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
        assert self.config is not None
        jobs = {row_key(c, swept): c for c in combos}
        rows = list(jobs)
        table = table_spec(self.config)
        named = table.get("reference")
        candidates = [named] if isinstance(named, str) else list(named or [])
        reference: str | list[str] = [r for r in candidates if r in rows] or rows[0]
        higher = table.primary not in LOWER_IS_BETTER
        have = dict.fromkeys(rows, 0)
        state = RaceState(plan, racing=rows)
        returns: list[list[JobReturn]] = []
        started, launched, stopped = time.monotonic(), 0, ""
        trained: list[str] = []  # the row of each job that trained in this command
        cost = job_costs({})  # each row's job time, read with the values after each look
        while not state.over:
            look = state.looks_done + 1
            n = plan.looks[state.looks_done]
            batch_rows = [r for r in state.racing for _ in range(have[r], n)]
            batch = [jobs[r] + [f"seed={s}"] for r in state.racing for s in range(have[r], n)]
            elapsed = time.monotonic() - started
            needed = look_estimate(elapsed, [cost(r) for r in trained], [cost(r) for r in batch_rows])
            if plan.budget_min and elapsed + needed > plan.budget_min * 60:
                stopped = (
                    f"the wall-time budget of {plan.budget_min:g} min stopped the race before look {look} "
                    f"({elapsed / 60:.1f} min spent, about {needed / 60:.1f} more needed)"
                )
                break
            log.info(
                "Look %d of %d: %d job(s), seeds up to %d for %s",
                look,
                len(plan.looks),
                len(batch),
                n,
                ", ".join(state.racing),
            )
            progress.replan(sdir, launched + len(batch))
            returns.append(self._launch(batch, launched))
            launched += len(batch)
            trained += [row_key(list(r.overrides), swept) for r in returns[-1] if r.return_value != SKIPPED]
            for r in state.racing:
                have[r] = n
            try:
                tracker = self._tracker(sdir)
                runs = job_runs(tracker, str(table.name))
            except (ServerUnreachable, AccessDenied) as err:
                print(f"error: {err}; the race stopped after look {look}: the same command resumes it", file=sys.stderr)
                raise SystemExit(1) from None
            values = table_values(runs, table)
            if trained:
                cost = self._costs(tracker, runs)
            state = race(values, rows, reference, plan, higher, stop_after=look)
            if state.looks_done < look:
                stopped = f"look {look} gave no values (its jobs failed): the race stopped there"
                break
            for c in state.comparisons.values():
                log.info("  %s vs %s (%s): %s", c.a, c.b, c.why, c.verdict())
        open_ = [f"{c.a} vs {c.b}" for c in state.undecided()]
        outcome = stopped or (f"left undecided after the last look: {', '.join(open_)}" if open_ else "all decided")
        log.info("Race over after %d look(s) and %d job(s): %s", state.looks_done, launched, outcome)
        self._tag_parent(sdir, {"race_looks": str(state.looks_done), "race_jobs": str(launched), "race": outcome})
        return returns

    def _tracker(self, sdir: Path) -> Tracker:
        assert self.config is not None
        path = sdir / STORE_FILE
        if path.exists():
            recorded = json.loads(path.read_text())
            return Tracker(str(recorded["uri"]), recorded["artifact_location"])
        return Tracker.from_config(self.config)

    @staticmethod
    def _costs(tracker: Tracker, runs: pd.DataFrame) -> Callable[[str], float]:
        try:
            return job_costs(row_seconds(tracker, runs))
        except Exception as err:  # an estimate: never the reason a sweep fails
            log.warning("Could not read the rows' job times (every row counted alike): %s", err)
            return job_costs({})

    def _tag_parent(self, sdir: Path, tags: dict[str, str]) -> None:
        parent = sdir / PARENT_FILE
        if not parent.exists():
            return
        try:
            self._tracker(sdir).set_tags(parent.read_text().strip(), tags)
        except Exception as err:  # a convenience: never the reason a sweep fails
            log.warning("Could not tag the sweep's run with the race's outcome: %s", err)
