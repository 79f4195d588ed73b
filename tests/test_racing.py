"""Racing seeds (ablate.tables.racing, hydra_plugins.ablate_racing_sweeper): the real sweeper, through a launcher
that returns fake metrics, stops where the table is decided and races on where it is not; the correction for
repeated looks holds the false-positive rate of a null table, and without it the rate is above alpha."""

import random
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from hydra import compose, initialize_config_dir
from hydra.core.utils import JobReturn, JobStatus

import hydra_plugins.ablate_racing_sweeper._impl as impl
import hydra_plugins.ablate_racing_sweeper._race as racing
from ablate.sweep import progress, state
from ablate.tables.raceplan import RacePlan
from ablate.tables.racing import race, race_lines, wilson
from hydra_plugins.ablate_racing_sweeper.racing_sweeper import RacingSweeper

CONF = Path(__file__).resolve().parents[1] / "conf"


class FakeLauncher:
    """Runs no job: records each (row, seed) it is given, as a store would hold its primary metric; ``shuffle``
    hands the jobs back in another order, as a launcher whose jobs finish out of order."""

    def __init__(self, metric, shuffle: bool = False):
        self.metric, self.shuffle, self.store, self.batches = metric, shuffle, {}, []
        self.seconds: dict[str, float] = {}  # a row's job seconds, as the store's runs say (none: rows alike)

    def launch(self, job_overrides, initial_job_idx):
        jobs = [dict(o.split("=", 1) for o in overrides) for overrides in job_overrides]
        self.batches.append([(j["row"], int(j["seed"])) for j in jobs])
        order = list(range(len(jobs)))
        if self.shuffle:
            random.Random(initial_job_idx).shuffle(order)
        out = []
        for i in order:
            row, seed = jobs[i]["row"], int(jobs[i]["seed"])
            self.store.setdefault(row, {})[seed] = self.metric(row, seed)
            ret = JobReturn(overrides=job_overrides[i], status=JobStatus.COMPLETED)
            ret.return_value = "FINISHED"
            out.append(ret)
        return out


def sweeper_for(tmp_path, monkeypatch, metric, *overrides, shuffle=False, launcher=None):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        config = compose("config", overrides=["experiment=chinet_table2", *overrides], return_hydra_config=True)
    config.hydra.runtime.cwd = str(tmp_path)
    config.hydra.sweep.dir = "sweep"
    sweeper = RacingSweeper(params=dict(config.hydra.sweeper.params or {}))
    launcher = launcher or FakeLauncher(metric, shuffle)
    sweeper.sweeper.config, sweeper.sweeper.launcher = config, launcher
    sweeper.sweeper.hydra_context = type("Context", (), {"config_loader": None})()
    monkeypatch.setattr(impl, "job_runs", lambda tracker, table: None)
    monkeypatch.setattr(impl, "table_values", lambda runs, table: {r: pd.Series(v) for r, v in launcher.store.items()})
    monkeypatch.setattr(impl, "row_seconds", lambda tracker, runs: getattr(launcher, "seconds", {}))
    monkeypatch.setattr(impl, "earlier_wall", lambda runs, sweep: getattr(launcher, "earlier_min", 0.0))
    monkeypatch.setattr(impl.RacingSweeperImpl, "_tracker", lambda self: None)
    # no store: no parent run, no plan's estimate, no table at the end (the sweep's state file is written all the same)
    monkeypatch.setattr(impl.RacingSweeperImpl, "_open", lambda self, plan, sdir: None)
    monkeypatch.setattr(impl, "finish", lambda config: None)
    return sweeper, launcher


def planned(tmp_path) -> int:
    """The jobs the sweep in ``tmp_path/sweep`` planned, as its state file says."""
    return state.read(tmp_path / "sweep")["progress"]["planned"]


def noise(row: str, seed: int, sd: float = 0.3) -> float:
    return float(np.random.default_rng([sum(map(ord, row)), seed]).normal(0, sd))


def test_a_row_clearly_better_stops_the_race_at_the_first_look(tmp_path, monkeypatch):
    means = {"chinet": 97.0, "unet": 90.0, "fusenet": 94.0}
    sweeper, launcher = sweeper_for(tmp_path, monkeypatch, lambda r, s: means[r] + noise(r, s))
    sweeper.sweep([])
    assert len(launcher.batches) == 1
    assert sorted(launcher.batches[0]) == sorted((r, s) for r in means for s in range(3))
    assert planned(tmp_path) == 9


