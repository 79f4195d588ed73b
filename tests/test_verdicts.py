"""Verdicts of practical size (ablate.tables.verdicts) through the race (ablate.tables.racing.race), on simulated
tables: a shared effect per seed (the data order and initialisation every row of a seed shares) plus each row's own
noise, the paired differences' standard deviation 1; looks at 3, 5 and 8 seeds, α = 0.05."""

from __future__ import annotations

import glob
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from omegaconf import OmegaConf

from ablate.config import compose
from ablate.tables.raceplan import RacePlan
from ablate.tables.racing import race
from ablate.tables.spec import LOWER_IS_BETTER
from ablate.tables.verdicts import BETTER, DIFFERENT, EQUIVALENT, WORSE, paired_tests, rejected, rope_rule

ALPHA = 0.05


def at_most_alpha(rate: float, tables: int) -> bool:
    """Whether a rate measured on ``tables`` simulated tables is consistent with a true rate of at most α: within
    two binomial standard errors above it (the simulations' own sampling error; each is seeded, so it does not vary
    from run to run)."""
    return rate <= ALPHA + 2 * math.sqrt(ALPHA * (1 - ALPHA) / tables)


CONF = Path(__file__).resolve().parents[1] / "conf"


def rates(offsets: list[float], tables: int, rope: float | None, correction: str = "bonferroni", over: str = "holm"):
    """Over ``tables`` simulated tables whose rows' true means are ``offsets`` (the first row the reference): the
    share of tables where some comparison against the reference is declared different (better, worse, or different),
    and where some is declared equivalent."""
    rng = np.random.default_rng(7)
    plan = RacePlan((3, 5, 8), ALPHA, correction, rope=rope, multiplicity=over)
    rows = [f"r{i}" for i in range(len(offsets))]
    declared = equivalent = 0
    for _ in range(tables):
        shared = rng.normal(0.0, 1.0, 8)
        values = {r: pd.Series(shared + m + rng.normal(0.0, math.sqrt(0.5), 8)) for r, m in zip(rows, offsets)}
        kinds = [c.kind for c in race(values, rows, rows[0], plan).comparisons.values() if c.why == "reference"]
        declared += any(k in (BETTER, WORSE, DIFFERENT) for k in kinds)
        equivalent += EQUIVALENT in kinds
    return declared / tables, equivalent / tables


def test_two_rows_exactly_delta_apart_are_declared_equivalent_at_most_alpha_of_the_time() -> None:
    _, equivalent = rates([0.0, 2.0], 2000, rope=2.0)
    assert at_most_alpha(equivalent, 2000), equivalent  # 0.039
    _, uncorrected = rates([0.0, 2.0], 2000, rope=2.0, correction="none")
    assert uncorrected > 2 * ALPHA, uncorrected  # 0.11: three looks at alpha each


def test_two_identical_rows_are_rarely_declared_different_and_mostly_equivalent_by_the_last_look() -> None:
    different, _ = rates([0.0, 0.0], 2000, rope=0.5)  # δ under the seeds' spread: the race runs its looks
    assert at_most_alpha(different, 2000), different  # 0.036
    uncorrected, _ = rates([0.0, 0.0], 2000, rope=0.5, correction="none")
    assert uncorrected > 2 * ALPHA, uncorrected  # 0.11
    different, equivalent = rates([0.0, 0.0], 500, rope=3.0)  # δ three times the spread of the differences
    assert at_most_alpha(different, 500) and equivalent >= 0.9, (different, equivalent)  # 0.0, 1.0


@pytest.mark.parametrize("n_rows", [2, 4, 8])
def test_a_null_table_keeps_its_table_wise_rate_with_holm_and_exceeds_it_without(n_rows: int) -> None:
    declared, _ = rates([0.0] * n_rows, 1000, rope=None)  # the default: Holm over the table's comparisons
    assert at_most_alpha(declared, 1000), declared  # 0.056, 0.039, 0.039
    if n_rows > 2:  # a 2-row table makes one comparison: nothing to correct
        uncorrected, _ = rates([0.0] * n_rows, 1000, rope=None, over="none")
        assert uncorrected > 2 * ALPHA, uncorrected  # 0.11, 0.22: the rates of the race before the correction


