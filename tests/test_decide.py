"""What deciding an undecided comparison would take (ablate.tables.decide), against simulated tables, and the
committed tables' words against their own numbers."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from ablate.tables.decide import MOST_FRAMES, POWER, frames_to_decide, job_cpu_hours, seeds_to_decide
from ablate.tables.verdicts import Kernels, paired_tests
from tests.published import RESULTS, published_tables


def decided_share(n: int, mean: float, sd: float, frames_se: float, rope: float | None, level: float) -> float:
    """The share of 2000 simulated comparisons at ``n`` seeds that reach the claim the estimate aims at: the paired
    differences drawn around ``mean`` with the seeds' sd, all moved by one draw of the test set (``frames_se``),
    tested with the frames' variance added as the tables add it."""
    rng = np.random.default_rng(int(1000 * abs(mean)) + n)
    hits = 0
    for _ in range(2000):
        d = mean + rng.normal(0, frames_se) + rng.normal(0, sd, n)
        t = paired_tests(d, rope, frames_se**2)
        if rope is None:
            hits += t.p_diff <= level
        elif abs(mean) > rope:
            hits += t.p_beyond <= level
        else:
            hits += t.p_equiv <= level
    return hits / 2000


@pytest.mark.parametrize(
    "mean,sd,frames_se,rope",
    [
        (0.5, 0.4, 0.0, 0.2),  # beyond δ, the seeds alone
        (0.5, 0.4, 0.03, 0.2),  # beyond δ, with the test set's variance
        (0.05, 0.3, 0.02, 0.3),  # equivalent within ±δ
        (0.4, 0.6, 0.05, None),  # different, a table without δ
    ],
)
def test_the_estimated_seeds_decide_about_the_share_they_promise(mean, sd, frames_se, rope) -> None:
    level = 0.0167
    n = seeds_to_decide(mean, sd, frames_se, rope, level)
    assert n is not None and 3 <= n <= 200
    share = decided_share(n, mean, sd, frames_se, rope, level)
    assert share == pytest.approx(POWER, abs=0.06)
    assert decided_share(max(2, n // 2), mean, sd, frames_se, rope, level) < POWER - 0.1  # fewer seeds: less often


def test_no_number_of_seeds_decides_what_the_test_set_alone_leaves_open() -> None:
    assert seeds_to_decide(0.25, 0.1, 0.05, 0.2, 0.0167) is None  # 0.05 beyond δ, the frames' se alone 0.05
    assert seeds_to_decide(0.2, 0.1, 0.0, 0.2, 0.0167) is None  # on δ


@pytest.mark.parametrize(
    "mean,sd,frames_se,rope",
    [
        (-7.2, 3.6, 2.4, 0.61),  # DGFN Table II's camera SSD against DGFN, beyond δ: 100 frames leave it open
        (0.08, 0.05, 0.12, 0.2),  # equivalent within ±δ (nearer +δ), the test set's term the larger
        (1.5, 0.6, 0.9, None),  # different, a table without δ
    ],
)
def test_the_estimated_test_frames_decide_about_the_share_they_promise(mean, sd, frames_se, rope) -> None:
    level, seeds, frames = 0.0083, 8, 100
    more = frames_to_decide(mean, sd, frames_se, rope, level, seeds, frames)
    assert more is not None and frames < more <= MOST_FRAMES * frames
    at = frames_se * np.sqrt(frames / more)  # the frames' standard error at the estimated test split
    assert decided_share(seeds, mean, sd, at, rope, level) == pytest.approx(POWER, abs=0.06)
    assert (
        decided_share(seeds, mean, sd, frames_se * np.sqrt(frames / max(frames, more // 2)), rope, level) < POWER - 0.1
    )


def test_no_number_of_test_frames_decides_what_the_seeds_alone_leave_open() -> None:
    assert frames_to_decide(2.24, 2.64, 1.46, 1.12, 0.0083, 8, 100) is None  # DGFN Table I: 8 seeds are too few
    assert frames_to_decide(0.5, 0.4, 0.0, 0.2, 0.0167, 8, 100) is None  # no frames' term to shrink
    assert frames_to_decide(0.5, 0.4, 0.2, 0.2, 0.0167, 8, 0) is None  # frames not kept
    assert frames_to_decide(-7.2, 3.6, 2.4, 0.61, 0.0083, 8, 100) == frames_to_decide(
        7.2, 3.6, 2.4, 0.61, 0.0083, 8, 100
    )


def test_a_jobs_cpu_hours_are_its_wall_time_by_its_threads_and_a_copy_costs_nothing() -> None:
    runs = pd.DataFrame(
        {
            "row": ["a", "a", "b", "c"],
            "seconds": [3600.0, 7200.0, 1800.0, 0.1],
            "made_threads": ["2", "2", "1", "1"],
            "reused_from": ["", "", "", "abc"],
        }
    )
    assert job_cpu_hours(runs, "a") == pytest.approx(3.0)  # median of 2 h and 4 h of CPU
    assert job_cpu_hours(runs, "c") == pytest.approx(job_cpu_hours(runs.iloc[:3], "zzz"))  # a copy: the table's


CLAIMS = re.compile(r"ahead|beyond seed noise")
FIGURES = re.compile(
    r"\[(?P<lo>[−+\-0-9.]+), (?P<hi>[−+\-0-9.]+)\].*?p = (?P<p>[0-9.e\-]+)(?:[^:]*?against (?P<level>0\.[0-9]+))?"
)


def number(text: str) -> float:
    return float(text.replace("−", "-"))


@pytest.mark.parametrize("path", sorted(RESULTS.glob("*_table*.md")), ids=lambda p: p.name)
def test_no_line_of_a_published_table_claims_more_than_its_interval_and_p(path: Path) -> None:
    for line in path.read_text().splitlines():
        if not line.startswith(("Top row", "Headline")) or not CLAIMS.search(line.split(":")[-1]):
            continue
        found = FIGURES.search(line)
        assert found, line
        lo, hi = number(found["lo"]), number(found["hi"])
        assert not lo <= 0 <= hi, line
        assert float(found["p"]) < float(found["level"] or 0.05), line


@pytest.mark.parametrize("path", published_tables(), ids=lambda p: p.stem)
def test_a_published_tables_test_frames_to_decide_are_in_its_footer_as_in_its_csv(path: Path) -> None:
    numbers = pd.read_csv(path.with_suffix(".csv"))
    text = path.read_text()
    said = {int(n) for n in re.findall(r"about (\d+) test frames would decide it", text)}
    kept = {
        int(n) for column in ("decide_frames", "top_decide_frames") for n in numbers.get(column, pd.Series()).dropna()
    }
    assert said == kept


def test_the_footer_offers_test_frames_where_the_races_seeds_would_not_decide() -> None:
    from ablate.tables.decide import ToDecide

    names = {"a": "A", "b": "B"}
    beyond = ToDecide("a", "b", 34, 52, 5.2, 0.0167, at_seeds=8, frames_now=100, frames=617)
    assert "about 34 seeds per row" in beyond.words(names, "a CPU")
    assert "Or, at 8 seeds per row (the race's last look), about 617 test frames would decide it" in beyond.words(
        names, "a CPU"
    )
    only = ToDecide("a", "b", None, 0, float("nan"), 0.0167, at_seeds=8, frames_now=100, frames=617)
    assert "the test set's own variance leaves too little room. At 8 seeds per row" in only.words(names, "a CPU")
    neither = ToDecide("a", "b", None, 0, float("nan"), 0.0167, at_seeds=8, frames_now=100, frames=None)
    assert "test frames would decide" not in neither.words(names, "a CPU")


def test_a_shift_every_seed_shares_caps_what_seeds_and_frames_can_decide() -> None:
    """Another CPU's shared shift stays whatever the seeds and the test frames: a difference within reach of seeds
    alone is out of reach once that shift is as large as its distance from δ."""
    from ablate.tables.comparison import Comparison
    from ablate.tables.decide import to_decide
    from ablate.tables.raceplan import RacePlan

    assert seeds_to_decide(1.0, 0.3, 0.0, 0.5, 0.0167) is not None
    assert seeds_to_decide(1.0, 0.3, 0.5, 0.5, 0.0167) is None  # the shared 0.5 never shrinks
    assert frames_to_decide(1.0, 0.3, 0.3, 0.5, 0.0167, 8, 100) is not None
    assert frames_to_decide(1.0, 0.3, 0.3, 0.5, 0.0167, 8, 100, shared=0.5) is None
    c = Comparison(
        "a", "b", "reference", 3, 8, 1.0, 0.5, 0.0167, True, 1.0, 0.5, 1.0, sd=0.3, kernels=Kernels(shared=0.5)
    )
    todo = to_decide(c, RacePlan((3, 5, 8), rope=0.5), 1, pd.DataFrame())
    assert todo.seeds is None and "the shift another CPU gives every seed alike" in todo.words({}, "a CPU")
