"""A real race through the parallel launcher and the store, the reproduction check on its runs, and the race going on
from its published records in a fresh store, as a user runs them (scale=smoke: one seed at the first look decides
nothing, and two seeds of these tiny jobs decide nothing)."""

import re
import shutil

import numpy as np
import pandas as pd
import pytest

from ablate.tables.records import reseal_records
from ablate.tables.significance import prediction_interval
from tests.test_cli import REPO, SERIAL, TINY, ablate, runs

#: Where the race's published folder is kept as it was published (the reproduction check edits the records).
PUBLISHED = "published"


@pytest.fixture(scope="module")
def raced(tmp_path_factory):
    cwd = tmp_path_factory.mktemp("raced")
    out = ablate(cwd, "-m", "experiment=chinet_table2", "row=chinet,unet", "scale.race.looks=[1,2]", *TINY)
    if (cwd / "results").is_dir():
        shutil.copytree(cwd / "results", cwd.parent / f"{cwd.name}-{PUBLISHED}")
    return cwd, out


def test_an_undecided_race_adds_seeds_at_the_next_look_through_the_launcher(raced):
    cwd, out = raced
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    _, jobs = runs(cwd, "chinet_table2")
    assert sorted((r.data.tags["row"], r.data.tags["seed"]) for r in jobs) == [
        ("chinet", "0"),
        ("chinet", "1"),
        ("unet", "0"),
        ("unet", "1"),
    ]
    assert all(r.info.status == "FINISHED" for r in jobs)
    client, (sweep,) = runs(cwd, "chinet_table2", kind="sweep")
    assert sweep.data.tags["race_looks"] == "2"
    assert sweep.data.tags["race"].startswith("left undecided after the last look")
    table = (cwd / "results" / "chinet_table2.md").read_text()
    assert "Racing seeds: looks at 1, 2 seeds per row, alpha = 0.05, Bonferroni" in table
    assert "Left undecided, after the last look: ChiNet vs U-Net." in table
    made = r"Made on .+, precision 32-true, 1 thread\(s\) per job; wall time \d+ min over 1 sweep\(s\)"
    assert re.search(made, table), table[-1500:]


