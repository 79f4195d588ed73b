"""A sweep's overall progress (ablate.sweep.progress): jobs finished of planned, and the ETA from finished jobs."""

from pathlib import Path

from hydra import compose, initialize_config_dir

from ablate.sweep import state
from ablate.sweep.launches import SweepPlan
from ablate.sweep.progress import (
    estimated,
    experts_planned,
    finished,
    job_kind,
    job_row,
    job_trial,
    replan,
    start,
    summary,
)

CONF = Path(__file__).resolve().parents[1] / "conf"


def sweep_config(*overrides: str):
    """The config a multirun's callback sees: its base config, the command line's overrides in
    hydra.overrides.task (swept ones included, which a single composition does not take)."""
    fixed = [o for o in overrides if "," not in o]
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        config = compose("config", overrides=fixed, return_hydra_config=True)
    config.hydra.overrides.task = list(overrides)
    return config


def planned_jobs(config) -> list[list[str]]:
    """The jobs the sweeper of ``config`` launches before its first look ends (its plan's)."""
    return SweepPlan.of_config(config).jobs()


def test_the_plan_multiplies_the_tables_rows_seeds_and_the_command_lines_sweeps():
    assert len(planned_jobs(sweep_config("experiment=chinet_table2"))) == 9  # 3 rows x 3 seeds at the cpu scale
    assert len(planned_jobs(sweep_config("experiment=chinet_table2", "scale=smoke"))) == 3  # 1 seed
    assert len(planned_jobs(sweep_config("fusion=sum,max,sharpen,smoe"))) == 4
    # a key on the command line replaces the table's own sweep of it
    assert len(planned_jobs(sweep_config("experiment=chinet_table2", "row=chinet,unet", "seed=0"))) == 2


def test_the_eta_comes_from_the_trained_jobs_durations_and_the_jobs_at_a_time():
    records = [
        {"status": "FINISHED", "seconds": 600},
        {"status": "SKIPPED", "seconds": 2},
        {"status": "FINISHED", "seconds": 840},
    ]
    line = summary(records, 9, parallel=2)
    # 6 to go, 2 at a time: 3 rounds of the trained jobs' mean, 720 s
    assert line == (
        "Sweep progress: 3/9 jobs finished (1 skipped), 6 to go, ETA 36.0 min (12.0 min per trained job, 2 at a time)"
    )
    assert summary([{"status": "SKIPPED", "seconds": 1}], 2) == "Sweep progress: 1/2 jobs finished (1 skipped), 1 to go"
    assert summary(records, 3) == "Sweep progress: 3/3 jobs finished (1 skipped)"


def test_every_finished_job_is_counted_once_in_the_sweep_directory(tmp_path):
    assert start(tmp_path, planned_jobs(sweep_config("experiment=chinet_table2", "scale=smoke"))) == 3
    finished(tmp_path, "FINISHED", 30.0)
    line = finished(tmp_path, "FAILED", 10.0, parallel=2)
    assert line == "Sweep progress: 2/3 jobs finished (1 failed), 1 to go, ETA 20 s (20 s per trained job, 2 at a time)"


def test_a_job_kind_follows_its_overrides():
    assert job_kind(["row=smoe_fpn", "++experts.tune=rgb", "seed=1000", "trial=2"]) == "expert trial"
    assert job_kind(["row=chinet", "optim.lr=0.002", "seed=1000", "trial=1"]) == "trial"
    assert job_kind(["row=chinet", "seed=3"]) == "job"
    assert (job_row(["row=smoe_fpn", "++experts.tune=rgb", "trial=2"]), job_trial(["row=smoe_fpn", "trial=2"])) == (
        "expert rgb",
        2,
    )
    assert (job_row(["row=chinet", "seed=3"]), job_trial(["row=chinet", "seed=3"]), job_row(["fusion=sum"])) == (
        "chinet",
        None,
        "",
    )


