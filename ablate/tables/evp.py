"""Expected validation performance against the number of tuning trials (Dodge et al. 2019, "Show your work:
improved reporting of experimental results", EMNLP, §3), with the unbiased without-replacement estimator (Tang et
al. 2020, "Showing your work doesn't always work", ACL, eq. 4).

Of N random (i.i.d.) trials with validation values v_(1) <= ... <= v_(N), the best of n of them drawn without
replacement is v_(i) with probability [C(i, n) - C(i - 1, n)] / C(N, n), so

    E[max of n] = sum_i v_(i) [C(i, n) - C(i - 1, n)] / C(N, n),

n = 1 giving the mean and n = N the maximum. The band is one standard deviation of the same distribution
(sqrt(E[max^2] - E[max]^2)). Valid for random draws; below about 5 trials the curve says little (Tang et al.).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np


def max_of_n_weights(total: int, n: int) -> np.ndarray:
    """P(the best of ``n`` of ``total`` sorted values, drawn without replacement, is the i-th smallest), i = 1..N."""
    if not 1 <= n <= total:
        raise ValueError(f"n = {n} trials of {total}: n must lie in 1..{total}")
    i = np.arange(1, total + 1)
    return np.array([math.comb(int(k), n) - math.comb(int(k) - 1, n) for k in i], dtype=float) / math.comb(total, n)


def expected_max(values: Sequence[float], higher_is_better: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """(E[best of n], its standard deviation) for n = 1 .. N over the trials' validation ``values`` (NaN: a failed
    trial, left out); the best is the lowest where lower is better."""
    v = np.sort(np.asarray([x for x in values if not math.isnan(x)], dtype=float))
    if not higher_is_better:
        v = -v[::-1]
    means, stds = [], []
    for n in range(1, len(v) + 1):
        w = max_of_n_weights(len(v), n)
        mean = float(w @ v)
        means.append(mean)
        stds.append(math.sqrt(max(0.0, float(w @ (v * v)) - mean * mean)))
    sign = 1.0 if higher_is_better else -1.0
    return sign * np.asarray(means), np.asarray(stds)


def crossing(curves: dict[str, np.ndarray], higher_is_better: bool = True) -> bool:
    """Whether the rows' curves (E[best of n] over the same n) change order somewhere: the ranking depends on the
    tuning budget."""
    rows = list(curves)
    length = min(len(c) for c in curves.values()) if curves else 0
    orders = {
        tuple(sorted(rows, key=lambda r: -curves[r][n] if higher_is_better else curves[r][n])) for n in range(length)
    }
    return len(orders) > 1
