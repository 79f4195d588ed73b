"""Sweeps through the launchers of conf/hydra/launcher/, end to end at scale=smoke: submitit on this machine, Ray on
a cluster that the test starts elsewhere on 127.0.0.1 with token authentication, and the SLURM config as composed."""

from __future__ import annotations

import os
import re
import secrets
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from datetime import datetime
from pathlib import Path

import pytest

from tests.scaleout import REPO, TINY, ablate, free_port, need, output, runs


def test_submitit_local_runs_a_table_its_jobs_at_once_on_a_fresh_sqlite_store(tmp_path):
    need("submitit", "hydra_plugins.hydra_submitit_launcher")
    # two rows: two job processes (each imports torch and Lightning afresh) show them at once as well as three
    rows = "row=chinet,unet"
    out = ablate(
        tmp_path, "-m", "experiment=chinet_table2", rows, "hydra/launcher=submitit_local", *TINY, fresh_store=True
    )
    assert out.returncode == 0, output(out)
    _, jobs = runs(f"sqlite:///{tmp_path / 'mlflow.db'}", "chinet_table2")
    assert sorted(r.data.tags["row"] for r in jobs) == ["chinet", "unet"]
    assert {r.info.status for r in jobs} == {"FINISHED"}
    # in processes of their own, at once (submitit's log of each job process: its start, its end; a job's process
    # lives from before its imports to after its run, so a loaded machine that staggers the runs still overlaps them)
    assert processes_at_once(tmp_path / "multirun") >= 2
    _, (sweep,) = runs(f"sqlite:///{tmp_path / 'mlflow.db'}", "chinet_table2", kind="sweep")
    assert sweep.info.status == "FINISHED" and {r.data.tags["mlflow.parentRunId"] for r in jobs} == {sweep.info.run_id}
    main = (tmp_path / "results" / "chinet_table2.md").read_text().split("All metrics:")[0]
    lines = [line for line in main.splitlines() if line.startswith("| ")]
    assert len(lines) == 1 + 2
    logs = list((tmp_path / "multirun").glob("*/*/.submitit/*/*_log.out"))
    assert len(logs) == 2 and all("FINISHED" in p.read_text() for p in logs)  # one log per job, in the sweep dir
    assert "validated against ConfigStore" not in out.stdout + out.stderr


def processes_at_once(sweeps: Path) -> int:
    """How many submitit job processes under ``sweeps`` ran at the same moment, at most, from the start and end
    times submitit logs in each job's log ("Starting with JobEnvironment", "Job completed successfully")."""
    stamp = re.compile(r"^submitit INFO \((\S+ \S+)\) - (Starting with|Job completed successfully)", re.MULTILINE)
    events = []
    for log in sweeps.glob("*/*/.submitit/*/*_log.*"):
        for when, what in stamp.findall(log.read_text()):
            moment = datetime.strptime(when, "%Y-%m-%d %H:%M:%S,%f")
            events.append((moment, 1 if what == "Starting with" else -1))
    best = now = 0
    for _, step in sorted(events, key=lambda e: (e[0], e[1])):  # an end before a start at the same moment
        now += step
        best = max(best, now)
    return best