def test_a_trial_index_takes_as_long_as_its_slowest_row_before_the_race_begins():
    """Two rows of unequal cost on two workers: trial k of both is one launch, which waits for the slower row; the
    jobs were once packed as if the faster row's next trial could start beside the slower's."""
    trials, launches = {"trial": 12}, {"trial": ["chinet", "miso"]}  # 2 rows x 6 trials, then 3 seeds each
    records = [
        {"status": "FINISHED", "seconds": 480, "kind": "trial", "row": "chinet", "trial": 0},
        {"status": "FINISHED", "seconds": 300, "kind": "trial", "row": "miso", "trial": 0},
    ]
    estimates = {"trial": 400, "job": 500}  # the trials took 780 s of 800 planned: a raced job 487.5 s
    line = summary(records, 18, parallel=2, kinds=trials, estimates=estimates, launches=launches)
    # 5 launches of ChiNet's 480 s, then 6 raced jobs in 3 rounds of 487.5 s: 3862.5 s (packed: 3412.5 s)
    assert line == (
        "Sweep progress: 2/18 jobs finished, 16 to go, ETA 64.4 min "
        "(6.5 min per tuning trial, 8.1 min per trained job as planned, 2 at a time)"
    )
    # half a launch done: its other row still runs alone
    more = [*records, {"status": "FINISHED", "seconds": 480, "kind": "trial", "row": "chinet", "trial": 1}]
    line = summary(more, 18, parallel=2, kinds=trials, estimates=estimates, launches=launches)
    # 300 + 4 x 480 + 3 x 520: the trials took 1260 s of 1200 planned (1.05), a raced job 1.05 x 400 s of its 500
    # planned, the 100 s beyond the trials' size at the plan's pace
    assert " ETA 63.0 min " in line
    # a progress file without rows (an older sweep's) packs the trials as before
    bare = [{k: v for k, v in r.items() if k not in ("row", "trial")} for r in records]
    line = summary(bare, 18, parallel=2, kinds=trials, estimates=estimates, launches=launches)
    assert " ETA 56.9 min " in line


def test_each_kind_of_job_to_go_is_timed_at_its_own_kind_or_its_plan_scaled_to_the_finished():
    records = [{"status": "FINISHED", "seconds": 300, "kind": "trial"}] * 2
    # 4 trials to go at their mean, 5 min; the 4 raced jobs at their plan's 900 s, halved as the trials were
    line = summary(records, 10, parallel=2, kinds={"trial": 6}, estimates={"trial": 600, "job": 900})
    assert line == (
        "Sweep progress: 2/10 jobs finished, 8 to go, ETA 25.0 min "
        "(5.0 min per tuning trial, 7.5 min per trained job as planned, 2 at a time)"
    )
    # once a raced job has finished, its own duration times the rest; the trials are over
    records = [*records] * 3 + [{"status": "FINISHED", "seconds": 1200, "kind": "job"}]
    line = summary(records, 10, parallel=2, kinds={"trial": 6}, estimates={"trial": 600, "job": 900})
    assert line == "Sweep progress: 7/10 jobs finished, 3 to go, ETA 40.0 min (20.0 min per trained job, 2 at a time)"
    # no plan: a kind none of whose jobs has finished takes every trained job's mean
    line = summary(records[:2], 10, parallel=1, kinds={"trial": 6})
    assert line.endswith("(5.0 min per tuning trial, 5.0 min per trained job, 1 at a time)")


def test_a_tuned_tables_sweep_counts_its_trials_apart_from_its_raced_jobs(tmp_path):
    assert start(tmp_path, planned_jobs(sweep_config("experiment=chinet_table3", "tune=lr_wd"))) == 18
    planned = state.read(tmp_path)["progress"]  # 2 rows x (6 trials + 3 seeds)
    assert (planned["kinds"], planned["launches"]) == ({"trial": 12}, {"trial": ["chinet", "simo"]})
    estimated(tmp_path, {"trial": 60.0, "job": 120.0})
    line = finished(tmp_path, "FINISHED", 30.0, parallel=2, kind="trial")
    # 11 trials at 30 s, then 6 raced jobs at 60 s, on 2 workers: 360 s
    assert line.endswith("ETA 6.0 min (30 s per tuning trial, 60 s per trained job as planned, 2 at a time)")


def planned(**modalities: int | tuple[int, float]) -> dict:
    """The sweep's record of the experts its jobs will train (:func:`experts_planned`): ``modality=count`` or
    ``modality=(count, the plan's seconds of one)``."""
    each = {
        m: {"planned": n} if isinstance(n, int) else {"planned": n[0], "seconds": n[1]} for m, n in modalities.items()
    }
    return {"planned": sum(e["planned"] for e in each.values()), "modalities": each}


