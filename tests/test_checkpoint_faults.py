"""Checkpoints and disks that fail: a kill in the middle of a checkpoint write, a corrupt or truncated ``last.ckpt``
on resume, a full disk under a checkpoint or an artifact; and the bad frames a job skips, counted in its run and
in the table's footer."""

import errno
import logging
import os
import shutil
import signal
import time
from pathlib import Path

import pytest
import torch
from mlflow.tracking import MlflowClient
from test_cli import REPO, TINY, ablate, runs

from ablate.jobs.checkpoint import AtomicCheckpointIO, resume_point, write_atomic
from ablate.store import DiskFull, Tracker
from tests import forkserver
from tests.stores import sqlite_uri

JOB = ["row=unet", "experiment=chinet_table2", *TINY]


def checkpoint(step: int, size: int = 10) -> dict:
    """What Lightning's training checkpoint holds, small."""
    return {"state_dict": {"w": torch.full((size,), float(step))}, "epoch": step, "global_step": step, "loops": {}}


# --- atomic writes ------------------------------------------------------------------------------------------------

SLOW_SAVE = """
import sys, time, torch
from pathlib import Path
from ablate.jobs.checkpoint import AtomicCheckpointIO

class Slow:  # pickling it announces the write has begun, then stalls it
    def __reduce__(self):
        Path(sys.argv[2]).write_text("writing")
        time.sleep(60)
        return (int, (0,))

ckpt = {"state_dict": {"w": torch.zeros(1 << 20)}, "epoch": 2, "global_step": 2, "loops": {}, "slow": Slow()}
AtomicCheckpointIO().save_checkpoint(ckpt, sys.argv[1])
"""


def test_a_kill_during_a_checkpoint_write_leaves_the_previous_checkpoint_whole(tmp_path):
    last = tmp_path / "ckpt" / "last.ckpt"
    AtomicCheckpointIO().save_checkpoint(checkpoint(1), last)
    before = last.read_bytes()
    started = tmp_path / "started"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    (tmp_path / "slow_save.py").write_text(SLOW_SAVE)
    proc = forkserver.start(tmp_path, str(tmp_path / "slow_save.py"), [str(last), str(started)], env)
    deadline = time.monotonic() + 60
    while not started.exists():
        assert proc.poll() is None and time.monotonic() < deadline, "the writer never started"
        time.sleep(0.05)
    leftover = list(last.parent.glob(".last.ckpt.*.tmp"))
    assert leftover, "the write does not go to a temporary file beside the checkpoint"
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)
    assert last.read_bytes() == before
    assert torch.load(last, weights_only=False)["global_step"] == 1
    start = resume_point(last.parent)  # the rerun removes the half-written file and resumes from the whole one
    assert start.path == last and start.step == 1 and not list(last.parent.glob(".*.tmp"))


def test_a_full_disk_during_a_checkpoint_write_names_the_file_and_keeps_the_previous(tmp_path, monkeypatch):
    last = tmp_path / "last.ckpt"
    AtomicCheckpointIO().save_checkpoint(checkpoint(1), last)

    def full(obj, handle):
        handle.write(b"partial")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(torch, "save", full)
    with pytest.raises(DiskFull) as caught:
        AtomicCheckpointIO().save_checkpoint(checkpoint(2), last)
    assert str(last) in str(caught.value) and "no space left" in str(caught.value)
    assert caught.value.errno == errno.ENOSPC
    monkeypatch.undo()
    assert torch.load(last, weights_only=False)["global_step"] == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["last.ckpt"]


def test_write_atomic_replaces_the_file_whole(tmp_path):
    path = tmp_path / "sub" / "file.bin"
    write_atomic(path, lambda f: f.write(b"one"))
    write_atomic(path, lambda f: f.write(b"two"))
    assert path.read_bytes() == b"two" and [p.name for p in path.parent.iterdir()] == ["file.bin"]


# --- corrupt checkpoints on resume -------------------------------------------------------------------------------