@pytest.mark.parametrize("term", ["kernels_sd", "kernels_cpu"])
def test_the_live_race_reads_each_of_the_tables_kernels_terms(tmp_path, monkeypatch, term):
    """Another CPU's kernels' variance the table measured (per seed, or shared by every seed) widens the live race's
    tests as it widens the rendered table's: a lead clear on the seeds alone is not decided at the first look."""
    means = {"chinet": 97.0, "unet": 90.0, "fusenet": 94.0}
    sweeper, launcher = sweeper_for(tmp_path, monkeypatch, lambda r, s: means[r] + noise(r, s), f"+table.{term}=20")
    sweeper.sweep([])
    assert len(launcher.batches) == 3  # every look: the seeds alone decided at the first (the test above)


def test_two_identical_rows_race_to_the_last_look_and_nothing_is_declared(tmp_path, monkeypatch):
    sweeper, launcher = sweeper_for(tmp_path, monkeypatch, lambda r, s: 95.0 + noise("same", s) + noise(r, s, 0.5))
    sweeper.sweep(["row=chinet,unet"])
    assert [sorted({s for _, s in b}) for b in launcher.batches] == [[0, 1, 2], [3, 4], [5, 6, 7]]
    values = {r: pd.Series(v) for r, v in launcher.store.items()}
    state = race(values, ["chinet", "unet"], "unet", RacePlan((3, 5, 8)))
    assert state.looks_done == 3 and not any(c.decided for c in state.comparisons.values())
    assert "Left undecided, after the last look: chinet vs unet." in race_lines(state, {})


def test_only_the_undecided_rows_get_more_seeds(tmp_path, monkeypatch):
    # chinet is far ahead of both; fusenet and the reference unet are close: chinet stops after the first look
    means = {"chinet": 99.0, "unet": 90.0, "fusenet": 90.2}
    sweeper, launcher = sweeper_for(tmp_path, monkeypatch, lambda r, s: means[r] + noise(r, s, 0.5))
    sweeper.sweep([])
    assert {r for r, _ in launcher.batches[1]} == {"unet", "fusenet"}
    assert planned(tmp_path) == sum(len(b) for b in launcher.batches)


def test_the_outcome_does_not_depend_on_the_order_jobs_finish(tmp_path, monkeypatch):
    means = {"chinet": 95.5, "unet": 95.0, "fusenet": 94.0}

    def metric(r, s):
        return means[r] + noise(r, s, 0.6)

    ordered, a = sweeper_for(tmp_path / "a", monkeypatch, metric)
    ordered.sweep([])
    shuffled, b = sweeper_for(tmp_path / "b", monkeypatch, metric, shuffle=True)
    shuffled.sweep([])
    assert [sorted(x) for x in a.batches] == [sorted(x) for x in b.batches]


def test_a_seed_on_the_command_line_runs_every_job_at_once(tmp_path, monkeypatch):
    sweeper, launcher = sweeper_for(tmp_path, monkeypatch, lambda r, s: 90.0)
    sweeper.sweep(["seed=0,1"])
    assert len(launcher.batches) == 1 and len(launcher.batches[0]) == 6


class TimedLauncher(FakeLauncher):
    """A launcher on a fake clock: a job the store already holds (``held``) returns SKIPPED and costs no time; every
    other job trains for ``minutes`` (a number, or per row), two at a time."""

    def __init__(self, metric, clock: list[float], held: set, minutes: float | dict[str, float]):
        super().__init__(metric)
        self.clock, self.held = clock, held
        self.minutes = minutes if isinstance(minutes, dict) else dict.fromkeys(("chinet", "unet", "fusenet"), minutes)

    def launch(self, job_overrides, initial_job_idx):
        out = super().launch(job_overrides, initial_job_idx)
        jobs = self.batches[-1]
        for ret, job in zip(out, jobs):
            ret.return_value = "SKIPPED" if job in self.held else "FINISHED"
        self.clock[0] += sum(self.minutes[row] * 60 for row, seed in jobs if (row, seed) not in self.held) / 2
        return out


