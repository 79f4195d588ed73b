"""CI arithmetic on hand-made numbers, the paired test against the unpaired one, and failed-seed flags."""

import math

import numpy as np
import pandas as pd
import pytest
from omegaconf import OmegaConf

from ablate.tables.rows import to_markdown
from ablate.tables.significance import difference, disagreeing_seeds, mean_ci

T_975_DF2 = 4.302653  # Student's t, 97.5 % quantile, 2 degrees of freedom (any t table)


def test_t_interval_of_three_values():
    ci = mean_ci([1.0, 2.0, 3.0])  # mean 2, s = 1
    half = T_975_DF2 / math.sqrt(3)
    assert ci.method == "t"
    assert (ci.lo, ci.hi) == pytest.approx((2 - half, 2 + half), abs=1e-5)
    assert not ci.excludes_zero()


def test_one_value_has_no_interval_and_nans_are_dropped():
    assert math.isnan(mean_ci([5.0]).lo)
    assert mean_ci([1.0, float("nan"), 2.0, 3.0]).method == "t"


def test_bootstrap_from_thirty_values_is_deterministic_and_within_the_range():
    few = [10.0, 11.0, 12.0, 13.0, 14.0, 15.0, 16.0, 30.0]
    assert mean_ci(few).method == "t"  # the few seeds a table has: Student's t, never the too narrow percentiles
    values = [10.0 + i % 5 for i in range(29)] + [30.0]
    a, b = mean_ci(values), mean_ci(values)
    assert a.method == "bootstrap" and (a.lo, a.hi) == (b.lo, b.hi)
    assert 10.0 < a.lo < np.mean(values) < a.hi < 30.0
    assert a.hi - np.mean(values) > np.mean(values) - a.lo  # the outlier skews the percentile interval


def test_paired_difference_over_shared_seeds():
    row = pd.Series({"0": 10.0, "1": 12.0, "2": 14.0})
    ref = pd.Series({"0": 9.0, "1": 10.0, "2": 11.0})  # per-seed differences 1, 2, 3
    d = difference(row, ref)
    half = T_975_DF2 / math.sqrt(3)
    assert d.paired and d.n == 3 and d.delta == pytest.approx(2.0)
    assert (d.ci.lo, d.ci.hi) == pytest.approx((2 - half, 2 + half), abs=1e-5)
    # paired t: t = 2 / (1 / sqrt 3) = 3.4641 on 2 degrees of freedom -> two-sided p = 0.0742
    assert d.p == pytest.approx(0.0742, abs=5e-4)
    assert not d.significant


def test_a_paired_difference_at_eight_seeds_keeps_students_t():
    ref = pd.Series({str(s): 10.0 for s in range(8)})
    row = pd.Series({str(s): 10.0 + v for s, v in enumerate([0.1, 0.3, -0.2, 0.5, 0.0, 0.2, 0.4, -0.1])})
    d = difference(row, ref)
    from scipy.stats import t

    diffs = row.to_numpy() - 10.0
    half = t.ppf(0.975, 7) * diffs.std(ddof=1) / math.sqrt(8)
    assert d.ci.method == "t" and (d.ci.lo, d.ci.hi) == pytest.approx((diffs.mean() - half, diffs.mean() + half))


def test_pairing_removes_the_seed_to_seed_spread():
    ref = pd.Series({"0": 9.0, "1": 19.0, "2": 29.0})
    paired = difference(pd.Series({"0": 10.0, "1": 20.0, "2": 30.5}), ref)
    unpaired = difference(pd.Series({"3": 10.0, "4": 20.0, "5": 30.5}), ref)
    assert paired.paired and paired.significant and paired.test == "paired t"
    assert not unpaired.paired and not unpaired.significant and unpaired.test == "Welch t"


def test_welch_interval_by_hand():
    a, b = [1.0, 2.0, 3.0], [4.0, 5.0, 6.0, 7.0]
    va, vb = 1.0 / 3, (5.0 / 3) / 4
    dof = (va + vb) ** 2 / (va**2 / 2 + vb**2 / 3)
    from scipy.stats import t

    half = t.ppf(0.975, dof) * math.sqrt(va + vb)
    d = difference(pd.Series(a, index=["0", "1", "2"]), pd.Series(b, index=["3", "4", "5", "6"]))
    assert d.delta == pytest.approx(-3.5)
    assert (d.ci.lo, d.ci.hi) == pytest.approx((-3.5 - half, -3.5 + half))
    assert d.significant


def test_a_collapsed_seed_is_flagged():
    assert disagreeing_seeds(pd.Series({"0": 80.0, "1": 82.0, "2": 1.5})) == [("2", 1.5, 81.0)]
    assert disagreeing_seeds(pd.Series({"0": 80.0, "1": 70.0, "2": 75.0})) == []


def test_table_marks_significant_rows_names_the_reference_and_flags_commits():
    table = OmegaConf.create(
        {
            "name": "t",
            "title": "T",
            "primary": "ap",
            "metrics": {"ap": "AP", "iou": "IoU"},
            "reference": ["rgb", "ddm"],
            "rows": [
                {"row": "rgb", "name": "RGB"},
                {"row": "ddm", "name": "DDM"},
                {"row": "sum", "name": "Sum"},
                {"row": "max", "name": "Max"},
            ],
        }
    )
    runs = pd.DataFrame.from_records(
        [
            {
                "row": r,
                "seed": str(s),
                "scale": "cpu",
                "git_commit": "a" * 40 if r != "max" else "b" * 40 + "-dirty",
                "ap": v + s,
                "iou": 50.0 if (r, s) != ("max", 2) else 0.5,
            }
            for r, v in [("rgb", 10.0), ("ddm", 20.0), ("sum", 25.0), ("max", 20.2)]
            for s in range(3)
        ]
    )
    from ablate.tables.summary import summarise

    text = to_markdown(summarise(runs, table), runs, table)
    main = text.split("All metrics:")[0]
    rows = {line.split("|")[1].strip(): line for line in main.splitlines() if line.startswith("| ")}
    assert "AP 95% CI" in text and "Δ AP vs DDM [95% CI]" in text  # the better of the two experts
    assert "reference" in rows["DDM"]
    assert "+5.00 [+5.00, +5.00] *" in rows["Sum"]  # the same +5 on every shared seed
    assert "+0.20 [+0.20, +0.20] *" in rows["Max"]
    assert "[9.00, 13.00]" not in rows["RGB"] and "[8.52, 13.48]" in rows["RGB"]  # 11 ± t(2) / sqrt 3
    assert "Top row Sum against the second, Max" in text and "ahead beyond seed noise" in text
    assert "**Seeds disagree**: Max, IoU, seed 2 gives 0.50" in text
    assert "aaaaaaaaaaaa (9 runs)" in text and "bbbbbbbbbbbb-dirty (3 runs)" in text
    assert "**Mixed commits**" in text


def test_the_footer_names_a_t_and_a_bootstrap_ci_once_where_rows_have_different_seed_counts():
    from ablate.tables.columns import tests_used

    # unpaired rows of 3 seeds get a t CI of their difference, of 30 a bootstrap CI: both are Welch t-tests
    assert tests_used({("Welch t", False), ("Welch t", True)}) == "Welch t, bootstrap CI from n = 30"
    assert tests_used({("paired t", False)}) == "paired t"
    assert tests_used({("paired t", True)}) == "paired t, bootstrap CI"
    assert tests_used({("Welch t", False), ("paired t", False)}) == "Welch t, paired t"
    assert tests_used(set()) == "no test: too few seeds"
