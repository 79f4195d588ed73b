"""Real signals on smoke jobs: SIGTERM (SLURM's preemption) to a job saves its checkpoint, marks its run KILLED
with the reason and exits 143, and the rerun resumes losing less than an epoch, and tests as the uninterrupted job does; SIGTERM to a joblib sweep's parent
takes its workers with it, each job checkpointed and KILLED; ``python -m ablate.report`` during a sweep leaves the
RUNNING runs out and counts them in the footer."""

import os
import signal
import sqlite3
import time
from pathlib import Path

from test_cli import REPO, TINY, ablate, runs

from tests import forkserver
from tests.stores import seed_data, seed_store

EPOCHS = 30  # 3 steps an epoch at TINY: long enough to be stopped in the middle, both jobs of a sweep
RESUMED_EPOCHS = 10  # a job stopped after its first epoch and rerun to its end: the rerun trains the rest


def start(cwd: Path, *args: str) -> forkserver.Command:
    """``python -m ablate ARGS`` in ``cwd`` in the background (a :class:`subprocess.Popen` with its output captured)."""
    seed_store(cwd)
    seed_data(cwd)
    env = {**os.environ, "PYTHONPATH": str(REPO), "HYDRA_FULL_ERROR": "0"}
    env.pop("MLFLOW_TRACKING_URI", None)
    return forkserver.start(cwd, "ablate", list(args), env)


def wait_for(cwd: Path, pattern: str, count: int, proc: forkserver.Command, timeout: float = 300) -> None:
    deadline = time.monotonic() + timeout
    while len(list(cwd.glob(pattern))) < count:
        assert proc.poll() is None, proc.communicate()[1][-3000:]
        assert time.monotonic() < deadline, f"no {pattern} after {timeout} s"
        time.sleep(0.1)


def steps(client, run_id: str) -> list[int]:
    return sorted(m.step for m in client.get_metric_history(run_id, "train/loss"))


def test_sigterm_checkpoints_a_job_marks_it_killed_and_the_rerun_loses_less_than_an_epoch(tmp_path):
    job = ["row=unet", "experiment=chinet_table2", *TINY, f"trainer.max_epochs={RESUMED_EPOCHS}"]
    proc = start(tmp_path, *job)
    wait_for(tmp_path, "checkpoints/chinet_table2/*/last.ckpt", 1, proc)  # an epoch is done: it is training
    time.sleep(0.5)
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 143, out[-3000:] + err[-3000:]
    stopped = [ln for ln in err.splitlines() if ln.startswith("stopped:")]
    assert len(stopped) == 1 and "last.ckpt saved at step" in stopped[0], err[-3000:]
    assert "Traceback" not in err
    client, (killed,) = runs(tmp_path, "chinet_table2")
    assert killed.info.status == "KILLED" and killed.data.tags["killed_by"] == "SIGTERM"
    assert "last.ckpt saved at step" in killed.data.tags["kill_reason"]
    done = steps(client, killed.info.run_id)
    again = ablate(tmp_path, *job)
    assert again.returncode == 0, again.stdout[-3000:] + again.stderr[-3000:]
    _, jobs = runs(tmp_path, "chinet_table2")
    (rerun,) = [r for r in jobs if r.info.status == "FINISHED"]
    resumed = int(rerun.data.tags["resumed_step"])
    assert rerun.data.tags["resumed_from"].endswith("last.ckpt")
    total = max(steps(client, rerun.info.run_id)) + 1
    per_epoch = total / RESUMED_EPOCHS
    lost = (max(done) + 1 - resumed) / per_epoch  # steps trained before the signal that the rerun does again
    print(
        f"preempted at step {max(done) + 1} of {total} ({per_epoch:.0f} an epoch); resumed at {resumed}; lost {lost:.2f} epochs"
    )
    assert 0 <= lost < 1
    assert min(steps(client, rerun.info.run_id)) == resumed and total == RESUMED_EPOCHS * per_epoch
    # the resumed job trained on what the uninterrupted one trains on: the same test metrics, to every digit
    whole = tmp_path / "uninterrupted"
    whole.mkdir()
    seed_data(whole)
    assert ablate(whole, *job).returncode == 0
    _, (reference,) = runs(whole, "chinet_table2")
    tested = ("loss", "det_rate", "iou_free_space", "val/loss")  # the test's loss and scores, the last validation
    assert {k: reference.data.metrics[k] for k in tested} == {k: rerun.data.metrics[k] for k in tested}