def test_the_experts_a_look_trains_first_are_timed_apart_from_its_jobs():
    """A look of raced jobs on experts: its first jobs train the experts within them (10 min each here), the rest
    only their fusion network (about 5 min). The ETA once took every job at the first ones' mean."""
    records = [
        {
            "status": "FINISHED",
            "seconds": 900,
            "kind": "job",
            "row": "smoe_fpn",
            "experts": {"rgb": 600.0},
            "stage1": 610.0,
        },
        {"status": "FINISHED", "seconds": 300, "kind": "job", "row": "smoe_late"},
    ]
    line = summary(records, 8, parallel=2, experts=planned(rgb=4))
    # 3 experts to go at the trained one's 600 s, then 6 jobs at (290 + 300) / 2 s, on 2 workers: 1790 s
    assert line == (
        "Sweep progress: 2/8 jobs finished, 6 to go, ETA 29.8 min "
        "(3 expert(s) to train at 10.0 min, 4.9 min per trained job, 2 at a time)"
    )
    # every expert trained: the jobs alone (3 rounds of 295 s), not at the 600 s mean of the first two
    assert " ETA 14.8 min (4.9 min per trained job, " in summary(records, 8, 2, experts=planned(rgb=1))
    # no expert trained yet: the plan's 1000 s, scaled as the jobs came out against theirs (300 s of 600)
    line = summary(records[1:], 8, 2, estimates={"job": 600.0}, experts=planned(rgb=(2, 1000.0)))
    assert "(2 expert(s) to train at 8.3 min as planned, 5.0 min per trained job, 2 at a time)" in line


def test_each_expert_to_go_is_timed_at_its_own_modalitys_not_at_the_other_modalitys():
    """BiFNet's camera expert takes about 4 min, its BEV expert about 1.2. The ETA once timed the BEV experts to go
    at the trained camera experts' mean: 25 min at `make run`'s first job's end for a look that took 15."""
    records = [
        {"status": "FINISHED", "seconds": 330, "kind": "job", "row": "dst", "experts": {"rgb": 260.0}, "stage1": 270},
        {"status": "FINISHED", "seconds": 60, "kind": "job", "row": "dst"},
    ]
    experts = planned(rgb=(3, 200.0), bev=(3, 60.0))
    # 2 camera experts at the trained one's 260 s; 3 BEV ones at the plan's 60 s, scaled as the camera expert came
    # out against its plan (260 / 200): 78 s each
    line = summary(records, 6, parallel=1, experts=experts)
    assert "(5 expert(s) to train at 78 s to 4.3 min, " in line
    assert line.startswith("Sweep progress: 2/6 jobs finished, 4 to go, ETA 16.6 min ")  # 2 x 260 + 3 x 78 + 4 x 60 s
    # once a BEV expert has trained: the other two at its own seconds
    records[1].update(experts={"bev": 90.0}, stage1=95.0, seconds=155.0)
    assert "(4 expert(s) to train at 1.5 min to 4.3 min, " in summary(records, 6, parallel=1, experts=experts)
    # nothing trained, nothing estimated: no time for the experts, the jobs alone
    plain = [{"status": "FINISHED", "seconds": 60, "kind": "job", "row": "dst"}]
    assert "expert" not in summary(plain, 6, parallel=1, experts=planned(rgb=1))


def test_a_sweep_recorded_before_experts_had_modalities_resumes_with_its_eta():
    """A sweep folder written before experts were counted by modality: experts a list of seconds per job, the
    planned ones a count and one estimate. Resumed, its ETA reads them as one modality."""
    records = [{"status": "FINISHED", "seconds": 900, "kind": "job", "row": "fpn", "experts": [600.0], "stage1": 610}]
    line = summary(records, 4, parallel=1, experts={"planned": 3, "seconds": 500.0})
    assert "(2 expert(s) to train at 10.0 min, " in line  # at the trained one's 600 s


