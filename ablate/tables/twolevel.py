"""Two sources of variance in one interval: the seeds' (training) and the test frames' (the test set's draw).

A table's test split is one draw of frames; a difference smaller than what another draw would move does not carry
to new data (Bouthillier et al. 2021, "Accounting for variance in machine learning benchmarks", MLSys). A
comparison of rows A and B over n paired seeds has per-seed differences ``d_s`` on the one test set; their mean
``d̄`` estimates the difference, and its variance over new seeds *and* a new test set is, to first order, the sum of
the two levels' terms (a nested two-stage design; Searle, Casella & McCulloch 1992, "Variance components", ch. 3):

    Var(d̄) = s_d² / n + V_frames

* ``s_d² / n``: the seeds' term, the sample variance of the paired differences over n (the paired t-test's);
* ``V_frames``: the frames' term, the variance of the seed-mean difference ``θ(F) = mean_s [M(A_s, F) - M(B_s, F)]``
  over draws of the frames F, the seeds held fixed, estimated for a metric of counts by the delete-one **jackknife over
  frames** (Efron & Stein 1981, Ann. Statist. 9(3): the jackknife variance is conservative in expectation; Efron 1982,
  "The jackknife, the bootstrap and other resampling plans", ch. 3): ``(F - 1) / F · Σ_i (θ_(i) - θ_(.))²`` with frame i
  left out of every (row, seed)'s counts. Each such metric is a function of its counts summed over frames (a ratio, an
  F-score's maximum over thresholds); at the hundreds of frames a test split has, these are smooth enough that the
  jackknife estimates the same first-order variance as the bootstrap over frames (checked against 2000 resamples on
  three published tables, ``docs/verdicts.md``), without Monte Carlo error: the same records give the same verdicts,
  whatever the order the records list the runs in (the frames are sorted by name, the seeds by number).
* **An AP metric's** frames' term is the paired bootstrap over frames instead (Efron & Tibshirani 1993, "An introduction
  to the bootstrap", ch. 6 and 11): the variance of ``θ(F*)`` over 1000 draws ``F*`` of the frames with replacement,
  every run's AP re-accumulated on the same draws from its frames' matched detections (:mod:`ablate.metrics.accumulate`:
  the matching is per frame, so a draw changes only the accumulation), from one fixed stream (the same records give the
  same term on any machine). AP is not smooth in the frames: the 11-point AP moves only where a frame tips one of its
  eleven recall points, and the delete-one jackknife, inconsistent for such statistics (as for a median; Efron 1982, ch.
  3), misjudged it by an order of magnitude both ways on DGFN Table II (0.5 to 15 points per run against 2.4 to 4.6 from
  draws; ``tests/test_twolevel.py`` simulates it: 4-9x the variance of another test set, the draws within 0.87-1.21x).

**The interval and the tests** use Student's t on the seeds' n - 1 degrees of freedom with the two-level standard
error ``sqrt(s_d² / n + V_frames)`` (:func:`ablate.tables.verdicts.paired_tests`). Reading chosen: the
Welch-Satterthwaite degrees of freedom of the sum would lie between n - 1 and n - 1 plus the frames' (many), and
their smaller t quantile can make the interval narrower than the seeds' own t interval at 3-8 seeds (the
percentile bootstrap over seeds this replaced lost the small-sample correction the same way). Keeping the
smaller component's degrees of freedom is the conservative bound of Satterthwaite's approximation (Satterthwaite
1946, Biometrics Bull. 2(6); the same rule as Welch's conservative ``min(n1, n2) - 1``): the interval is never
narrower than the seeds' t interval, and equals it where the frames add no variance. The jackknife term counts the
row-by-frame interaction a second time beside the seeds' variance (each seed's difference already varies with
it): conservative again, never liberal. Simulations of the race (``tests/test_twolevel.py``) check the error rates.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import numpy as np
import pandas as pd

from ablate.store import Tracker
from ablate.tables.collect import latest
from ablate.tables.frames import (
    AP_DRAWS,
    FROM_COUNTS,
    FROM_DETECTIONS,
    ap_resampled,
    counts_by_run,
    detections_by_run,
    detections_from_store,
    frame_draws,
    from_store,
)

#: frames_var(row_a, row_b, seeds) -> V_frames of the seed-mean difference a - b over those seeds.
FramesVariance = Callable[[str, str, list[int]], float]


def jackknife_variance(a: np.ndarray, b: np.ndarray, metric: Callable[[np.ndarray], np.ndarray]) -> float:
    """The delete-one jackknife variance over frames of ``mean_s [metric(a_s) - metric(b_s)]``, where ``a`` and ``b``
    are [seeds, frames, k] counts paired by seed and frame and ``metric`` maps counts summed over frames ([..., k])
    to the metric; 0 with fewer than two frames."""
    return variance_of(
        [(pd.Series(left_out_of(x, metric)), pd.Series(left_out_of(y, metric))) for x, y in zip(a, b, strict=True)]
    )


def left_out_of(counts: np.ndarray, metric: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """The metric of one run's counts [frames, k] with each frame left out in turn: [frames]."""
    if not len(counts):
        return np.zeros(0)
    return np.nan_to_num(metric(counts.sum(axis=0, keepdims=True) - counts))


