"""A shared store: ``mlflow server`` on PostgreSQL, started on 127.0.0.1 by scripts/tracking_server.py and stopped
after. Parallel jobs log to it, their artifacts go through it, and skip, resume, row reuse and the report work.
With MLflow's basic-auth app on (``--auth``), a client without credentials gets 401 and one with them writes a run
and reads it back; without it, an address other than loopback is refused."""

from __future__ import annotations

import base64
import contextlib
import json
import re
import shutil
import stat
import subprocess
import sys
import tempfile
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from tests.scaleout import FIGURES, REPO, SERIAL, TINY, ablate, free_port, most_at_once, need, output, runs

SCRIPT = REPO / "scripts" / "tracking_server.py"


def postgres_missing() -> str | None:
    sys.path.insert(0, str(SCRIPT.parent))
    try:
        from tracking_server import ServerError, pg_bin

        for name in ("initdb", "pg_ctl", "createdb"):
            pg_bin(name)
    except ServerError as err:
        return str(err)
    finally:
        sys.path.remove(str(SCRIPT.parent))
    return None


def running(pid: int) -> bool:
    """Whether ``pid`` runs: it exists and is not a zombie waiting for a parent that does not reap it (the server
    outlives the start command, so its parent is init, which may reap late)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def test_an_address_other_than_loopback_is_refused_without_auth(tmp_path):
    store = tmp_path / "store"
    for host in ("0.0.0.0", "::"):
        out = subprocess.run(
            [sys.executable, str(SCRIPT), "start", str(store), "--host", host], capture_output=True, text=True
        )
        assert out.returncode == 1 and not out.stdout
        assert out.stderr.startswith(f"error: --host {host} is not a loopback address") and "Add --auth" in out.stderr
        assert out.stderr.count("\n") == 1  # one line
    assert not store.exists()  # refused before anything is created
    sys.path.insert(0, str(SCRIPT.parent))
    try:
        from tracking_server import is_loopback
    finally:
        sys.path.remove(str(SCRIPT.parent))
    assert is_loopback("127.0.0.1") and is_loopback("localhost") and is_loopback("::1")
    assert not is_loopback("0.0.0.0") and not is_loopback("::")


@contextlib.contextmanager
def store_server(*options: str):
    """Start a store with scripts/tracking_server.py in a folder of its own: ``(start's stdout, store folder)``;
    stopped and removed after, checking that nothing it started is left."""
    folder = Path(tempfile.mkdtemp(prefix="ablate-store-", dir="/tmp"))
    folder.chmod(0o755)  # PostgreSQL runs as the user postgres when we are root: it must reach its data folder
    store = folder / "store"
    started = subprocess.run(
        [
            sys.executable,
            str(SCRIPT),
            "start",
            str(store),
            "--port",
            str(free_port()),
            "--pg-port",
            str(free_port()),
            "--workers",
            "1",
            *options,
        ],
        capture_output=True,
        text=True,
    )
    try:
        assert started.returncode == 0, started.stderr
        yield started.stdout, store
    finally:
        state = json.loads((store / "server.json").read_text()) if (store / "server.json").exists() else None
        stopped = subprocess.run([sys.executable, str(SCRIPT), "stop", str(store)], capture_output=True, text=True)
        shutil.rmtree(folder, ignore_errors=True)
        assert stopped.returncode == 0, stopped.stderr
        if state:  # nothing it started is left
            assert not running(state["mlflow_pid"])
            assert not (Path(state["pgdata"]) / "postmaster.pid").exists()


@pytest.fixture(scope="module")
def server():
    need("psycopg")
    if reason := postgres_missing():
        pytest.skip(reason)
    with store_server() as (stdout, store):
        uri = stdout.strip().split("=", 1)[1]
        assert uri.startswith("http://127.0.0.1:")
        yield uri, store


@pytest.fixture(scope="module")
def auth_server():
    """``(uri, store, credentials)`` of a server with MLflow's basic-auth app; the credentials are in this process's
    environment too (for the tests' own MlflowClient) until the module ends."""
    need("psycopg", "flask_wtf")  # flask_wtf: mlflow[auth]
    if reason := postgres_missing():
        pytest.skip(reason)
    with store_server("--auth") as (stdout, store):
        exports = dict(re.findall(r"^export (\w+)=(.*)$", stdout, re.M))
        uri, user = exports["MLFLOW_TRACKING_URI"], exports["MLFLOW_TRACKING_USERNAME"]
        assert uri.startswith("http://127.0.0.1:") and user == "admin"
        assert (
            exports["MLFLOW_TRACKING_PASSWORD"] == f'"$(cat {store / "auth.password"})"'
        )  # the file, not the password
        password = (store / "auth.password").read_text().strip()
        assert len(password) >= 32 and password not in stdout
        for name in ("auth.password", "auth.secret", "basic_auth.ini"):  # readable by the user alone
            assert stat.S_IMODE((store / name).stat().st_mode) == 0o600, name
        assert password not in (store / "basic_auth.ini").read_text()
        credentials = {"MLFLOW_TRACKING_USERNAME": user, "MLFLOW_TRACKING_PASSWORD": password}
        with pytest.MonkeyPatch.context() as env:
            for key, value in credentials.items():
                env.setenv(key, value)
            yield uri, store, credentials


def call(uri: str, path: str, body: dict | None = None, auth: tuple[str, str] | None = None) -> int:
    """The HTTP status of a REST call: GET, or POST of ``body``; basic auth with ``auth``."""
    request = urllib.request.Request(
        f"{uri}{path}",
        data=None if body is None else json.dumps(body).encode(),
        headers={"Content-Type": "application/json"},
    )
    if auth:
        request.add_header("Authorization", "Basic " + base64.b64encode(":".join(auth).encode()).decode())
    try:
        with urllib.request.urlopen(request, timeout=30) as answer:
            return answer.status
    except urllib.error.HTTPError as err:
        return err.code


def test_a_client_without_credentials_gets_401(auth_server, monkeypatch):
    from mlflow.exceptions import MlflowException
    from mlflow.tracking import MlflowClient

    uri, _, credentials = auth_server
    search = "/api/2.0/mlflow/experiments/search?max_results=5"
    assert call(uri, "/health") == 200  # the health check stays open
    assert call(uri, search) == 401
    assert call(uri, "/api/2.0/mlflow/experiments/create", {"name": "intruder"}) == 401
    assert call(uri, search, auth=("admin", "wrong")) == 401
    assert call(uri, search, auth=tuple(credentials.values())) == 200
    for key in credentials:
        monkeypatch.delenv(key)
    with pytest.raises(MlflowException, match="401"):
        MlflowClient(uri).search_experiments()


def test_with_credentials_a_run_is_written_and_read_back(auth_server, tmp_path):
    from mlflow.tracking import MlflowClient

    uri, store, _ = auth_server
    client = MlflowClient(uri)  # MLFLOW_TRACKING_USERNAME / _PASSWORD from the environment
    exp = client.create_experiment("auth_roundtrip")
    run = client.create_run(exp, tags={"row": "chinet"})
    for step, value in enumerate((0.5, 0.7)):
        client.log_metric(run.info.run_id, "val/iou", value, step=step)
    client.log_param(run.info.run_id, "seed", "0")
    (tmp_path / "note.txt").write_text("through the server\n")
    client.log_artifact(run.info.run_id, str(tmp_path / "note.txt"))
    client.set_terminated(run.info.run_id)
    back = MlflowClient(uri).get_run(run.info.run_id)
    assert back.info.status == "FINISHED" and back.data.params == {"seed": "0"} and back.data.tags["row"] == "chinet"
    assert [m.value for m in client.get_metric_history(run.info.run_id, "val/iou")] == [0.5, 0.7]
    fetched = client.download_artifacts(run.info.run_id, "note.txt", str(tmp_path / "back"))
    assert Path(fetched).read_text() == "through the server\n"
    assert (store / "artifacts" / exp / run.info.run_id / "artifacts" / "note.txt").is_file()


@pytest.mark.parametrize("password", [None, "wrong"])
def test_a_job_the_server_refuses_ends_in_one_line_naming_the_credentials(auth_server, tmp_path, password):
    uri, _, credentials = auth_server
    env = {"MLFLOW_TRACKING_URI": uri, "MLFLOW_TRACKING_USERNAME": credentials["MLFLOW_TRACKING_USERNAME"]}
    if password is None:
        env = {"MLFLOW_TRACKING_URI": uri, "MLFLOW_TRACKING_USERNAME": "", "MLFLOW_TRACKING_PASSWORD": ""}
    else:
        env["MLFLOW_TRACKING_PASSWORD"] = password
    for args in (
        ["row=unet", "experiment=chinet_table2", *TINY],
        ["-m", "row=unet", "experiment=chinet_table2", *TINY],
    ):
        out = ablate(tmp_path, *args, env=env)
        assert out.returncode == 1, output(out)
        errors = [ln for ln in out.stderr.splitlines() if ln.startswith("error:")]
        assert len(errors) == 1, output(out)
        assert uri in errors[0] and "HTTP 401" in errors[0], errors[0]
        assert "MLFLOW_TRACKING_USERNAME" in errors[0] and "MLFLOW_TRACKING_PASSWORD" in errors[0]
        assert "Traceback" not in out.stderr and (password or "x") not in errors[0].replace("wrong ones", "")


@pytest.fixture(scope="module")
def sweep(server, tmp_path_factory):
    uri, store = server
    cwd = tmp_path_factory.mktemp("server_sweep")
    out = ablate(
        cwd,
        "-m",
        "experiment=chinet_table2",
        "row=chinet,unet",
        "hydra/launcher=joblib",
        "hydra.launcher.n_jobs=2",
        *TINY,
        FIGURES,
        env={"MLFLOW_TRACKING_URI": uri},
    )
    return uri, store, cwd, out


def test_two_parallel_jobs_log_to_the_server_and_their_artifacts_are_stored_by_it(sweep):
    uri, store, cwd, out = sweep
    assert out.returncode == 0, output(out)
    client, jobs = runs(uri, "chinet_table2")
    assert sorted(r.data.tags["row"] for r in jobs) == ["chinet", "unet"]
    assert {r.info.status for r in jobs} == {"FINISHED"} and most_at_once(jobs) == 2
    _, (parent,) = runs(uri, "chinet_table2", kind="sweep")
    assert {r.data.tags["mlflow.parentRunId"] for r in jobs} == {parent.info.run_id}
    exp = client.get_experiment_by_name("chinet_table2")
    assert exp.artifact_location.startswith("mlflow-artifacts:")  # never a file:// path of one machine
    assert exp.tags["mlflow.experimentKind"] == "custom_model_development"
    for job in jobs:  # on the server's side, under its --artifacts-destination
        files = store / "artifacts" / exp.experiment_id / job.info.run_id / "artifacts"
        assert {"config.yaml", "predictions.png"} <= {p.name for p in files.iterdir()}
        assert (files / "checkpoints" / "best.ckpt").stat().st_size > 0
        assert {a.path for a in client.list_artifacts(job.info.run_id)} >= {"config.yaml", "checkpoints"}
    assert not (cwd / "mlflow.db").exists() and not (cwd / "mlartifacts").exists()
    assert (cwd / "results" / "chinet_table2.md").exists()


def test_against_the_server_a_rerun_skips_a_shared_row_is_reused_and_a_killed_job_resumes(sweep):
    uri, _, cwd, first = sweep
    assert first.returncode == 0, output(first)
    again = ablate(
        cwd, "-m", "experiment=chinet_table2", "row=chinet,unet", SERIAL, *TINY, env={"MLFLOW_TRACKING_URI": uri}
    )
    assert again.returncode == 0, output(again)
    assert again.stdout.count("Skipping") == 2
    reuse = ablate(cwd, "experiment=chinet_table3", "row=chinet", *TINY, env={"MLFLOW_TRACKING_URI": uri})
    assert reuse.returncode == 0 and "Reusing chinet (seed 0)" in reuse.stdout, output(reuse)
    client, jobs = runs(uri, "chinet_table2")
    unet = next(r for r in jobs if r.data.tags["row"] == "unet")
    client.update_run(unet.info.run_id, status="RUNNING")  # as if its process had been killed
    resume = ablate(cwd, "experiment=chinet_table2", "row=unet", *TINY, env={"MLFLOW_TRACKING_URI": uri})
    assert resume.returncode == 0, output(resume)
    assert "Marked 1 stale RUNNING run" in resume.stdout and "Resuming from" in resume.stdout
    _, jobs = runs(uri, "chinet_table2")
    assert sorted(r.info.status for r in jobs if r.data.tags["row"] == "unet") == ["FINISHED", "KILLED"]


def test_the_report_reads_the_server(sweep, tmp_path):
    uri, _, _, first = sweep
    assert first.returncode == 0, output(first)
    report = ablate(
        tmp_path, "--publish", "experiment=chinet_table2", module="ablate.report", env={"MLFLOW_TRACKING_URI": uri}
    )
    assert report.returncode == 0, output(report)
    text = (tmp_path / "results" / "chinet_table2.md").read_text()
    assert "ChiNet" in text and "U-Net" in text


def test_a_local_artifact_root_with_a_server_is_refused_by_name(server, tmp_path):
    uri, _ = server
    out = ablate(
        tmp_path,
        "-m",
        "experiment=chinet_table2",
        "logger.artifact_root=mlartifacts",
        *TINY,
        env={"MLFLOW_TRACKING_URI": uri},
    )
    assert out.returncode != 0
    assert "logger.artifact_root=mlartifacts is a local path" in out.stderr + out.stdout
