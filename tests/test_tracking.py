"""Config hashing, param flattening and the SQLite retry of ablate.store.tracker."""

import sqlite3
import time

import pytest
import sqlalchemy.exc
from omegaconf import OmegaConf

from ablate.store import config_hash, flatten, git_commit
from ablate.store.retry import retry
from ablate.store.tracker import Tracker
from ablate.store.uris import SHARED_VIEW_KEY, SHARED_VIEW_TAG, runs_link
from tests.stores import sqlite_uri


def _cfg(**over):
    base = {
        "seed": 0,
        "model": {"width": 0.25},
        "force": False,
        "logger": {"tracking_uri": "sqlite:///a.db"},
        "trainer": {"max_epochs": 2, "enable_progress_bar": True},
        "data": {"num_workers": 0, "frames": 8},
        "table": {"name": "t", "rows": []},
    }
    return OmegaConf.merge(OmegaConf.create(base), OmegaConf.create(over))


def test_hash_ignores_keys_that_do_not_change_results():
    h = config_hash(_cfg())
    assert h == config_hash(_cfg(force=True, logger={"tracking_uri": "sqlite:///b.db"}))
    assert h == config_hash(_cfg(trainer={"enable_progress_bar": False}, data={"num_workers": 4}))
    assert h == config_hash(_cfg(table={"name": "t", "rows": [{"row": "x"}]}))
    frozen = config_hash(_cfg(experts={"freeze": True}))
    assert frozen == config_hash(_cfg(experts={"freeze": True, "cache_features": True})) != h


def test_hash_changes_with_results_relevant_keys():
    h = config_hash(_cfg())
    assert h != config_hash(_cfg(seed=1))
    assert h != config_hash(_cfg(model={"width": 0.5}))
    assert h != config_hash(_cfg(trainer={"max_epochs": 3}))


def test_flatten_nested_dicts_and_lists():
    assert flatten({"a": {"b": 1, "c": [2, {"d": 3}]}, "e": None}) == {
        "a.b": "1",
        "a.c.0": "2",
        "a.c.1.d": "3",
        "e": "None",
    }


def test_retry_waits_out_a_locked_database():
    calls = []

    def flaky():
        calls.append(1)
        if len(calls) < 3:
            raise sqlite3.OperationalError("database is locked")
        return "ok"

    assert retry(flaky) == "ok" and len(calls) == 3


def test_a_lock_is_waited_out_for_its_budget_not_a_number_of_tries_then_raised():
    calls = []

    def held():
        calls.append(time.monotonic())
        raise sqlite3.OperationalError("database is locked")

    with pytest.raises(sqlite3.OperationalError, match="locked"):
        retry(held, locked_s=1.5, outage_s=0)
    assert calls[-1] - calls[0] >= 1.5  # waited for the whole budget, however many tries that took
    assert max(b - a for a, b in zip(calls, calls[1:])) <= 1.6  # a pause is at most 1 s (jittered ±50 %)


def test_retry_reraises_other_errors_at_once():
    calls = []

    def broken():
        calls.append(1)
        raise ValueError("no such column")

    with pytest.raises(ValueError):
        retry(broken)
    assert len(calls) == 1


def test_experiment_creation_is_idempotent_and_stale_runs_are_killed(tmp_path):
    tracker = Tracker(sqlite_uri(tmp_path), str(tmp_path / "artifacts"))
    exp = tracker.experiment_id("table")
    assert tracker.experiment_id("table") == exp
    run = tracker.start(exp, "job", {"config_hash": "abc"})
    assert tracker.finished_run(exp, "abc") is None
    assert tracker.close_stale(exp, "abc") == 1
    assert tracker.get_run(run).info.status == "KILLED"
    done = tracker.start(exp, "job", {"config_hash": "abc"})
    tracker.end(done, "FINISHED")
    assert tracker.finished_run(exp, "abc").info.run_id == done


def test_a_downloaded_artifact_draws_no_progress_bar(tmp_path, capfd, monkeypatch):
    monkeypatch.delenv("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", raising=False)
    tracker = Tracker(sqlite_uri(tmp_path), str(tmp_path / "artifacts"))
    run = tracker.start(tracker.experiment_id("table"), "job", {})
    (tmp_path / "records.csv").write_text("a,b\n1,2\n")
    tracker.log_artifact(run, tmp_path / "records.csv")
    capfd.readouterr()
    got = tracker.download_artifact(run, "records.csv", tmp_path / "out")
    assert got.read_text() == "a,b\n1,2\n"
    assert "Downloading artifacts" not in capfd.readouterr().err  # a sweep reads one such file per run