def test_the_budget_counts_only_the_jobs_that_trained(tmp_path, monkeypatch):
    # look 1: six of the nine jobs are held (a resumed race), three train for 4 min each, two at a time: 6 min
    # spent, 2 min per trained job; look 2's six jobs need about 12 min more, past a budget of 15
    clock = [0.0]
    monkeypatch.setattr(impl.time, "monotonic", lambda: clock[0])
    held = {(r, s) for r in ("chinet", "unet") for s in range(3)}
    launcher = TimedLauncher(lambda r, s: 95.0 + noise(r, s), clock, held, 4.0)
    sweeper, _ = sweeper_for(tmp_path, monkeypatch, None, "scale.race.budget_min=15", launcher=launcher)
    sweeper.sweep([])
    assert len(launcher.batches) == 1
    assert racing.look_estimate(6 * 60, [1.0] * 3, [1.0] * 6) == 12 * 60
    assert racing.look_estimate(60, [], [1.0] * 6) == 0


def test_a_look_is_estimated_from_each_rows_own_job_time(tmp_path, monkeypatch):
    # look 1: chinet's three seeds are copied from another table (held), where each took 8 min; U-Net and FuseNet
    # train their three for 2 min each, two at a time: 6 min. Look 2 (two seeds of each row) needs 4 x 2 + 2 x 8 =
    # 24 min of jobs, 12 of wall time: past a budget of 15. Counted per job alike, it would look like 6 min.
    clock = [0.0]
    monkeypatch.setattr(impl.time, "monotonic", lambda: clock[0])
    held = {("chinet", s) for s in range(3)}
    minutes = {"chinet": 8.0, "unet": 2.0, "fusenet": 2.0}
    launcher = TimedLauncher(lambda r, s: 95.0 + noise(r, s), clock, held, minutes)
    launcher.seconds = {row: m * 60 for row, m in minutes.items()}
    sweeper, _ = sweeper_for(tmp_path, monkeypatch, None, "scale.race.budget_min=15", launcher=launcher)
    sweeper.sweep([])
    assert len(launcher.batches) == 1
    costs = racing.job_costs({"chinet": 480.0, "unet": 120.0})
    assert costs("fusenet") == 300.0 and racing.job_costs({})("unet") == 1.0


def test_a_look_whose_jobs_were_all_held_does_not_stop_the_race(tmp_path, monkeypatch):
    clock = [0.0]
    monkeypatch.setattr(impl.time, "monotonic", lambda: clock[0])
    held = {(r, s) for r in ("chinet", "unet", "fusenet") for s in range(3)}
    launcher = TimedLauncher(lambda r, s: 95.0 + noise(r, s), clock, held, 4.0)
    sweeper, _ = sweeper_for(tmp_path, monkeypatch, None, "scale.race.budget_min=15", launcher=launcher)
    sweeper.sweep([])
    assert len(launcher.batches) == 2  # look 2 trained 6 jobs in 12 min: look 3's 9 would need 18 more


def test_a_resumed_race_counts_the_time_its_earlier_sweeps_spent_against_its_budget(tmp_path, monkeypatch, caplog):
    # look 1: chinet's and U-Net's seeds were raced by an earlier sweep (held), fusenet's three train here for 4 min
    # each, two at a time: 6 min. Look 2 needs about 12 more: inside a budget of 25 min alone (18), past it with
    # the 8 min the earlier sweep spent (26).
    def resumed(earlier_min: float) -> TimedLauncher:
        clock = [0.0]
        monkeypatch.setattr(impl.time, "monotonic", lambda: clock[0])
        held = {(r, s) for r in ("chinet", "unet") for s in range(3)}
        launcher = TimedLauncher(lambda r, s: 95.0 + noise("same", s) + noise(r, s), clock, held, 4.0)
        launcher.earlier_min = earlier_min
        sweeper, _ = sweeper_for(
            tmp_path / str(earlier_min), monkeypatch, None, "scale.race.budget_min=25", launcher=launcher
        )
        sweeper.sweep([])
        return launcher

    assert len(resumed(0.0).batches) > 1
    with caplog.at_level("INFO", logger=impl.__name__):
        assert len(resumed(8.0).batches) == 1
    assert "before look 2 (14.0 min spent, 8.0 of them in earlier sweeps, about 12.0 more needed)" in caplog.text


