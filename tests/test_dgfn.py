"""DGFN Tables I and II end to end at scale=smoke, as a user runs them, and the detection task on real KITTI."""

import math

import numpy as np
import pytest
from test_cli import FIGURES, SERIAL, TINY, ablate, runs

CONDITIONS = [
    "full",
    "normal",
    "camera_blank",
    "lidar_blank",
    "camera_occlusion",
    "lidar_occlusion",
    "camera_noise",
    "camera_illumination",
]


#: Two of the four test frames: every frame is tested once per condition, each through SSD300 at 300 px (most of a
#: smoke DGFN job's time).
FEW = "data.limit_frames={test:2}"


@pytest.fixture(scope="module")
def tables(tmp_path_factory):
    cwd = tmp_path_factory.mktemp("dgfn")
    first = ablate(cwd, "-m", "experiment=dgfn_table1", SERIAL, FEW, *TINY, FIGURES, "trace.every=1")
    second = ablate(cwd, "-m", "experiment=dgfn_table2", SERIAL, FEW, *TINY)
    return cwd, first, second


def table_rows(text: str) -> list[str]:
    """The row names of the main table of ``text``."""
    main = text.split("All metrics:")[0]
    return [line.split("|")[1].strip() for line in main.splitlines() if line.startswith("| ")][1:]


def test_table1_tests_each_model_under_every_condition(tables):
    cwd, first, _ = tables
    assert first.returncode == 0, first.stdout[-3000:] + first.stderr[-3000:]
    client, jobs = runs(cwd, "dgfn_table1")
    assert sorted(r.data.tags["row"] for r in jobs) == ["dgfn", "dgfn_baseline"]
    assert {r.info.status for r in jobs} == {"FINISHED"}
    for job in jobs:
        metrics = job.data.metrics
        for condition in CONDITIONS:
            for key in ("car_easy", "car_moderate", "car_hard", "car_moderate_ap40", "gate_rgb", "gate_dhi"):
                assert f"{condition}/{key}" in metrics, f"{condition}/{key}"
        assert "camera_noise-s2/car_moderate" in metrics and "camera_blank-s2/car_moderate" not in metrics
        assert "latency_ms" in metrics and job.data.params["model._target_"] == "ablate.tasks.detection.DGFN"
    gated = next(r for r in jobs if r.data.tags["row"] == "dgfn").data.metrics
    baseline = next(r for r in jobs if r.data.tags["row"] == "dgfn_baseline").data.metrics
    assert baseline["camera_blank/gate_rgb"] == 1.0 and 0 < gated["camera_blank/gate_rgb"] < 1
    assert not math.isclose(gated["camera_blank/gate_rgb"], gated["normal/gate_rgb"])
    # trace.every=1 (ablate.jobs.trace): each trunk's gradient norm; the gated row's weight maps at each SSD map
    assert (
        gated["trace/grad_branches.rgb"] > 0 and gated["trace/grad_branches.dhi"] > 0 and gated["trace/grad_head"] > 0
    )
    assert {f"trace/gate{k}_{m}" for k in range(6) for m in ("rgb", "dhi")} <= set(gated)
    assert 0 < gated["trace/gate0_rgb"] < 1 and 0 <= gated["trace/gate0_rgb_shut"] <= 1
    assert "trace/grad_fuse" in baseline and not any(k.startswith("trace/gate") for k in baseline)
    dgfn = next(r for r in jobs if r.data.tags["row"] == "dgfn")
    assert {"gates.png", "predictions.png"} <= {a.path for a in client.list_artifacts(dgfn.info.run_id)}
    # Table II's sweep ran with logger.log_figures=false (TINY): its jobs drew no figure
    _, second = runs(cwd, "dgfn_table2")
    assert second and not any(a.path.endswith(".png") for r in second for a in client.list_artifacts(r.info.run_id))
    # each frame's matched detections: AP re-accumulated from them equals the logged AP (ablate.metrics.accumulate)
    from ablate.store import FRAME_DETECTIONS
    from ablate.tables.frames import _read_detections, ap_resampled

    path = client.download_artifacts(dgfn.info.run_id, FRAME_DETECTIONS, str(cwd))
    rows = _read_detections(path)
    for condition in ("full", "normal", "camera_blank"):
        mine = rows[(rows["metric"] == "car_moderate") & (rows["condition"] == condition)]
        frames = sorted(set(mine["frame"]))  # one draw: every frame once
        (whole,) = ap_resampled(mine, "car_moderate", frames, np.arange(len(frames))[None])
        assert whole == pytest.approx(dgfn.data.metrics[f"{condition}/car_moderate"], rel=1e-6, abs=1e-6)
        assert len(frames) > 1


