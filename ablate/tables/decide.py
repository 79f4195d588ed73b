"""What deciding an undecided comparison would take: about how many seeds per row, and how many CPU hours.

At the spread a comparison shows (the seeds' standard deviation of the paired differences ``s``, with another CPU's
kernels' where the table measured it, and the test frames' standard error ``f``, :mod:`ablate.tables.twolevel`), the
standard error at n seeds is
``se(n) = sqrt(s² / n + f²)``: more seeds shrink the seeds' term, never the test set's. Taking the observed mean
difference ``Δ`` as the truth (the usual reading of a sample-size estimate: Julious 2004, Stat. Med. 23(12),
"Sample sizes for clinical trials with normal data", sec. 3 for equivalence), the claim the race could still reach
is

* *beyond δ* where ``|Δ| > δ``: the one-sided t-test of ``|d| <= δ``, whose power at n seeds is the noncentral t's
  ``P(T_{n-1}(λ) > t_{n-1, 1-α})`` with ``λ = (|Δ| - δ) / se(n)``;
* *equivalent within ±δ* where ``|Δ| < δ``: TOST, whose power is at least ``P1 + P2 - 1`` with ``P1``, ``P2`` the
  two one-sided tests' powers at ``λ = (δ ∓ Δ) / se(n)`` (Bonferroni's lower bound, close where one bound dominates);
* *different* in a table without δ: the two-sided test against 0, at ``λ = |Δ| / se(n)``.

:func:`seeds_to_decide` is the smallest n (up to :data:`MOST`) whose power reaches :data:`POWER`, at the level
``α`` of the race's last look divided over the comparisons still open (the strictest step of Holm's correction).
None where no n does: ``|Δ|`` sits on δ, or the test set's own standard error ``f`` leaves too little room, which more
test frames would change and more seeds would not. The CPU hours are the jobs the two rows would add (seeds per
row beyond what each has) times the median CPU time of a job of each row in the table's records (its wall seconds
times its threads), on the machine that made them.

**More test frames instead.** Where the race's own seeds cannot decide a comparison (no n up to :data:`MOST`, or more
than its last look's), :func:`frames_to_decide` gives the test frames that would at the last look's seeds: the
smallest ``F'`` whose ``se = sqrt(s² / n + f² F / F')`` reaches :data:`POWER` at the same level, ``F`` the frames the
runs were tested on. Reading chosen: the frames' variance falls as ``1 / F'``, as a mean's does over independent
frames drawn from the same scenes (the delete-one jackknife and the bootstrap over frames both estimate that
variance at ``F``: :mod:`ablate.tables.twolevel`). Checked on the records (``bench/decide_design.py --scaling``): on
random halves of the test split the counts tables' term is 1.7-2.1x the whole's, as 1 / frames says; the AP tables'
1.2-1.9x, so for them the estimate may be too few frames. A test split is fixed before a race, so this is the figure
to size the next race's test set by, not a reason to extend this one's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy import stats

from ablate.tables.comparison import Comparison
from ablate.tables.kept import kept
from ablate.tables.raceplan import RacePlan
from ablate.tables.racing import RaceState

#: The share of tables the estimate's n decides, at the spread observed.
POWER = 0.8
#: The most seeds per row an estimate looks at.
MOST = 1000
#: The most test frames an estimate looks at, as a multiple of those the runs were tested on.
MOST_FRAMES = 100


def power(
    n: np.ndarray, mean: float, sd: float, frames_se: float | np.ndarray, rope: float | None, level: float
) -> np.ndarray:
    """The chance of deciding at ``n`` seeds (an array) a comparison whose true mean difference is ``mean``, the test
    frames' standard error ``frames_se`` (a number, or an array beside ``n``; see the module)."""
    n = np.asarray(n, dtype=float)
    se = np.sqrt(sd * sd / n + frames_se * frames_se)
    df = n - 1
    if rope is None:
        crit = stats.t.ppf(1 - level / 2, df)
        return np.asarray(stats.nct.sf(crit, df, abs(mean) / se))
    crit = stats.t.ppf(1 - level, df)
    if abs(mean) > rope:
        return np.asarray(stats.nct.sf(crit, df, (abs(mean) - rope) / se))
    one, two = (stats.nct.sf(crit, df, (rope - s * mean) / se) for s in (1, -1))
    return np.clip(one + two - 1, 0.0, 1.0)