def test_a_race_goes_on_from_its_published_records_in_a_fresh_store_and_trains_only_what_they_lack(raced, tmp_path):
    """``--extend``: the published records of a race of looks 1, 2 become the fresh store's jobs, and the same
    command with a third look trains seed 2 alone; a record made on other numerics (here: edited to another CPU) is
    named and not loaded, and its job trains again, to the very number recorded (the same machine and code)."""
    cwd, out = raced
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    here = tmp_path / "later"
    shutil.copytree(cwd.parent / f"{cwd.name}-{PUBLISHED}", here / "results")
    records = here / "results" / "runs" / "chinet_table2.csv"
    before = pd.read_csv(records, dtype=str, keep_default_na=False)
    edited = before.copy()
    edited.loc[(edited["row"] == "unet") & (edited["seed"] == "1"), "made_cpu"] = "Another CPU"
    edited.to_csv(records, index=False)
    assert reseal_records(here / "results", "chinet_table2") is not None
    loaded = ablate(here, "--extend", "experiment=chinet_table2", *TINY, module="ablate.report")
    assert loaded.returncode == 0, loaded.stdout[-3000:] + loaded.stderr[-3000:]
    assert "chinet_table2: 3 run(s) loaded" in loaded.stdout and "1 not loaded" in loaded.stdout
    assert re.search(r"unet seed 1: made on other numerics than this machine's \(CPU: Another CPU -> ", loaded.stdout)
    again = ablate(here, "--extend", "experiment=chinet_table2", *TINY, module="ablate.report")
    assert "0 run(s) loaded" in again.stdout and "3 already there" in again.stdout  # nothing loaded twice

    looks = ["-m", "experiment=chinet_table2", "row=chinet,unet", "scale.race.looks=[1,2,3]", SERIAL, *TINY]
    raced_on = ablate(here, *looks)
    assert raced_on.returncode == 0, raced_on.stdout[-3000:] + raced_on.stderr[-3000:]
    client, jobs = runs(here, "chinet_table2")
    assert all(r.info.status == "FINISHED" for r in jobs)
    # each run has the config its footer's fingerprint check reads where the code changed since its commit
    assert all("config.yaml" in {a.path for a in client.list_artifacts(r.info.run_id)} for r in jobs)
    trained = sorted((r.data.tags["row"], r.data.tags["seed"]) for r in jobs if "loaded_from" not in r.data.tags)
    assert trained == [("chinet", "2"), ("unet", "1"), ("unet", "2")]
    # each row is timed from a checkpoint trained here: a loaded run (chinet seed 0, its lowest) has none here
    hashes = {r.data.tags["config_hash"] for r in jobs if "loaded_from" not in r.data.tags}
    timed = {r.data.tags["row"]: r.data.tags["latency_checkpoint"] for r in jobs}
    assert all(any(h in path for h in hashes) for path in timed.values()), timed
    after = pd.read_csv(records, dtype=str, keep_default_na=False).set_index(["row", "seed"])
    assert sorted(after.index) == [(r, str(s)) for r in ("chinet", "unet") for s in range(3)]
    # the loaded runs publish their recorded values; the retrained one the recorded numbers again
    kept = before.set_index(["row", "seed"])
    same = [c for c in kept.columns if c != "run_id" and not c.startswith("latency")]
    for key in [("chinet", "0"), ("chinet", "1"), ("unet", "0")]:
        assert after.loc[key, same].to_dict() == kept.loc[key, same].to_dict(), key
    assert after.loc[("unet", "1"), "det_rate"] == kept.loc[("unet", "1"), "det_rate"]
    origin = {k: f"results/runs/chinet_table2.csv#{kept.loc[k, 'run_id']}" for k in [("chinet", "0"), ("chinet", "1")]}
    assert after.loc[list(origin), "loaded_from"].tolist() == list(origin.values())
    assert after.loc[("unet", "2"), "loaded_from"] == ""
    table = (here / "results" / "chinet_table2.md").read_text()
    assert "Racing seeds: looks at 1, 2, 3 seeds per row" in table and "over 2 sweep(s)" in table
    assert "3 of 6 runs were loaded from the published records of an earlier store" in table


def test_a_table_with_a_tuning_phase_is_not_extended_from_its_records(raced, tmp_path):
    from ablate.analysis.extend import extend_table
    from ablate.store import Tracker

    cwd, _ = raced
    results = tmp_path / "results"
    shutil.copytree(cwd.parent / f"{cwd.name}-{PUBLISHED}", results)
    (results / "runs" / "chinet_table2.trials.csv").write_text("run_id,row,trial\n")
    tracker = Tracker(f"sqlite:///{tmp_path / 'mlflow.db'}")
    with pytest.raises(ValueError, match="records hold a tuning phase .*race the table again from the start"):
        extend_table(tracker, "chinet_table2", results, lambda cfg: {}, ["experiment=chinet_table2", *TINY])


def test_the_reproduction_check_reruns_a_seed_and_names_what_differs(raced):
    cwd, _ = raced
    out = ablate(cwd, "--reproduce", "experiment=chinet_table2", "row=unet", "seed=1", *TINY, module="ablate.report")
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    # the same machine, threads and code: the very number again
    assert re.search(r"unet, seed 1, det_rate: (\S+) rerun here; recorded \1 \(\+0\.00\)", out.stdout), out.stdout[
        -800:
    ]
    assert "inside the row's 95 % prediction interval for a new seed" in out.stdout
    assert "same CPU, precision and threads as the recorded runs" in out.stdout
    # the published records as if made on another machine with two threads
    records = cwd / "results" / "runs" / "chinet_table2.csv"
    published = pd.read_csv(records, dtype=str, keep_default_na=False)
    published["made_threads"] = "2"
    published.to_csv(records, index=False)
    assert reseal_records(cwd / "results", "chinet_table2") is not None  # an intended edit, sealed again
    out = ablate(cwd, "--reproduce", "experiment=chinet_table2", "row=unet", *TINY, module="ablate.report")
    assert "differs from the recorded runs: threads: 2 -> 1" in out.stdout
    assert "unet, seed 0" in out.stdout  # the first recorded seed by default
    # chinet_table2 has not measured how far other numerics move a run: its interval leaves them out, and says so
    assert "the table has not measured how far other numerics move a run (table.kernels_run" in out.stdout


