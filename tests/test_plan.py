"""A sweep's plan (ablate.sweep.plan): the jobs and the experts they train first, each estimated from its recipe's
steps at a measured step time, and the wall time on the sweep's workers; on a fake clock and fake step times."""

from __future__ import annotations

from pathlib import Path

import pytest
from omegaconf import DictConfig, OmegaConf

from ablate.jobs.spec import best_checkpoint
from ablate.jobs.steptime import StepTimes
from ablate.store import config_hash
from ablate.sweep.plan import (
    Item,
    estimate,
    expert_seconds,
    items,
    lines,
    row_jobs,
    seconds,
    trains_alone,
    wall_seconds,
)
from tests.test_progress import planned_jobs, sweep_config
from tests.test_tuning import FULL_BUDGET

EXPERT = StepTimes(train_s=2.0, cached_s=2.0, eval_s=0.5, train_batches=10, eval_batches=2, test_batches=4)
FUSED = StepTimes(train_s=1.0, cached_s=0.25, eval_s=0.5, train_batches=10, eval_batches=2, test_batches=4)


class Clock:
    """A fake clock: each step time measured takes 20 s of it."""

    def __init__(self) -> None:
        self.now = 0.0
        self.measured: list[str] = []

    def __call__(self) -> float:
        return self.now

    def measure(self, cfg: DictConfig) -> StepTimes:
        self.now += 20.0
        expert = cfg.stage.name == "single"
        self.measured.append(f"expert {cfg.stage.modality}" if expert else str(cfg.fusion.name))
        return EXPERT if expert else FUSED


def test_the_headline_sweep_plans_its_two_experts_first_and_estimates_its_wall_time(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)  # no expert trained yet: ./checkpoints is empty
    plan = items(sweep_config("fusion=sum,max,sharpen,smoe"))
    names = [item.name for item in plan]
    assert names == [
        "expert rgb seed 0",
        "expert ddm_jet seed 0",
        *(f"fusion={f} seed 0" for f in ("sum", "max", "sharpen", "smoe")),
    ]
    assert all(item.needs == ["expert rgb seed 0", "expert ddm_jet seed 0"] for item in plan[2:])
    clock = Clock()
    estimate(plan, measure_s=50, measure=clock.measure, clock=clock)
    # 50 s of measuring at 20 s each: the two experts and the first fused row; the others as the measured row
    assert clock.measured == ["expert rgb", "expert ddm_jet", "sum"]
    assert [item.how for item in plan] == ["measured"] * 3 + ["as the measured"] * 3
    expert_epochs, fused_epochs = 10, 4  # the cpu scale's recipe (conf/recipe/instance_cpu.yaml)
    conditions = len(plan[2].config.task.get("eval_conditions") or {}) or 1
    test = 4 * conditions * 0.5
    # an expert: 10 epochs of 10 steps at 2 s, a validation epoch (2 batches at 0.5 s) after each, its test
    assert plan[0].seconds == pytest.approx(expert_epochs * (10 * 2.0 + 2 * 0.5) + test)
    # a fused row: its first epoch runs the experts (1 s a step), the later ones read their cached features
    fused = 10 * 1.0 + (fused_epochs - 1) * 10 * 0.25 + fused_epochs * 2 * 0.5 + test
    assert [item.seconds for item in plan[2:]] == pytest.approx([fused] * 4)
    # two at a time: both experts side by side, then the four rows two by two
    assert wall_seconds(plan, 2) == pytest.approx(plan[0].seconds + 2 * fused)
    assert wall_seconds(plan, 1) == pytest.approx(2 * plan[0].seconds + 4 * fused)
    text = lines(plan, 2, race=0)
    assert text[0] == "Sweep plan: 4 job(s), 2 at a time; 2 expert(s) to train first"
    assert text[-1] == f"Sweep ETA: ~{(plan[0].seconds + 2 * fused) / 60:.1f} min"


