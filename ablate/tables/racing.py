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
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import pandas as pd
from omegaconf import DictConfig, OmegaConf
from scipy import stats

from ablate.tables.collect import latest, under_condition
from ablate.tables.twolevel import FramesVariance
from ablate.tables.verdicts import (
    BETTER,
    DIFFERENT,
    EQUIVALENT,
    MULTIPLICITY,
    UNDECIDED,
    WORSE,
    PairedTests,
    adjusted,
    paired_tests,
    verdict,
    wilson,
    words,
)

CORRECTIONS = ("bonferroni", "pocock", "obrien_fleming", "none")
#: The test each verdict rests on (:class:`~ablate.tables.verdicts.PairedTests`' p-value), and how a line names it.
CLAIM_TESTS = {BETTER: "p_beyond", WORSE: "p_beyond", EQUIVALENT: "p_equiv", DIFFERENT: "p_diff", UNDECIDED: "p_diff"}
TEST_WORDS = {"p_beyond": "beyond ±δ", "p_equiv": "TOST within ±δ", "p_diff": "against 0"}
LEVEL = 0.95
#: What a comparison of fewer than 2 paired seeds says: no spread, so no test and no verdict.
NO_VERDICT = "no verdict"


@dataclass(frozen=True)
class RacePlan:
    """The looks (seeds per row at each), the error rate ``alpha`` of one comparison, its correction over the
    looks, and the wall-time budget of the race in minutes (None: none)."""

    looks: tuple[int, ...]
    alpha: float = 0.05
    correction: str = "bonferroni"
    budget_min: float | None = None
    rope: float | None = None  # δ of the table's region of practical equivalence (table.rope.delta); None: none
    multiplicity: str = "holm"  # the correction over a table's comparisons (ablate.tables.verdicts)

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
        if self.rope is not None and not self.rope > 0:
            raise ValueError(f"table.rope.delta: {self.rope} must be positive (or null: no region of equivalence)")
        if self.multiplicity not in MULTIPLICITY:
            raise ValueError(f"table.seeds.multiplicity: {self.multiplicity!r} is not one of {', '.join(MULTIPLICITY)}")

    @classmethod
    def from_config(cls, seeds: Mapping[str, Any] | None) -> RacePlan | None:
        """The plan of ``table.seeds``, or None where the table does not race."""
        if not seeds:
            return None
        unknown = set(seeds) - {"looks", "alpha", "correction", "budget_min", "multiplicity"}
        if unknown:
            raise ValueError(f"table.seeds: unknown option(s) {', '.join(sorted(unknown))}")
        budget = seeds.get("budget_min")
        return cls(
            tuple(seeds.get("looks") or ()),
            float(seeds.get("alpha", 0.05)),
            str(seeds.get("correction", "bonferroni")),
            None if budget is None else float(budget),
            multiplicity=str(seeds.get("multiplicity", "holm")),
        )

    def with_rope(self, table: Mapping[str, Any] | DictConfig | None) -> RacePlan:
        """This plan with the δ of ``table`` (``table.rope.delta``; none where the table states none)."""
        rope = (table or {}).get("rope") or {}
        delta = rope.get("delta") if isinstance(rope, Mapping | DictConfig) else None
        return replace(self, rope=None if delta is None else float(delta))

    @classmethod
    def of_table(cls, cfg: DictConfig) -> RacePlan | None:
        """The plan of a composed config's table (``table.seeds``, which experiments take from ``scale.race``): the
        one source of a table's seeds, for the racing sweeper, the tables, the diagnosis and the capacity plan."""
        seeds = cfg.table.get("seeds")
        plan = cls.from_config(OmegaConf.to_container(seeds, resolve=True) if seeds is not None else None)  # type: ignore[arg-type]
        return plan.with_rope(cfg.table) if plan is not None else None

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
        over = {
            "holm": "Holm's step-down over the table's comparisons (family-wise)",
            "bh": "Benjamini-Hochberg over the table's comparisons (false discovery rate)",
            "none": "no correction over the table's comparisons (each holds alpha on its own)",
        }[self.multiplicity]
        tests = (
            f"paired t-tests against 0 and against ±δ = {self.rope:g} (TOST for equivalence)"
            if self.rope is not None
            else "a two-sided paired t-test"
        )
        return (
            f"Racing seeds: looks at {', '.join(map(str, self.looks))} seeds per row, alpha = {self.alpha:g}, "
            f"{how}: per-look levels {levels} of {tests}; {over}{budget}"
        )