class ExpertLauncher(TimedLauncher):
    """A launcher on a fake clock whose jobs sit on two experts (SMoE §4.3): the first job of each new seed trains
    both (``expert_min`` each) within it, and every job records its progress as the sweep's callback does."""

    def __init__(self, metric, clock: list[float], sweep_dir: Path, job_min: float, expert_min: float):
        super().__init__(metric, clock, set(), job_min)
        self.sweep_dir, self.expert_min, self.seeds = sweep_dir, expert_min, set()

    def launch(self, job_overrides, initial_job_idx):
        before = self.clock[0]
        out = FakeLauncher.launch(self, job_overrides, initial_job_idx)
        total = 0.0
        for row, seed in self.batches[-1]:
            experts = {} if seed in self.seeds else {"rgb": self.expert_min * 60, "depth": self.expert_min * 60}
            self.seeds.add(seed)
            stage1 = sum(experts.values())
            seconds = self.minutes[row] * 60 + stage1
            progress.finished(self.sweep_dir, "FINISHED", seconds, 2, "job", row, None, experts, stage1)
            total += seconds
        self.clock[0] = before + total / 2
        return out


def test_a_look_counts_the_experts_its_new_seeds_train(tmp_path, monkeypatch, caplog):
    # look 1: nine jobs of 2 min, the first job of each of the three seeds training two experts of 10 min: 78 min
    # of jobs, 39 of wall time. Only U-Net and FuseNet race on: look 2's four jobs train four experts, 24 min. Scaled
    # from look 1's jobs alone (four ninths of its time) it would look like 17 min, inside a budget of 60 (56).
    clock = [0.0]
    monkeypatch.setattr(impl.time, "monotonic", lambda: clock[0])
    means = {"chinet": 99.0, "unet": 90.0, "fusenet": 90.2}
    launcher = ExpertLauncher(lambda r, s: means[r] + noise(r, s, 0.5), clock, tmp_path / "sweep", 2.0, 10.0)

    def look_experts(self, batch: list[list[str]]) -> dict[str, int]:  # each new seed's two experts
        return dict.fromkeys(("rgb", "depth"), len({b[-1] for b in batch}))

    monkeypatch.setattr(impl.RacingSweeperImpl, "_look_experts", look_experts)
    sweeper, _ = sweeper_for(tmp_path, monkeypatch, None, "scale.race.budget_min=60", launcher=launcher)
    with caplog.at_level("INFO", logger=impl.__name__):
        sweeper.sweep([])
    assert len(launcher.batches) == 1
    assert "before look 2 (39.0 min spent, about 24.0 more needed)" in caplog.text
    assert progress.look_seconds(tmp_path / "sweep", 4, {}, 2) == 4 * 60  # no new seed: the jobs alone, 2 min each
    assert progress.look_seconds(tmp_path / "none", 4, {"rgb": 2}, 2) is None  # no job has trained: nothing to go by


def test_the_time_a_race_spent_before_is_its_other_sweeps_spans_of_the_runs_it_uses() -> None:
    from ablate.tables.collect import earlier_wall

    minute = 60000
    runs = pd.DataFrame(
        [  # row, seed, sweep, job start, run start, end (minutes)
            ("a", 0, "old", 0, 5, 10),  # superseded by the later run of (a, 0): not the race's
            ("a", 0, "s1", 20, 22, 30),
            ("b", 0, "s1", 21, 21, 32),
            ("a", 1, "s2", 100, 101, 110),  # this sweep's own
        ],
        columns=["row", "seed", "sweep_id", "job_started", "started", "ended"],
    )
    runs[["job_started", "started", "ended"]] *= minute
    runs["scale"] = "cpu"
    assert earlier_wall(runs, "s2") == 12.0  # s1: 20 .. 32
    assert earlier_wall(runs, "s1") == 10.0 and earlier_wall(runs.drop(columns="job_started"), "s2") == 11.0
    assert earlier_wall(None, "s2") == 0.0 and earlier_wall(runs[runs["sweep_id"] == "s2"], "s2") == 0.0


def null_rate(correction: str, tables: int = 1000) -> float:
    """The share of ``tables`` null tables (two rows of one distribution, a seed effect shared by both) in which
    the race declares a difference."""
    plan, rng, declared = RacePlan((3, 5, 8), 0.05, correction), np.random.default_rng(2026), 0
    for _ in range(tables):
        shared = rng.normal(0, 1, 8)
        values = {r: pd.Series(90 + shared + rng.normal(0, 1, 8)) for r in ("a", "b")}
        declared += any(c.decided for c in race(values, ["a", "b"], "b", plan).comparisons.values())
    return declared / tables


@pytest.mark.parametrize("correction", ["bonferroni", "pocock", "obrien_fleming"])
def test_a_corrected_race_holds_the_false_positive_rate_of_null_tables(correction):
    assert null_rate(correction) <= 0.05


def test_without_the_correction_null_tables_are_declared_more_often_than_alpha():
    assert null_rate("none") > 0.05