def test_a_truncated_last_checkpoint_resumes_from_best_with_one_warning(tmp_path, caplog):
    io = AtomicCheckpointIO()
    io.save_checkpoint(checkpoint(3), tmp_path / "best.ckpt")
    io.save_checkpoint(checkpoint(5), tmp_path / "last.ckpt")
    data = (tmp_path / "last.ckpt").read_bytes()
    (tmp_path / "last.ckpt").write_bytes(data[: len(data) // 2])
    with caplog.at_level(logging.WARNING):
        start = resume_point(tmp_path)
    warnings = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1 and str(tmp_path / "last.ckpt") in warnings[0].getMessage()
    assert start.path == tmp_path / "best.ckpt" and start.step == 3
    assert (
        start.tags["resumed_from"] == str(tmp_path / "best.ckpt") and "last.ckpt" in start.tags["checkpoint_unreadable"]
    )
    assert (tmp_path / "last.ckpt.corrupt").exists() and not (tmp_path / "last.ckpt").exists()


def test_corrupt_last_and_best_train_from_scratch_with_one_warning(tmp_path, caplog):
    (tmp_path / "last.ckpt").write_bytes(os.urandom(4096))
    torch.save({"not": "a checkpoint"}, tmp_path / "best.ckpt")
    with caplog.at_level(logging.WARNING):
        start = resume_point(tmp_path)
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1 and "last.ckpt" in warnings[0] and "best.ckpt" in warnings[0]
    assert "from scratch" in warnings[0]
    assert start.path is None and start.tags["resumed_from"] == "scratch"


def test_no_checkpoint_is_a_fresh_start_without_tags(tmp_path):
    start = resume_point(tmp_path / "none")
    assert start.path is None and start.tags == {}


# --- a full disk under an artifact -------------------------------------------------------------------------------


def test_a_full_disk_during_an_artifact_upload_names_the_file(tmp_path, monkeypatch):
    tracker = Tracker(sqlite_uri(tmp_path), str(tmp_path / "mlartifacts"))
    exp = tracker.experiment_id("t")
    run_id = tracker.start(exp, "r", {"kind": "job"})
    tracker.log_text(run_id, "kept", "kept.txt")
    source = tmp_path / "best.ckpt"
    source.write_bytes(b"x" * 100)

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(shutil, "copyfileobj", full)  # how MLflow's local artifact store writes a file
    with pytest.raises(DiskFull) as caught:
        tracker.log_artifact(run_id, source, "checkpoints")
    assert str(source) in str(caught.value) and str(tmp_path / "mlartifacts") in str(caught.value)
    monkeypatch.undo()
    assert "kept.txt" in tracker.list_artifacts(run_id)
    assert tracker.list_artifacts(run_id, "checkpoints") == []  # no half-written file


# --- whole jobs ---------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """A store with one FINISHED smoke job (ChiNet Table II's U-Net row) and its checkpoints."""
    cwd = tmp_path_factory.mktemp("faults")
    out = ablate(cwd, *JOB)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    return cwd


def finished(cwd: Path) -> dict[str, dict]:
    _, jobs = runs(cwd, "chinet_table2")
    return {r.info.run_id: dict(r.data.metrics) for r in jobs if r.info.status == "FINISHED"}


def test_a_job_resuming_from_a_truncated_last_checkpoint_warns_once_and_finishes(store):
    client, (job,) = runs(store, "chinet_table2")
    client.update_run(job.info.run_id, status="RUNNING")  # as if killed while writing last.ckpt
    (last,) = store.glob("checkpoints/chinet_table2/*/last.ckpt")
    last.write_bytes(last.read_bytes()[:1000])
    again = ablate(store, *JOB)
    assert again.returncode == 0, again.stdout[-3000:] + again.stderr[-3000:]
    warnings = [ln for ln in (again.stdout + again.stderr).splitlines() if "is unreadable" in ln]
    assert len(warnings) == 1 and str(last.relative_to(store)) in warnings[0] and "resuming from" in warnings[0]
    _, jobs = runs(store, "chinet_table2")
    rerun = next(r for r in jobs if r.info.status == "FINISHED")
    assert rerun.data.tags["resumed_from"].endswith("best.ckpt")
    assert "last.ckpt" in rerun.data.tags["checkpoint_unreadable"]


FULL_DISK = """
import errno, runpy, sys
import ablate.jobs.checkpoint as checkpoint

real, writes = checkpoint.write_atomic, []

def write_atomic(path, write, what="checkpoint"):  # the second checkpoint write finds the disk full
    writes.append(path)
    if len(writes) == 2:
        def write(handle):
            handle.write(b"partial")
            raise OSError(errno.ENOSPC, "No space left on device")
    return real(path, write, what)

checkpoint.write_atomic = write_atomic
sys.argv = ["ablate", *sys.argv[1:]]
runpy.run_module("ablate", run_name="__main__", alter_sys=True)
"""


def test_a_full_disk_fails_the_job_naming_the_checkpoint_and_keeps_the_store(store):
    before = finished(store)
    dirs = set(store.glob("checkpoints/chinet_table2/*"))
    script = store / "full_disk.py"
    script.write_text(FULL_DISK)
    env = {**os.environ, "PYTHONPATH": str(REPO), "HYDRA_FULL_ERROR": "0"}
    env.pop("MLFLOW_TRACKING_URI", None)
    args = ["row=fusenet", "experiment=chinet_table2", *TINY, "trainer.max_epochs=3"]
    out = forkserver.run(store, str(script), args, env, timeout=600)
    assert out.returncode == 1, out.stdout[-3000:] + out.stderr[-3000:]
    errors = [ln for ln in out.stderr.splitlines() if ln.startswith("error:")]
    assert len(errors) == 1 and "no space left" in errors[0] and "checkpoints/chinet_table2/" in errors[0]
    assert "Traceback" not in out.stderr
    _, jobs = runs(store, "chinet_table2")
    failed = [r for r in jobs if r.data.tags["row"] == "fusenet"]
    assert [r.info.status for r in failed] == ["FAILED"] and "no space left" in failed[0].data.tags["error"]
    assert finished(store) == before  # the earlier runs, their metrics as they were
    (ckpt_dir,) = set(store.glob("checkpoints/chinet_table2/*")) - dirs
    assert str(ckpt_dir.relative_to(store) / "last.ckpt") in errors[0]
    assert [p.name for p in ckpt_dir.iterdir()] == ["best.ckpt"]
    for path in ckpt_dir.iterdir():  # what was written before the disk filled loads; no temporary file is left
        assert not path.name.startswith(".") and torch.load(path, weights_only=False)["global_step"] >= 0
    check = MlflowClient(f"sqlite:///{store / 'mlflow.db'}")
    assert check.search_experiments()  # the store still opens
    import sqlite3

    assert sqlite3.connect(store / "mlflow.db").execute("pragma integrity_check").fetchone() == ("ok",)


def test_skipped_bad_frames_are_counted_in_the_run_and_the_table_footer(store):
    (synth,) = [p for p in store.glob("data/synth-*") if (p / "ImageSets").is_dir()]
    train = (synth / "ImageSets" / "train.txt").read_text().split()
    scan = synth / "velodyne" / f"{train[0]}.bin"
    scan.write_bytes(scan.read_bytes()[:1007])  # no longer a whole number of points
    out = ablate(store, "row=chinet", "experiment=chinet_table2", *TINY, "data.on_bad_frame=skip")
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    _, jobs = runs(store, "chinet_table2")
    job = next(r for r in jobs if r.data.tags["row"] == "chinet")
    assert job.data.metrics["data/skipped_frames"] == 1
    report = ablate(store, "--publish", "experiment=chinet_table2", module="ablate.report")
    assert report.returncode == 0, report.stderr[-3000:]
    text = (store / "results" / "chinet_table2.md").read_text()
    assert "1 bad frame(s) skipped (data.on_bad_frame=skip) in 1 run(s)" in text
