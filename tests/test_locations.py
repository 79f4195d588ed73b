"""Where a job's store, artifacts and files go: against the launch directory, whatever directory runs the job; the
sweep's recorded store; artifacts through a server; experiments' kind; the Ray driver's token."""

from __future__ import annotations

import json
import os
import pickle
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.core.hydra_config import HydraConfig
from mlflow.tracking import MlflowClient
from omegaconf import OmegaConf, open_dict

from ablate.jobs.job import JobFailed, in_launch_dir
from ablate.store import SweepContext
from ablate.store.context import STATE_FILE
from ablate.store.tracker import EXPERIMENT_KIND, Tracker
from ablate.store.uris import artifact_location, resolve_uri, tracking_uri
from ablate.sweep.parent import check_launcher, ray_driver_auth
from tests.scaleout import REPO, need
from tests.stores import sqlite_uri


@pytest.fixture
def job_in(tmp_path):
    """A Hydra job config launched from ``tmp_path/launch`` (hydra.runtime.cwd), as a launcher sets it up; yields a
    function that installs it, with the multirun's sweep directory if asked."""

    def install(multirun: bool = False):
        with initialize_config_dir(str(REPO / "conf"), version_base="1.3"):
            cfg = compose("config", return_hydra_config=True)
        with open_dict(cfg):
            cfg.hydra.runtime.cwd = str(tmp_path / "launch")
            cfg.hydra.sweep.dir = str(tmp_path / "launch" / "multirun" / "s")
            if multirun:
                cfg.hydra.mode = "MULTIRUN"
        HydraConfig.instance().set_config(cfg)
        return cfg

    (tmp_path / "launch").mkdir()
    yield install
    HydraConfig.instance().cfg = None


def test_relative_stores_resolve_against_the_launch_directory_not_the_working_one(job_in, tmp_path, monkeypatch):
    job_in()
    monkeypatch.chdir(tmp_path)  # a Ray task runs where its cluster was started
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    launch = tmp_path / "launch"
    with in_launch_dir(SweepContext.current().launch_dir):  # where a job starts
        assert tracking_uri({"tracking_uri": "sqlite:///mlflow.db"}) == f"sqlite:///{launch / 'mlflow.db'}"
        assert tracking_uri(None) == f"sqlite:///{launch / 'mlflow.db'}"
        assert artifact_location(tracking_uri(None), None) == (launch / "mlartifacts").as_uri()
        assert artifact_location(tracking_uri(None), "store/art") == (launch / "store" / "art").as_uri()
        assert resolve_uri("sqlite:////abs/x.db") == "sqlite:////abs/x.db"
        assert resolve_uri("http://127.0.0.1:5000") == "http://127.0.0.1:5000"
        assert resolve_uri("runs") == str(launch / "runs")
    # and explicitly, from anywhere
    assert tracking_uri(None, launch) == f"sqlite:///{launch / 'mlflow.db'}"


def test_a_server_keeps_the_artifacts_and_a_local_root_with_it_is_refused_by_name():
    assert artifact_location("http://127.0.0.1:5000", None) is None
    assert artifact_location("https://tracking.lab", "s3://bucket/mlflow") == "s3://bucket/mlflow"
    with pytest.raises(ValueError, match="logger.artifact_root=mlartifacts is a local path"):
        artifact_location("http://127.0.0.1:5000", "mlartifacts")
    with pytest.raises(ValueError, match="logger.artifact_root=file:///tmp/a"):
        artifact_location("http://127.0.0.1:5000", "file:///tmp/a")