def children(pid: int) -> list[int]:
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            if stat.read_text().rsplit(")", 1)[1].split()[1] == str(pid):
                out.append(int(stat.parent.name))
        except (OSError, IndexError):
            pass
    return out


def alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def test_sigterm_to_a_joblib_sweep_takes_its_workers_with_it(tmp_path):
    sweep = [
        "-m",
        "row=unet,fusenet",
        "experiment=chinet_table2",
        "hydra/launcher=joblib",
        "hydra.launcher.n_jobs=2",
        *TINY,
        f"trainer.max_epochs={EPOCHS}",
    ]
    proc = start(tmp_path, *sweep)
    wait_for(tmp_path, "checkpoints/chinet_table2/*/last.ckpt", 2, proc)  # both jobs are training
    workers = children(proc.pid)
    assert workers
    sent = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=120)
    ended = time.monotonic()
    assert proc.returncode == 143, out[-3000:] + err[-3000:]
    assert "stopped: sweep stopped by SIGTERM" in err
    while any(alive(p) for p in workers) and time.monotonic() - ended < 10:
        time.sleep(0.1)
    left = [p for p in workers if alive(p)]
    assert not left, f"workers {left} outlived their parent by 10 s"
    after = time.monotonic() - ended
    print(f"sweep parent exited {ended - sent:.1f} s after SIGTERM; its {len(workers)} workers {after:.1f} s after it")
    _, jobs = runs(tmp_path, "chinet_table2")
    assert sorted(r.data.tags["row"] for r in jobs) == ["fusenet", "unet"]
    for job in jobs:
        assert job.info.status == "KILLED" and job.data.tags["killed_by"] == "SIGTERM", job.data.tags
        assert "saved at step" in job.data.tags["kill_reason"]
    _, (parent,) = runs(tmp_path, "chinet_table2", kind="sweep")
    assert parent.info.status == "KILLED" and parent.data.tags["killed_by"] == "SIGTERM"


def readable(db: Path) -> bool:
    """Whether the SQLite store ``db`` can be read now (no other process is in the middle of a write)."""
    try:
        with sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=0.5) as con:
            con.execute("SELECT count(*) FROM sqlite_master").fetchone()
        return True
    except sqlite3.OperationalError:
        return False


def report_while_paused(cwd: Path, proc: forkserver.Command) -> str:
    """The table ``python -m ablate.report`` writes while the sweep ``proc`` is stopped (SIGSTOP) in the middle of a
    job: the job's run stays RUNNING for the whole report, however slow the machine. A sweep stopped in the middle of
    writing to its SQLite store would hold the store's lock for the whole report ("database is locked"): it is let
    go on and stopped again until the store can be read."""
    for _ in range(50):
        proc.send_signal(signal.SIGSTOP)
        if readable(cwd / "mlflow.db"):
            break
        proc.send_signal(signal.SIGCONT)
        time.sleep(0.1)
    else:  # never found readable: stopped all the same, as the report must run beside a stopped sweep
        proc.send_signal(signal.SIGSTOP)
    try:
        report = ablate(cwd, "--publish", "experiment=chinet_table2", module="ablate.report")
    finally:
        proc.send_signal(signal.SIGCONT)
    assert report.returncode == 0, report.stderr[-3000:]
    return (cwd / "results" / "chinet_table2.md").read_text()


def test_a_report_while_a_sweep_writes_leaves_running_runs_out_and_counts_them(tmp_path):
    # one job at a time (hydra/launcher=basic), the report beside it: while the first job trains, then the second
    sweep = ["-m", "row=unet,fusenet", "experiment=chinet_table2", "hydra/launcher=basic", *TINY]
    proc = start(tmp_path, *sweep, "trainer.max_epochs=5")  # stopped while it trains: its length does not matter
    wait_for(tmp_path, "checkpoints/chinet_table2/*/last.ckpt", 1, proc)  # U-Net is training
    first = report_while_paused(tmp_path, proc)
    wait_for(tmp_path, "checkpoints/chinet_table2/*/last.ckpt", 2, proc)  # U-Net is done, FuseNet is training
    second = report_while_paused(tmp_path, proc)
    out, err = proc.communicate()
    assert proc.returncode == 0, out[-3000:] + err[-3000:]
    assert "No finished runs yet." in first and "1 run(s) still RUNNING are left out" in first, first
    assert "1 run(s) still RUNNING are left out" in second, second
    assert "| U-Net" in second and "| FuseNet" not in second, second
    final = (tmp_path / "results" / "chinet_table2.md").read_text()  # the sweep's own table, written at its end
    assert "still RUNNING" not in final and "| U-Net" in final and "| FuseNet" in final
