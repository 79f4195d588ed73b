"""The kernels' terms (ablate.tables.margin): a shift another CPU gives every seed alike, the split of measured
reruns into the seeds' own part and the shared one, and the margin a table that has not measured them states."""

from __future__ import annotations

import math
import re

import numpy as np
import pandas as pd
import pytest

from ablate.tables.margin import PRECISION, claims, floor_2, kernels_margin, shift_parts
from ablate.tables.raceplan import RacePlan
from ablate.tables.racing import race
from ablate.tables.verdicts import Kernels, paired_tests
from tests.published import published_tables


def seeds(values: list[float]) -> pd.Series:
    return pd.Series(values, index=range(len(values)), dtype=float)


def test_the_margin_is_the_edge_where_the_first_claim_is_lost() -> None:
    # "far" is far worse than the reference, "near" just beyond δ, "same" equivalent: the near claim goes first
    rng = np.random.default_rng(7)
    ref = 50 + rng.normal(0, 0.3, 8)
    values = {
        "ref": seeds(list(ref)),
        "far": seeds(list(ref - 10 + rng.normal(0, 0.3, 8))),
        "near": seeds(list(ref - 1.6 + rng.normal(0, 0.3, 8))),
        "same": seeds(list(ref + rng.normal(0, 0.05, 8))),
    }
    plan = RacePlan((3, 5, 8), rope=1.0)

    def at(sd: float):
        return race(values, list(values), "ref", plan, kernels=Kernels(shared=sd))

    made = claims(at(0.0))
    assert len(made) == 3
    margin = kernels_margin(at)
    assert margin is not None and 0 < margin.sd < math.inf
    assert claims(at(margin.sd)) == made  # every claim holds at the margin
    beyond = claims(at(margin.sd * (1 + 2 * PRECISION)))
    assert beyond != made and "far" not in {margin.a, margin.b}  # and just beyond it the weaker one is lost
    assert {margin.a, margin.b} in ({"near", "ref"}, {"same", "ref"})
    assert all(frozenset({"far", "ref"}) in c for c in [made, beyond])


def test_a_table_without_claims_has_no_margin_and_an_unbeatable_claim_is_unbounded() -> None:
    noise = seeds([0.1, -0.2, 0.15, 0.0, -0.1, 0.05, 0.2, -0.15])
    plan = RacePlan((3, 5, 8), rope=0.01)
    assert (
        kernels_margin(lambda sd: race({"a": noise, "b": noise * 2}, ["a", "b"], "b", plan, kernels=Kernels(shared=sd)))
        is None
    )
    exact = {"a": seeds([1.0, 2.0, 3.0]), "b": seeds([1.0, 2.0, 3.0])}  # no plan with δ: identical rows, no claim
    assert kernels_margin(lambda sd: race(exact, ["a", "b"], "b", RacePlan((3,)), kernels=Kernels(shared=sd))) is None


def test_a_margin_is_shown_rounded_down() -> None:
    assert floor_2(0.5678) == pytest.approx(0.56) and floor_2(12.99) == 12 and floor_2(0.0999) == pytest.approx(0.099)


def test_a_table_without_its_kernels_measured_says_how_much_its_claims_bear() -> None:
    """Each published table whose footer says its kernels are not measured gives the margin, in the metric's units,
    and the comparison that binds it."""
    unmeasured = [p for p in published_tables() if "kernels' variance is not measured" in p.read_text()]
    assert unmeasured  # ChiNet III and V at least
    for path in unmeasured:
        said = re.search(
            r"Every claim would still hold with .* alike by an sd of up to ([0-9.]+) .*? vs .*? changes first",
            path.read_text(),
        )
        assert said is not None and float(said.group(1)) > 0, path.name


def test_a_shift_every_seed_shares_does_not_shrink_with_more_seeds() -> None:
    """Another CPU that moves a comparison's every seed alike moves its mean by as much at 3 seeds as at 300."""
    rng = np.random.default_rng(3)
    for n in (3, 30, 300):
        d = 1.0 + rng.normal(0, 0.2, n)
        own, shared = paired_tests(d, 0.5, kernels=Kernels(0.3)), paired_tests(d, 0.5, kernels=Kernels(shared=0.3))
        assert own.se == pytest.approx(np.sqrt((d.var(ddof=1) + 0.09) / n))
        assert shared.se == pytest.approx(np.sqrt(d.var(ddof=1) / n + 0.09))
    assert shared.se > 0.3 > 10 * own.se  # at 300 seeds the per-seed part is gone, the shared one is not


def test_reruns_split_into_the_seeds_own_shift_and_the_one_they_share() -> None:
    rng = np.random.default_rng(11)
    noise = [rng.normal(0, 0.5, 3) for _ in range(400)]  # every seed on its own: nothing shared
    own, shared = shift_parts(noise)
    assert own == pytest.approx(0.5, rel=0.05) and shared < 0.1
    bias = [np.full(3, b) for b in rng.normal(0, 0.8, 400)]  # every seed of a pair alike: all shared
    own, shared = shift_parts(bias)
    assert own < 1e-9 and shared == pytest.approx(0.8, rel=0.1)
    both = [b + e for b, e in zip(bias, noise)]
    own, shared = shift_parts(both)
    assert own == pytest.approx(0.5, rel=0.05) and shared == pytest.approx(0.8, rel=0.1)
    assert shift_parts([]) == (0.0, 0.0)


def test_a_tables_two_kernels_terms_are_read_together_and_a_bad_value_names_its_option() -> None:
    from omegaconf import OmegaConf

    from ablate.tables.columns import kernels

    assert kernels(OmegaConf.create({"kernels_sd": 0.2, "kernels_cpu": 0.1})) == Kernels(0.2, 0.1)
    assert kernels(OmegaConf.create({"kernels_sd": 0.2, "kernels_cpu": None})) == Kernels(0.2, 0.0)
    with pytest.raises(ValueError, match="table.kernels_cpu"):
        kernels(OmegaConf.create({"kernels_cpu": "high"}))
