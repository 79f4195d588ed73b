"""The tuning phase (ablate.sweep.tuning): N trials per row in batches of one trial index, the budget stopping only
between batches, the choice on validation, and a table's tune spec checked option by option."""

from __future__ import annotations

import json
import logging
import math
import re

import pandas as pd
import pytest

from ablate.sweep.tuning import TuneSpec, choose, run_phase, tuned_overrides

SPACE = {"task.optimizer.lr": "tag(log, interval(1e-4, 1e-2))"}
#: A 2-trial phase that trains every trial in full, on tables whose `tune=lr_wd` halves (`table.tune_halving`)
FULL_BUDGET = ("tune=lr_wd", "table.tune.trials=2", "table.tune.halving=null")


def test_every_row_gets_the_same_trials_one_batch_per_trial_index() -> None:
    spec = TuneSpec.from_config({"trials": 4, "space": SPACE})
    assert spec is not None
    batches: list[list[list[str]]] = []
    phase = run_phase(spec, "t", {"a": ["row=a"], "b": ["row=b"]}, batches.append)
    assert phase.done == 4 and len(batches) == 4 and all(len(b) == 2 for b in batches)
    assert batches[0] == [["row=a", "seed=1000", "trial=0"], ["row=b", "seed=1000", "trial=0"]]  # the recipe
    for k, batch in enumerate(batches[1:], start=1):
        (a_lr, a_rest), (b_lr, b_rest) = [(job[1], job[2:]) for job in batch]
        assert a_lr == b_lr and a_lr.startswith("++draws.task.optimizer.lr=")  # common random numbers
        assert a_rest == b_rest == ["seed=1000", f"trial={k}"]


def test_the_budget_stops_the_phase_only_between_trial_indices(caplog: pytest.LogCaptureFixture) -> None:
    spec = TuneSpec.from_config({"trials": 10, "space": SPACE, "budget_min": 1.0})
    assert spec is not None
    now = [0.0]
    launched: list[int] = []

    def launch(batch: list[list[str]]) -> None:
        launched.append(len(batch))
        now[0] += 25.0  # a trial index takes 25 s: the third would end at 75 s, past the minute

    with caplog.at_level(logging.INFO, logger="ablate.sweep.tuning"):
        phase = run_phase(spec, "t", {"a": [], "b": [], "c": []}, launch, clock=lambda: now[0])
    assert phase.done == 2 and launched == [3, 3] and "after trial 1 of every row" in phase.stopped
    # the progress line before each trial index: none before the first has ended, then the ETA for the rest
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("Tuning trial")]
    assert lines == [
        "Tuning trial 0 of 10 for 3 row(s)",
        "Tuning trial 1 of 10 for 3 row(s); 0.4 min spent, tuning ETA 3.8 min (0.4 min a trial index)",
    ]


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
        ({"trials": 3, "space": SPACE, "experts": "yes"}, r"table\.tune\.experts: 'yes' must be true or false"),
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
    trials["started"] = [i * 30_000 for i in range(len(trials))]  # two at a time: a trial every 30 s
    table = OmegaConf.create({"name": "t", "title": "T", "tune": {"trials": 4, "space": SPACE, "seed": 0}})
    text = "\n".join(section(trials, table, {"a": "Row A", "b": "Row B"}))
    assert "| Row A | 4 | 2 | lr=0.008 | 0.95 | 4.0 |" in text
    assert "| Row B | 4 | 0 | lr=0.001 | 0.62 | 4.0 |" in text  # its failed trial counts as spent
    assert "the ranking depends on the tuning budget" in text
    assert "Tuned: task.optimizer.lr; N = 4" in text  # records without their search: the tuned keys alone
    assert "The tuning phase: 8 trials, 8 CPU min, 4 min of wall time" in text  # 7 x 30 s + the last one's 60 s
    trials["search"] = json.dumps({"space": SPACE, "seed": 3})  # the trials' own record of their search
    text = "\n".join(section(trials, table, {"a": "Row A", "b": "Row B"}))
    assert f"Tuned: task.optimizer.lr ~ {SPACE['task.optimizer.lr']}, tuning seed 3; N = 4" in text
    assert write_figure(trials, table, {}, tmp_path) == tmp_path / "t_tuning.png"
    # a stage-2 row's trials record the experts' values too: named as the experts', not listed as its own
    fused = (
        '{"experts.bev.task.optimizer.lr": 0.0049, "experts.rgb.task.optimizer.lr": 0.0011, "task.optimizer.lr": 3e-4}'
    )
    trials.loc[trials["row"] == "b", "trial_config"] = fused
    text = "\n".join(section(trials, table, {"a": "Row A", "b": "Row B"}))
    assert "| Row B | 4 | 0 | lr=0.0003 (on the experts' chosen trials: bev, rgb) | 0.62 | 4.0 |" in text
    runs = pd.DataFrame({"row": ["a", "a", "b"], "tuned_config": [lr(0.008), lr(0.001), lr(0.001)]})
    with pytest.raises(ValueError, match="row a: its runs were tuned to different configs"):
        check_tuned(runs)
    check_tuned(runs[runs["row"] == "b"])


