"""Racing seeds: a table's rows compared at a few planned looks, seeds added only where a comparison is undecided.

The plan is ``table.seeds`` (``{looks: [3, 5, 8], alpha: 0.05, correction: bonferroni, budget_min: 120}``): at
look k every row still racing has seeds ``0 .. looks[k]-1``. At each look, each row is compared with the
reference row, and the top row (highest mean so far) with the second, by a two-sided paired t-test over the seeds
the two share. A comparison is *decided* when its p-value is at most the look's share of ``alpha``; it is not
tested again. A row stops once every comparison it is part of is decided; the others get seeds up to the next
look. After the last look (or when ``budget_min`` of wall time would be exceeded, or when a look was not run) the
comparisons still open are *undecided*.

Repeated looks at accumulating data inflate the error rate: uncorrected, three looks at alpha = 0.05 each declare
a difference between two identical rows about 11 % of the time. The correction splits ``alpha`` over the planned
looks, so that by the union bound a comparison of two identical rows is declared at some look with probability at
most ``alpha``:

* ``bonferroni`` (the default): ``alpha / K`` at each of the K looks;
* ``pocock``: the increments of Lan & DeMets' Pocock-type spending function ``alpha * ln(1 + (e - 1) t)``
  (Lan & DeMets 1983, Biometrika 70(3), eq. for alpha_2*), at the information times ``t_k = n_k / n_K``;
* ``obrien_fleming``: the increments of the O'Brien-Fleming-type spending function
  ``2 - 2 Phi(z_{1 - alpha/2} / sqrt(t))`` (same paper), which keeps most of ``alpha`` for the last look;
* ``none``: ``alpha`` at every look, which does not hold the error rate (kept to show why a correction is needed).

Reading chosen: the spending increments are used as nominal per-look levels of the t-test (a union bound), not as
exact group-sequential boundaries, which at 3-8 seeds with an unknown variance have no closed form; the union
bound is conservative (about 4 % false positives at looks 3, 5, 8 in simulation). Each comparison also reports
P(A > B) over its paired seeds (Bouthillier et al. 2021, "Accounting for variance in machine learning
benchmarks", MLSys: a claim A > B wants the interval's lower bound above 0.5) with a Wilson score interval.

Both the racing sweeper (``hydra_plugins.ablate_racing_sweeper``) and the tables decide with :func:`race`, from
the runs' per-seed values, so the two can never disagree: the table reconstructs the race from the seeds each row
has. The outcome depends on the values per (row, seed) only, never on the launcher or on the order jobs finish.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd
from omegaconf import DictConfig, OmegaConf
from scipy import stats

from ablate.tables.collect import latest, under_condition

CORRECTIONS = ("bonferroni", "pocock", "obrien_fleming", "none")
LEVEL = 0.95


@dataclass(frozen=True)
class RacePlan:
    """The looks (seeds per row at each), the error rate ``alpha`` of one comparison, its correction over the
    looks, and the wall-time budget of the race in minutes (None: none)."""

    looks: tuple[int, ...]
    alpha: float = 0.05
    correction: str = "bonferroni"
    budget_min: float | None = None

    def __post_init__(self) -> None:
        looks = list(self.looks)
        if not looks or any(not isinstance(n, int) or isinstance(n, bool) or n < 1 for n in looks):
            raise ValueError(f"table.seeds.looks: {looks} must be a non-empty list of positive integers")
        if looks != sorted(set(looks)):
            raise ValueError(f"table.seeds.looks: {looks} must increase strictly")
        if not 0 < self.alpha < 1:
            raise ValueError(f"table.seeds.alpha: {self.alpha} must lie between 0 and 1")
        if self.correction not in CORRECTIONS:
            raise ValueError(f"table.seeds.correction: {self.correction!r} is not one of {', '.join(CORRECTIONS)}")
        if self.budget_min is not None and self.budget_min <= 0:
            raise ValueError(f"table.seeds.budget_min: {self.budget_min} must be positive (or null: no budget)")

    @classmethod
    def from_config(cls, seeds: Mapping[str, Any] | None) -> RacePlan | None:
        """The plan of ``table.seeds``, or None where the table does not race."""
        if not seeds:
            return None
        unknown = set(seeds) - {"looks", "alpha", "correction", "budget_min"}
        if unknown:
            raise ValueError(f"table.seeds: unknown option(s) {', '.join(sorted(unknown))}")
        budget = seeds.get("budget_min")
        return cls(
            tuple(seeds.get("looks") or ()),
            float(seeds.get("alpha", 0.05)),
            str(seeds.get("correction", "bonferroni")),
            None if budget is None else float(budget),
        )

    @classmethod
    def of_table(cls, cfg: DictConfig) -> RacePlan | None:
        """The plan of a composed config's table (``table.seeds``, which experiments take from ``scale.race``): the
        one source of a table's seeds, for the racing sweeper, the tables, the diagnosis and the capacity plan."""
        seeds = cfg.table.get("seeds")
        return cls.from_config(OmegaConf.to_container(seeds, resolve=True) if seeds is not None else None)  # type: ignore[arg-type]

    @property
    def first(self) -> int:
        """The seeds every row gets: the first look's."""
        return self.looks[0]

    def levels(self) -> list[float]:
        """The nominal level of each look's test; they add up to ``alpha`` (but for ``none``)."""
        k = len(self.looks)
        if self.correction == "none":
            return [self.alpha] * k
        if self.correction == "bonferroni":
            return [self.alpha / k] * k
        t = np.asarray(self.looks, dtype=float) / self.looks[-1]
        if self.correction == "pocock":
            spent = self.alpha * np.log1p((math.e - 1) * t)
        else:
            spent = 2 - 2 * stats.norm.cdf(stats.norm.ppf(1 - self.alpha / 2) / np.sqrt(t))
        return [float(x) for x in np.diff(np.concatenate([[0.0], spent]))]

    def describe(self) -> str:
        """One sentence for a table's footer."""
        levels = " / ".join(f"{x:.4f}" for x in self.levels())
        how = {
            "bonferroni": "Bonferroni over the planned looks",
            "pocock": "Pocock-type alpha spending (Lan-DeMets)",
            "obrien_fleming": "O'Brien-Fleming-type alpha spending (Lan-DeMets)",
            "none": "no correction for the repeated looks (the error rate is not held)",
        }[self.correction]
        budget = f"; wall-time budget {self.budget_min:g} min" if self.budget_min else ""
        return (
            f"Racing seeds: looks at {', '.join(map(str, self.looks))} seeds per row, alpha = {self.alpha:g} per "
            f"comparison, {how}: per-look levels {levels} of a two-sided paired t-test{budget}"
        )


