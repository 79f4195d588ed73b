"""What a table's decisions cost: the CPU minutes its tuning phase and its race spent, per comparison the race decided,
so that tables (and ways of racing or tuning them) compare by how much evidence a CPU hour buys.

- The race: every job of the table trained here (a row copied from another table, ``reused_from``, cost nothing
  here), from the moment it began (its experts' training included, where the records say when it began:
  ``job_started``) to its end, times its threads.
- The tuning phase: each trial run's seconds, failed and repeated ones too (``runs/<table>.trials.csv``), times the
  threads of the table's jobs (the
  trials' records do not carry their own; a phase and its race run with the same ``trainer.threads``).
- Decided: the comparisons the race gave no more seeds (:attr:`ablate.tables.comparison.Comparison.decided`: better,
  worse or equivalent at δ; different, in a table without δ).

The figures are CPU time on the machine that made the runs (the footer names it): another CPU kind takes another
time for the same jobs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import pandas as pd

from ablate.tables.kept import kept
from ablate.tables.racing import RaceState


@dataclass(frozen=True)
class Cost:
    """A table's CPU minutes (tuning, race) and how many of its race's comparisons were decided, of how many."""

    tuning_min: float
    race_min: float
    decided: int
    compared: int
    # whether the records keep each job's start (else each run's: the experts trained before it are left out)
    job_starts: bool = True

    @property
    def total_min(self) -> float:
        return self.tuning_min + self.race_min

    @property
    def per_decision_min(self) -> float:
        """CPU minutes per decided comparison; NaN where none was decided."""
        return self.total_min / self.decided if self.decided else math.nan

    def words(self) -> str:
        """The footer's line."""
        spent = f"{self.total_min:.0f} CPU min ({self.tuning_min:.0f} tuning, {self.race_min:.0f} racing)"
        caveat = (
            ""
            if self.job_starts
            else " Racing counts from each run's start: these records keep no job start, so the experts a job "
            "trained before its run are left out."
        )
        if not self.decided:
            return f"Cost of the evidence: {spent}, and none of the {self.compared} comparison(s) decided.{caveat}"
        return (
            f"Cost of the evidence: {spent} for {self.decided} of {self.compared} comparison(s) decided: "
            f"{self.per_decision_min:.0f} CPU min per decided comparison (ablate.tables.cost).{caveat}"
        )


def threads(runs: pd.DataFrame) -> pd.Series:
    """Each run's threads (``made_threads``; 1 where the records do not say)."""
    made = runs.get("made_threads", pd.Series(1, index=runs.index))
    return pd.to_numeric(made, errors="coerce").fillna(1)


def race_minutes(runs: pd.DataFrame) -> float:
    """The CPU minutes of the table's jobs trained here (see the module); 0 without job times."""
    if not len(runs) or "ended" not in runs:
        return 0.0
    trained = runs[runs.get("reused_from", pd.Series("", index=runs.index)).fillna("").astype(str) == ""]
    began = pd.to_numeric(trained.get("started"), errors="coerce")
    if "job_started" in trained:
        at = pd.to_numeric(trained["job_started"], errors="coerce")
        began = at.where(at > 0, began)
    wall = (pd.to_numeric(trained["ended"], errors="coerce") - began) / 60000.0
    return float((wall * threads(trained)).sum(skipna=True))


def tuning_minutes(trials: pd.DataFrame | None, runs: pd.DataFrame) -> float:
    """The CPU minutes of the table's tuning trials (see the module); 0 without any."""
    if trials is None or not len(trials) or "seconds" not in trials:
        return 0.0
    per_job = float(threads(runs).median()) if len(runs) else 1.0
    return float(pd.to_numeric(trials["seconds"], errors="coerce").sum(skipna=True) / 60.0 * per_job)


def table_cost(raced: RaceState, runs: pd.DataFrame) -> Cost:
    """The cost of ``raced``'s decisions from the table's ``runs`` and the trials kept beside them
    (``runs.attrs["trials"]``)."""
    comparisons = list(raced.comparisons.values())
    return Cost(
        tuning_minutes(kept(runs, "trials"), runs),
        race_minutes(runs),
        sum(c.decided for c in comparisons),
        len(comparisons),
        "job_started" in runs,
    )