def test_trained_experts_and_finished_jobs_cost_nothing_and_a_race_plans_its_first_look(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    config = sweep_config("experiment=smoe_table1", "row=smoe_sum,smoe_max")
    first = items(config)
    assert [item.name for item in first if item.key.startswith("expert")] == [
        f"expert {m} seed {s}" for s in range(3) for m in ("rgb", "ddm_jet")
    ]  # the first look: three seeds, an expert of each modality per seed
    for expert in first[:6]:  # trained: their best checkpoints exist
        best = best_checkpoint("experts", config_hash(expert.config))
        best.parent.mkdir(parents=True)
        best.write_text("weights")
    plan = items(config, done=lambda cfg: cfg.seed == 0)  # seed 0 of both rows FINISHED in the store
    experts, jobs = plan[:4], plan[4:]  # a finished job needs no expert: seed 0's are not planned
    assert [e.name for e in experts] == [f"expert {m} seed {s}" for s in (1, 2) for m in ("rgb", "ddm_jet")]
    assert all(e.done for e in experts) and [j.done for j in jobs] == [True, False, False] * 2
    assert all(item.needs == [] for item in plan)
    clock = Clock()
    estimate(plan, measure=clock.measure, clock=clock)
    assert clock.measured == ["sum", "max"]  # each row once, its first seed to train
    text = lines(plan, 2, race=3)
    assert text[0] == "Sweep plan: 6 job(s) (the first look of a race), 2 at a time; 2 done already (skipped)"
    assert len(text) == 2 + 4 and text[-1].endswith("; later looks add seeds where rows are undecided")
    text = lines(plan, 2, race=1)  # a race of one planned look (`make run`'s): no later look to promise
    assert text[0] == "Sweep plan: 6 job(s) (a race of one look), 2 at a time; 2 done already (skipped)"
    assert "later looks" not in text[-1]


def test_a_later_look_plans_the_experts_of_its_new_seeds_only(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The racing sweeper counts the experts a later look's jobs train first for the progress ETA (new seeds' only:
    the first look's are trained by then)."""
    monkeypatch.chdir(tmp_path)
    config = sweep_config("experiment=smoe_table1", "row=smoe_sum,smoe_max")
    first = items(config)
    assert expert_seconds(first) == ({"rgb": 3, "ddm_jet": 3}, {})  # not estimated yet
    for expert in (item for item in first if item.kind == "expert"):
        best = best_checkpoint("experts", config_hash(expert.config))
        best.parent.mkdir(parents=True)
        best.write_text("weights")
    look2 = [[*job[:-1], f"seed={seed}"] for job in planned_jobs(config)[::3] for seed in (3, 4)]
    plan = items(config, jobs=look2)
    assert [item.name for item in plan if item.kind == "expert"] == [
        f"expert {m} seed {s}" for s in (3, 4) for m in ("rgb", "ddm_jet")
    ]
    clock = Clock()
    estimate(plan, measure_s=50, measure=clock.measure, clock=clock)
    each = {"rgb": pytest.approx(plan[0].seconds), "ddm_jet": pytest.approx(plan[1].seconds)}
    assert expert_seconds(plan) == ({"rgb": 2, "ddm_jet": 2}, each)


def test_without_time_to_measure_the_eta_waits_for_the_first_job_and_one_job_is_always_measured(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    plan = items(sweep_config("task=semantic", "model=unet,fusenet", "scale=smoke"))
    clock = Clock()
    estimate(plan, measure_s=0, measure=clock.measure, clock=clock)
    assert clock.measured == [] and lines(plan, 1, race=False)[-1] == "Sweep ETA: unknown until a job ends"
    # a budget shorter than one measurement: the first job is measured all the same, the other taken as it
    plan = items(sweep_config("task=semantic", "model=unet,fusenet", "scale=smoke"))
    estimate(plan, measure_s=1, measure=clock.measure, clock=clock)
    assert len(clock.measured) == 1 and [item.how for item in plan] == ["measured", "as the measured"]


def test_a_tuned_table_plans_its_trials_before_its_first_look(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    config = sweep_config("experiment=chinet_table2", "tune=lr_wd", "table.tune.trials=2")
    assert len(planned_jobs(config)) == 3 * 2 + 3 * 3  # 2 trials of each row, then 3 seeds of each
    plan = items(config)
    assert [i.name for i in plan[:3]] == ["chinet trial 0", "unet trial 0", "fusenet trial 0"]  # rows in order
    assert [i.config.trial for i in plan[:6]] == [0, 0, 0, 1, 1, 1] and plan[6].config.trial is None


@pytest.fixture
def tuned_on_experts(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> list:
    """The plan of BiFNet Table IV with a tuning phase of 2 trials: the experts' trials, stage 2's, the first look."""
    monkeypatch.chdir(tmp_path)
    return items(sweep_config("experiment=bifnet_table4", *FULL_BUDGET))


def test_stage_2_trials_plan_no_experts_they_copy_them_from_the_experts_chosen_trials(tuned_on_experts: list) -> None:
    plan = tuned_on_experts
    trials = [i for i in plan if i.config.get("trial") is not None]
    assert {i.config.seed for i in trials} == {1000} and any(i.config.get("experts") for i in trials)
    experts = [i for i in plan if i.key.startswith("expert ") and i.name.startswith("expert ")]
    assert experts and all(i.config.seed != 1000 for i in experts if not i.done)  # the race's experts alone
    assert all(not i.needs for i in trials)
    stage1 = [i.name.startswith("expert ") for i in trials]  # the experts' trials first, all of them, as the phase
    assert stage1 == sorted(stage1, reverse=True) and sum(stage1) == 4 and len(stage1) == 4 + 2 * 2


def test_an_item_not_measured_is_timed_at_its_kinds_step_times_an_experts_trial_as_an_expert(
    tuned_on_experts: list,
) -> None:
    plan = tuned_on_experts
    clock = Clock()
    estimate(plan, measure_s=1, measure=clock.measure, clock=clock)
    # the first of each kind, whatever the time: each expert's modality (a camera expert's step is about three BEV
    # ones'), then a fused network's
    assert clock.measured[:2] == ["expert rgb", "expert bev"] and len(clock.measured) == 3
    alone = [i for i in plan if trains_alone(i)]
    assert any(i.config.get("trial") is not None for i in alone)  # the experts' own trials train an expert alone
    for item in (i for i in plan if not i.done):  # a fused trial is not timed as the expert trial before it
        assert item.seconds == pytest.approx(seconds(item.config, EXPERT if item in alone else FUSED)), item.name


def test_a_resumed_tuning_phase_plans_stage_2_and_the_race_on_the_trials_it_chose(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    config = sweep_config("experiment=bifnet_table4", *FULL_BUDGET)
    objectives = {  # the store's after the phase: the LiDAR expert and the summing row chose trial 1
        "expert bev": {0: 0.5, 1: 0.9},
        "expert rgb": {0: 0.9, 1: 0.5},
        "bifnet_dst_sum": {0: 0.5, 1: 0.9},
        "bifnet_dst_cbf": {0: 0.9, 1: float("nan")},
    }
    plan = {item.name: item.config for item in items(config, objectives=objectives)}
    drawn = plan["expert bev trial 1"].task.optimizer  # a trial's config as its job hashes it: its draws applied
    assert drawn.lr != plan["expert bev trial 0"].task.optimizer.lr
    for name in ("bifnet_dst_sum trial 0", "bifnet_dst_cbf trial 1", "bifnet_dst_sum seed 2"):  # on the chosen experts
        on = plan[name].experts.draws
        assert (on.bev.task.optimizer.lr, on.bev.task.optimizer.weight_decay) == (drawn.lr, drawn.weight_decay), name
        assert "rgb" not in on, name  # the image expert chose the recipe
    assert plan["expert bev seed 0"].task.optimizer.lr == drawn.lr  # the race's experts: their chosen trial's values
    rows = {"bifnet_image": 0, "bifnet_bev": 1, "bifnet_dst_sum": 1, "bifnet_dst_cbf": 0}  # the LiDAR row: its expert's
    assert {row: plan[f"{row} seed 0"].tuned for row in rows} == rows
    raced = {row: plan[f"{row} seed 0"].task.optimizer.lr for row in ("bifnet_dst_sum", "bifnet_dst_cbf")}
    assert raced == {"bifnet_dst_sum": drawn.lr, "bifnet_dst_cbf": plan["bifnet_dst_cbf trial 0"].task.optimizer.lr}
    # without the store's objectives (a sweep not yet tuned), the race is planned on the recipe
    fresh = {item.name: item.config for item in items(config)}
    assert fresh["bifnet_dst_sum seed 0"].get("tuned") is None
    assert OmegaConf.select(fresh["bifnet_dst_sum trial 1"], "experts.draws", default=None) is None


def test_a_tuning_phases_launches_wait_for_each_other_in_the_wall_time(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    plan = items(sweep_config("experiment=chinet_table2", "tune=lr_wd", "table.tune.trials=2"))
    for item in plan:
        item.seconds = 10.0
    # 3 rows on 2 workers: trial 0's three jobs take two rounds, and trial 1 starts after them; then the first look
    # (9 jobs, one launch): 20 + 20 + 50 s, where packing the 15 jobs without waits would take 80 s
    assert wall_seconds(plan, 2) == pytest.approx(90.0)
    assert wall_seconds(plan, 3) == pytest.approx(10 + 10 + 30)
    assert wall_seconds(plan[6:], 2) == pytest.approx(50.0)  # the race alone: one launch


def test_the_plan_gives_each_rows_jobs_and_their_estimate_for_the_eta():
    cfg = OmegaConf.create({})
    plan = [
        Item("expert rgb seed 0", "expert rgb", cfg, seconds=900.0),
        Item("smoe_rgb seed 0", "a", cfg, done=True, seconds=0.0, kind="job", row="smoe_rgb"),  # in the store
        Item("smoe_rgb seed 1", "a", cfg, seconds=20.0, kind="job", row="smoe_rgb"),
        Item("smoe_fpn seed 0", "b", cfg, seconds=200.0, kind="job", row="smoe_fpn"),
        Item("smoe_fpn seed 1", "b", cfg, seconds=280.0, kind="job", row="smoe_fpn"),
        Item("smoe_fpn trial 0", "c", cfg, seconds=100.0, kind="trial", row="smoe_fpn"),  # a tuning trial: not raced
    ]
    # a done job counts among its row's jobs (its record ends it), not in the row's estimate
    assert row_jobs(plan) == {"smoe_rgb": [2, 20.0], "smoe_fpn": [2, 240.0]}


def test_a_job_whose_steps_cannot_be_timed_is_taken_as_its_kind_and_the_plan_goes_on(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    monkeypatch.chdir(tmp_path)
    plan = items(sweep_config("task=semantic", "model=unet,fusenet", "scale=smoke"))
    clock = Clock()

    def measure(cfg: DictConfig) -> StepTimes:
        if not clock.now:  # the first job's (U-Net's), before any was timed
            clock.now += 1.0
            raise RuntimeError("the dataset is missing")  # the job itself will say it
        return clock.measure(cfg)

    with caplog.at_level("WARNING", logger="ablate.sweep.plan"):
        estimate(plan, measure_s=50, measure=measure, clock=clock)
    assert "Could not time the steps of model=unet seed 0 for the sweep's plan: the dataset is missing" in caplog.text
    assert [item.how for item in plan] == ["as the measured", "measured"]