@dataclass(frozen=True)
class Comparison:
    """Row ``a`` against row ``b`` (``a - b``) at the look where it was decided or last tested."""

    a: str
    b: str
    why: str  # "reference" or "top vs second"
    look: int  # 1-based
    n: int  # paired seeds
    delta: float
    p: float
    level: float
    decided: bool
    p_ab: float  # P(A > B) over the paired seeds (ties count one half)
    p_ab_lo: float
    p_ab_hi: float

    def verdict(self) -> str:
        """``decided at look k`` or ``undecided``, with the figures."""
        state = f"decided at look {self.look}" if self.decided else "undecided"
        if self.n < 2:
            return f"{state} (n = {self.n}: no test below 2 paired seeds)"
        return (
            f"{state} (n = {self.n}, Δ {self.delta:+.2f}, p = {self.p:.3g} against {self.level:.4f}; "
            f"P(A > B) = {self.p_ab:.2f} [{self.p_ab_lo:.2f}, {self.p_ab_hi:.2f}])"
        )


@dataclass
class RaceState:
    """Where a race stands: its comparisons (the latest of each pair), the looks evaluated, and the rows that
    need seeds at the next look (empty when the race is over)."""

    plan: RacePlan
    comparisons: dict[frozenset[str], Comparison] = field(default_factory=dict)
    looks_done: int = 0
    racing: list[str] = field(default_factory=list)
    top: tuple[str, str] | None = None  # (top, second) at the last look
    reference: str | None = None  # the reference at the last look

    @property
    def over(self) -> bool:
        return not self.racing or self.looks_done >= len(self.plan.looks)

    def undecided(self) -> list[Comparison]:
        return [c for c in self.comparisons.values() if not c.decided]

    def seeds_wanted(self) -> int:
        """Seeds per racing row at the next look (0 when the race is over)."""
        return 0 if self.over else self.plan.looks[self.looks_done]