class TuningLauncher:
    """Runs no job: a trial job (``trial=k``) gets ``val(row, lr)`` as its objective, a raced job
    ``test(row, lr, seed)`` as its primary metric, where ``lr`` is the job's learning rate (the recipe's without a
    draw); a trial ``fail`` names fails (no objective)."""

    def __init__(self, val, test, fail=(), at_rung=None):
        self.val, self.test, self.fail = val, test, set(fail)
        self.at_rung = at_rung or (lambda row, lr, rung: val(row, lr))  # a trial's objective at a rung of halving
        self.store: dict[str, dict[int, float]] = {}  # raced jobs: row -> seed -> metric
        self.trials: dict[str, dict[int, float]] = {}  # trials: row -> trial -> objective (its furthest rung's)
        self.at: dict[float, dict[str, dict[int, float]]] = {}  # rung -> row -> trial -> objective (full: 1.0)
        self.batches: list[list[dict[str, str]]] = []

    def objectives(self, rung=None):
        return self.at.get(1.0 if rung is None else float(f"{rung:.6g}"), {})

    def launch(self, job_overrides, initial_job_idx):
        from hydra.core.utils import JobReturn, JobStatus

        out = []
        jobs = [dict(o.lstrip("+").split("=", 1) for o in overrides) for overrides in job_overrides]
        self.batches.append(jobs)
        for overrides, job in zip(job_overrides, jobs):
            row, lr = job["row"], float(job.get("draws.task.optimizer.lr", RECIPE_LR))
            row = f"expert {job['experts.tune']}" if "experts.tune" in job else row  # an expert's own trial
            if "trial" in job:
                failed, rung = (row, int(job["trial"])) in self.fail, float(job.get("rung", 1.0))
                value = math.nan if failed else self.at_rung(row, lr, rung)
                self.trials.setdefault(row, {})[int(job["trial"])] = value
                self.at.setdefault(rung, {}).setdefault(row, {})[int(job["trial"])] = value
            else:
                self.store.setdefault(row, {})[int(job["seed"])] = self.test(row, lr, int(job["seed"]))
            ret = JobReturn(overrides=overrides, status=JobStatus.COMPLETED)
            ret.return_value = "FINISHED"
            out.append(ret)
        return out


RECIPE_LR = 1e-3  # chinet_table2's at the cpu scale (conf/recipe/semantic_cpu.yaml)


def narrow(lr: float) -> float:
    """Row A: a narrow optimum at lr = 0.008, far from the recipe; 90 elsewhere."""
    return 90.0 + 8.0 * math.exp(-(((math.log10(lr) - math.log10(0.008)) / 0.25) ** 2))


def tuned_sweep(tmp_path, monkeypatch, launcher, *overrides):
    import pandas as pd

    import hydra_plugins.ablate_racing_sweeper._impl as impl
    from tests.test_racing import sweeper_for

    sweeper, _ = sweeper_for(
        tmp_path, monkeypatch, None, "tune=lr_wd", "table.tune.trials=16", *overrides, launcher=launcher
    )
    monkeypatch.setattr(impl, "trial_objectives", lambda tracker, table, rung=None: launcher.objectives(rung))
    monkeypatch.setattr(impl, "table_values", lambda runs, table: {r: pd.Series(v) for r, v in launcher.store.items()})
    monkeypatch.setattr(impl.RacingSweeperImpl, "_tag_parent", lambda self, tags: None)
    return sweeper