def test_the_levels_add_up_to_alpha_and_the_spending_keeps_its_shape():
    for correction in ("bonferroni", "pocock", "obrien_fleming"):
        assert sum(RacePlan((3, 5, 8), 0.05, correction).levels()) == pytest.approx(0.05)
    obf = RacePlan((3, 5, 8), 0.05, "obrien_fleming").levels()
    assert obf[0] < obf[1] < obf[2]  # O'Brien-Fleming keeps most of alpha for the last look
    assert RacePlan((3, 5, 8), 0.05, "pocock").levels()[0] == pytest.approx(0.05 * np.log1p((np.e - 1) * 3 / 8))


def test_a_bad_plan_is_one_error_naming_the_option():
    with pytest.raises(ValueError, match=r"table\.seeds\.looks"):
        RacePlan.from_config({"looks": [5, 3]})
    with pytest.raises(ValueError, match=r"table\.seeds\.correction"):
        RacePlan.from_config({"looks": [3], "correction": "holm"})
    with pytest.raises(ValueError, match=r"table\.seeds: unknown option\(s\) look"):
        RacePlan.from_config({"look": [3]})


def test_p_a_beats_b_has_a_wilson_interval_that_needs_five_clean_wins_to_clear_one_half():
    assert wilson(3, 3)[0] < 0.5 < wilson(5, 5)[0]
    lo, hi = wilson(4, 8)
    assert lo < 0.5 < hi and hi - 0.5 == pytest.approx(0.5 - lo)


def test_a_bad_plan_stops_the_sweep_with_one_line_before_any_job(tmp_path, monkeypatch, capsys):
    sweeper, launcher = sweeper_for(tmp_path, monkeypatch, lambda r, s: 90.0, "scale.race.looks=[3,2]")
    with pytest.raises(SystemExit):
        sweeper.sweep([])
    assert capsys.readouterr().err.strip().startswith("error: scale.race.looks: [3, 2] must be a non-empty list of")
    assert launcher.batches == []


def test_one_seed_a_row_gives_no_verdict_anywhere(tmp_path, monkeypatch, caplog):
    # equal values at one seed: no spread to test against, so neither "equivalent" nor "undecided" is claimed
    values = {"chinet": pd.Series({0: 95.0}), "unet": pd.Series({0: 95.0})}
    state = race(values, ["chinet", "unet"], "unet", RacePlan((1,), rope=0.5))
    (c,) = state.comparisons.values()
    assert (
        c.verdict() == "no verdict (n = 1: a test needs 2 paired seeds or more)" and c.short() == "no verdict (n = 1)"
    )
    said = race_lines(state, {})
    assert "No verdict, fewer than 2 paired seeds: chinet vs unet (race 2 seeds or more)." in said
    assert not any("undecided" in line or "equivalent" in line for line in said[1:]), said
    sweeper, _ = sweeper_for(tmp_path, monkeypatch, lambda r, s: 95.0, "scale.race.looks=[1]")
    with caplog.at_level("INFO"):
        sweeper.sweep(["row=chinet,unet"])
    assert "no verdict, fewer than 2 paired seeds: chinet vs unet" in caplog.text
    assert "(n = 1: a test needs 2 paired seeds or more)" in caplog.text and "undecided" not in caplog.text


def test_a_sweep_whose_plan_cannot_be_estimated_or_counted_races_all_the_same(tmp_path, monkeypatch, caplog):
    import ablate.sweep.plan as plan

    def broken(*args, **kwargs):
        raise RuntimeError("no step times")

    opened = impl.RacingSweeperImpl._open
    sweeper, launcher = sweeper_for(tmp_path, monkeypatch, lambda r, s: 95.0 + noise("same", s) + noise(r, s, 0.5))
    monkeypatch.setattr(impl.RacingSweeperImpl, "_open", opened)
    monkeypatch.setattr(impl, "open_parent", lambda config: (None, None))
    monkeypatch.setattr(plan, "log_sweep", broken)  # the plan's estimate fails: the jobs will say what is wrong
    monkeypatch.setattr(plan, "items", broken)  # and so does counting a later look's experts
    with caplog.at_level("INFO", logger=impl.__name__):
        sweeper.sweep(["row=chinet,unet"])
    assert "Could not plan the sweep: no step times" in caplog.text and "Sweep of 6 job(s), " in caplog.text
    assert "Could not count the experts of the look: no step times" in caplog.text
    assert len(launcher.batches) == 3  # every look ran, as without the estimate
