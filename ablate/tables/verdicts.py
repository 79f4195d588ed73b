"""Verdicts of practical size: a region of practical equivalence (ROPE) of ±δ around no difference, the paired tests
a race's comparison ends with, and the correction over a table's comparisons.

**δ, one rule for every table** (:func:`rope_rule`), fixed in each experiment's ``table.rope`` before its first run
and never from the comparisons it judges: *a quarter of the lead the paper's best row holds over the paper's second
row on the table's primary metric* (under its ``primary_condition`` where it has one), at least :data:`FLOOR`. The
paper's own smallest claim of superiority within the table is that lead; a difference under a quarter of it would
not change the order the paper reports by a practical amount. A follow-up table the paper does not have takes the δ
of the table it follows (``table.rope.follows``). The floor keeps δ above the tables' display precision (two
decimals) and the run-to-run noise of a single evaluation.

**Three verdicts** for a comparison of rows A and B over n paired seeds, ``d = A - B`` (:func:`paired_tests`), each
a test at the look's level α_k (the race's split of α over its looks, :class:`~ablate.tables.raceplan.RacePlan`):

* *better / worse by more than δ*: the one-sided test of ``H0: d <= δ`` (or ``d >= -δ``, in the direction of the
  observed mean) rejects; equivalently the (1 - 2α_k) interval of the mean difference lies beyond ±δ;
* *equivalent within ±δ*: TOST, the two one-sided tests of ``H0: d <= -δ`` and ``H0: d >= δ`` (Schuirmann 1987),
  both reject; the (1 - 2α_k) interval lies inside (-δ, δ);
* *different, of uncertain practical size*: the two-sided paired t-test of ``H0: d = 0`` rejects, neither of the
  above does; or *undecided*: nothing rejects.

Both claims of practical size end the comparison (the race gives it no more seeds); a difference of uncertain size
and an undecided comparison go on to the next look, where more seeds may place the difference beyond δ or inside it.
Without a δ (an ad-hoc sweep) a comparison ends as soon as the two-sided test rejects, as before.

**Multiplicity** across a table's comparisons (each row against the reference, the top row against the second), on
top of the split over looks: at each look, each kind of claim (beyond δ, equivalent, different) is corrected over
the comparisons still open (:func:`rejected`):

* ``holm`` (the default): Holm's step-down (Holm 1979), the family-wise error rate: the chance that a table makes
  any false claim of that kind stays at α. A reader takes each line of a table as a finding, and a table has at most
  eight comparisons, where Holm costs little power against Bonferroni's single split;
* ``bh``: Benjamini-Hochberg's step-up (1995), the false discovery rate: the expected share of false claims among
  the table's claims stays at α (for independent or positively dependent tests: comparisons against one reference
  share it, a positive dependence);
* ``none``: each comparison at the look's level, as before (kept to show the rate a table reaches without it).

Each look's correction holds its rate at α_k over the comparisons it tests, and the looks' levels add up to α, so by
the union bound the rate over the race holds at α.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from scipy import special, stats

MULTIPLICITY = ("holm", "bh", "none")
#: The smallest δ: above the tables' display precision, in the primary metric's points.
FLOOR = 0.1
#: δ's share of the lead of the paper's best row over its second.
FRACTION = 0.25

BETTER, WORSE, EQUIVALENT, DIFFERENT, UNDECIDED = "better", "worse", "equivalent", "different", "undecided"
#: The level of P(A > B)'s interval, and its normal quantile.
LEVEL = 0.95
Z_LEVEL = float(stats.norm.ppf(1 - (1 - LEVEL) / 2))


@dataclass(frozen=True)
class Kernels:
    """Another CPU's kernels as a source of variance of a seed's paired difference (docs/verdicts.md), where a table
    measured them (``bench/kernel_spread.py``): ``per_seed``, the standard deviation each seed's difference gets on
    its own (``table.kernels_sd``); ``shared``, that of the shift every seed of a comparison gets alike
    (``table.kernels_cpu``), which more seeds do not average away (:mod:`ablate.tables.margin`)."""

    per_seed: float = 0.0
    shared: float = 0.0


@dataclass(frozen=True)
class PairedTests:
    """The paired tests of one comparison: ``n`` seeds, the mean difference and its standard error, and the p-values
    of the two-sided test against 0 (``p_diff``), the one-sided test beyond ±δ in the direction of the mean
    (``p_beyond``) and TOST (``p_equiv``); the last two NaN without a δ. ``sd`` is the seeds' standard deviation of
    the paired differences and ``frames_se`` the test frames' share of ``se`` (0: the seeds alone; see
    :func:`paired_tests`)."""

    n: int
    mean: float
    se: float
    p_diff: float
    p_beyond: float
    p_equiv: float
    sd: float = math.nan
    frames_se: float = 0.0
    kernels: Kernels = Kernels()

    def interval(self, level: float) -> tuple[float, float]:
        """The (1 - 2 ``level``) interval of the mean difference: what TOST at ``level`` reads."""
        if self.n < 2:
            return math.nan, math.nan
        half = float(special.stdtrit(self.n - 1, 1 - level)) * self.se
        return self.mean - half, self.mean + half


def paired_tests(
    d: Sequence[float] | np.ndarray,
    rope: float | None,
    frames_var: float = 0.0,
    kernels: Kernels = Kernels(),
) -> PairedTests:
    """The tests of :class:`PairedTests` on the paired differences ``d``: Student's t on n - 1 degrees of freedom.

    ``frames_var`` adds the test set as a second source of variance (:mod:`ablate.tables.twolevel`): the variance
    of the seeds' mean difference over draws of the test frames. The standard error is then the two levels' sum,
    ``sqrt(s_d^2 / n + frames_var)``, on the seeds' n - 1 degrees of freedom, so the interval is never narrower than
    the seeds' own t interval and equals it where the frames add nothing. A difference without spread at either
    level is exact: each test rejects (p = 0) or not (p = 1) by its value. ``kernels``: another CPU's kernels'
    variance, where the table measured it (:class:`Kernels`): ``sqrt((s_d^2 + per_seed^2) / n + shared^2 +
    frames_var)``."""
    d = np.asarray(d, dtype=float)
    n = len(d)
    if n < 2:
        mean = float(d.mean()) if n else math.nan
        return PairedTests(n, mean, math.nan, math.nan, math.nan, math.nan)
    mean, sd = float(d.mean()), float(d.std(ddof=1))
    frames_var = max(0.0, float(frames_var))
    own, shared = kernels.per_seed, kernels.shared
    se = math.sqrt((sd * sd + own * own) / n + shared * shared + frames_var)
    if se == 0:
        exact = PairedTests(n, mean, 0.0, 0.0 if mean else 1.0, math.nan, math.nan, 0.0)
        if rope is None:
            return exact
        beyond = 0.0 if abs(mean) > rope else 1.0
        return PairedTests(n, mean, 0.0, exact.p_diff, beyond, 0.0 if abs(mean) < rope else 1.0, 0.0)
    tests = t_tests(n, mean, se, rope, sd, math.sqrt(frames_var))
    return replace(tests, kernels=kernels)


def t_tests(
    n: int, mean: float, se: float, rope: float | None, sd: float = math.nan, frames_se: float = 0.0
) -> PairedTests:
    """:class:`PairedTests` of a mean difference ``mean`` with standard error ``se`` > 0 over ``n`` seeds (Student's
    t, n - 1 degrees of freedom)."""
    df = n - 1  # Student's t: special.stdtr(df, x) is its cdf at x (scipy.stats.t's, without its overhead)
    p_diff = float(2 * special.stdtr(df, -abs(mean) / se))
    if rope is None:
        return PairedTests(n, mean, se, p_diff, math.nan, math.nan, sd, frames_se)
    p_beyond = float(special.stdtr(df, -(abs(mean) - rope) / se))  # H0: |d| <= δ on the side of the observed mean
    p_equiv = float(max(special.stdtr(df, -(mean + rope) / se), special.stdtr(df, (mean - rope) / se)))
    return PairedTests(n, mean, se, p_diff, p_beyond, p_equiv, sd, frames_se)


def adjusted(ps: Sequence[float], method: str = "holm") -> list[float]:
    """The p-values ``ps`` (NaN: no test) adjusted for the family by ``method`` (see the module), so that a claim is
    made exactly where its adjusted p is at most the level: Holm's ``max_{j <= r} min(1, (m - j + 1) p_(j))``,
    Benjamini-Hochberg's ``min_{j >= r} min(1, m p_(j) / j)`` (Wright 1992, Biometrics 48(4)), or ``p`` itself."""
    if method not in MULTIPLICITY:
        raise ValueError(f"table.seeds.multiplicity: {method!r} is not one of {', '.join(MULTIPLICITY)}")
    tested = [i for i, p in enumerate(ps) if not math.isnan(p)]
    out = [math.nan] * len(ps)
    m = len(tested)
    order = sorted(tested, key=lambda i: ps[i])
    if method == "none":
        for i in tested:
            out[i] = float(ps[i])
    elif method == "holm":
        running = 0.0
        for rank, i in enumerate(order):
            running = max(running, min(1.0, (m - rank) * ps[i]))
            out[i] = running
    else:
        running = 1.0
        for rank in range(m - 1, -1, -1):
            i = order[rank]
            running = min(running, min(1.0, m * ps[i] / (rank + 1)))
            out[i] = running
    return out