def test_tuning_lets_the_row_with_a_narrow_optimum_win_where_the_recipe_favours_the_plateau(tmp_path, monkeypatch):
    objective = {"chinet": narrow, "unet": lambda lr: 93.0}  # unet: a broad plateau
    launcher = TuningLauncher(lambda r, lr: objective[r](lr), lambda r, lr, s: objective[r](lr) + 0.05 * s)
    assert objective["unet"](RECIPE_LR) > objective["chinet"](RECIPE_LR)  # at the recipe the plateau wins
    tuned_sweep(tmp_path, monkeypatch, launcher).sweep(["experiment=chinet_table2", "row=chinet,unet"])
    trials = [b for b in launcher.batches if "trial" in b[0]]
    assert len(trials) == 16 and all(sorted(j["row"] for j in b) == ["chinet", "unet"] for b in trials)
    raced = [j for b in launcher.batches if "trial" not in b[0] for j in b]
    chosen = {j["row"]: (int(j["tuned"]), float(j.get("draws.task.optimizer.lr", RECIPE_LR))) for j in raced}
    assert chosen["unet"][0] == 0  # the plateau: the recipe, the first of equals
    assert chosen["chinet"][0] > 0 and abs(math.log10(chosen["chinet"][1] / 0.008)) < 0.25  # near its optimum
    means = {r: sum(v.values()) / len(v) for r, v in launcher.store.items()}
    assert means["chinet"] > means["unet"]  # after tuning, the row with the narrow optimum wins the race
    assert all(int(j["seed"]) < 1000 for j in raced) and all(j["seed"] == "1000" for b in trials for j in b)


def test_a_failed_trial_is_spent_and_validation_alone_chooses(tmp_path, monkeypatch):
    # validation prefers lr near 0.008 for chinet; its test metric would prefer the recipe: validation decides
    launcher = TuningLauncher(
        lambda r, lr: narrow(lr) if r == "chinet" else 93.0,
        lambda r, lr, s: 99.0 if (r == "chinet" and lr == RECIPE_LR) else 91.0,
        fail={("chinet", 0), ("unet", 5)},
    )
    tuned_sweep(tmp_path, monkeypatch, launcher).sweep(["experiment=chinet_table2", "row=chinet,unet"])
    assert {r: len(t) for r, t in launcher.trials.items()} == {"chinet": 16, "unet": 16}  # N each, failures spent
    raced = [j for b in launcher.batches if "trial" not in b[0] for j in b]
    assert {int(j["tuned"]) for j in raced if j["row"] == "chinet"} != {0}  # the failed recipe trial not chosen
    assert all(float(j["draws.task.optimizer.lr"]) != RECIPE_LR for j in raced if j["row"] == "chinet")


def test_a_rerun_draws_the_same_trials_and_chooses_the_same(tmp_path, monkeypatch):
    objective = {"chinet": narrow, "unet": lambda lr: 93.0}
    runs = []
    for _ in range(2):  # the second as a resumed phase: its jobs would be skipped by their config hash
        launcher = TuningLauncher(lambda r, lr: objective[r](lr), lambda r, lr, s: objective[r](lr))
        tuned_sweep(tmp_path, monkeypatch, launcher).sweep(["experiment=chinet_table2", "row=chinet,unet"])
        runs.append(launcher.batches)
    assert runs[0] == runs[1]


