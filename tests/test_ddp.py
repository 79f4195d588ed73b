"""trainer=ddp_cpu inside a multirun: 2 gloo processes spawned by the job, one parent run, rank 0 logging."""

from __future__ import annotations

from tests.scaleout import TINY, ablate, output, runs


def test_a_ddp_job_in_a_sweep_makes_one_parent_run_and_logs_once(tmp_path):
    out = ablate(tmp_path, "-m", "experiment=chinet_table2", "row=unet", "trainer=ddp_cpu", *TINY)
    assert out.returncode == 0, output(out)
    text = out.stdout + out.stderr
    assert "Starting with 2 processes" in text and "distributed_backend=gloo" in text
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    client, sweeps = runs(uri, "chinet_table2", kind="sweep")
    _, jobs = runs(uri, "chinet_table2")
    assert [r.info.status for r in sweeps] == ["FINISHED"]  # strategy=ddp would start the sweep again for rank 1
    assert [r.info.status for r in jobs] == ["FINISHED"] and jobs[0].data.tags["mlflow.parentRunId"] == sweeps[
        0
    ].info.run_id
    job = jobs[0]
    assert job.data.params["trainer.devices"] == "2" and job.data.params["trainer.strategy.start_method"] == "spawn"
    history = client.get_metric_history(job.info.run_id, "train/loss")
    steps = [m.step for m in history]
    assert steps and len(steps) == len(set(steps))  # logged by rank 0 alone, from its own process
    assert "det_rate" in job.data.metrics
    assert "checkpoints" in {a.path for a in client.list_artifacts(job.info.run_id)}
    assert len(list((tmp_path / "checkpoints" / "chinet_table2").glob("*/best.ckpt"))) == 1
