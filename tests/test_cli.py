"""`python -m ablate` end to end at scale=smoke, as a user runs it: sweeps, tables, skip, failure and resume."""

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.scaleout import FIGURES, REPO, SERIAL, TINY, ablate  # noqa: F401 (the other end-to-end tests import them from here)
from tests.scaleout import runs as store_runs
from tests.shared import smoke_table2


def runs(cwd: Path, experiment: str, kind: str = "job"):
    """:func:`tests.scaleout.runs` of the store ``cwd/mlflow.db``."""
    return store_runs(f"sqlite:///{cwd / 'mlflow.db'}", experiment, kind)


@pytest.fixture(scope="module")
def table2(tmp_path_factory):
    """ChiNet Table II swept at scale=smoke: the session's sweep (tests/shared.py), in a directory of this module."""
    return smoke_table2(tmp_path_factory, "table2")


def test_a_table_sweep_leaves_one_parent_with_a_finished_child_per_row(table2):
    cwd, first = table2
    assert first.returncode == 0, first.stdout[-3000:] + first.stderr[-3000:]
    client, jobs = runs(cwd, "chinet_table2")
    assert sorted(r.data.tags["row"] for r in jobs) == ["chinet", "fusenet", "unet"]
    assert {r.info.status for r in jobs} == {"FINISHED"}
    _, sweeps = runs(cwd, "chinet_table2", kind="sweep")
    assert len(sweeps) == 1 and sweeps[0].info.status == "FINISHED"
    assert {r.data.tags["mlflow.parentRunId"] for r in jobs} == {sweeps[0].info.run_id}
    job = jobs[0]
    for tag in ("table", "row", "seed", "config_hash", "git_commit", "sweep_id", "ablate_version", "fingerprint"):
        assert tag in job.data.tags
    # the commit of the ablate that ran (this checkout), though the sweep ran in a folder that is no git checkout
    assert len(job.data.tags["git_commit"].removesuffix("-dirty")) == 40 and "launch_commit" not in job.data.tags
    assert set(json.loads(job.data.tags["fingerprint"])) == {"data", "model", "loss", "schedule", "metric"}
    assert "det_rate" in job.data.metrics and "comp_time_ms" not in job.data.metrics  # not timed while training
    for metric in ("latency_ms", "latency_q1_ms", "latency_q3_ms", "params_m", "macs_g"):  # timed at the end
        assert job.data.metrics[metric] > 0, metric
    assert job.data.tags["latency_threads"] == "1" and job.data.tags["latency_device"] == "cpu"
    assert job.data.params["model._target_"] == "ablate.nn.chinet.build"
    artifacts = {a.path for a in client.list_artifacts(job.info.run_id)}
    assert {"config.yaml", "predictions.png", "checkpoints"} <= artifacts


def test_the_table_has_the_rows_in_paper_order_beside_the_paper(table2):
    cwd, _ = table2
    text = (cwd / "results" / "chinet_table2.md").read_text()
    rows = [line for line in text.split("All metrics:")[0].splitlines() if line.startswith("| ")][1:]
    assert [r.split("|")[1].strip() for r in rows] == ["ChiNet", "U-Net", "FuseNet"]
    assert len(rows[0].strip("|").split("|")) <= 10
    assert "Det. Rate % (paper)" in text and "97.35" in text and "Kendall τ" in text
    assert "Comp Time (ms) (paper)" in text and "Comp Time (ms) ratio" in text and "MACs (G)" in text
    assert "side by side" in text and "Δ Det. Rate % vs U-Net [95% CI]" in text
    assert (cwd / "results" / "chinet_table2.png").stat().st_size > 0


def test_running_a_table_again_trains_nothing_and_rewrites_the_same_table(table2):
    cwd, _ = table2
    before = (cwd / "results" / "chinet_table2.md").read_bytes()
    again = ablate(cwd, "-m", "experiment=chinet_table2", SERIAL, *TINY)
    assert again.returncode == 0, again.stderr[-3000:]
    assert again.stdout.count("Skipping") == 3 and "Epoch" not in again.stdout + again.stderr
    _, jobs = runs(cwd, "chinet_table2")
    assert len(jobs) == 3
    assert (cwd / "results" / "chinet_table2.md").read_bytes() == before
    report = ablate(cwd, "--publish", "experiment=chinet_table2", module="ablate.report")
    assert report.returncode == 0, report.stderr[-3000:]
    assert (cwd / "results" / "chinet_table2.md").read_bytes() == before