def test_table1_is_written_with_conditions_as_rows(tables):
    cwd, _, _ = tables
    text = (cwd / "results" / "dgfn_table1.md").read_text()
    assert table_rows(text.split("Per model")[0]) == [
        "Full",
        "Lidar + RGB (normal)",
        "Lidar + RGB (blank)",
        "Lidar (blank) + RGB",
        "Lidar + RGB (occlusion)",
        "Lidar (occlusion) + RGB",
        "Lidar + RGB (noise)",
        "Lidar + RGB (illumination)",
        "Kendall τ vs paper (n)",
    ]
    assert "Proposed (with GFU): Easy (paper)" in text and "98.69" in text and "72.21" in text
    assert "Δ Moderate (Full) vs Baseline (without GFU) [95% CI]" in text and "side by side" in text
    gates = (cwd / "results" / "dgfn_table1_gates.md").read_text()
    assert "w_C (camera)" in gates and len(table_rows(gates)) == 8
    for name in ("dgfn_table1.png", "dgfn_table1_robustness.png", "dgfn_table1_gates.png"):
        assert (cwd / "results" / name).stat().st_size > 0, name
    before = (cwd / "results" / "dgfn_table1.md").read_bytes()
    report = ablate(cwd, "--publish", "experiment=dgfn_table1", module="ablate.report")
    assert report.returncode == 0, report.stderr[-3000:]
    assert (cwd / "results" / "dgfn_table1.md").read_bytes() == before
    # the detections per frame are published beside the records, and the verdicts read the test frames too
    assert (cwd / "results" / "runs" / "dgfn_table1.detections.csv.gz").is_file()
    assert "interval over seeds and test frames" in before.decode()


def test_table2_reuses_table1s_dgfn_and_lists_the_papers_other_systems(tables):
    cwd, _, second = tables
    assert second.returncode == 0, second.stdout[-3000:] + second.stderr[-3000:]
    assert "Reusing dgfn (seed 0)" in second.stdout
    _, jobs = runs(cwd, "dgfn_table2")
    assert sorted(r.data.tags["row"] for r in jobs) == ["dgfn", "ssd_dhi", "ssd_rgb"]
    ssd_rgb = next(r for r in jobs if r.data.tags["row"] == "ssd_rgb")
    assert ssd_rgb.data.params["model.single"] == "rgb" and ssd_rgb.data.params["task.train_corruptions"] == "None"
    text = (cwd / "results" / "dgfn_table2.md").read_text()
    assert table_rows(text) == [
        "SSD* [3]",
        "SSD* [3]",
        "3DOP [18]",
        "Mono3D [19]",
        "Deep MANTA [20]",
        "MV3D [7]",
        "Our DGFN",
    ]
    assert "| Stereo" in text and "paper only" in text and "97.58" in text and "Kendall τ" in text
    assert "Rows without a finished run" not in text


def test_detection_runs_on_real_kitti_boxes(kitti_root, tmp_path):
    out = ablate(
        tmp_path,
        "experiment=dgfn_table1",
        "row=dgfn",
        "data=kitti",
        f"data.root={kitti_root / 'object'}",
        "task.classes=[Car,Pedestrian,Cyclist]",
        "task.eval_severities=[]",
        *TINY,
    )
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    _, (job,) = runs(tmp_path, "dgfn_table1")
    assert job.info.status == "FINISHED" and job.data.params["data.root"].endswith("kitti/object")
    assert {"normal/cyclist_moderate", "full/car_easy", "lidar_blank/gate_dhi"} <= set(job.data.metrics)
    assert not (tmp_path / "data" / "synth").exists() and any((tmp_path / "data" / "cache").iterdir())


def test_the_table2_follow_up_reuses_every_row_but_its_clean_trained_dgfn():
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf
    from test_cli import REPO

    from ablate.store import config_hash

    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):

        def cfg(experiment, row):
            return compose("config", overrides=[f"experiment={experiment}", f"row={row}", "seed=1"])

        for row in ("dgfn", "ssd_rgb", "ssd_dhi"):
            assert config_hash(cfg("dgfn_table2_followup", row)) == config_hash(cfg("dgfn_table2", row)), row
        assert config_hash(cfg("dgfn_table2_followup", "dgfn_baseline")) == config_hash(
            cfg("dgfn_table1", "dgfn_baseline")
        )
        clean, dgfn = (
            OmegaConf.to_container(cfg("dgfn_table2_followup", r), resolve=True) for r in ("dgfn_clean", "dgfn")
        )
    assert clean["task"].pop("train_corruptions") is None and dgfn["task"].pop("train_corruptions")
    clean.pop("table"), dgfn.pop("table")
    assert clean == dgfn  # the control differs from DGFN in its training data only
