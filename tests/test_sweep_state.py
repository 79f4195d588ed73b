"""A sweep's one state file (ablate.sweep.state) and the ends of its life: every job's end lands whole whatever runs
at once, the jobs read the store and parent run from it, and what fails in the sweep's bookkeeping or its table
never hides the jobs' own outcome (ablate.sweep.callback, ablate.sweep.finish, ablate.sweep.parent)."""

from __future__ import annotations

import json
import logging
import threading
from pathlib import Path
from types import SimpleNamespace

import pytest
from omegaconf import OmegaConf

from ablate.store import ServerUnreachable, SweepContext, Tracker
from ablate.store.context import STATE_FILE
from ablate.sweep import finish, progress, state
from ablate.sweep.callback import SweepCallback
from ablate.sweep.parent import stop_sweep
from tests.stores import sqlite_uri
from tests.test_progress import sweep_config


def test_every_jobs_end_lands_whole_in_the_one_state_file_and_the_jobs_read_their_sweep_from_it(tmp_path: Path):
    state.record(tmp_path, store={"uri": "sqlite:///x.db", "artifact_location": None}, parent_run="p1", swept=["row"])
    progress.start(tmp_path, [["row=a", "seed=0"], ["row=b", "seed=0"]] * 20)

    def jobs(worker: int) -> None:  # eight workers ending five jobs each, at once
        for k in range(5):
            progress.finished(tmp_path, "FINISHED", 10.0 + k, 8, "job", f"w{worker}")

    threads = [threading.Thread(target=jobs, args=(w,)) for w in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    now = json.loads((tmp_path / STATE_FILE).read_text())
    assert len(now["ended"]) == 40 and now["progress"]["planned"] == 40
    assert sorted(p.name for p in tmp_path.iterdir()) == [STATE_FILE, state.LOCK_FILE]  # nothing else, nothing hidden
    context = SweepContext.of_sweep(tmp_path, tmp_path)
    assert (context.store, context.parent_run, context.swept) == (
        {"uri": "sqlite:///x.db", "artifact_location": None},
        "p1",
        ("row",),
    )
    assert SweepContext.of_sweep(tmp_path / "none", tmp_path).swept is None  # no state yet: not a sweep's job


def job_end(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A job of the sweep in ``tmp_path`` that starts and ends, as Hydra calls the callback in the job's process."""
    monkeypatch.setattr(SweepContext, "current", classmethod(lambda cls: SweepContext(tmp_path, tmp_path)))
    config = OmegaConf.create({"hydra": {"overrides": {"task": ["row=a", "seed=1"]}, "launcher": {}}})
    callback = SweepCallback()
    callback.on_job_start(config)
    ended = SimpleNamespace(status=SimpleNamespace(name="COMPLETED"), _return_value="FINISHED")
    callback.on_job_end(config, ended)


def test_a_jobs_end_is_reported_and_bookkeeping_that_fails_leaves_the_job_as_it_ended(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    progress.start(tmp_path, [["row=a", "seed=0"], ["row=a", "seed=1"]])
    with caplog.at_level(logging.INFO, logger="ablate.sweep.callback"):
        job_end(tmp_path, monkeypatch)
    assert "Sweep progress: 1/2 jobs finished, 1 to go" in caplog.text
    assert state.read(tmp_path)["ended"][0]["row"] == "a"
    (tmp_path / STATE_FILE).write_text("{not json")  # a state file another hand broke
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="ablate.sweep.callback"):
        job_end(tmp_path, monkeypatch)  # does not raise: the job's outcome stands
    assert "Could not record the sweep's progress" in caplog.text


def test_a_sweep_stopped_while_its_store_is_down_still_says_so(capsys: pytest.CaptureFixture) -> None:
    class Down:
        def set_tags(self, run_id: str, tags: dict[str, str]) -> None:
            raise ServerUnreachable("http://store", 5.0, 5.0, "connection refused")

    stop_sweep(Down(), "p1", "SIGTERM", 2, 0)  # type: ignore[arg-type]
    assert capsys.readouterr().err.startswith("stopped: sweep stopped by SIGTERM: 2 worker(s) stopped")


def test_a_table_that_cannot_be_written_fails_the_sweep_after_its_parent_is_closed(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    config = sweep_config("experiment=chinet_table2", "scale=smoke")
    config.hydra.runtime.cwd, config.hydra.sweep.dir = str(tmp_path), "sweep"
    tracker = Tracker(sqlite_uri(tmp_path), str(tmp_path / "artifacts"))
    parent = tracker.start(tracker.experiment_id("chinet_table2"), "sweep", {"kind": "sweep"})
    state.record(tmp_path / "sweep", store={"uri": tracker.uri, "artifact_location": None}, parent_run=parent)

    def broken(*args: object, **kwargs: object) -> None:
        raise RuntimeError("no such column")

    monkeypatch.setattr(finish, "measure", broken)  # the rows cannot be timed: the table is written all the same
    monkeypatch.setattr(finish, "write_table", broken)  # nor can the table: the sweep fails, after its parent
    with caplog.at_level(logging.INFO, logger="ablate.sweep.finish"), pytest.raises(SystemExit) as stopped:
        finish.finish(config)
    assert stopped.value.code == 1
    assert "Could not time the rows side by side (python -m ablate.latency): no such column" in caplog.text
    assert "Could not write the table 'chinet_table2': no such column" in caplog.text
    assert "report: the table could not be written" in caplog.text
    assert tracker.get_run(parent).info.status == "FAILED"


def test_a_job_returns_its_stage_one_with_its_status_and_both_survive_a_launchers_pickle():
    import pickle

    from ablate.jobs.stage1 import Ended, StageOne

    ended = pickle.loads(pickle.dumps(Ended("FINISHED", StageOne([12.5], 14.0))))
    assert ended == "FINISHED" and ended != "SKIPPED" and isinstance(ended, Ended)
    assert ended.stage1 == StageOne([12.5], 14.0) and Ended("SKIPPED").stage1 == StageOne()


def test_the_closing_summary_names_the_class_a_job_could_not_instantiate_and_where() -> None:
    from ablate.sweep.finish import note_line

    note = (
        "InstantiationException: Error locating target 'my_ops.Product', set env var HYDRA_FULL_ERROR=1 to see "
        "chained stack trace.\nfull_key: model.fusion\n"
    )
    line = note_line(note)
    assert "Error locating target 'my_ops.Product'" in line and line.endswith("full_key: model.fusion"), line
    assert "\n" not in line and len(note_line("x" * 1000)) == 400 and note_line("") == "the table could not be written"