def wilson(successes: float, n: int) -> tuple[float, float]:
    """The 95 % Wilson score interval of a proportion (Wilson 1927), sound at the few seeds a table has."""
    if n == 0:
        return math.nan, math.nan
    z = float(stats.norm.ppf(1 - (1 - LEVEL) / 2))
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return max(0.0, centre - half), min(1.0, centre + half)


def paired_test(a: pd.Series, b: pd.Series) -> tuple[int, float, float, float, float, float]:
    """(n, mean of a - b, two-sided paired t-test p, P(A > B), its Wilson interval) over the seeds both have."""
    shared = a.index.intersection(b.index)
    d = (a[shared] - b[shared]).to_numpy(dtype=float)
    n = len(d)
    if n == 0:
        return 0, math.nan, math.nan, math.nan, math.nan, math.nan
    delta = float(d.mean())
    if n < 2:
        p = math.nan
    elif np.all(d == d[0]):  # no spread: the difference is exact
        p = 0.0 if delta else 1.0
    else:
        p = float(stats.ttest_1samp(d, 0.0).pvalue)
    wins = float((d > 0).sum() + 0.5 * (d == 0).sum())
    lo, hi = wilson(wins, n)
    return n, delta, p, wins / n, lo, hi


def _ranked(values: Mapping[str, pd.Series], rows: list[str], higher_is_better: bool) -> list[str]:
    means = {r: float(values[r].mean()) for r in rows if r in values and len(values[r])}
    order = sorted(means, key=lambda r: (-means[r] if higher_is_better else means[r], rows.index(r)))
    return order


def race(
    values: Mapping[str, pd.Series],
    rows: list[str],
    reference: str | list[str],
    plan: RacePlan,
    higher_is_better: bool = True,
    stop_after: int | None = None,
) -> RaceState:
    """Replay the race of ``rows`` on ``values``: per row, the primary metric indexed by integer seed.
    ``reference`` is a row, or a list of rows of which the best so far is the reference at each look (the table's
    reading of ``table.reference``, :func:`ablate.tables.summary.reference`). Looks are evaluated in order while their seeds are there (a look none of the racing rows reached
    was not run: the race stops before it), at most ``stop_after`` looks. Returns the state after the last look
    evaluated, with the rows that need seeds at the next one."""
    state = RaceState(plan, racing=list(rows))
    last = len(plan.looks) if stop_after is None else min(stop_after, len(plan.looks))
    levels = plan.levels()
    for k in range(last):
        n_k = plan.looks[k]
        seen = {r: _first(values.get(r), n_k) for r in rows}
        if k > 0 and not any(len(seen[r]) > plan.looks[k - 1] for r in state.racing):
            break  # the look was not run
        ranked = _ranked(seen, rows, higher_is_better)
        candidates = [reference] if isinstance(reference, str) else list(reference)
        ref = next((r for r in ranked if r in candidates), candidates[0])
        state.reference = ref
        pairs = [(r, ref, "reference") for r in rows if r != ref]
        state.top = (ranked[0], ranked[1]) if len(ranked) >= 2 else None
        if state.top and frozenset(state.top) not in {frozenset(p[:2]) for p in pairs}:
            pairs.append((*state.top, "top vs second"))
        current = {frozenset(p[:2]) for p in pairs}
        for key in [k for k in state.comparisons if k not in current]:
            del state.comparisons[key]  # an earlier top vs second (or reference) that no longer is one
        for a, b, why in pairs:
            key = frozenset((a, b))
            if key in state.comparisons and state.comparisons[key].decided:
                continue
            n, delta, p, p_ab, lo, hi = paired_test(seen[a], seen[b])
            decided = n >= 2 and not math.isnan(p) and p <= levels[k]
            state.comparisons[key] = Comparison(a, b, why, k + 1, n, delta, p, levels[k], decided, p_ab, lo, hi)
        state.looks_done = k + 1
        open_pairs = state.undecided()
        state.racing = [r for r in rows if any(r in (c.a, c.b) for c in open_pairs)]
    return state