def test_raced_jobs_to_go_are_timed_at_their_own_rows_not_at_the_first_rows_to_end(tmp_path):
    """SMoE Table 1's follow-up: its single-modal rows only test a trained expert (about 35 s a job), its fused rows
    train for minutes. Its first jobs to end were the single-modal ones, and the ETA once took every job to go, and
    every expert scaled from them, at about 35 s: 22 min where 105 were due."""
    start(tmp_path, planned_jobs(sweep_config("experiment=chinet_table2", "scale=smoke")))
    estimated(tmp_path, {"job": 149.0}, {"smoe_rgb": [3, 21.0], "smoe_fpn": [3, 240.0]})
    experts_planned(tmp_path, {"rgb": 1, "ddm_jet": 1}, {"rgb": 960.0, "ddm_jet": 960.0})
    replan(tmp_path, 6)
    for _ in range(3):
        line = finished(tmp_path, "FINISHED", 35.0, 2, "job", "smoe_rgb")
    # 35 s against the row's 21 planned: a job's first 21 s of estimate at that ratio (35 s), the rest at the
    # plan's pace: the experts at 974 s each, then the FPN's 3 jobs at 254 s: 1482 s (scaled by the ratio alone,
    # 2400 s: the test-only row's fixed costs counted as if they grew with a job's steps)
    assert line.endswith(
        "ETA 24.7 min (2 expert(s) to train at 16.2 min as planned, trained jobs at their rows' 4.2 min, 2 at a time)"
    )
    # an FPN job has trained the camera expert in 1000 s: the depth expert at its plan's 960 s scaled as the camera's
    # came out against its own (1000 / 960), beside the two jobs to go at the row's own 300 s
    line = finished(tmp_path, "FINISHED", 1300.0, 2, "job", "smoe_fpn", None, {"rgb": 1000.0}, 1000.0)
    assert line.endswith(
        "ETA 16.7 min (1 expert(s) to train at 16.7 min as planned, trained jobs at their rows' 5.0 min, 2 at a time)"
    )


def test_each_look_adds_its_experts_and_each_job_records_its_stage_one(tmp_path):
    assert start(tmp_path, planned_jobs(sweep_config("experiment=chinet_table2", "scale=smoke"))) == 3
    experts_planned(tmp_path, {"rgb": 1, "depth": 1}, {"rgb": 480.0})  # the first look's, from the sweep's plan
    experts_planned(tmp_path, {"rgb": 1})  # a later look's new seed
    assert state.read(tmp_path)["progress"]["experts"] == {
        "planned": 3, "modalities": {"rgb": {"planned": 2, "seconds": 480.0}, "depth": {"planned": 1}}
    }  # fmt: skip
    line = finished(tmp_path, "FINISHED", 700.0, 2, "job", "chinet", None, {"rgb": 400.0, "depth": 200.0}, 620.0)
    # 1 camera expert to go at the trained one's 400 s, beside the 2 jobs to go at 700 - 620 s each: 400 s
    assert line.endswith("ETA 6.7 min (1 expert(s) to train at 6.7 min, 80 s per trained job, 2 at a time)")
    (record,) = state.read(tmp_path)["ended"]
    assert (record["experts"], record["stage1"]) == ({"rgb": 400.0, "depth": 200.0}, 620.0)


def test_a_rows_fixed_costs_do_not_scale_a_larger_rows_estimate():
    """`make run` (BiFNet Table IV): its single-modal rows only test their expert, 9 s of steps planned and 17 s
    taken, mostly a job's fixed costs (its start, its checkpoint, the test's data), which the plan does not time.
    Their ratio (1.9) once scaled the fused rows' 108 s to 204 s where they took 140: up to their size a job to go
    takes their ratio, beyond it the plan's pace. Faster than planned, every size takes the ratio."""
    rows = {"bifnet_image": [3, 9.0], "bifnet_dst_sum": [3, 108.0]}
    ended = [{"status": "FINISHED", "seconds": 17.0, "kind": "job", "row": "bifnet_image"}]
    line = summary(ended, 6, parallel=1, estimates={"job": 60.0}, rows=rows)
    # 2 image jobs at their own 17 s, 3 fused ones at 1.9 x 9 + 99 = 116 s
    assert line.endswith("ETA 6.4 min (trained jobs at their rows' 17 s to 1.9 min, 1 at a time)"), line
    fast = [{**ended[0], "seconds": 4.5}]
    assert summary(fast, 6, parallel=1, estimates={"job": 60.0}, rows=rows).endswith(
        "(trained jobs at their rows' 4 s to 54 s, 1 at a time)"
    )  # half the plan: 54 s each