def test_sweeps_whose_process_died_are_closed_as_killed(tmp_path):
    import os
    import socket
    import subprocess
    import sys

    from ablate.store.tracker import KIND_SWEEP
    from ablate.sweep.parent import close_dead_sweeps

    tracker = Tracker(sqlite_uri(tmp_path), str(tmp_path / "artifacts"))
    exp = tracker.experiment_id("table")
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    host = socket.gethostname()
    gone = tracker.start(exp, "s1", {"kind": KIND_SWEEP, "host": host, "pid": dead.stdout.strip()})
    alive = tracker.start(exp, "s2", {"kind": KIND_SWEEP, "host": host, "pid": str(os.getpid())})
    elsewhere = tracker.start(exp, "s3", {"kind": KIND_SWEEP, "host": "another-host", "pid": dead.stdout.strip()})
    assert close_dead_sweeps(tracker, exp) == 1
    status = {r: tracker.get_run(r).info.status for r in (gone, alive, elsewhere)}
    assert status == {gone: "KILLED", alive: "RUNNING", elsewhere: "RUNNING"}


def test_the_table_view_is_an_mlflow_shared_view_with_the_metric_columns(tmp_path):
    import json

    tracker = Tracker(sqlite_uri(tmp_path))
    exp = tracker.experiment_id("chinet_table2")
    link = tracker.share_table_view(exp, ["det_rate", "normal/ap11"])
    state = json.loads(tracker.experiment_tags(exp)[SHARED_VIEW_TAG + SHARED_VIEW_KEY])
    assert state["selectedColumns"] == ["tags.`row`", "metrics.`det_rate`", "metrics.`normal/ap11`"]  # the UI's keys
    assert link == (
        f"http://127.0.0.1:5000/#/experiments/{exp}/runs?viewStateShareKey={SHARED_VIEW_KEY}"
        "&workflowType=machine_learning"
    )
    # on a tracking server the link is the server's own UI
    assert runs_link("http://10.0.0.2:5001/", "7").startswith("http://10.0.0.2:5001/#/experiments/7/runs?")


def test_a_run_is_dirty_for_changed_code_not_for_what_a_published_sweep_wrote(tmp_path, monkeypatch):
    import subprocess

    def git(*args):
        subprocess.run(["git", *args], cwd=tmp_path, check=True, capture_output=True)

    (tmp_path / "results").mkdir()
    (tmp_path / "results" / "t.md").write_text("old table")
    (tmp_path / "model.py").write_text("x = 1")
    (tmp_path / "README.md").write_text("| old summary line |")
    git("init", "-q")
    git("add", ".")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "c")
    monkeypatch.chdir(tmp_path)
    clean = git_commit()
    assert len(clean) == 40
    (tmp_path / "results" / "t.md").write_text("regenerated table")
    (tmp_path / "README.md").write_text("| new summary line |")
    assert git_commit() == clean
    (tmp_path / "model.py").write_text("x = 2")
    assert git_commit() == clean + "-dirty"


def test_a_dataset_two_jobs_record_at_once_links_the_second_run_and_other_errors_stay(tmp_path, monkeypatch):
    first, second = Tracker(sqlite_uri(tmp_path)), Tracker(sqlite_uri(tmp_path))
    exp = first.experiment_id("t")
    runs = [t.start(exp, f"job {i}", {"kind": "job"}) for i, t in enumerate((first, second))]
    first.log_dataset(runs[0], "synth-abc", "d1", "/data/synth-abc", {"train": 12})
    real = second._client.log_inputs
    calls = []

    def raced(*args, **kwargs):  # what the loser of the race sees: the other job's insert of the same dataset
        calls.append(args)
        if len(calls) == 1:
            raise sqlalchemy.exc.IntegrityError(
                "INSERT INTO datasets", {}, sqlite3.IntegrityError("UNIQUE constraint failed: datasets.digest")
            )
        return real(*args, **kwargs)

    monkeypatch.setattr(second._client, "log_inputs", raced)
    second.log_dataset(runs[1], "synth-abc", "d1", "/data/synth-abc", {"train": 12})
    assert len(calls) == 2
    inputs = [second._client.get_run(r).inputs.dataset_inputs for r in runs]
    assert [[d.dataset.digest for d in i] for i in inputs] == [["d1"], ["d1"]]
    monkeypatch.setattr(second._client, "log_inputs", lambda *a, **k: (_ for _ in ()).throw(ValueError("bad input")))
    with pytest.raises(ValueError, match="bad input"):
        second.log_dataset(runs[1], "synth-abc", "d1", "/data/synth-abc", {"train": 12})