#: left_out(row, seed) -> a run's metric with each test frame left out in turn, by frame name.
LeftOut = Callable[[str, int], pd.Series]


def counts_left_out(frames: pd.DataFrame, primary: str, condition: str = "") -> LeftOut:
    """:data:`LeftOut` from counts per frame (:data:`ablate.tables.frames.FROM_COUNTS`)."""
    metric = FROM_COUNTS[primary]
    by_run = functools.cache(lambda: counts_by_run(frames, condition))  # split on the first run asked for

    def left_out(row: str, seed: int) -> pd.Series:
        counts = by_run().get((row, int(seed)))
        if counts is None:  # a run that kept no counts: no frames (variance_of then finds none shared)
            return pd.Series(dtype=float)
        return pd.Series(left_out_of(counts.to_numpy(), metric), index=counts.index)

    return left_out


def detections_bootstrap(
    detections: pd.DataFrame, primary: str, condition: str = "", draws: int = AP_DRAWS
) -> FramesVariance:
    """The frames' term of an AP metric (:data:`ablate.tables.frames.FROM_DETECTIONS`) from its runs' detections per
    frame: the variance over ``draws`` paired draws of the test frames (with
    replacement, the table's frames sorted by name, one fixed stream) of the seed-mean difference; every run is
    re-accumulated on the same draws. A pair with a run that kept no detections gets 0."""
    by_run = functools.cache(lambda: detections_by_run(detections, primary, condition))  # split on first use
    frames = functools.cache(lambda: sorted({str(f) for rows in by_run().values() for f in rows["frame"]}))
    drawn = functools.cache(lambda: frame_draws(len(frames()), draws))
    replicates: dict[tuple[str, int], np.ndarray | None] = {}

    def one(row: str, seed: int) -> np.ndarray | None:
        if (row, seed) not in replicates:
            rows = by_run().get((row, int(seed)))
            ok = rows is not None and len(rows) > 0
            replicates[(row, seed)] = ap_resampled(rows, primary, frames(), drawn()) if ok else None
        return replicates[(row, seed)]

    def frames_var(row_a: str, row_b: str, seeds: list[int]) -> float:
        runs = [(one(row_a, int(s)), one(row_b, int(s))) for s in sorted(int(s) for s in seeds)]
        pairs = [(a, b) for a, b in runs if a is not None and b is not None]
        if not pairs or len(pairs) < len(runs) or len(frames()) < 2:
            return 0.0
        theta = np.mean([np.nan_to_num(a - b) for a, b in pairs], axis=0)
        return float(np.var(theta, ddof=1))

    return frames_var


def variance_of(left: list[tuple[pd.Series, pd.Series]]) -> float:
    """The jackknife variance of the seed-mean difference from each seed's (a, b) metrics with each frame left out,
    over the frames every one of them has; 0 under two such frames."""
    if not left:
        return 0.0
    frames = sorted(set.intersection(*(set(a.index) & set(b.index) for a, b in left)))
    if len(frames) < 2:
        return 0.0
    theta = np.mean([np.nan_to_num(a[frames].to_numpy() - b[frames].to_numpy()) for a, b in left], axis=0)
    n = len(frames)
    return float((n - 1) / n * ((theta - theta.mean()) ** 2).sum())


def frames_variance(
    frames: pd.DataFrame | None, primary: str, condition: str = "", detections: pd.DataFrame | None = None
) -> FramesVariance | None:
    """The frames' term for a table whose runs kept counts (``frames``) or detections (``detections``) per test
    frame (:mod:`ablate.tables.frames`), on its primary metric under ``condition``; None where they kept neither for
    it. A pair whose runs lack them, or were tested on other frames, gets no frames' term (0)."""
    if frames is not None and not frames.empty and primary in FROM_COUNTS:
        left_out = counts_left_out(frames, primary, condition)
    elif detections is not None and not detections.empty and primary in FROM_DETECTIONS:
        return detections_bootstrap(detections, primary, condition)
    else:
        return None
    runs: dict[tuple[str, int], pd.Series] = {}
    pairs: dict[tuple[str, str, tuple[int, ...]], float] = {}

    def one(row: str, seed: int) -> pd.Series:
        if (row, seed) not in runs:
            runs[(row, seed)] = left_out(row, seed)
        return runs[(row, seed)]

    def frames_var(row_a: str, row_b: str, seeds: list[int]) -> float:
        key = (row_a, row_b, tuple(sorted(int(s) for s in seeds)))
        if key not in pairs:
            pairs[key] = variance_of([(one(row_a, s), one(row_b, s)) for s in key[2]])
        return pairs[key]

    return frames_var


def store_frames(tracker: Tracker, runs: pd.DataFrame, primary: str, condition: str = "") -> FramesVariance | None:
    """The frames' term of a race in progress, from the counts or detections per frame its runs (``runs``, the
    store's) logged: what the racing sweeper decides with at each look, as the table will; None where they kept
    none."""
    if not isinstance(runs, pd.DataFrame) or not len(runs):
        return None
    if primary in FROM_COUNTS:
        return frames_variance(from_store(tracker, latest(runs)), primary, condition)
    if primary in FROM_DETECTIONS:
        return frames_variance(None, primary, condition, detections_from_store(tracker, latest(runs)))
    return None