def test_a_failing_job_is_recorded_failed_and_the_others_still_run(tmp_path):
    # lr 1e30 blows the weights up: the NaN guard fails that job at once
    out = ablate(tmp_path, "-m", "task=semantic", "task.optimizer.lr=0.001,1e30", SERIAL, *TINY)
    assert out.returncode == 1
    assert "1 job(s) failed" in out.stdout + out.stderr
    assert "NonFiniteLossError" in out.stdout + out.stderr
    _, jobs = runs(tmp_path, "ablate")
    assert sorted(r.info.status for r in jobs) == ["FAILED", "FINISHED"]
    text = (tmp_path / "results" / "ablate.md").read_text()
    assert "task.optimizer.lr=0.001" in text and "1e30" not in text


def test_a_killed_job_resumes_from_its_checkpoint_without_duplicates(tmp_path):
    first = ablate(tmp_path, "row=unet", "experiment=chinet_table2", *TINY)
    assert first.returncode == 0, first.stderr[-3000:]
    client, (job,) = runs(tmp_path, "chinet_table2")
    # as if the process had been killed mid-job: the run stays RUNNING, its last checkpoint on disk
    client.update_run(job.info.run_id, status="RUNNING")
    again = ablate(tmp_path, "row=unet", "experiment=chinet_table2", *TINY)
    assert again.returncode == 0, again.stderr[-3000:]
    assert "Marked 1 stale RUNNING run" in again.stdout and "Resuming from" in again.stdout
    _, jobs = runs(tmp_path, "chinet_table2")
    assert sorted(r.info.status for r in jobs) == ["FINISHED", "KILLED"]


def test_an_unknown_option_fails_with_the_valid_choices(tmp_path):
    out = ablate(tmp_path, "fusion=bogus", *TINY)
    assert out.returncode != 0
    assert "Could not find 'fusion/bogus'" in out.stderr and "smoe" in out.stderr and "sharpen" in out.stderr


def test_one_job_of_a_paper_table_without_a_row_is_one_error_naming_the_rows_and_records_nothing(tmp_path):
    # the root config's defaults are no row of DGFN Table I (its SSD task cannot build them): refused before a run
    out = ablate(tmp_path, "experiment=dgfn_table1", *TINY)
    assert out.returncode == 1, out.stdout[-3000:] + out.stderr[-3000:]
    errors = [line for line in out.stderr.splitlines() if line.startswith("error:")]
    assert errors == [
        "error: experiment=dgfn_table1 is a table of 2 rows (dgfn, dgfn_baseline): name one with row=<row> "
        "(python -m ablate experiment=dgfn_table1 row=dgfn), or race them all (python -m ablate -m "
        "experiment=dgfn_table1)"
    ]
    assert "Traceback" not in out.stderr and "MLflow run" not in out.stdout + out.stderr


def test_a_row_shared_with_another_table_is_reused_not_retrained(table2):
    cwd, _ = table2
    out = ablate(cwd, "-m", "experiment=chinet_table3", SERIAL, *TINY)
    assert out.returncode == 0, out.stderr[-3000:]
    assert "Reusing chinet (seed 0)" in out.stdout
    plan = re.search(r"Sweep plan: (\d+) job\(s\)[^\n]*", out.stdout + out.stderr)
    assert plan and "; 1 done already (skipped)" in plan[0], plan  # the plan counts the copy: it trains nothing
    _, jobs = runs(cwd, "chinet_table3")
    reused = [r for r in jobs if "reused_from" in r.data.tags]
    assert [r.data.tags["row"] for r in reused] == ["chinet"] and reused[0].data.metrics["det_rate"] >= 0
    main = (cwd / "results" / "chinet_table3.md").read_text().split("All metrics:")[0]
    rows = [line for line in main.splitlines() if line.startswith("| ")]
    assert len(rows) == 3  # header + ChiNet + ChiNet SIMO


