"""System metrics are one option away (``logger.system_metrics=true``, or MLflow's own
``MLFLOW_ENABLE_SYSTEM_METRICS_LOGGING=true``): the machine's CPU and memory land in the job's run while it trains."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from ablate.store.tracker import Tracker


@pytest.mark.parametrize("how", ["option", "environment", "off"])
def test_the_machines_cpu_and_memory_are_recorded_while_a_run_trains(tmp_path: Path, monkeypatch, how: str) -> None:
    monkeypatch.delenv("MLFLOW_ENABLE_SYSTEM_METRICS_LOGGING", raising=False)
    if how == "environment":
        monkeypatch.setenv("MLFLOW_ENABLE_SYSTEM_METRICS_LOGGING", "true")
    tracker = Tracker(f"sqlite:///{tmp_path / 'mlflow.db'}", str(tmp_path / "artifacts"))
    run_id = tracker.start(tracker.experiment_id("t"), "job", {"kind": "job"})
    wanted = {"system/cpu_utilization_percentage", "system/system_memory_usage_megabytes"}
    with tracker.system_metrics(run_id, on=how == "option", interval_s=0.5):
        deadline = time.monotonic() + (2.0 if how == "off" else 60.0)  # a job training; on a busy machine, longer
        while time.monotonic() < deadline and not wanted <= set(tracker.get_run(run_id).data.metrics):
            time.sleep(0.5)
    metrics = set(tracker.get_run(run_id).data.metrics)
    if how == "off":
        assert not any(m.startswith("system/") for m in metrics)
    else:
        assert wanted <= metrics, metrics