def seeds_to_decide(mean: float, sd: float, frames_se: float, rope: float | None, level: float) -> int | None:
    """The smallest number of seeds per row (2 to :data:`MOST`) at which the comparison is decided with
    :data:`POWER`; None where none is (see the module)."""
    if any(math.isnan(x) for x in (mean, sd, frames_se)) or (rope is not None and abs(mean) == rope):
        return None
    n = np.arange(2, MOST + 1)
    reach = np.nonzero(power(n, mean, sd, frames_se, rope, level) >= POWER)[0]
    return int(n[reach[0]]) if len(reach) else None


def frames_to_decide(
    mean: float,
    sd: float,
    frames_se: float,
    rope: float | None,
    level: float,
    seeds: int,
    frames: int,
    shared: float = 0.0,
) -> int | None:
    """The fewest test frames (up to :data:`MOST_FRAMES` times ``frames``, those the runs were tested on) at which
    ``seeds`` seeds per row decide the comparison with :data:`POWER`, the frames' standard error ``frames_se`` scaled
    by ``sqrt(frames / F')`` (see the module) beside the ``shared`` shift another CPU gives every seed, which more
    frames keep; None where none does, or where the runs kept no test frames' term."""
    if frames < 2 or seeds < 2 or not frames_se > 0 or any(math.isnan(x) for x in (mean, sd, frames_se)):
        return None
    if rope is not None and abs(mean) == rope:
        return None
    more = np.arange(frames, MOST_FRAMES * frames + 1)
    fixed = np.sqrt(frames_se**2 * frames / more + shared**2)
    reach = power(np.full(len(more), float(seeds)), mean, sd, fixed, rope, level)
    found = np.nonzero(reach >= POWER)[0]
    return int(more[found[0]]) if len(found) else None


def tested_frames(runs: pd.DataFrame) -> int:
    """The test frames a table's runs were tested on: the frames its records keep counts or detections of (0 where
    they keep none)."""
    for key in ("frames", "detections"):
        kept_frames = kept(runs, key)
        if isinstance(kept_frames, pd.DataFrame) and "frame" in kept_frames and len(kept_frames):
            return int(kept_frames["frame"].astype(str).nunique())
    return 0


def job_cpu_hours(runs: pd.DataFrame, row: str) -> float:
    """The median CPU hours of one job of ``row`` in a table's runs or records (wall seconds from the job's start,
    its experts included where the records say when it began, times threads), over
    the runs trained in this table (a run copied from another took no time here; a row of copies only is priced at
    the table's other jobs); NaN where they have no times."""
    if not len(runs) or not ("seconds" in runs or {"started", "ended"} <= set(runs.columns)):
        return math.nan
    trained = runs[runs.get("reused_from", pd.Series("", index=runs.index)).fillna("").astype(str) == ""]
    sel = trained[trained["row"].astype(str) == row]
    sel = sel if len(sel) else trained  # a row copied from another table: a job of this table's, as a guide
    threads = pd.to_numeric(sel.get("made_threads", pd.Series(1, index=sel.index)), errors="coerce").fillna(1)
    if "job_started" in sel and (pd.to_numeric(sel["job_started"], errors="coerce") > 0).all():
        wall = (pd.to_numeric(sel["ended"]) - pd.to_numeric(sel["job_started"])) / 1000.0  # with its experts
    else:
        wall = sel["seconds"] if "seconds" in sel else (sel["ended"] - sel["started"]) / 1000.0
    cpu = pd.to_numeric(wall, errors="coerce") * threads
    return float(cpu.median() / 3600) if cpu.notna().any() else math.nan


