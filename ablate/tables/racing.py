"""Racing seeds: a table's rows compared at a few planned looks, seeds added only where a comparison is undecided.

The plan (``table.seeds``, :class:`~ablate.tables.raceplan.RacePlan`) names the looks: at look k every row still
racing has seeds ``0 .. looks[k]-1``. At each look, each row is compared with the reference row, and the top row
(highest mean so far) with the second, by a two-sided paired t-test over the seeds the two share. A comparison is
*decided* when its p-value is at most the look's share of ``alpha``; it is not tested again. A row stops once every
comparison it is part of is decided; the others get seeds up to the next look. After the last look (or when
``budget_min`` of wall time would be exceeded, or when a look was not run) the comparisons still open are
*undecided*. Each comparison's verdict and figures are a :class:`~ablate.tables.comparison.Comparison`.

Both the racing sweeper (``hydra_plugins.ablate_racing_sweeper``) and the tables decide with :func:`race`, from
the runs' per-seed values, so the two can never disagree: the table reconstructs the race from the seeds each row
has. The outcome depends on the values per (row, seed) only, never on the launcher or on the order jobs finish.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd
from omegaconf import DictConfig

from ablate.tables.collect import latest, under_condition
from ablate.tables.comparison import CLAIM_TESTS, Comparison
from ablate.tables.raceplan import RacePlan
from ablate.tables.twolevel import FramesVariance
from ablate.tables.verdicts import (
    BETTER,
    DIFFERENT,
    EQUIVALENT,
    UNDECIDED,
    WORSE,
    Kernels,
    PairedTests,
    adjusted,
    paired_tests,
    verdict,
    wilson,
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


def _paired(d: np.ndarray, tests: PairedTests) -> tuple[int, float, float, float, float, float]:
    """(n, mean of the differences ``d``, two-sided paired t-test p, P(A > B), its Wilson interval) from ``d`` and
    their tests."""
    n = len(d)
    if n == 0:
        return 0, math.nan, math.nan, math.nan, math.nan, math.nan
    wins = float((d > 0).sum() + 0.5 * (d == 0).sum())
    lo, hi = wilson(wins, n)
    return n, tests.mean, tests.p_diff, wins / n, lo, hi


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
    frames_var: FramesVariance | None = None,
    kernels: Kernels = Kernels(),
) -> RaceState:
    """Replay the race of ``rows`` on ``values``: per row, the primary metric indexed by integer seed.
    ``reference`` is a row, or a list of rows of which the best so far is the reference at each look (the table's
    reading of ``table.reference``, :func:`ablate.tables.summary.reference`). Looks are evaluated in order while their seeds are there (a look none of the racing rows reached
    was not run: the race stops before it), at most ``stop_after`` looks. Returns the state after the last look
    evaluated, with the rows that need seeds at the next one. ``frames_var`` adds the test frames' variance to each
    comparison's (:mod:`ablate.tables.twolevel`); without it the tests read the seeds alone. ``kernels`` adds another
    CPU's kernels' variance, where the table measured it (:class:`ablate.tables.verdicts.Kernels`)."""
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
        to_test = [pair for pair in pairs if not decided(state, *pair[:2])]
        _look(state, to_test, seen, k, levels[k], frames_var, kernels)
        state.looks_done = k + 1
        open_pairs = state.undecided()
        state.racing = [r for r in rows if any(r in (c.a, c.b) for c in open_pairs)]
    return state


def _look(
    state: RaceState,
    pairs: list[tuple[str, str, str]],
    seen: dict[str, pd.Series],
    k: int,
    level: float,
    frames_var: FramesVariance | None = None,
    kernels: Kernels = Kernels(),
) -> None:
    """Test the open comparisons ``pairs`` at look ``k`` (0-based) at ``level``, each kind of claim corrected over
    them (:func:`ablate.tables.verdicts.rejected`), and record each one's verdict: a claim of practical size (beyond
    δ, or equivalent within it) ends it; so does a difference where the table has no δ. A difference found at an
    earlier look stays found."""
    plan = state.plan
    shared = [_shared(seen[a], seen[b]) for a, b, _ in pairs]
    diffs = [d for _, d in shared]
    extra = [
        frames_var(a, b, seeds) if frames_var is not None and len(seeds) >= 2 else 0.0
        for (a, b, _), (seeds, _) in zip(pairs, shared)
    ]
    tests = [paired_tests(d, plan.rope, v, kernels) for d, v in zip(diffs, extra)]
    family = {kind: adjusted([getattr(t, kind) for t in tests], plan.multiplicity) for kind in CLAIM_TESTS.values()}
    claims = {kind: [not math.isnan(q) and q <= level for q in ps] for kind, ps in family.items()}
    for i, (a, b, why) in enumerate(pairs):
        key = frozenset((a, b))
        n, delta, _, p_ab, lo, hi = _paired(diffs[i], tests[i])
        kind = verdict(claims["p_beyond"][i], claims["p_equiv"][i], claims["p_diff"][i], tests[i].mean)
        p = family[CLAIM_TESTS.get(kind, "p_diff")][i]  # the adjusted p of the claim made (or of the test against 0)
        earlier = state.comparisons.get(key)
        if kind == UNDECIDED and earlier is not None and earlier.kind == DIFFERENT:
            continue  # a difference found at an earlier look stays found, with the figures it was found on
        done = kind in (BETTER, WORSE, EQUIVALENT) or (plan.rope is None and kind == DIFFERENT)
        ilo, ihi = tests[i].interval(level)
        state.comparisons[key] = Comparison(
            a,
            b,
            why,
            k + 1,
            n,
            delta,
            p,
            level,
            done,
            p_ab,
            lo,
            hi,
            kind,
            ilo,
            ihi,
            plan.rope,
            frames_var is not None,
            tests[i].sd,
            tests[i].frames_se,
            tests[i].kernels,
        )


def _shared(a: pd.Series, b: pd.Series) -> tuple[list[int], np.ndarray]:
    """The seeds both have (in increasing order) and ``a - b`` over them."""
    seeds, ia, ib = np.intersect1d(a.index.to_numpy(), b.index.to_numpy(), return_indices=True)
    return [int(s) for s in seeds], a.to_numpy(dtype=float)[ia] - b.to_numpy(dtype=float)[ib]


def _first(series: pd.Series | Sequence[float] | np.ndarray | None, n: int) -> pd.Series:
    """The values of seeds ``0 .. n-1`` that are there (by position where ``series`` has no index)."""
    if series is None or not len(series):
        return pd.Series(dtype=float)
    # values in seed order where they come as an array or a list
    given = series if isinstance(series, pd.Series) else pd.Series(series, dtype=float)
    # on the arrays, one Series made at the end: a race is replayed thousands of times by the tests of its rates
    values, seeds = given.to_numpy(dtype=float), np.asarray(given.index, dtype=int)
    keep = ~np.isnan(values) & (seeds >= 0) & (seeds < n)
    order = np.argsort(seeds[keep], kind="stable")
    return pd.Series(values[keep][order], index=seeds[keep][order])


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
    still = state.undecided()
    if still:
        if state.looks_done < len(state.plan.looks):
            why = (
                f"the race ended after look {state.looks_done} of {len(state.plan.looks)} "
                "(its wall-time budget, failed jobs, or a race that decided on a narrower interval than the table's "
                "verdicts read now; the sweep's run says which)"
            )
        else:
            why = "after the last look"
        for kind, head in ((UNDECIDED, "Left undecided"), (DIFFERENT, "Different, of uncertain practical size")):
            open_ = [f"{names.get(c.a, c.a)} vs {names.get(c.b, c.b)}" for c in still if c.kind == kind and c.n >= 2]
            if open_:
                lines.append(f"{head}, {why}: {', '.join(open_)}.")
        unseen = [f"{names.get(c.a, c.a)} vs {names.get(c.b, c.b)}" for c in still if c.n < 2]
        if unseen:
            lines.append(f"No verdict, fewer than 2 paired seeds: {', '.join(unseen)} (race 2 seeds or more).")
    return lines