@pytest.fixture
def ray_cluster(tmp_path_factory):
    """A Ray head on 127.0.0.1 with token authentication, started from a directory of its own, stopped after."""
    need("ray", "hydra_plugins.hydra_ray_launcher")
    started_in = tmp_path_factory.mktemp("cluster_cwd")
    temp = Path(tempfile.mkdtemp(prefix="ray", dir="/tmp"))  # short: Ray's socket paths live under it
    token, port = secrets.token_hex(16), free_port()
    env = {**os.environ, "RAY_AUTH_TOKEN": token, "RAY_USAGE_STATS_ENABLED": "0", "PYTHONPATH": str(REPO)}
    env.pop("RAY_AUTH_MODE", None)  # with a token and no mode, `ray start` turns token authentication on
    log = temp / "head.log"
    with open(log, "wb") as sink:
        head = subprocess.Popen(
            [
                str(Path(sys.executable).with_name("ray")),
                "start",
                "--head",
                "--block",
                "--node-ip-address=127.0.0.1",
                f"--port={port}",
                "--num-cpus=2",
                "--include-dashboard=false",
                "--disable-usage-stats",
                f"--temp-dir={temp}",
            ],
            cwd=started_in,
            env=env,
            stdout=sink,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
    try:
        deadline = time.monotonic() + 120
        while "Ray runtime started" not in log.read_text(errors="replace"):
            assert head.poll() is None and time.monotonic() < deadline, log.read_text(errors="replace")[-3000:]
            time.sleep(0.5)
        assert "Token authentication is disabled" not in log.read_text(errors="replace")
        yield f"127.0.0.1:{port}", token, started_in
    finally:  # the head and everything it started share its process group; a head drains for up to 30 s
        os.killpg(head.pid, signal.SIGTERM)
        try:
            head.wait(timeout=3)
        except subprocess.TimeoutExpired:
            os.killpg(head.pid, signal.SIGKILL)
            head.wait()
        shutil.rmtree(temp, ignore_errors=True)


def test_ray_on_a_cluster_started_elsewhere_writes_the_table_into_the_drivers_store(ray_cluster, tmp_path):
    address, token, started_in = ray_cluster
    out = ablate(
        tmp_path,
        "-m",
        "experiment=chinet_table2",
        "row=chinet,unet",
        "hydra/launcher=ray",
        f"hydra.launcher.ray.init.address={address}",
        *TINY,
        env={"RAY_AUTH_TOKEN": token, "RAY_USAGE_STATS_ENABLED": "0"},
    )
    assert out.returncode == 0, output(out)
    assert "(_run_job pid=" in out.stdout + out.stderr  # the jobs ran as Ray tasks
    _, jobs = runs(f"sqlite:///{tmp_path / 'mlflow.db'}", "chinet_table2")
    assert sorted(r.data.tags["row"] for r in jobs) == ["chinet", "unet"]
    assert {r.info.status for r in jobs} == {"FINISHED"}
    _, sweeps = runs(f"sqlite:///{tmp_path / 'mlflow.db'}", "chinet_table2", kind="sweep")
    assert len(sweeps) == 1 and {r.data.tags["mlflow.parentRunId"] for r in jobs} == {sweeps[0].info.run_id}
    assert (tmp_path / "results" / "chinet_table2.md").exists()
    assert len(list((tmp_path / "checkpoints" / "chinet_table2").glob("*/best.ckpt"))) == 2
    assert len(list((tmp_path / "multirun").glob("*/*/[0-9]/*.log"))) == 2  # job logs in the driver's sweep dir
    assert not any(started_in.iterdir()), sorted(started_in.rglob("*"))  # nothing where the cluster was started


def compose_launcher(*overrides: str):
    from hydra import compose, initialize_config_dir

    import ablate.__main__  # noqa: F401  (its warning filter, set before Hydra composes)

    with initialize_config_dir(str(REPO / "conf"), version_base="1.3"):
        return compose("config", overrides=list(overrides), return_hydra_config=True).hydra


def test_the_slurm_launcher_is_the_plugins_schema_with_the_projects_defaults():
    need("submitit", "hydra_plugins.hydra_submitit_launcher")
    hydra = compose_launcher("hydra/launcher=slurm", "hydra.launcher.partition=gpu")
    launcher = hydra.launcher
    assert launcher._target_ == "hydra_plugins.hydra_submitit_launcher.submitit_launcher.SlurmLauncher"
    assert (
        launcher.partition,
        launcher.gpus_per_node,
        launcher.tasks_per_node,
        launcher.timeout_min,
        launcher.array_parallelism,
    ) == ("gpu", 1, 1, 240, 16)
    assert launcher.submitit_folder.endswith("/.submitit/%j") and launcher.submitit_folder.startswith("/")
    assert launcher.signal_delay_s == 120  # the plugin's own keys are still there
    with pytest.raises(Exception, match="partiton"):  # a misspelt key is refused, by name
        compose_launcher("hydra/launcher=slurm", "hydra.launcher.partiton=gpu")


@pytest.mark.filterwarnings("ignore:(?s).*validated against ConfigStore")  # pytest resets the filter of ablate.__main__
def test_the_ray_launcher_never_passes_an_object_store_size_to_a_running_cluster():
    need("ray", "hydra_plugins.hydra_ray_launcher")
    init = compose_launcher("hydra/launcher=ray", "hydra.launcher.ray.init.address=auto").launcher.ray.init
    init.setdefault("object_store_memory", 78643200)  # what hydra_plugins.hydra_ray_launcher._core.launch does
    assert init.object_store_memory is None
