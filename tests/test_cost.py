"""What a table's decisions cost (ablate.tables.cost): the tuning phase's and the race's CPU minutes per comparison
decided, in the footer, the numbers and the results summary; and every committed table states it."""

from __future__ import annotations

import re

import numpy as np
import pandas as pd
import pytest

from ablate.tables.cost import race_minutes, table_cost, tuning_minutes
from ablate.tables.index import cost_of
from ablate.tables.raceplan import RacePlan
from ablate.tables.racing import race
from tests.published import published_tables

MIN = 60_000  # ms


def test_the_race_counts_each_job_trained_here_from_its_start_times_its_threads():
    runs = pd.DataFrame(
        {
            "row": ["a", "a", "b"],
            "started": [0, 0, 0],
            "job_started": [0, np.nan, 0],
            "ended": [10 * MIN, 4 * MIN, 6 * MIN],
            "made_threads": [2, 2, 2],
            "reused_from": ["", "", "run-of-another-table"],  # a copy cost nothing here
        }
    )
    runs.loc[1, "started"] = 1 * MIN  # no job_started: from its run's start
    assert race_minutes(runs) == pytest.approx(2 * 10 + 2 * 3)
    trials = pd.DataFrame({"seconds": [60.0, 120.0, 30.0]})  # failed or repeated trials count too
    assert tuning_minutes(trials, runs) == pytest.approx(3.5 * 2)
    assert tuning_minutes(None, runs) == 0.0 and race_minutes(runs.iloc[0:0]) == 0.0


def test_the_cost_is_per_comparison_the_race_decided():
    seeds = pd.Series({s: float(s % 2) * 0.01 for s in range(3)})
    values = {"top": 90.0 + seeds, "mid": 80.0 + seeds, "same": 80.0 + seeds.iloc[::-1].values}
    state = race(values, ["top", "mid", "same"], "mid", RacePlan((3,), rope=1.0))
    runs = pd.DataFrame({"row": ["top"], "started": [0], "job_started": [0], "ended": [30 * MIN], "made_threads": [1]})
    runs.attrs["trials"] = pd.DataFrame({"seconds": [1800.0]})
    cost = table_cost(state, runs)
    assert (cost.decided, cost.compared) == (sum(c.decided for c in state.comparisons.values()), 2)
    assert cost.decided == 2 and cost.per_decision_min == pytest.approx(30.0)
    assert cost.words() == (
        "Cost of the evidence: 60 CPU min (30 tuning, 30 racing) for 2 of 2 comparison(s) decided: "
        "30 CPU min per decided comparison (ablate.tables.cost)."
    )
    numbers = pd.DataFrame({"cpu_min": [120.0], "decided": [2], "cpu_min_per_decision": [60.0]})
    assert cost_of(numbers) == "1.0 (2 decided, 2.0 CPU h)"
    assert cost_of(numbers.assign(decided=0, cpu_min_per_decision=np.nan)) == "none decided (2.0 CPU h)"
    assert cost_of(pd.DataFrame({"kendall_tau": [1.0]})) == "—"  # numbers from before the cost


@pytest.mark.parametrize("path", published_tables(), ids=lambda p: p.stem)
def test_every_raced_table_states_the_cost_of_its_evidence_as_its_numbers_do(path):
    text = path.read_text()
    assert "Racing seeds:" in text, f"{path.name}: a published table that did not race"
    said = re.search(r"Cost of the evidence: (\d+) CPU min \((\d+) tuning, (\d+) racing", text)
    assert said, path.name
    total, tuning, racing = map(int, said.groups())
    assert abs(total - tuning - racing) <= 1
    numbers = pd.read_csv(path.with_suffix(".csv"))
    assert round(float(numbers["cpu_min"].iloc[0])) == total