def test_experts_are_tuned_first_as_rows_of_their_own_and_stay_fixed_while_stage_2_is_tuned(tmp_path, monkeypatch):
    # BiFNet Table IV: two single-modal rows (each its expert) and two fused rows on the frozen rgb and bev experts;
    # the bev expert has a narrow optimum away from the recipe, the rgb expert a plateau
    expert = {"expert rgb": lambda lr: 90.0, "expert bev": narrow}
    fused = {"bifnet_dst_sum": lambda lr: 94.0, "bifnet_dst_cbf": narrow}
    launcher = TuningLauncher(lambda r, lr: {**expert, **fused}[r](lr), lambda r, lr, s: 95.0 + 0.01 * s)
    rows = "row=bifnet_image,bifnet_bev,bifnet_dst_sum,bifnet_dst_cbf"
    tuned_sweep(tmp_path, monkeypatch, launcher, "table.tune.trials=6").sweep(["experiment=bifnet_table4", rows])
    trials = [b for b in launcher.batches if "trial" in b[0]]
    assert len(trials) == 12  # 6 trial indices of the experts, then 6 of the fused rows
    assert all(sorted(j["experts.tune"] for j in b) == ["bev", "rgb"] for b in trials[:6])
    assert all(sorted(j["row"] for j in b) == ["bifnet_dst_cbf", "bifnet_dst_sum"] for b in trials[6:])
    assert [int(b[0]["trial"]) for b in trials] == [*range(6), *range(6)]  # the same draws for experts and rows
    bev = max(range(6), key=lambda k: (launcher.trials["expert bev"][k], -k))  # the bev expert's validation winner
    assert bev > 0
    drawn = {k[len("draws.") :]: v for k, v in trials[bev][0].items() if k.startswith("draws.")}
    fixed = {f"experts.draws.bev.{k}": v for k, v in drawn.items()}  # rgb's recipe: nothing to fix
    for job in [j for b in launcher.batches[6:] for j in b]:  # the fused rows' trials and every raced job
        assert {k: v for k, v in job.items() if k.startswith("experts.draws.")} == fixed
    raced = {j["row"]: j for b in launcher.batches if "trial" not in b[0] for j in b}
    assert raced["bifnet_bev"]["tuned"] == str(bev) and raced["bifnet_image"]["tuned"] == "0"  # as their experts
    assert not any(k.startswith("draws.") for r in ("bifnet_bev", "bifnet_image") for k in raced[r])
    assert raced["bifnet_dst_sum"]["tuned"] == "0" and int(raced["bifnet_dst_cbf"]["tuned"]) > 0


def test_a_budget_spent_on_the_experts_leaves_stage_2_its_recipe_trial_at_least() -> None:
    from ablate.sweep.tuning import Experts, tune

    clock = iter(range(0, 10_000, 60))  # every call a minute later
    spec = TuneSpec(4, SPACE, budget_min=5.0)
    batches: list[list[list[str]]] = []
    experts = Experts({"rgb": ["row=a"], "bev": ["row=a"]}, {"b": "bev"})
    tuned = tune(
        spec, "t", {"a": ["row=a"], "b": ["row=b"]}, experts, batches.append, lambda: {}, clock=lambda: next(clock)
    )
    assert tuned.experts_done < 4 and tuned.done == 1 and len(tuned.stopped) == 2
    assert [len(b) for b in batches] == [2] * tuned.experts_done + [1]  # the single row b is tuned as its expert
    assert tuned.overrides["b"] == ["tuned=0"] and tuned.overrides["a"] == ["tuned=0"]


def test_a_resumed_phase_counts_the_earlier_sweeps_time_against_its_budget() -> None:
    from ablate.sweep.tuning import Experts, tune

    def phase(earlier: float) -> tuple[int, list[str]]:
        now = [0.0]

        def launch(batch: list[list[str]]) -> None:
            now[0] += 60.0  # a trial index takes a minute

        spec = TuneSpec(4, SPACE, budget_min=5.0)
        jobs = {"a": ["row=a"], "b": ["row=b"]}
        out = tune(spec, "t", jobs, Experts(), launch, lambda: {}, clock=lambda: now[0], earlier=earlier)
        return out.done, out.stopped

    assert phase(0.0) == (4, [])  # 4 minutes: within the 5
    done, stopped = phase(180.0)  # 3 minutes spent by an earlier sweep: 2 more fit
    assert done == 2 and stopped == [
        "the tuning budget of 5 min stopped the phase after trial 1 of every row (5.0 min spent, about 1.0 more a trial)"
    ]