def test_smoe_table1_in_parallel_trains_each_expert_once_loses_no_run_and_is_diagnosed(tmp_path):
    # two jobs at a time in joblib's processes: the rows that need the same two experts wait for them under a file
    # lock, and all of them load the same expert runs. Both single modals and two fused rows, the paper's SMoE among
    # them (the diagnosis reads its gates); every fusion operator trains in tests/fusion
    chosen = ["smoe_rgb", "smoe_ddm", "smoe_sum", "smoe_fpn"]
    out = ablate(
        tmp_path, "-m", "experiment=smoe_table1", f"row={','.join(chosen)}", "hydra/launcher=joblib",
        "hydra.launcher.n_jobs=2", *TINY,
    )  # fmt: skip
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    _, experts = runs(tmp_path, "experts", kind="expert")
    assert sorted(r.data.tags["row"] for r in experts) == ["expert ddm_jet", "expert rgb"]
    assert {r.info.status for r in experts} == {"FINISHED"}
    _, jobs = runs(tmp_path, "smoe_table1")
    assert sorted(r.data.tags["row"] for r in jobs) == sorted(chosen) and {r.info.status for r in jobs} == {"FINISHED"}
    fused = [r for r in jobs if r.data.tags["row"] not in ("smoe_rgb", "smoe_ddm")]
    assert len(fused) == 2
    for modality in ("rgb", "ddm_jet"):
        expert = next(r.info.run_id for r in experts if r.data.tags["row"] == f"expert {modality}")
        assert {r.data.tags[f"expert_{modality}"] for r in fused} == {expert}
    main = (tmp_path / "results" / "smoe_table1.md").read_text().split("All metrics:")[0]
    rows = [line for line in main.splitlines() if line.startswith("| ")]
    assert len(rows) == 1 + 4 and "AP (paper)" in rows[0]
    # each job keeps its mask AP's matches per test frame: AP re-accumulated from them is the logged AP
    from ablate.store import FRAME_DETECTIONS
    from ablate.tables.frames import _read_detections, ap_resampled

    client, _ = runs(tmp_path, "smoe_table1")
    for job in jobs[:2]:
        kept = _read_detections(client.download_artifacts(job.info.run_id, FRAME_DETECTIONS, str(tmp_path)))
        mine = kept[kept["metric"] == "map"]
        frames = sorted(set(mine["frame"]))  # one draw: every frame once
        (whole,) = ap_resampled(mine, "map", frames, np.arange(len(frames))[None])
        assert whole == pytest.approx(job.data.metrics["map"], abs=1e-4) and len(frames) > 1
    diag = ablate(tmp_path, "experiment=smoe_table1", f"row={','.join(chosen)}", *TINY, module="ablate.diagnose")
    assert diag.returncode == 0, diag.stdout[-3000:] + diag.stderr[-3000:]
    text = (tmp_path / "results" / "smoe_table1_diagnosis.md").read_text()
    assert "RGB ∪ DDM" in text and "RGB only" in text and "MoE+Sharpening fusion (SMoE)" in text
    assert "Mean gate weight" in text and (tmp_path / "results" / "smoe_table1_diagnosis.png").stat().st_size > 0


def test_diagnose_without_the_tables_checkpoints_names_the_command_that_makes_them(tmp_path):
    out = ablate(tmp_path, "experiment=smoe_table2", *TINY, module="ablate.diagnose")
    assert out.returncode == 1
    assert "error: no checkpoint for row smoe_early seed 0" in out.stderr
    assert "python -m ablate -m experiment=smoe_table2" in out.stderr
    out = ablate(tmp_path, "experiment=smoe_table2", "row=smoe_early,smoe_sum", *TINY, module="ablate.diagnose")
    assert out.returncode == 1 and "error: row=smoe_sum: not a row of smoe_table2" in out.stderr, out.stderr[-2000:]


def test_a_commands_help_names_it_as_the_user_typed_it():
    from ablate.cli import as_typed

    assert as_typed("python -m ablate.report", "/venv/bin/ablate-report") == "ablate-report"
    assert as_typed("python -m ablate.report", "/repo/ablate/report.py") == "python -m ablate.report"
    assert as_typed("python -m ablate.report", "/venv/bin/pytest") == "python -m ablate.report"
    done = subprocess.run(
        [str(Path(sys.executable).parent / "ablate-report"), "--help"], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0 and done.stdout.startswith("usage: ablate-report [-h]")