def test_jobs_of_a_sweep_write_to_the_store_it_recorded_whatever_their_environment(job_in, tmp_path, monkeypatch):
    cfg = job_in(multirun=True)
    sdir = Path(cfg.hydra.sweep.dir)
    sdir.mkdir(parents=True)
    recorded = f"sqlite:///{tmp_path / 'sweep.db'}"
    store = {"uri": recorded, "artifact_location": (tmp_path / "a").as_uri()}
    (sdir / STATE_FILE).write_text(json.dumps({"store": store}))
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'other.db'}")
    cfg = OmegaConf.create({"logger": {"tracking_uri": "sqlite:///third.db"}})
    tracker = Tracker.from_config(cfg, SweepContext.current())
    assert tracker.uri == recorded and tracker.artifact_location == (tmp_path / "a").as_uri()


def test_a_tracker_pickles_for_ddp_spawn_and_tags_every_experiment_as_model_training(tmp_path):
    uri = sqlite_uri(tmp_path)
    tracker = Tracker(uri, str(tmp_path / "art"))
    exp = tracker.experiment_id("table")
    copy = pickle.loads(pickle.dumps(tracker))
    assert (copy.uri, copy.artifact_location) == (uri, (tmp_path / "art").as_uri())
    assert copy.experiment_id("table") == exp
    client = MlflowClient(uri)
    assert client.get_experiment(exp).tags["mlflow.experimentKind"] == "custom_model_development"
    assert client.get_experiment(exp).artifact_location == (tmp_path / "art" / "table").as_uri()
    old = client.create_experiment("made_before")  # an experiment of an older store, untagged
    assert tracker.experiment_id("made_before") == old
    assert {k: client.get_experiment(old).tags.get(k) for k in EXPERIMENT_KIND} == EXPERIMENT_KIND


def test_a_job_runs_in_the_launch_directory_and_goes_back(job_in, tmp_path, monkeypatch):
    job_in()
    monkeypatch.chdir(tmp_path)
    launch = SweepContext.current().launch_dir
    with in_launch_dir(launch) as where:
        assert Path.cwd() == where == tmp_path / "launch"
    assert Path.cwd() == tmp_path
    (tmp_path / "launch").rmdir()  # a machine that does not see the launch directory
    with pytest.raises(JobFailed, match="launch directory .*launch does not exist"):
        with in_launch_dir(launch):
            pass


def test_the_ray_driver_takes_the_clusters_token_as_ray_start_does(monkeypatch):
    need("ray")
    cfg = OmegaConf.create(
        {
            "hydra": {
                "launcher": {
                    "_target_": "hydra_plugins.hydra_ray_launcher.ray_launcher.RayLauncher",
                    "ray": {"init": {"address": None}},
                }
            }
        }
    )
    monkeypatch.setenv("RAY_AUTH_MODE", "")  # recorded, so that teardown removes what Ray sets
    monkeypatch.delenv("RAY_AUTH_MODE")
    monkeypatch.setenv("RAY_AUTH_TOKEN", "a" * 32)
    assert ray_driver_auth(cfg) is False  # a local Ray: Ray decides itself
    cfg.hydra.launcher.ray.init.address = "127.0.0.1:6379"
    assert ray_driver_auth(cfg) is True and os.environ["RAY_AUTH_MODE"] == "token"
    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")  # an explicit mode is respected
    assert ray_driver_auth(cfg) is False and os.environ["RAY_AUTH_MODE"] == "disabled"
    cfg.hydra.launcher._target_ = "hydra_plugins.hydra_joblib_launcher.joblib_launcher.JoblibLauncher"
    assert ray_driver_auth(cfg) is False


def test_a_launcher_whose_plugin_is_missing_is_named_with_its_extra():
    cfg = OmegaConf.create(
        {
            "hydra": {
                "launcher": {"_target_": "hydra_plugins.hydra_nope_launcher.x.Launcher"},
                "runtime": {"choices": {"hydra/launcher": "nope"}},
            }
        }
    )
    with pytest.raises(ValueError, match="hydra/launcher=nope needs hydra_plugins.hydra_nope_launcher"):
        check_launcher(cfg)
    cfg.hydra.launcher._target_ = "hydra._internal.core_plugins.basic_launcher.BasicLauncher"
    check_launcher(cfg)  # Hydra's own
