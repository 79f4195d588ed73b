"""The interval over seeds and test frames (ablate.tables.twolevel), simulated on the project's own race: error rates
at 3, 5 and 8 seeds with frame noise, never narrower than the seeds' t, equal to it where the frames add nothing,
and the same verdicts whatever the order of the records."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from ablate.metrics.accumulate import COLUMNS, as_arrays
from ablate.tables.frames import FROM_COUNTS
from ablate.tables.raceplan import RacePlan
from ablate.tables.racing import race
from ablate.tables.twolevel import frames_variance, jackknife_variance
from ablate.tables.verdicts import BETTER, DIFFERENT, EQUIVALENT, WORSE, Kernels, paired_tests
from tests.published import RESULTS, published_tables

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

    from ablate.tables.columns import kernels

    d = np.array([0.20, 0.25, 0.22])
    seeds, both = paired_tests(d, 0.1), paired_tests(d, 0.1, 0.0, Kernels(0.08))
    assert both.se == pytest.approx(np.sqrt((d.var(ddof=1) + 0.08**2) / 3))
    assert both.p_beyond > seeds.p_beyond and both.interval(0.0167)[0] < seeds.interval(0.0167)[0]
    assert kernels(OmegaConf.create({"kernels_sd": None})) == Kernels()
    with pytest.raises(ValueError, match="table.kernels_sd"):
        kernels(OmegaConf.create({"kernels_sd": -1}))


def kitti_rows(rng: np.random.Generator, frames: int) -> pd.DataFrame:
    """Two detectors' (rows a, b) KITTI rows (ablate.metrics.accumulate) on a population of ``frames`` frames
    (``source``), each frame's detections fixed (a trained model's): per frame 1-5 counted cars; each found with a
    probability that follows the frame's difficulty (shared by both) and the detector, at a score that does too;
    about one false positive a frame at lower scores."""
    out = []
    hard = rng.uniform(0, 1, frames)
    cars = rng.integers(1, 6, frames)
    for row, skill in (("a", 0.85), ("b", 0.75)):
        for f in range(frames):
            found = rng.uniform(0, 1, cars[f]) < skill * (1 - 0.5 * hard[f])
            tp = rng.beta(6, 2, found.sum()) * (1 - 0.3 * hard[f])
            fp = rng.beta(2, 4, rng.poisson(1.0))
            out += [(row, f, "gt", int(cars[f]), 0, np.nan)]
            out += [(row, f, "tp", 0, 0, x) for x in tp] + [(row, f, "cut", 1, 0, x) for x in tp]
            out += [(row, f, "cut", 0, 1, x) for x in fp]
    rows = pd.DataFrame(out, columns=["row", "source", "kind", "a", "b", "score"])
    return rows.assign(cls="Car", level=1, metric="car_moderate", condition="", seed=0, run_id=rows["row"])


def ap_left_out(rows: pd.DataFrame, metric: str) -> pd.Series:
    """The delete-one jackknife's replicates of ``metric`` over one run's rows: the metric with each frame left out
    (by frame name), what the AP tables read before the draws replaced it."""
    from ablate.tables.frames import FROM_DETECTIONS

    arrays = as_arrays({c: rows[c].to_numpy() for c in COLUMNS})
    frame_of = rows.groupby("index")["frame"].first()
    left = {}
    for frame, indices in frame_of.groupby(frame_of).groups.items():
        left[str(frame)] = FROM_DETECTIONS[metric](arrays, frame_of.index.difference(indices).to_numpy())
    return pd.Series(left).sort_index()


def test_an_ap_tables_frames_term_estimates_the_variance_of_another_draw_of_frames() -> None:
    """KITTI's 11-point AP steps where a frame tips one of its eleven recall points: a frame left out moves it by
    nothing or by a step, and the delete-one jackknife misjudges its variance (DGFN Table II: 0.5 to 15 points
    against 2.4 to 4.6 from draws). The AP tables' frames' term draws the frames; over new test sets of the same
    population it estimates the variance of the difference that another test set gives."""
    from ablate.tables.frames import FROM_DETECTIONS
    from ablate.tables.twolevel import detections_bootstrap, variance_of

    rng = np.random.default_rng(3)
    population = kitti_rows(rng, 1500)
    ap = FROM_DETECTIONS["car_moderate"]

    def table(frames: np.ndarray) -> pd.DataFrame:  # a test set: the population's frames, in image order
        rows = population[population["source"].isin(frames)]
        index = rows["source"].map({f: i for i, f in enumerate(frames)})
        return rows.assign(index=index, frame=index.map("{:06d}".format)).sort_values(["row", "index"], kind="stable")

    def difference(rows: pd.DataFrame) -> float:
        one = {r: ap(as_arrays({c: rows[rows["row"] == r][c].to_numpy() for c in COLUMNS}), None) for r in "ab"}
        return one["a"] - one["b"]

    # another test set of 60 frames each time, the models held fixed: the variance the term should estimate
    truth = np.var([difference(table(rng.choice(1500, 60, replace=False))) for _ in range(300)], ddof=1)
    drawn, left_out = [], []
    for _ in range(25):
        rows = table(rng.choice(1500, 60, replace=False))
        drawn.append(detections_bootstrap(rows, "car_moderate", draws=150)("a", "b", [0]))
        left_out.append(variance_of([tuple(ap_left_out(rows[rows["row"] == r], "car_moderate") for r in "ab")]))
    assert np.mean(drawn) == pytest.approx(truth, rel=0.3)
    assert np.mean(left_out) > 2 * truth  # what the delete-one jackknife would have said
    # one stream: the same records, listed in another order, give the same term
    rows = table(np.arange(60))
    again = rows.sample(frac=1, random_state=1).sort_values(["row", "index"], kind="stable")
    first = detections_bootstrap(rows, "car_moderate", draws=200)("a", "b", [0])
    assert detections_bootstrap(again, "car_moderate", draws=200)("a", "b", [0]) == first > 0


@pytest.mark.parametrize("path", published_tables(), ids=lambda p: p.stem)
def test_every_raced_table_says_which_test_frames_term_its_verdicts_read(path: Path) -> None:
    """A table of counts per frame: the jackknife's line; an AP table with detections per frame: the draws' line;
    an AP table without them, a conditions table (primary ``<condition>/<metric>``) too: that it reads the seeds
    alone. Exactly one of them."""
    from ablate.tables.columns import AP_FRAMES_LINE, FRAMES_LINE, NO_FRAMES_LINE

    text = path.read_text()
    assert "Racing seeds:" in text, f"{path.name}: a published table that did not race"
    runs = RESULTS / "runs"
    said = [line for line in (FRAMES_LINE, AP_FRAMES_LINE, NO_FRAMES_LINE) if line in text]
    if (runs / f"{path.stem}.frames.csv.gz").exists():
        assert said == [FRAMES_LINE], path.name
    elif (runs / f"{path.stem}.detections.csv.gz").exists():
        assert said == [AP_FRAMES_LINE], path.name
    else:
        assert said == [NO_FRAMES_LINE], path.name


@pytest.mark.parametrize("path", published_tables(), ids=lambda p: p.stem)
def test_a_table_that_claims_something_says_whether_another_cpus_kernels_were_measured(path: Path) -> None:
    """A verdict made on one CPU's kernels alone can fail on another's (BiFNet Table VI's equivalence did): a table
    with a claim either adds the measured kernels' variance or says its claims hold for its records' CPU."""
    from ablate.tables.columns import KERNELS_UNMEASURED

    text = path.read_text()
    claims = re.search(r"\((?:reference|top vs second)\): (?:better|worse|equivalent|different)", text)
    measured = "carries another CPU's kernels' variance too" in text
    unmeasured = KERNELS_UNMEASURED.split("{cpu}")[0] in text
    assert not (measured and unmeasured), path.name
    assert measured or unmeasured or not claims, path.name