def test_the_reproduction_check_without_runs_is_one_error(tmp_path):
    out = ablate(tmp_path, "--reproduce", "experiment=chinet_table2", "row=unet", *TINY, module="ablate.report")
    assert out.returncode == 1
    assert out.stderr.strip().splitlines()[-1].startswith("error: no FINISHED runs of row 'unet' of chinet_table2")


def test_the_prediction_interval_is_wider_than_the_mean_by_sqrt_1_plus_1_over_n():
    values = [96.87, 97.11, 97.0]
    lo, hi = prediction_interval(values)
    # t(0.975, 2) = 4.303; s = 0.1201; sqrt(1 + 1/3) = 1.1547
    assert (hi - lo) / 2 == pytest.approx(4.303 * np.std(values, ddof=1) * 1.1547, rel=1e-3)
    assert np.isnan(prediction_interval([97.0])[0])


def test_other_numerics_widen_the_prediction_interval_by_the_shift_measured_and_never_narrow_it():
    """A run made with other numerics than the recorded ones (another CPU's kernels, another thread count) also
    moves by their rounding: ``table.kernels_run``'s sd is added to the new value's variance, with Welch and
    Satterthwaite's degrees of freedom."""
    values = [96.87, 97.11, 97.0]
    plain = prediction_interval(values)
    lo, hi = prediction_interval(values, (0.254, 3))
    # s² (1 + 1/n) = 0.01923, sd² = 0.06452: 4.46 degrees of freedom, t = 2.667, half 2.667 · 0.2894 = 0.772
    assert (hi - lo) / 2 == pytest.approx(0.7718, abs=1e-3) and (lo + hi) / 2 == pytest.approx(np.mean(values))
    assert lo < plain[0] and hi > plain[1]
    assert prediction_interval(values, (0.0, 3)) == pytest.approx(plain)
    # a small shift measured on more seeds than the row has: t's degrees of freedom grow past n - 1 and would
    # narrow the interval (half 4.21 < 4.97); it keeps the interval without the shift instead
    assert prediction_interval([94.0, 95.0, 96.0], (0.5, 3)) == pytest.approx(prediction_interval([94.0, 95.0, 96.0]))


@pytest.mark.parametrize("seeds", [3, 5, 8])
def test_the_widened_interval_holds_a_new_run_on_other_numerics_95_percent_of_the_time(seeds):
    """Simulated at the tables' seed counts: the recorded seeds ~ N(0, 1), another CPU's shift ~ N(0, k) measured as
    the root mean square of m reruns, a new run on that CPU = a new seed + a shift; the interval holds it about 95 %
    of the time (2,000 draws: Monte Carlo se 0.005), for a shift small or large against the seeds' spread."""
    rng = np.random.default_rng(seeds)
    for k, m in ((0.5, 3), (2.0, 3), (3.0, 6)):
        held = 0
        for _ in range(2000):
            values = rng.normal(0, 1, seeds)
            measured = float(np.sqrt(np.mean(rng.normal(0, k, m) ** 2)))
            lo, hi = prediction_interval(values, (measured, m))
            held += lo <= rng.normal(0, 1) + rng.normal(0, k) <= hi
        assert 0.925 <= held / 2000 <= 0.975, (seeds, k, m, held / 2000)