def test_holm_steps_down_and_benjamini_hochberg_steps_up() -> None:
    ps = [0.01, 0.04, 0.03, 0.005, math.nan]
    assert rejected(ps, 0.05, "none") == [True, True, True, True, False]
    # Holm: 0.005 <= 0.05/4, 0.01 <= 0.05/3, 0.03 > 0.05/2: stops there
    assert rejected(ps, 0.05, "holm") == [True, False, False, True, False]
    # BH: the largest rank k with p_(k) <= k/4 * 0.05 is 4 (0.04 <= 0.05): all four
    assert rejected(ps, 0.05, "bh") == [True, True, True, True, False]
    with pytest.raises(ValueError, match="multiplicity"):
        rejected(ps, 0.05, "bonferroni-holm")


def test_tost_reads_the_interval_at_twice_the_level() -> None:
    d = np.array([0.1, -0.1, 0.05, 0.0, -0.05, 0.02])
    t = paired_tests(d, rope=0.2)
    lo, hi = t.interval(0.05)  # the 90 % interval
    assert -0.2 < lo < hi < 0.2 and t.p_equiv <= 0.05  # inside ±δ: equivalent at 0.05
    assert paired_tests(d, rope=abs(hi) * 0.9).p_equiv > 0.05  # a δ inside the interval: not equivalent
    exact = paired_tests(np.full(4, 0.3), rope=0.2)  # no spread: exact
    assert (exact.p_diff, exact.p_beyond, exact.p_equiv) == (0.0, 0.0, 1.0)


def experiments() -> list[str]:
    return sorted(Path(f).stem for f in glob.glob(str(CONF / "experiment" / "*.yaml")))


@pytest.mark.parametrize("name", experiments())
def test_every_tables_delta_is_the_rules(name: str) -> None:
    table = OmegaConf.to_container(compose([f"experiment={name}"]).table, resolve=True)
    assert isinstance(table, dict) and table.get("rope"), f"{name}: no table.rope"
    rope = table["rope"]
    if rope.get("follows"):  # a follow-up the paper does not have: the δ of the table it follows
        table = OmegaConf.to_container(compose([f"experiment={rope['follows']}"]).table, resolve=True)
        assert isinstance(table, dict)
    found = rope_rule(table, str(table["primary"]) in LOWER_IS_BETTER)
    assert found is not None and rope["delta"] == found[0], (name, rope, found)


def test_a_table_says_each_verdict_in_words_and_draws_them_against_the_band(tmp_path: Path) -> None:
    from ablate.store import KIND_JOB, Tracker
    from ablate.tables import write_table
    from tests.stores import sqlite_uri

    rows = [("base", 0.0, "Reference"), ("same", 0.0, "Same"), ("big", 3.0, "Much better")]
    cfg = OmegaConf.create(
        {
            "table": {
                "name": "tv",
                "title": "Verdicts",
                "primary": "det_rate",
                "reference": "base",
                "rope": {"delta": 0.5, "reason": "a test's"},
                "seeds": {"looks": [3, 5], "alpha": 0.05, "correction": "bonferroni", "budget_min": None},
                "metrics": {"det_rate": "Det. Rate %"},
                "rows": [{"row": r, "name": name} for r, _, name in rows],
            }
        }
    )
    tracker = Tracker(sqlite_uri(tmp_path), str(tmp_path / "artifacts"))
    exp = tracker.experiment_id("tv")
    rng = np.random.default_rng(0)
    shared = rng.normal(90.0, 1.0, 5)  # a seed's own luck, shared by its rows
    for row, offset, _ in rows:
        for seed in range(5):
            tags = {"kind": KIND_JOB, "row": row, "seed": str(seed), "config_hash": f"{row}{seed}", "scale": "cpu"}
            run = tracker.start(exp, row, tags)
            tracker.log_metrics(run, {"det_rate": shared[seed] + offset + rng.normal(0.0, 0.02)})
            tracker.end(run, "FINISHED")
    written = write_table(cfg, tracker, results_dir=tmp_path / "out")
    text = (tmp_path / "out" / "tv.md").read_text()
    assert "Region of practical equivalence: ±δ = 0.5 Det. Rate %: a test's (the rule: docs/verdicts.md)." in text
    assert "Same vs Reference (reference): equivalent within ±0.5 at look 1" in text
    assert "Much better vs Reference (reference): better by more than δ = 0.5 at look 1" in text
    assert "Top row Much better against the second, Reference, on Det. Rate %: " in text
    assert "ahead by more than δ = 0.5 (the race's verdict)." in text
    numbers = pd.read_csv(tmp_path / "out" / "tv.csv").set_index("row")
    assert numbers.loc["same", "verdict"] == "equivalent" and numbers.loc["big", "verdict"] == "better"
    assert numbers.loc["base", "rope"] == 0.5
    assert tmp_path / "out" / "tv_verdicts.png" in written