def _first(series: pd.Series | None, n: int) -> pd.Series:
    """The values of seeds ``0 .. n-1`` that are there."""
    if series is None or not len(series):
        return pd.Series(dtype=float)
    s = pd.Series(series, dtype=float).dropna()
    s.index = [int(i) for i in s.index]
    return s[[i for i in s.index if 0 <= i < n]].sort_index()


def recorded_plan(runs: pd.DataFrame) -> dict[str, Any] | None:
    """The race plan the latest of ``runs`` ran under (its ``race_plan`` tag), or None: a table replays the race
    its runs ran, whatever the scale or overrides of the command that writes it."""
    plans = [p for p in runs.get("race_plan", pd.Series(dtype=str)) if isinstance(p, str) and p]
    return json.loads(plans[-1]) if plans else None


def seed_values(runs: pd.DataFrame, key: str) -> dict[str, pd.Series]:
    """Per row, the values of metric ``key`` indexed by integer seed (from :func:`ablate.tables.collect`)."""
    if not len(runs) or key not in runs:
        return {}
    out = {}
    for row, sel in runs.groupby("row"):
        seeds = pd.to_numeric(sel["seed"], errors="coerce")
        keep = seeds.notna().to_numpy()
        values = sel[key].to_numpy(dtype=float)[keep]
        out[str(row)] = pd.Series(values, index=seeds.to_numpy()[keep].astype(int)).dropna().sort_index()
    return out


def table_values(runs: pd.DataFrame, table: DictConfig) -> dict[str, pd.Series]:
    """Per row, the primary metric by seed of ``table``'s FINISHED runs (``runs``, from
    :func:`ablate.tables.collect.job_runs`; under ``primary_condition`` where the table has one): the very values
    the table shows."""
    runs = under_condition(latest(runs), table)
    return seed_values(runs, str(table.primary))


def decided(state: RaceState, a: str, b: str) -> bool:
    """Whether the race decided ``a`` against ``b``."""
    c = state.comparisons.get(frozenset((a, b)))
    return bool(c and c.decided)


def race_lines(state: RaceState, names: Mapping[str, str]) -> list[str]:
    """The footer's lines on a race: the plan and its correction, each comparison's outcome, and what was left
    undecided (and why the race ended there)."""
    lines = [state.plan.describe() + "."]
    for c in state.comparisons.values():
        lines.append(f"{names.get(c.a, c.a)} vs {names.get(c.b, c.b)} ({c.why}): {c.verdict()}.")
    open_ = [f"{names.get(c.a, c.a)} vs {names.get(c.b, c.b)}" for c in state.undecided()]
    if open_:
        if state.looks_done < len(state.plan.looks):
            why = (
                f"the race ended after look {state.looks_done} of {len(state.plan.looks)} "
                "(its wall-time budget, or failed jobs; the sweep's run says which)"
            )
        else:
            why = "after the last look"
        lines.append(f"Left undecided, {why}: {', '.join(open_)}.")
    return lines
