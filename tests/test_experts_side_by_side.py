"""Two jobs that need the same two experts train them side by side, one each (recorded start and end times), instead
of one job training both while the other waits on each expert's lock; each expert is trained once."""

from __future__ import annotations

import threading
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from ablate.config import compose
from ablate.jobs.experts import prepare
from ablate.jobs.spec import checkpoint_dir
from ablate.store import config_hash


def test_two_jobs_train_their_two_experts_at_the_same_time(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)  # the experts' checkpoints and locks live under ./checkpoints
    cfg = compose(["experiment=smoe_table1", "row=smoe_fpn", "scale=smoke"])  # fused: needs the rgb and ddm experts
    trained: list[tuple[str, str, float, float]] = []  # (job, expert, start, end)
    # an expert's training ends only once the other expert's has begun: side by side, whatever the threads' timing;
    # where one job trained both (the other waiting on a lock), the first training's wait times out and fails
    both_training = threading.Barrier(2, timeout=60)

    def job(name: str) -> dict[str, Any]:
        def run(ecfg: Any, kind: str, row: str) -> SimpleNamespace:
            folder = checkpoint_dir("experts", config_hash(ecfg))
            if not (folder / "best.ckpt").exists():  # as the job does: a FINISHED expert is not trained again
                start = time.monotonic()
                both_training.wait()  # an expert training
                folder.mkdir(parents=True, exist_ok=True)
                (folder / "best.ckpt").write_text("weights")
                trained.append((name, row, start, time.monotonic()))
            return SimpleNamespace(ckpt_dir=folder, run_id=f"run of {row}")

        return prepare(cfg, run)

    results: dict[str, dict[str, Any]] = {}
    workers = [threading.Thread(target=lambda n=n: results.__setitem__(n, job(n))) for n in ("sum", "max")]
    for w in workers:
        w.start()
    for w in workers:
        w.join()
    assert sorted(row for _, row, _, _ in trained) == ["expert ddm_jet", "expert rgb"]  # each once
    (_, _, a0, a1), (_, _, b0, b1) = trained
    assert a0 < b1 and b0 < a1, trained  # the two trainings overlap: side by side
    assert {job for job, _, _, _ in trained} == {"sum", "max"}  # one each
    assert list(results["sum"]) == list(results["max"]) == ["rgb", "ddm_jet"]  # in the job's own order


def test_a_job_holds_no_running_run_while_it_waits_for_its_experts(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from ablate.jobs import experts, job
    from ablate.jobs.spec import JobSpec
    from ablate.store import SweepContext, Tracker
    from tests.stores import seed_store

    monkeypatch.chdir(tmp_path)
    seed_store(tmp_path)  # ./mlflow.db, the default store
    cfg = compose(["experiment=smoe_table1", "row=smoe_fpn", "scale=smoke"])
    spec = JobSpec.of(cfg, SweepContext(launch_dir=tmp_path))
    tracker = Tracker.from_config(spec.cfg, spec.context)
    seen: list[list[str]] = []

    def prepare(cfg: Any, run: Any) -> dict[str, Any]:  # an expert in training elsewhere: the job waits here
        seen.append([r.info.status for r in tracker.runs(tracker.experiment_id(spec.table))])
        raise job.JobFailed("expert rgb: FAILED")

    monkeypatch.setattr(experts, "prepare", prepare)
    with pytest.raises(job.JobFailed, match="an expert failed"):
        job.run(spec)
    assert seen == [[]]  # no run of the job while it waited
    runs = tracker.runs(tracker.experiment_id(spec.table))  # its failure is recorded, naming the expert
    assert [r.info.status for r in runs] == ["FAILED"]
    assert runs[0].data.tags["error"].startswith("an expert failed: expert rgb")


def test_a_jobs_run_records_when_the_job_began_training_its_experts(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from ablate.jobs import experts, job
    from ablate.jobs.spec import JobSpec
    from ablate.store import SweepContext, Tracker
    from tests.stores import seed_store

    monkeypatch.chdir(tmp_path)
    seed_store(tmp_path)
    cfg = compose(["experiment=smoe_table1", "row=smoe_fpn", "scale=smoke"])
    spec = JobSpec.of(cfg, SweepContext(launch_dir=tmp_path))
    tracker = Tracker.from_config(spec.cfg, spec.context)
    monkeypatch.setattr(experts, "prepare", lambda cfg, run: time.sleep(0.5) or {})  # its experts: 0.5 s
    monkeypatch.setattr(job, "train", lambda *args: {"mask_ap": 1.0})
    monkeypatch.setattr(job, "attach_logs", lambda *args: None)
    job.run(spec)
    (run,) = tracker.runs(tracker.experiment_id(spec.table))
    # the table's footer counts the job's wall time from here (ablate.tables.collect.made_lines)
    assert run.info.start_time - int(run.data.tags["job_started"]) >= 500
