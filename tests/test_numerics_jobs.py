"""Jobs end to end with the numerics options (ablate.hardware) at scale=smoke, and a job's result whatever runs beside
it: one pinned thread per job, jobs in parallel (conf/hydra/launcher/parallel.yaml)."""

import json

import pytest
import torch

from tests.test_cli import TINY, ablate, runs

ONE_STEP = [
    *TINY,
    "trainer.max_epochs=1",
    "trainer.limit_train_batches=1",
    "trainer.limit_val_batches=1",
    "trainer.limit_test_batches=1",
]


@pytest.mark.parametrize(
    "options",
    [  # each option once: precision and memory format together, then the compiled model
        ["trainer.precision=bf16-mixed", "trainer.channels_last=true"],
        ["trainer.channels_last=true", "trainer.compile=eager"],
    ],
)
def test_the_numerics_options_compose_and_run_a_job(tmp_path, options):
    out = ablate(tmp_path, "experiment=chinet_table2", "row=unet", *ONE_STEP, *options)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    _, jobs = runs(tmp_path, "chinet_table2")
    assert [r.info.status for r in jobs] == ["FINISHED"]
    tags, params = jobs[0].data.tags, jobs[0].data.params
    precision = "bf16-mixed" if "trainer.precision=bf16-mixed" in options else "32-true"
    assert tags["precision"] == params["trainer.precision"] == precision
    assert tags["channels_last"] == "True" and tags["threads"] == "1" and tags["cpu"]
    assert "Numerics: precision" in out.stdout + out.stderr
    # the checkpoint keeps the model's own keys, compiled or not
    state = torch.load(next((tmp_path / "checkpoints").rglob("best.ckpt")), weights_only=True)["state_dict"]
    assert not any("_orig_mod" in key for key in state)


def test_a_jobs_metrics_do_not_change_when_another_job_runs_beside_it(tmp_path):
    alone, beside = tmp_path / "alone", tmp_path / "beside"
    alone.mkdir(), beside.mkdir()
    first = ablate(alone, "experiment=chinet_table2", "row=chinet", *TINY)
    assert first.returncode == 0, first.stdout[-3000:] + first.stderr[-3000:]
    both = ablate(beside, "-m", "experiment=chinet_table2", "row=chinet,fusenet", "hydra.launcher.n_jobs=2", *TINY)
    assert both.returncode == 0, both.stdout[-3000:] + both.stderr[-3000:]
    assert "2 at a time" in both.stdout + both.stderr
    _, solo = runs(alone, "chinet_table2")
    _, pair = runs(beside, "chinet_table2")
    twin = next(r for r in pair if r.data.tags["row"] == "chinet")
    assert twin.data.tags["config_hash"] == solo[0].data.tags["config_hash"]
    keep = {k: v for k, v in solo[0].data.metrics.items() if not k.startswith(("latency", "comp_time"))}
    assert keep and keep == {k: twin.data.metrics[k] for k in keep}
    # the sweep counted both jobs against its plan, and logged its progress
    ended = json.loads(next(beside.glob("multirun/*/*/sweep.json")).read_text())["ended"]
    assert sorted(job["status"] for job in ended) == ["FINISHED", "FINISHED"]
    assert "Sweep progress: 2/2 jobs finished" in both.stdout + both.stderr
