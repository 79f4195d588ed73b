"""Successive halving in the tuning phase (ablate.sweep.halving): every row the same rungs and promotions, the
promoted trials resumed, the choice replayable from full-budget curves."""

from __future__ import annotations

import json
import math
import re

import pandas as pd
import pytest

from ablate.sweep.halving import Halving, full_choice, promote, replay
from ablate.tables.tuning import FULL, halving_lines, last_trials
from tests.test_tuning import RECIPE_LR, TuningLauncher, narrow, tuned_sweep

HALVING = ["table.tune.halving={eta:3,rungs:[0.25,0.5,1.0]}"]


def test_each_rung_keeps_the_top_third_and_costs_less_than_the_full_budget() -> None:
    halving = Halving(3, (1 / 9, 1 / 3, 1.0))
    assert halving.counts(8) == [8, 3, 1] and halving.counts(1) == [1, 1, 1] and halving.counts(27) == [27, 9, 3]
    assert halving.rung_epochs(10) == [1, 3, 10] and halving.rung_epochs(2) == [1, 1, 2]
    assert halving.cost(8) == pytest.approx(8 / 9 + 3 * 2 / 9 + 2 / 3)  # each trial's epochs once: resumed
    assert halving.cost(8, epochs=6) == pytest.approx((8 * 1 + 3 * 1 + 1 * 4) / 6)  # whole epochs 1, 2, 6
    assert halving.cost(6, epochs=2) == pytest.approx((6 * 1 + 2 * 0 + 1 * 1) / 2)  # 58%: a 2-epoch recipe
    assert halving.override(0) == ["++rung=0.111111"] and halving.override(2) == []  # the last: the full budget