def rejected(ps: Sequence[float], level: float, method: str = "holm") -> list[bool]:
    """Which of the p-values ``ps`` (NaN: no test) are rejected at ``level`` over the family, by ``method`` (see the
    module): those whose :func:`adjusted` p is at most ``level``."""
    return [not math.isnan(q) and q <= level for q in adjusted(ps, method)]


def verdict(beyond: bool, equivalent: bool, different: bool, mean: float) -> str:
    """The comparison's verdict from its claims' rejections (see the module); a claim of size goes first."""
    if beyond:
        return BETTER if mean > 0 else WORSE
    if equivalent:
        return EQUIVALENT
    return DIFFERENT if different else UNDECIDED


def words(kind: str, rope: float | None, unit: str = "") -> str:
    """A verdict as a table's lines say it."""
    d = f"{rope:g}{(' ' + unit) if unit else ''}" if rope is not None else ""
    return {
        BETTER: f"better by more than δ = {d}",
        WORSE: f"worse by more than δ = {d}",
        EQUIVALENT: f"equivalent within ±{d}",
        DIFFERENT: "different, of uncertain practical size" if rope is not None else "different beyond seed noise",
        UNDECIDED: "undecided",
    }[kind]


def paper_values(table: Mapping[str, Any]) -> dict[str, float]:
    """The paper's primary metric per row of ``table`` (a composed ``table`` config as plain data) that the table
    runs: from each row's ``paper`` (a ``paper_only`` row left out), or, for a table of conditions, from its
    ``primary_condition``'s ``paper`` per row."""
    key = str(table["primary"])
    if table.get("primary_condition") and table.get("conditions"):
        for condition in table["conditions"]:
            if condition.get("condition") == table["primary_condition"]:
                paper = condition.get("paper") or {}
                return {r: float(v[key]) for r, v in paper.items() if isinstance(v, Mapping) and key in v}
        return {}
    rows = [r for r in table.get("rows") or [] if not r.get("paper_only")]  # another system the paper quotes: not run
    return {
        str(r["row"]): float(r["paper"][key]) for r in rows if isinstance(r.get("paper"), Mapping) and key in r["paper"]
    }


