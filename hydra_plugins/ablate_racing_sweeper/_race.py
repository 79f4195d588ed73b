"""A race in progress in the racing sweeper: the seeds each row has, its state after each look, and whether the
next look fits the table's wall-time budget (:mod:`ablate.tables.racing` decides; this counts the time)."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

from hydra.core.utils import JobReturn

from ablate.sweep.launches import SweepPlan, look_jobs
from ablate.tables.raceplan import RacePlan
from ablate.tables.racing import RaceState

#: What a job returns (``ablate.jobs.job.main``) when the store already held its run and nothing trained.
SKIPPED = "SKIPPED"


def look_estimate(elapsed: float, trained: list[float], batch: list[float]) -> float:
    """Seconds the next look should take: the wall time so far, scaled from the jobs that trained to the next look's
    jobs by their costs (``trained``: one per job that trained in this command; ``batch``: one per job of the next
    look; each its row's job seconds, :func:`job_costs`). With every row of one cost this is the wall time per
    trained job times the look's jobs; a row twice as costly counts twice. A job the store already held (skipped,
    or copied from another table: ``ablate.jobs.reuse``) took seconds, so it is not among ``trained``; until one job
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

    @classmethod
    def start(cls, sweep: SweepPlan) -> Race:
        """The race of ``sweep`` before its first look: every row racing."""
        assert sweep.race is not None
        jobs = sweep.rows
        rows = list(jobs)
        state = RaceState(sweep.race, racing=rows)
        return cls(sweep.race, jobs, sweep.reference, sweep.higher, state, dict.fromkeys(rows, 0))

    def next_look(self) -> tuple[int, int, list[list[str]], list[str]]:
        """The next look's number, its seeds per row, and its jobs' overrides and rows."""
        look, n = self.state.looks_done + 1, self.plan.looks[self.state.looks_done]
        rows = [r for r in self.state.racing for _ in range(self.have[r], n)]
        return look, n, look_jobs(self.jobs, self.state.racing, self.have, n), rows

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