@pytest.mark.parametrize(
    ("given", "message"),
    [
        ({"eta": 1}, r"halving\.eta: 1 must be an integer of at least 2"),
        ({"rungs": [0.5, 0.25, 1.0]}, r"halving\.rungs: .* must be increasing .* the last 1"),
        ({"rungs": [0.5]}, r"halving\.rungs: \[0\.5\] must be increasing"),
        ({"rate": 2}, r"halving: unknown option\(s\) rate"),
    ],
)
def test_a_bad_halving_is_one_clear_error_naming_the_option(given: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        Halving.from_config(given)


def test_promotion_takes_the_best_of_equals_the_lower_trial_and_a_failed_trial_last() -> None:
    values = {0: 0.5, 1: 0.7, 2: math.nan, 3: 0.7, 4: 0.1}
    assert promote(values, 2) == [1, 3] and promote(values, 3) == [0, 1, 3]
    assert promote(values, 2, higher_is_better=False) == [0, 4]
    assert promote({0: math.nan, 1: math.nan}, 1) == [0]  # all failed: the first


def test_replay_cuts_a_slow_starter_that_full_budget_selection_would_choose() -> None:
    # trial 2 starts slowly and ends best; trials 0 and 1 lead at the first rung: halving cuts trial 2 there
    curves = {
        0: {1: 0.60, 2: 0.62, 3: 0.63, 4: 0.64},
        1: {1: 0.55, 2: 0.60, 3: 0.66, 4: 0.67},
        2: {1: 0.20, 2: 0.40, 3: 0.65, 4: 0.80},
    }
    halving = Halving(2, (0.25, 1.0))
    got = replay(curves, halving, epochs=4)
    assert got.rungs == [[0, 1, 2], [0, 1]] and got.chosen == 1 and full_choice(curves, 4) == 2
    assert (got.epochs, got.full_epochs) == (3 * 1 + 2 * 3, 12)
    later = replay(curves, Halving(2, (0.75, 1.0)), epochs=4)  # judged at epoch 3: trial 2 is among the top 2
    assert later.rungs[1] == [1, 2] and later.chosen == 2


def test_every_row_gets_the_same_rungs_and_its_own_top_trials_go_on(tmp_path, monkeypatch) -> None:
    # at the first rung the objective is the recipe's distance from each row's optimum, halved: an order that holds
    def at_rung(row: str, lr: float, rung: float) -> float:
        full = narrow(lr) if row == "chinet" else 93.0 - abs(math.log10(lr / 3e-4))
        return full * (0.5 + 0.5 * rung)

    launcher = TuningLauncher(lambda r, lr: at_rung(r, lr, 1.0), lambda r, lr, s: at_rung(r, lr, 1.0), at_rung=at_rung)
    sweeper = tuned_sweep(tmp_path, monkeypatch, launcher, "table.tune.trials=9", *HALVING)
    sweeper.sweep(["experiment=chinet_table2", "row=chinet,unet"])
    trials = [j for b in launcher.batches if "trial" in b[0] for j in b]
    per = {  # rung -> row -> the trials that trained there
        rung: {row: sorted(int(j["trial"]) for j in trials if j["row"] == row and j.get("rung", "1") == rung)
               for row in ("chinet", "unet")}
        for rung in ("0.25", "0.5", "1")
    }  # fmt: skip
    assert {rung: [len(t) for t in rows.values()] for rung, rows in per.items()} == {
        "0.25": [9, 9], "0.5": [3, 3], "1": [1, 1]
    }  # fmt: skip
    for rung, before in (("0.5", 0.25), ("1", 0.5)):  # each row's own top third of the rung before went on
        for row, kept in per[rung].items():
            values = launcher.at[before][row]
            assert kept == sorted(sorted(values, key=lambda k: (-values[k], k))[: len(kept)]), (rung, row)
    assert all(
        b and len({j["rung"] if "rung" in j else "1" for j in b}) == 1 for b in launcher.batches if "trial" in b[0]
    )
    raced = [j for b in launcher.batches if "trial" not in b[0] for j in b]
    chosen = {j["row"]: int(j["tuned"]) for j in raced}
    assert chosen == {row: per["1"][row][0] for row in ("chinet", "unet")}  # the one trial at the full budget
    lr = {j["row"]: float(j.get("draws.task.optimizer.lr", RECIPE_LR)) for j in raced}
    assert abs(math.log10(lr["chinet"] / 0.008)) < 0.5  # its narrow optimum survived the first rung


def test_the_footer_says_the_rungs_and_chooses_from_the_full_budget_alone() -> None:
    def trial(row: str, k: int, rung: float, value: float, seconds: float) -> dict:
        return {"row": row, "trial": k, "rung": rung, "val_best": value, "seconds": seconds, "trial_config": "{}"}

    runs = [trial("a", k, 0.5, 0.9 if k == 2 else 0.5, 60) for k in range(4)]  # trial 2 best at the first rung
    runs += [trial("a", k, FULL, 0.6 + 0.1 * k, 60) for k in (1, 2)]  # both promoted; trial 2 best at the end
    trials = pd.DataFrame(runs)
    assert list(last_trials(trials)["rung"]) == [0.5, FULL, FULL, 0.5]  # each trial's furthest rung
    assert list(last_trials(trials, 0.5)["val_best"]) == [0.5, 0.5, 0.9, 0.5]
    (line,) = halving_lines(trials)
    assert "4 at 0.5, 2 at 1" in line
    assert halving_lines(trials[trials["rung"] == FULL]) == []


def test_a_promoted_trial_resumes_and_trains_as_a_full_budget_trial(tmp_path) -> None:
    """A smoke table tuned by successive halving end to end: its trials at the first rung, the promoted ones resumed
    from their checkpoints to the full budget, each trial's curve recorded; the chosen trial's curve over its rungs
    is the one its full-budget trial, trained in one go elsewhere, has."""
    from tests.scaleout import SERIAL, TINY, ablate, output, runs

    args = ["experiment=chinet_table2", "row=chinet", "tune=lr_wd", "table.tune.trials=3", "trainer.max_epochs=2"]
    halving = ["table.tune.halving={eta:3,rungs:[0.5,1.0]}"]
    for where in ("halved", "alone"):
        (tmp_path / where).mkdir()
    out = ablate(tmp_path / "halved", "-m", *args, *halving, SERIAL, *TINY)
    assert out.returncode == 0, output(out)
    store = f"sqlite:///{tmp_path / 'halved' / 'mlflow.db'}"
    _, trials = runs(store, "chinet_table2", kind="trial")
    rungs = sorted((r.data.tags["trial"], r.data.tags.get("rung", "1")) for r in trials)
    assert [t for t, rung in rungs if rung == "0.5"] == ["0", "1", "2"] and len(rungs) == 4, rungs
    (full,) = [r for r in trials if "rung" not in r.data.tags]
    (first,) = [
        r for r in trials if r.data.tags.get("rung") == "0.5" and r.data.tags["trial"] == full.data.tags["trial"]
    ]
    assert full.data.tags["resumed_from"].endswith("last.ckpt") and "resumed_from" not in first.data.tags  # resumed
    curve = json.loads(first.data.tags["val_curve"]) | json.loads(full.data.tags["val_curve"])
    assert sorted(curve) == ["1", "2"], curve
    text = (tmp_path / "halved" / "results" / "chinet_table2.md").read_text()
    assert re.search(r"Successive halving: .*3 at 0\.5, 1 at 1", text), text
    k = full.data.tags["trial"]
    alone = ablate(tmp_path / "alone", *args, f"trial={k}", "seed=1000", *draws(full), *TINY)
    assert alone.returncode == 0, output(alone)
    _, (one,) = runs(f"sqlite:///{tmp_path / 'alone' / 'mlflow.db'}", "chinet_table2", kind="trial")
    assert json.loads(one.data.tags["val_curve"]) == curve  # resumed at the rung, it trained as in one go
    assert one.data.metrics["val_best"] == full.data.metrics["val_best"]
    assert one.data.tags["config_hash"] == full.data.tags["config_hash"]  # the last rung's run is the full trial's


def draws(run) -> list[str]:
    """A trial run's drawn values as overrides (``++draws.<key>=<value>``); none for the recipe."""
    if run.data.tags["trial"] == "0":
        return []
    return [f"++draws.{k}={v}" for k, v in json.loads(run.data.tags["trial_config"]).items()]