@dataclass(frozen=True)
class Comparison:
    """Row ``a`` against row ``b`` (``a - b``) at the look where it was decided or last tested: its verdict
    (:mod:`ablate.tables.verdicts`: better, worse, equivalent, different, undecided), the paired figures, and the
    (1 - 2 ``level``) interval of the mean difference TOST reads (``lo``, ``hi``)."""

    a: str
    b: str
    why: str  # "reference" or "top vs second"
    look: int  # 1-based
    n: int  # paired seeds
    delta: float
    p: float
    level: float
    decided: bool  # the race gives it no more seeds
    p_ab: float  # P(A > B) over the paired seeds (ties count one half)
    p_ab_lo: float
    p_ab_hi: float
    kind: str = UNDECIDED
    lo: float = math.nan
    hi: float = math.nan
    rope: float | None = None
    frames: bool = False  # the interval adds the test frames' variance (ablate.tables.twolevel) to the seeds'
    sd: float = math.nan  # the seeds' standard deviation of the paired differences
    frames_se: float = 0.0  # the test frames' standard error of the mean difference (0: the seeds alone)
    kernels_sd: float = 0.0  # the sd another CPU's kernels add to each seed's difference (table.kernels_sd)

    def verdict(self) -> str:
        """The verdict in words, where it was reached, with the figures."""
        if self.n < 2:
            return f"{NO_VERDICT} (n = {self.n}: a test needs 2 paired seeds or more)"
        said = words(self.kind, self.rope)
        state = f"{said} at look {self.look}" if self.kind != UNDECIDED else said
        over = "t interval over seeds and test frames" if self.frames else "t interval"
        shown = self.rope is not None or self.frames
        share = f"{100 * (1 - 2 * self.level):.1f}%"
        interval = f"[{self.lo:+.2f}, {self.hi:+.2f}], the {share} {over}; " if shown else ""
        spread = (
            f"seeds' sd {self.sd:.3g}"
            + (f", kernels' sd {self.kernels_sd:.3g}" if self.kernels_sd else "")
            + (f", frames' se {self.frames_se:.3g}" if self.frames else "")
        )
        return (
            f"{state} (n = {self.n}, Δ {self.delta:+.2f} {interval}{spread}; p = {self.p:.3g} {self.p_words()} "
            f"against {self.level:.4f}; P(A > B) = {self.p_ab:.2f} [{self.p_ab_lo:.2f}, {self.p_ab_hi:.2f}])"
        )

    def short(self) -> str:
        """The verdict in a few words, as the table's figure labels it."""
        return words(self.kind, self.rope) if self.n >= 2 else f"{NO_VERDICT} (n = {self.n})"

    def p_words(self) -> str:
        """What ``p`` is: the test the verdict rests on, adjusted over the table's comparisons at its look."""
        test = TEST_WORDS[CLAIM_TESTS.get(self.kind, "p_diff")] if self.rope is not None else "against 0"
        return f"({test}, adjusted over the look's comparisons)"


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


def paired_test(a: pd.Series, b: pd.Series) -> tuple[int, float, float, float, float, float]:
    """(n, mean of a - b, two-sided paired t-test p, P(A > B), its Wilson interval) over the seeds both have."""
    return _paired(_differences(a, b), paired_tests(_differences(a, b), None))


def _paired(d: np.ndarray, tests: PairedTests) -> tuple[int, float, float, float, float, float]:
    """:func:`paired_test`'s figures from the differences ``d`` and their tests."""
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
    kernels_sd: float = 0.0,
) -> RaceState:
    """Replay the race of ``rows`` on ``values``: per row, the primary metric indexed by integer seed.
    ``reference`` is a row, or a list of rows of which the best so far is the reference at each look (the table's
    reading of ``table.reference``, :func:`ablate.tables.summary.reference`). Looks are evaluated in order while their seeds are there (a look none of the racing rows reached
    was not run: the race stops before it), at most ``stop_after`` looks. Returns the state after the last look
    evaluated, with the rows that need seeds at the next one. ``frames_var`` adds the test frames' variance to each
    comparison's (:mod:`ablate.tables.twolevel`); without it the tests read the seeds alone. ``kernels_sd`` adds the
    variance another CPU's kernels add to each seed (``table.kernels_sd``)."""
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
        _look(state, to_test, seen, k, levels[k], frames_var, kernels_sd)
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
    kernels_sd: float = 0.0,
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
    tests = [paired_tests(d, plan.rope, v, kernels_sd) for d, v in zip(diffs, extra)]
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
            tests[i].kernels_sd,
        )


def _differences(a: pd.Series, b: pd.Series) -> np.ndarray:
    """``a - b`` over the seeds both have."""
    return _shared(a, b)[1]


def _shared(a: pd.Series, b: pd.Series) -> tuple[list[int], np.ndarray]:
    """The seeds both have (in increasing order) and ``a - b`` over them."""
    seeds, ia, ib = np.intersect1d(a.index.to_numpy(), b.index.to_numpy(), return_indices=True)
    return [int(s) for s in seeds], a.to_numpy(dtype=float)[ia] - b.to_numpy(dtype=float)[ib]


def _first(series: pd.Series | None, n: int) -> pd.Series:
    """The values of seeds ``0 .. n-1`` that are there."""
    if series is None or not len(series):
        return pd.Series(dtype=float)
    s = pd.Series(series, dtype=float).dropna()
    seeds = np.asarray(s.index, dtype=int)
    keep = (seeds >= 0) & (seeds < n)
    return pd.Series(s.to_numpy()[keep], index=seeds[keep]).sort_index()


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