def test_a_tuned_row_is_rerun_on_the_config_it_was_tuned_to() -> None:
    import json

    import pandas as pd
    import pytest

    from ablate.analysis.reproduce import tuned_config
    from ablate.config import compose

    cfg = compose(["experiment=bifnet_table4", "row=bifnet_dst_sum", "scale=cpu"])
    recipe = cfg.task.optimizer.lr
    tuned = {"task.optimizer.lr": 0.0042, "task.optimizer.weight_decay": None, "experts.bev.task.optimizer.lr": 7e-4}
    runs = pd.DataFrame({"seed": [0, 1], "tuned_config": [json.dumps(tuned)] * 2})
    assert tuned_config(runs, cfg) == [
        "++draws.task.optimizer.lr=0.0042",
        "++experts.draws.bev.task.optimizer.lr=0.0007",
    ]
    # an expert's value is set again even where it equals stage 2's own (the sweep set it: it is in the expert's hash)
    same = {"task.optimizer.lr": recipe, "experts.rgb.task.optimizer.lr": recipe}
    assert tuned_config(pd.DataFrame({"tuned_config": [json.dumps(same)]}), cfg) == [
        f"++experts.draws.rgb.task.optimizer.lr={recipe}"
    ]
    recipe_only = {"task.optimizer.lr": recipe, "task.optimizer.weight_decay": None}  # tuned to trial 0: the recipe
    assert tuned_config(pd.DataFrame({"tuned_config": [json.dumps(recipe_only)]}), cfg) == []
    assert tuned_config(pd.DataFrame({"tuned_config": ["", None]}), cfg) == []  # raced untuned
    mixed = pd.DataFrame({"tuned_config": [json.dumps(tuned), json.dumps(recipe_only)]})
    with pytest.raises(ValueError, match="tuned to different configs"):
        tuned_config(mixed, cfg)


def on_published_hashes(args: list[str]):
    """The sweep plan of ``python -m ablate -m ARGS``, after checking that every row's job of seed 0 has the published
    run's config hash (with the records' own numerics)."""
    from ablate.config import compose
    from ablate.jobs.spec import resolved_config
    from ablate.store import config_hash
    from ablate.sweep.launches import SweepPlan
    from ablate.tables import published

    cfg = compose(args)
    plan = SweepPlan.of(cfg, args, {})
    records = pd.read_csv(published.records(str(cfg.table.name)))
    assert records["tuned_config"].notna().any()  # some row raced on a tuned config: the case that matters
    for row, overrides in plan.rows.items():
        mine = records[(records["row"] == row) & (records["seed"] == 0)]
        numerics = f"trainer.precision={mine['made_precision'].iloc[0]}"  # channels_last follows it (auto)
        job, _, _ = resolved_config(compose([*overrides, "seed=0", numerics]))
        assert config_hash(job) == mine["config_hash"].iloc[0], (row, overrides)
    return plan


@pytest.mark.parametrize("table", ["chinet_table2", "bifnet_table4"])
def test_one_command_races_every_row_on_its_published_config_hash_for_hash(table):
    """``table.tuned_from=published`` puts each row's jobs on the config its published records were tuned to: with
    the records' own numerics, every row's job of seed 0 has the published run's config hash, tuned rows included."""
    on_published_hashes([f"experiment={table}", "table.tuned_from=published"])


def test_make_run_races_a_paper_table_on_its_published_configs_in_one_look_of_3_seeds():
    """The Makefile's ``run`` recipe, as written: a paper table's every row on its published config hash, at least 3
    seeds per row, in one planned look."""
    import shlex

    recipe = re.search(r"^run:.*\n\t(.+)$", (REPO / "Makefile").read_text(), re.MULTILINE)
    assert recipe is not None
    words = shlex.split(recipe.group(1))
    assert words[1:4] == ["-m", "ablate", "-m"], words
    plan = on_published_hashes(words[4:])
    assert plan.race is not None and list(plan.race.looks) == [3] and len(plan.rows) >= 2


def test_racing_on_published_configs_is_refused_where_there_are_none_or_a_tuning_phase_is_asked_too():
    from ablate.config import compose
    from ablate.sweep.launches import SweepPlan

    for args, message in (
        (["fusion=sum", "table.tuned_from=published", "table.seeds={looks:[2]}"], r"ablate has no published records"),
        (["experiment=chinet_table2", "table.tuned_from=published", "tune=lr_wd"], r"leave tune= out"),
    ):
        with pytest.raises(ValueError, match=message):
            SweepPlan.of(compose(args), args, {})
