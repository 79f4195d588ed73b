"""Confidence intervals and significance over seeds, for the tables (:mod:`ablate.tables`).

* :func:`mean_ci` — a 95 % confidence interval for a row's mean over its seeds: Student's t for n < 30 (a
  percentile bootstrap's interval is too narrow at the few seeds a table has: it loses the small-sample correction
  t carries, Efron & Tibshirani 1993, "An introduction to the bootstrap", sec. 13.3; rliable, Agarwal et al. 2021,
  keeps t-based intervals there), a percentile bootstrap over seeds from n = 30 on (10 000 resamples, a fixed
  generator, so the same runs give the same bytes).
* :func:`difference` — a row against a reference row. Where the two share seeds (same data order and
  initialisation per seed), the test is *paired*: Student's t interval of the mean per-seed difference and the
  paired t-test, with the test frames' variance added where the table kept counts per frame
  (:mod:`ablate.tables.twolevel`: never narrower than the seeds' own t). Otherwise Welch's unequal-variance t
  interval and test (``ttest_ind``, ``equal_var=False``); from n = 30 per side a percentile bootstrap of the
  difference of means instead of the t interval. A difference is *significant* when its 95 % CI excludes 0.
* :func:`disagreeing_seeds` — seeds whose value falls far below the others of their row (a class never learnt,
  a run that diverged): such a row's mean hides a failure, so the report prints it under the table.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy import stats

from ablate.tables.verdicts import Kernels, paired_tests

LEVEL = 0.95
#: From this many values on, intervals come from a percentile bootstrap; below it from Student's t.
BOOTSTRAP_FROM = 30
RESAMPLES = 10_000
#: A seed disagrees with its row when its value is below this fraction of the median of the row's other seeds.
COLLAPSE_RATIO = 0.5


@dataclass(frozen=True)
class Interval:
    lo: float
    hi: float
    method: str  # "t", "t, frames" (seeds and test frames), "bootstrap" or "" (fewer than 2 values)

    def excludes_zero(self) -> bool:
        return bool(self.lo > 0 or self.hi < 0)


@dataclass(frozen=True)
class Difference:
    delta: float
    ci: Interval
    p: float
    paired: bool
    n: int  # seeds paired, or values of the smaller side

    @property
    def significant(self) -> bool:
        return self.ci.excludes_zero()

    @property
    def kind(self) -> str:
        return "paired t" if self.paired else "Welch t"

    @property
    def test(self) -> str:
        frames = " over seeds and test frames" if self.ci.method == "t, frames" else ""
        return self.kind + frames + (", bootstrap CI" if self.ci.method == "bootstrap" else "")


def _bootstrap(samples: list[np.ndarray], statistic: Callable[..., np.ndarray]) -> tuple[float, float]:
    rng = np.random.default_rng(0)
    draws = [s[rng.integers(0, len(s), size=(RESAMPLES, len(s)))] for s in samples]
    values = statistic(*draws)
    alpha = (1 - LEVEL) / 2
    return float(np.quantile(values, alpha)), float(np.quantile(values, 1 - alpha))


def mean_ci(values: Iterable[float] | pd.Series) -> Interval:
    """The 95 % CI of the mean of ``values`` (NaNs dropped); NaN bounds with fewer than two values."""
    x = np.asarray(pd.Series(values, dtype=float).dropna(), dtype=float)
    n = len(x)
    if n < 2:
        return Interval(np.nan, np.nan, "")
    if n >= BOOTSTRAP_FROM:
        return Interval(*_bootstrap([x], lambda d: d.mean(-1)), "bootstrap")
    half = stats.t.ppf(1 - (1 - LEVEL) / 2, n - 1) * x.std(ddof=1) / np.sqrt(n)
    return Interval(float(x.mean() - half), float(x.mean() + half), "t")


def prediction_interval(
    values: Iterable[float] | pd.Series, kernels: tuple[float, int] | None = None
) -> tuple[float, float]:
    """The 95 % prediction interval of one new value from the distribution ``values`` were drawn from:
    ``mean ± t(0.975, n-1) · s · sqrt(1 + 1/n)`` (normal values, unknown variance); NaN bounds below two values.

    ``kernels``: ``(sd, seeds)``, how far other numerics (another CPU's kernels, another thread count) move a run of
    the same seed, a root mean square over the reruns of ``seeds`` seeds (``table.kernels_run``,
    ``bench/kernel_spread.py``), for a new value made with other numerics than ``values``: its variance is added,
    ``s² (1 + 1/n) + sd²``, and t's degrees of freedom are Welch and Satterthwaite's for the sum (Satterthwaite
    1946), ``n - 1`` for the seeds' variance and ``seeds`` for the shift's; never narrower than without it (those
    degrees of freedom can exceed ``n - 1``, and t shrink more than the variance grows)."""
    x = np.asarray(pd.Series(values, dtype=float).dropna(), dtype=float)
    n = len(x)
    if n < 2:
        return np.nan, np.nan
    seeds = x.var(ddof=1) * (1 + 1 / n)
    sd, measured = kernels if kernels is not None else (0.0, 1)
    rounding = float(sd) ** 2
    total = seeds + rounding
    dof = total**2 / (seeds**2 / (n - 1) + rounding**2 / max(int(measured), 1)) if total > 0 else n - 1
    q = 1 - (1 - LEVEL) / 2
    half = max(stats.t.ppf(q, dof) * np.sqrt(total), stats.t.ppf(q, n - 1) * np.sqrt(seeds))
    return float(x.mean() - half), float(x.mean() + half)


def difference(
    row: pd.Series,
    ref: pd.Series,
    frames_var: Callable[[list[int]], float] | None = None,
    kernels: Kernels = Kernels(),
) -> Difference:
    """``row`` minus ``ref`` (values indexed by seed): mean difference, its 95 % CI and the test's p-value.

    Paired over the shared seeds when there are at least two (``frames_var(seeds)``: the test frames' variance of
    their mean difference, :mod:`ablate.tables.twolevel`; ``kernels``: another CPU's kernels' variance, where the
    table measured it); unpaired (Welch) otherwise."""
    row, ref = pd.Series(row, dtype=float).dropna(), pd.Series(ref, dtype=float).dropna()
    shared = row.index.intersection(ref.index)
    if len(shared) >= 2:
        shared = sorted(shared, key=lambda s: (float(s), str(s)))  # by seed: the same figures in any record order
        d = (row[shared] - ref[shared]).to_numpy()
        extra = frames_var([int(float(s)) for s in shared]) if frames_var is not None else 0.0
        t = paired_tests(d, None, extra, kernels)
        level = (1 - LEVEL) / 2
        lo, hi = t.interval(level) if t.se > 0 else (t.mean, t.mean)
        return Difference(
            t.mean, Interval(lo, hi, "t, frames" if frames_var is not None else "t"), t.p_diff, True, len(d)
        )
    a, b = row.to_numpy(), ref.to_numpy()
    delta = float(a.mean() - b.mean()) if len(a) and len(b) else np.nan
    if len(a) < 2 or len(b) < 2:
        return Difference(delta, Interval(np.nan, np.nan, ""), np.nan, False, min(len(a), len(b)))
    if min(len(a), len(b)) >= BOOTSTRAP_FROM:
        ci = Interval(*_bootstrap([a, b], lambda x, y: x.mean(-1) - y.mean(-1)), "bootstrap")
    else:
        va, vb = a.var(ddof=1) / len(a), b.var(ddof=1) / len(b)
        se = np.sqrt(va + vb)
        dof = (va + vb) ** 2 / (va**2 / (len(a) - 1) + vb**2 / (len(b) - 1)) if se > 0 else 1.0
        half = stats.t.ppf(1 - (1 - LEVEL) / 2, dof) * se
        ci = Interval(delta - half, delta + half, "t")
    p = float(stats.ttest_ind(a, b, equal_var=False).pvalue) if np.std(a) + np.std(b) > 0 else float(delta == 0)
    return Difference(delta, ci, p, False, min(len(a), len(b)))


def disagreeing_seeds(values: pd.Series) -> list[tuple[str, float, float]]:
    """(seed, value, median of the other seeds) for each seed below ``COLLAPSE_RATIO`` x that median."""
    values = pd.Series(values, dtype=float).dropna()
    out = []
    for seed, v in values.items():
        others = values.drop(seed)
        if len(others) and (med := float(others.median())) > 0 and v < COLLAPSE_RATIO * med:
            out.append((str(seed), float(v), med))
    return out