def rope_rule(table: Mapping[str, Any], lower_is_better: bool = False) -> tuple[float, str] | None:
    """δ by the rule of the module for ``table``, and the reason in words; None where the paper gives fewer than two
    rows of it (a follow-up: it takes the δ of the table it follows)."""
    paper = paper_values(table)
    if len(paper) < 2:
        return None
    ranked = sorted(paper.items(), key=lambda kv: kv[1], reverse=not lower_is_better)
    (top, a), (second, b) = ranked[0], ranked[1]
    delta = max(FLOOR, round(FRACTION * abs(a - b), 2))
    names = {str(r["row"]): str(r.get("name", r["row"])) for r in table.get("rows") or []}
    floor = f", at least {FLOOR:g}" if delta == FLOOR else ""
    reason = (
        f"a quarter of the paper's lead of its best row, {names.get(top, top)} ({a:g}), over its second, "
        f"{names.get(second, second)} ({b:g}){floor}"
    )
    return delta, reason


def wilson(successes: float, n: int) -> tuple[float, float]:
    """The 95 % Wilson score interval of a proportion (Wilson 1927), sound at the few seeds a table has."""
    if n == 0:
        return math.nan, math.nan
    z = Z_LEVEL
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return max(0.0, centre - half), min(1.0, centre + half)
