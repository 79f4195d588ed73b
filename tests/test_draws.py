"""A tuning phase's draws (ablate.sweep.draws): trial 0 is the recipe; every row of a table gets the same draws,
each parameter's independent of the others in the space; values within their interval or choice."""

from __future__ import annotations

import pytest

from ablate.sweep.draws import draw

SPACE = {
    "task.optimizer.lr": "tag(log, interval(1e-4, 1e-2))",
    "task.optimizer.weight_decay": "interval(0.0, 1e-3)",
    "trainer.max_epochs": "choice(2, 4)",
}


def test_trial_zero_is_the_recipe_and_the_others_stay_in_their_space() -> None:
    assert draw(SPACE, "chinet_table2", seed=0, trial=0) == {}
    trials = [draw(SPACE, "chinet_table2", seed=0, trial=k) for k in range(1, 41)]
    lrs = [t["task.optimizer.lr"] for t in trials]
    assert all(1e-4 <= lr <= 1e-2 for lr in lrs)
    below = sum(lr < 1e-3 for lr in lrs)  # log-uniform: about half below the geometric middle
    assert 10 <= below <= 30
    assert all(0.0 <= t["task.optimizer.weight_decay"] <= 1e-3 for t in trials)
    assert {t["trainer.max_epochs"] for t in trials} == {2, 4}


def test_the_draws_are_common_to_the_rows_and_each_parameters_are_its_own() -> None:
    a = draw(SPACE, "chinet_table2", seed=0, trial=3)
    assert a == draw(SPACE, "chinet_table2", seed=0, trial=3)  # the row plays no part: the same for every row
    assert a != draw(SPACE, "chinet_table2", seed=1, trial=3) and a != draw(SPACE, "bifnet_table4", seed=0, trial=3)
    fewer = draw({"task.optimizer.lr": SPACE["task.optimizer.lr"]}, "chinet_table2", seed=0, trial=3)
    assert fewer["task.optimizer.lr"] == a["task.optimizer.lr"]  # another parameter in the space moves nothing


@pytest.mark.parametrize(
    "space, message",
    [
        ({"task.optimizer.lr": "0.001"}, "is a value, not an interval"),
        ({"task.optimizer.lr": "tag(log, interval(0, 1))"}, "a log interval needs a positive start"),
        ({"task.optimizer.lr": "interval(1e-4"}, "does not parse"),
        ({"task.optimizer.lr": "tag(log, uniform(1e-4, 1e-2))"}, "does not parse: .*Unknown function 'uniform'"),
    ],
)
def test_a_space_that_is_not_a_sweep_is_one_clear_error_naming_the_parameter(space: dict, message: str) -> None:
    with pytest.raises(ValueError, match=r"table\.tune\.space\.task\.optimizer\.lr: .*" + message):
        draw(space, "t", seed=0, trial=1)
