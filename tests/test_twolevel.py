"""The interval over seeds and test frames (ablate.tables.twolevel), simulated on the project's own race: error rates
at 3, 5 and 8 seeds with frame noise, never narrower than the seeds' t, equal to it where the frames add nothing,
and the same verdicts whatever the order of the records."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from ablate.tables.frames import FROM_COUNTS
from ablate.tables.raceplan import RacePlan
from ablate.tables.racing import race
from ablate.tables.twolevel import frames_variance, jackknife_variance
from ablate.tables.verdicts import BETTER, DIFFERENT, EQUIVALENT, WORSE, paired_tests

RATE = FROM_COUNTS["det_rate"]
SIMS = 300
ALPHA = 0.05
#: What a rate of at most ALPHA may show over SIMS simulated tables: two binomial standard errors.
SLACK = 2 * np.sqrt(ALPHA * (1 - ALPHA) / SIMS)


def table_counts(
    rng: np.random.Generator, n: int, lead: float, frames: int = 30, seed_sd: float = 0.002, frame_sd: float = 0.03
) -> tuple[np.ndarray, np.ndarray]:
    """Confusion counts [seeds, frames, 9] of rows a and b on one fresh test set: each frame's free-space pixels
    right at 0.9 of 1000, moved by the frame (shared), by the row on that frame (frame noise the rows do not share:
    the test set's draw moves their difference), by the seed, and a by ``lead`` (a share of the pixels: ``100 ·
    lead`` points of detection rate over the population of frames, exactly)."""
    base = 0.9 + rng.normal(0, 0.02, frames)
    out = []
    for shift in (lead, 0.0):
        own = rng.normal(0, frame_sd, frames)
        luck = rng.normal(0, seed_sd, (n, 1))
        right = 1000 * np.clip(base + own + luck + shift, 0, 1)
        c = np.zeros((n, frames, 9))
        c[..., 4], c[..., 3] = right, 1000 - right
        out.append(c)
    return out[0], out[1]


def judge(a: np.ndarray, b: np.ndarray, plan: RacePlan, frames: bool = True) -> str:
    """The race's verdict on a - b, on the seeds and (``frames``) the test frames."""
    values = {r: pd.Series(RATE(c.sum(axis=1)), index=range(len(c))) for r, c in (("a", a), ("b", b))}

    def frames_var(x: str, y: str, seeds: list[int]) -> float:
        rows = {"a": a, "b": b}
        return jackknife_variance(rows[x][seeds], rows[y][seeds], RATE)

    state = race(values, ["a", "b"], "b", plan, frames_var=frames_var if frames else None)
    (c,) = state.comparisons.values()
    return c.kind if c.a == "a" else {BETTER: WORSE, WORSE: BETTER}.get(c.kind, c.kind)


@pytest.mark.parametrize("n", [3, 5, 8])
def test_two_identical_rows_with_frame_noise_are_declared_different_at_most_alpha_of_the_time(n: int) -> None:
    rng = np.random.default_rng(n)
    plan = RacePlan((n,), alpha=ALPHA, rope=0.5)
    tables = [table_counts(rng, n, 0.0) for _ in range(SIMS)]
    both = np.mean([judge(a, b, plan) in (BETTER, WORSE, DIFFERENT) for a, b in tables])
    seeds = np.mean([judge(a, b, plan, frames=False) in (BETTER, WORSE, DIFFERENT) for a, b in tables])
    assert both <= ALPHA + SLACK
    assert seeds > 0.3  # the seeds alone miss the test set's draw: the frames' term is what holds the rate


@pytest.mark.parametrize("n", [3, 5, 8])
def test_two_rows_exactly_delta_apart_are_declared_equivalent_at_most_alpha_of_the_time(n: int) -> None:
    rng = np.random.default_rng(10 + n)
    delta = 0.5  # detection-rate points: a lead of 0.005 of the pixels
    plan = RacePlan((n,), alpha=ALPHA, rope=delta)
    tables = [table_counts(rng, n, delta / 100, frame_sd=0.005) for _ in range(SIMS)]
    assert np.mean([judge(a, b, plan) == EQUIVALENT for a, b in tables]) <= ALPHA + SLACK


def test_the_looks_of_a_race_hold_the_rate_over_seeds_and_frames() -> None:
    rng = np.random.default_rng(99)
    plan = RacePlan((3, 5, 8), alpha=ALPHA, rope=0.5)
    declared = [judge(*table_counts(rng, 8, 0.0), plan) in (BETTER, WORSE, DIFFERENT) for _ in range(SIMS)]
    assert np.mean(declared) <= ALPHA + SLACK