def test_the_sweeper_reads_the_earlier_sweeps_spans_of_the_tables_trials(monkeypatch: pytest.MonkeyPatch) -> None:
    from hydra_plugins.ablate_racing_sweeper import _impl

    minute = 60_000
    trials = pd.DataFrame(  # two sweeps: 0-10 min, and 30-34 min (its trial 0 of row a run again: the latest counts)
        {
            "row": ["a", "b", "a", "a", "b"],
            "trial": [0, 0, 1, 0, 1],
            "started": [0, 0, 5 * minute, 30 * minute, 31 * minute],
            "seconds": [300.0, 300.0, 300.0, 60.0, 180.0],
            "sweep_id": ["s1", "s1", "s1", "s2", "s2"],
        }
    )
    monkeypatch.setattr(_impl, "tuning_trials", lambda tracker, name: trials)
    monkeypatch.setattr(_impl.RacingSweeperImpl, "_tracker", lambda self: None)
    sweeper = _impl.RacingSweeperImpl(None)
    assert sweeper._earlier_trials("t") == 60 * ((10 - 0) + (34 - 30))
    monkeypatch.setattr(_impl, "tuning_trials", lambda tracker, name: trials.iloc[:0])
    assert sweeper._earlier_trials("t") == 0.0


def test_a_smoke_table_on_experts_tunes_its_experts_then_stage_2_on_validation_and_races_on_the_choice(tmp_path):
    from tests.scaleout import SERIAL, TINY, ablate, output, runs

    rows = "row=bifnet_bev,bifnet_dst_sum"  # the LiDAR expert's row, and a fused row on frozen experts
    out = ablate(tmp_path, "-m", "experiment=bifnet_table4", rows, *FULL_BUDGET, SERIAL, *TINY)
    assert out.returncode == 0, output(out)
    # the progress counts the whole sweep from its first job: 4 experts' trials, 2 of stage 2, 2 raced jobs
    done = re.findall(r"Sweep progress: (\d+)/(\d+) jobs finished", out.stdout + out.stderr)
    assert done == [(str(k), "8") for k in range(1, 9)], done
    # each kind of job to go timed apart: experts' trials, stage 2's trials, raced jobs (each at its row's time)
    per = [
        re.findall(r"per ([a-z ]+?)(?: as planned)?[,)]", line)
        + [kind.strip() for kind in re.findall(r"([a-z ]+?)s at their rows'", line)]
        for line in re.findall(r"Sweep progress: .*", out.stdout + out.stderr)
    ]
    assert per[0] == ["expert trial", "tuning trial", "trained job"], per
    assert per[4] == ["tuning trial", "trained job"] and per[6] == ["trained job"] and per[7] == [], per
    # every trial's row and number recorded, and each tuned kind's launches: the ETA waits for a launch's slowest row
    (sweep_file,) = tmp_path.glob("multirun/*/*/sweep.json")  # the sweep's one state file
    sweep = json.loads(sweep_file.read_text())
    assert [p.name for p in sweep_file.parent.iterdir() if p.name.startswith(".")] == []  # no hidden state beside it
    recorded = sweep["ended"]
    assert sorted((r["row"], r["trial"]) for r in recorded if r["kind"] != "job") == [
        ("bifnet_dst_sum", 0), ("bifnet_dst_sum", 1),
        ("expert bev", 0), ("expert bev", 1), ("expert rgb", 0), ("expert rgb", 1),
    ]  # fmt: skip
    # the raced jobs trained seed 0's two experts within them, each timed apart for the ETA (ablate.jobs.stage1)
    assert sweep["progress"]["experts"]["planned"] == 2
    raced = [r for r in recorded if r["kind"] == "job"]
    assert sorted(len(r.get("experts", [])) for r in raced) in ([0, 2], [1, 1]), raced
    assert sorted(m for r in raced for m in r.get("experts", {})) == ["bev", "rgb"], raced  # by modality
    assert all(sum(r["experts"].values()) <= r["stage1"] < r["seconds"] for r in raced if r.get("experts")), raced
    launches = sweep["progress"]["launches"]
    assert {kind: sorted(rows) for kind, rows in launches.items()} == {
        "expert trial": ["expert bev", "expert rgb"],
        "trial": ["bifnet_dst_sum"],
    }
    store = f"sqlite:///{tmp_path / 'mlflow.db'}"
    _, trials = runs(store, "bifnet_table4", kind="trial")
    assert sorted((r.data.tags["row"], r.data.tags["trial"]) for r in trials) == [
        ("bifnet_dst_sum", "0"), ("bifnet_dst_sum", "1"),
        ("expert bev", "0"), ("expert bev", "1"), ("expert rgb", "0"), ("expert rgb", "1"),
    ]  # fmt: skip
    for run in trials:  # validation only: an objective, never a test metric; a seed no race reaches
        assert run.data.metrics["val_best"] > 0 and "max_f" not in run.data.metrics, run.data.metrics
        assert run.data.tags["seed"] == "1000" and "task.optimizer.lr" in run.data.tags["trial_config"]
    first = min(r.info.start_time for r in trials if r.data.tags["row"] == "bifnet_dst_sum")
    assert all(r.info.end_time <= first for r in trials if r.data.tags["row"].startswith("expert "))
    _, experts = runs(store, "experts", kind="expert")  # one per modality and seed: the trials share theirs
    assert sorted((r.data.tags["row"], r.data.tags["seed"]) for r in experts) == [
        ("expert bev", "0"), ("expert bev", "1000"), ("expert rgb", "0"), ("expert rgb", "1000"),
    ]  # fmt: skip
    chosen = {  # per expert, its trial with the best validation objective, the first of several that tie
        row: max(
            (r for r in trials if r.data.tags["row"] == row),
            key=lambda r: (r.data.metrics["val_best"], -int(r.data.tags["trial"])),
        )
        for row in ("expert bev", "expert rgb")
    }
    for expert in (r for r in experts if r.data.tags["seed"] == "1000"):  # stage 2's: copied from the chosen trial
        trial = chosen[expert.data.tags["row"]]
        assert expert.data.tags["reused_from"] == trial.info.run_id, expert.data.tags
        assert expert.data.tags["config_hash"] == trial.data.tags["expert_hash"] != trial.data.tags["config_hash"]
        assert "trial" not in expert.data.tags and "race_plan" not in expert.data.tags
        assert (tmp_path / "checkpoints" / "experts" / expert.data.tags["config_hash"] / "best.ckpt").is_file()
    bev = max(
        (r.data.metrics["val_best"], -int(r.data.tags["trial"])) for r in trials if r.data.tags["row"] == "expert bev"
    )
    _, jobs = runs(store, "bifnet_table4")
    tuned = {r.data.tags["row"]: r.data.tags["tuned"] for r in jobs}
    assert tuned["bifnet_bev"] == str(-bev[1]) and tuned["bifnet_dst_sum"] in ("0", "1")  # the LiDAR row: its expert's
    text = (tmp_path / "results" / "bifnet_table4.md").read_text()
    assert "Tuning (validation only; the race ran on each row's chosen trial):" in text
    assert "| expert bev | 2 |" in text and "The experts' own recipe was tuned first" in text
    assert "task.optimizer.lr ~ tag(log, interval(1e-4, 1e-2))" in text and "tuning seed 0; N = 2" in text
    assert (tmp_path / "results" / "runs" / "bifnet_table4.trials.csv").is_file()
    assert (tmp_path / "results" / "bifnet_table4_tuning.png").is_file()
    # the same command again: its plan finds every trial and raced job done, stage 2's on the chosen experts included
    again = ablate(tmp_path, "-m", "experiment=bifnet_table4", rows, *FULL_BUDGET, SERIAL, *TINY)
    assert again.returncode == 0, output(again)
    plan = re.search(r"Sweep plan: (\d+) job\(s\)[^\n]*", again.stdout + again.stderr)
    assert plan and f"; {plan[1]} done already (skipped)" in plan[0] and "to train first" not in plan[0], plan


def test_a_phase_resumed_by_a_later_sweep_counts_each_sweeps_span_not_the_time_between() -> None:
    from ablate.tables.tuning import phase_wall

    minute = 60000
    trials = pd.DataFrame(
        {
            "started": [0, 0, 10 * minute, 600 * minute],  # the second sweep ten hours later, the same command
            "seconds": [300.0, 360.0, 240.0, 120.0],
            "sweep_id": ["a", "a", "a", "b"],
        }
    )
    assert phase_wall(trials) == (14.0 + 2.0, 2)  # 0 -> 14 min, then 600 -> 602 min
    older = trials.drop(columns="sweep_id")  # records written before trials kept their sweep: one span
    assert phase_wall(older) == (602.0, 1)