@dataclass(frozen=True)
class ToDecide:
    """What deciding a comparison of rows ``a`` and ``b`` would take: seeds per row (None: no number up to
    :data:`MOST`), the jobs to add and their CPU hours (NaN without job times); and, where the race's seeds do not
    suffice, the test frames that would at its last look's ``at_seeds`` (None: none up to :data:`MOST_FRAMES` times
    the ``frames_now`` the runs were tested on, or no frames' term)."""

    a: str
    b: str
    seeds: int | None
    jobs: int
    cpu_hours: float
    level: float
    at_seeds: int = 0
    frames_now: int = 0
    frames: int | None = None
    shared: bool = False  # the table measured a shift another CPU gives every seed alike (more seeds keep it)

    def frames_words(self) -> str:
        """The sentence on test frames, where the race's seeds would not decide and more test frames would."""
        if self.frames is None:
            return ""
        lead = "At" if self.seeds is None else "Or, at"
        return (
            f" {lead} {self.at_seeds} seeds per row (the race's last look), about {self.frames} test frames would "
            f"decide it, against the {self.frames_now} its runs were tested on ({self.frames / self.frames_now:.1f}x; "
            "the frames' variance taken to fall as 1 / frames): a figure for the next race's test split."
        )

    def shared_words(self) -> str:
        return ", with the shift another CPU gives every seed alike," if self.shared else ""

    def words(self, names: dict[str, str], cpu: str) -> str:
        """The footer's line."""
        pair = f"{names.get(self.a, self.a)} vs {names.get(self.b, self.b)}"
        if self.seeds is None and self.frames is not None:
            return (
                f"Deciding {pair} would take more than {MOST} seeds per row at the spread observed: the test set's own "
                f"variance{self.shared_words()} leaves too little room." + self.frames_words()
            )
        if self.seeds is None:
            return (
                f"Deciding {pair} would take more than {MOST} seeds per row at the spread observed: the mean difference "
                f"sits on ±δ, or the test set's own variance{self.shared_words()} leaves too little room (more test "
                "frames would help, more seeds would not)."
            )
        hours = "" if math.isnan(self.cpu_hours) else f", about {self.cpu_hours:.1f} CPU hours on {cpu}"
        return (
            f"Deciding {pair} would take about {self.seeds} seeds per row ({self.jobs} more jobs{hours}), for "
            f"{POWER:.0%} power at the spread observed and level {self.level:.4f} (the last look's, over the open "
            "comparisons; ablate.tables.decide)." + self.frames_words()
        )


def to_decide(c: Comparison, plan: RacePlan, open_count: int, runs: pd.DataFrame, frames_now: int = 0) -> ToDecide:
    """:class:`ToDecide` for the undecided comparison ``c`` of a race on ``plan`` with ``open_count`` comparisons
    open, priced from ``runs``' job times; its test frames estimated against the ``frames_now`` its runs were tested
    on (0: none kept)."""
    level = plan.levels()[-1] / max(1, open_count)
    sd, shared = math.hypot(c.sd, c.kernels.per_seed), c.kernels.shared > 0
    n = seeds_to_decide(c.delta, sd, math.hypot(c.frames_se, c.kernels.shared), plan.rope, level)
    last = max(plan.looks[-1], c.n)
    short = c.frames and (n is None or n > last)  # the race's seeds would not decide it
    frames = (
        frames_to_decide(c.delta, sd, c.frames_se, plan.rope, level, last, frames_now, c.kernels.shared)
        if short
        else None
    )
    if n is None:
        return ToDecide(c.a, c.b, None, 0, math.nan, level, last, frames_now, frames, shared)
    have = {r: _seeds(runs, r) for r in (c.a, c.b)}
    more = {r: max(0, n - have[r]) for r in (c.a, c.b)}
    hours = sum(more[r] * job_cpu_hours(runs, r) for r in (c.a, c.b) if more[r])
    return ToDecide(c.a, c.b, n, sum(more.values()), float(hours), level, last, frames_now, frames, shared)


def _seeds(runs: pd.DataFrame, row: str) -> int:
    return int((runs["row"].astype(str) == row).sum()) if len(runs) and "row" in runs else 0


def undecided(raced: RaceState, runs: pd.DataFrame) -> dict[frozenset[str], ToDecide]:
    """:class:`ToDecide` of each comparison a race (:class:`ablate.tables.racing.RaceState`) left open."""
    still = [c for c in raced.undecided() if c.n >= 2]
    now = tested_frames(runs) if any(c.frames for c in still) else 0  # counted once, not per comparison
    return {frozenset((c.a, c.b)): to_decide(c, raced.plan, len(still), runs, now) for c in still}


def machine(runs: pd.DataFrame) -> str:
    """The CPU(s) that made a table's runs, as the records name them."""
    cpus = sorted({str(v) for v in runs.get("made_cpu", pd.Series(dtype=str)).dropna() if str(v)})
    return " / ".join(cpus) or "the machine that made them"
