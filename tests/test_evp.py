"""Expected validation performance against the number of trials (ablate.tables.evp): the without-replacement
estimator against values computed by hand."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from ablate.tables.evp import crossing, expected_max, max_of_n_weights


def test_one_trial_gives_the_mean_and_all_trials_the_maximum() -> None:
    values = [3.0, 1.0, 4.0, 1.5, 9.0]
    means, stds = expected_max(values)
    assert means[0] == pytest.approx(np.mean(values)) and means[-1] == 9.0 and stds[-1] == 0.0
    assert np.all(np.diff(means) >= 0)


def test_the_estimator_is_the_mean_best_over_every_subset() -> None:
    values = [0.2, 0.9, 0.4, 0.7]
    means, _ = expected_max(values)
    for n in range(1, 5):  # by hand: the best of each n-subset, averaged over the C(4, n) subsets
        subsets = list(itertools.combinations(values, n))
        assert means[n - 1] == pytest.approx(sum(max(s) for s in subsets) / len(subsets))
    assert means[1] == pytest.approx((0.9 + 0.4 + 0.7 + 0.9 + 0.9 + 0.7) / 6)
    assert max_of_n_weights(4, 2).sum() == pytest.approx(1.0)


def test_lower_is_better_takes_the_minimum_and_a_failed_trial_is_left_out() -> None:
    means, _ = expected_max([5.0, 2.0, math.nan, 3.0], higher_is_better=False)
    assert list(means) == pytest.approx([10.0 / 3, (2 + 2 + 3) / 3, 2.0])
    with pytest.raises(ValueError, match="n = 4 trials of 3"):
        max_of_n_weights(3, 4)


def test_curves_that_cross_say_the_ranking_depends_on_the_budget() -> None:
    narrow = expected_max([0.1, 0.1, 0.1, 0.95])[0]  # one good trial of four: poor at n = 1, best at n = 4
    broad = expected_max([0.6, 0.62, 0.61, 0.63])[0]
    assert crossing({"narrow": narrow, "broad": broad})
    assert not crossing({"broad": broad, "lower": broad - 0.1})
