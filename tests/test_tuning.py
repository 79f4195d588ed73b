"""The tuning phase (ablate.sweep.tuning): N trials per row in batches of one trial index, the budget stopping only
between batches, the choice on validation, and a table's tune spec checked option by option."""

from __future__ import annotations

import math

import pytest

from ablate.sweep.tuning import TuneSpec, choose, run_phase, tuned_overrides

SPACE = {"task.optimizer.lr": "tag(log, interval(1e-4, 1e-2))"}


def test_every_row_gets_the_same_trials_one_batch_per_trial_index() -> None:
    spec = TuneSpec.from_config({"trials": 4, "space": SPACE})
    assert spec is not None
    batches: list[list[list[str]]] = []
    phase = run_phase(spec, "t", {"a": ["row=a"], "b": ["row=b"]}, batches.append)
    assert phase.done == 4 and len(batches) == 4 and all(len(b) == 2 for b in batches)
    assert batches[0] == [["row=a", "seed=1000", "trial=0"], ["row=b", "seed=1000", "trial=0"]]  # the recipe
    for k, batch in enumerate(batches[1:], start=1):
        (a_lr, a_rest), (b_lr, b_rest) = [(job[1], job[2:]) for job in batch]
        assert a_lr == b_lr and a_lr.startswith("++task.optimizer.lr=")  # common random numbers
        assert a_rest == b_rest == ["seed=1000", f"trial={k}"]


def test_the_budget_stops_the_phase_only_between_trial_indices() -> None:
    spec = TuneSpec.from_config({"trials": 10, "space": SPACE, "budget_min": 1.0})
    assert spec is not None
    now = [0.0]
    launched: list[int] = []

    def launch(batch: list[list[str]]) -> None:
        launched.append(len(batch))
        now[0] += 25.0  # a trial index takes 25 s: the third would end at 75 s, past the minute

    phase = run_phase(spec, "t", {"a": [], "b": [], "c": []}, launch, clock=lambda: now[0])
    assert phase.done == 2 and launched == [3, 3] and "after trial 1 of every row" in phase.stopped


def test_the_choice_is_the_best_validation_trial_and_a_failed_trial_is_never_chosen() -> None:
    objectives = {"a": {0: 0.5, 1: 0.9, 2: math.nan, 3: 0.9}, "b": {0: 0.7, 1: 0.6}, "c": {1: math.nan}}
    assert choose(objectives, trials=4) == {"a": 1, "b": 0, "c": 0}  # a tie: the first; nothing scored: the recipe
    assert choose(objectives, trials=4, higher_is_better=False)["a"] == 0
    assert choose({"a": {0: 0.5, 5: 0.9}}, trials=4) == {"a": 0}  # a trial beyond N does not count
    assert tuned_overrides(TuneSpec(4, SPACE), "t", 0) == ["tuned=0"]


@pytest.mark.parametrize(
    "tune, message",
    [
        ({"trials": 0, "space": SPACE}, r"table\.tune\.trials: 0 must be a positive integer"),
        ({"trials": 3}, r"table\.tune\.space: empty"),
        ({"trials": 3, "space": {"task.optimizer.lr": "1e-3"}}, r"table\.tune\.space\.task\.optimizer\.lr: .* a value"),
        ({"trials": 3, "space": SPACE, "budget": 5}, r"table\.tune: unknown option\(s\) budget"),
    ],
)
def test_a_bad_tune_spec_is_one_clear_error_naming_the_option(tune: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        TuneSpec.from_config(tune)


def test_the_table_names_each_rows_chosen_trial_and_flags_crossing_curves(tmp_path) -> None:
    import pandas as pd
    from omegaconf import OmegaConf

    from ablate.tables.tuning import check_tuned, section, write_figure

    lr = lambda x: f'{{"task.optimizer.lr": {x}}}'  # noqa: E731
    trials = pd.DataFrame(
        [  # a: one good trial of four (narrow optimum); b: a broad plateau, best at the recipe
            ("a", 0, 0.10, lr(0.001)), ("a", 1, 0.12, lr(0.0002)), ("a", 2, 0.95, lr(0.008)), ("a", 3, 0.11, lr(0.0004)),
            ("b", 0, 0.62, lr(0.001)), ("b", 1, 0.60, lr(0.0002)), ("b", 2, 0.61, lr(0.008)), ("b", 3, math.nan, lr(0.0004)),
        ],
        columns=["row", "trial", "val_best", "trial_config"],
    )  # fmt: skip
    trials["seconds"] = 60.0
    table = OmegaConf.create({"name": "t", "title": "T", "tune": {"trials": 4, "space": SPACE, "seed": 0}})
    text = "\n".join(section(trials, table, {"a": "Row A", "b": "Row B"}))
    assert "| Row A | 4 | 2 | lr=0.008 | 0.95 | 4.0 |" in text
    assert "| Row B | 4 | 0 | lr=0.001 | 0.62 | 4.0 |" in text  # its failed trial counts as spent
    assert "the ranking depends on the tuning budget" in text
    assert write_figure(trials, table, {}, tmp_path) == tmp_path / "t_tuning.png"
    runs = pd.DataFrame({"row": ["a", "a", "b"], "tuned_config": [lr(0.008), lr(0.001), lr(0.001)]})
    with pytest.raises(ValueError, match="row a: its runs were tuned to different configs"):
        check_tuned(runs)
    check_tuned(runs[runs["row"] == "b"])