def test_where_the_frames_add_no_variance_the_interval_is_the_seeds_t_interval() -> None:
    rng = np.random.default_rng(3)
    a, b = table_counts(rng, 5, 0.01, frame_sd=0.0)
    a[:] = a[:, :1]  # every frame alike within a (row, seed): leaving one out moves nothing
    b[:] = b[:, :1]
    assert jackknife_variance(a, b, RATE) == pytest.approx(0.0, abs=1e-18)
    d = RATE(a.sum(axis=1)) - RATE(b.sum(axis=1))
    both, seeds = paired_tests(d, 0.5, jackknife_variance(a, b, RATE)), paired_tests(d, 0.5)
    assert both.interval(0.025) == pytest.approx(seeds.interval(0.025), abs=1e-12)


def test_the_interval_over_seeds_and_frames_is_never_narrower_than_the_seeds_t() -> None:
    rng = np.random.default_rng(4)
    for n in (2, 3, 5, 8):
        for _ in range(50):
            a, b = table_counts(rng, n, rng.normal(0, 0.005), frame_sd=rng.uniform(0, 0.05))
            d = RATE(a.sum(axis=1)) - RATE(b.sum(axis=1))
            lo, hi = paired_tests(d, 0.3, jackknife_variance(a, b, RATE)).interval(0.025)
            slo, shi = paired_tests(d, 0.3).interval(0.025)
            assert lo <= slo + 1e-12 and hi >= shi - 1e-12


def test_the_jackknife_estimates_the_variance_of_another_draw_of_frames() -> None:
    rng = np.random.default_rng(5)
    draws, estimates = [], []
    for _ in range(200):  # the seeds held fixed, a new test set each time
        a, b = table_counts(rng, 3, 0.0, seed_sd=0.0)
        draws.append(float((RATE(a.sum(axis=1)) - RATE(b.sum(axis=1))).mean()))
        estimates.append(jackknife_variance(a, b, RATE))
    assert np.mean(estimates) == pytest.approx(np.var(draws, ddof=1), rel=0.25)


def long_frames(a: np.ndarray, b: np.ndarray) -> pd.DataFrame:
    """The counts as a table's records keep them (ablate.tables.frames)."""
    out = []
    for row, c in (("a", a), ("b", b)):
        for s in range(c.shape[0]):
            for f in range(c.shape[1]):
                out.append(
                    {"row": row, "seed": s, "condition": "", "frame": f"{f:06d}"}
                    | {f"c{i}": c[s, f, i] for i in range(9)}
                )
    return pd.DataFrame(out)


def test_the_verdicts_are_the_same_whatever_order_the_records_list_the_runs_in() -> None:
    rng = np.random.default_rng(6)
    a, b = table_counts(rng, 5, 0.004)
    frames = long_frames(a, b)
    values = {r: pd.Series(RATE(c.sum(axis=1)), index=range(5)) for r, c in (("a", a), ("b", b))}
    plan = RacePlan((3, 5), rope=0.3)
    seen = set()
    for order in range(20):
        shuffled = frames.sample(frac=1.0, random_state=order)
        state = race(values, ["a", "b"], "b", plan, frames_var=frames_variance(shuffled, "det_rate"))
        seen.add(tuple((c.kind, c.look, c.lo, c.hi, c.p, c.frames_se) for c in state.comparisons.values()))
    assert len(seen) == 1
    ((comparison,),) = seen
    assert comparison[-1] > 0  # the frames were read, in every order alike


def test_another_cpus_kernels_widen_the_seeds_term_where_the_table_measured_them() -> None:
    from omegaconf import OmegaConf

    from ablate.tables.columns import kernels_sd

    d = np.array([0.20, 0.25, 0.22])
    seeds, both = paired_tests(d, 0.1), paired_tests(d, 0.1, 0.0, kernels_sd=0.08)
    assert both.se == pytest.approx(np.sqrt((d.var(ddof=1) + 0.08**2) / 3))
    assert both.p_beyond > seeds.p_beyond and both.interval(0.0167)[0] < seeds.interval(0.0167)[0]
    assert kernels_sd(OmegaConf.create({"kernels_sd": None})) == 0.0
    with pytest.raises(ValueError, match="table.kernels_sd"):
        kernels_sd(OmegaConf.create({"kernels_sd": -1}))
