"""Tables from runs: rows in the paper's order, mean ± std, failed runs left out, same runs -> same bytes."""

import math

import numpy as np
import pandas as pd
import pytest
from mlflow.tracking import MlflowClient
from omegaconf import OmegaConf

from ablate.store.tracker import KIND_JOB, Tracker
from ablate.tables import collect, write_table
from ablate.tables.collect import job_runs, row_seconds
from ablate.tables.summary import kendall, summarise
from tests.stores import sqlite_uri

TABLE = OmegaConf.create(
    {
        "table": {
            "name": "t2",
            "title": "Table II",
            "primary": "det_rate",
            "metrics": {"det_rate": "Det. Rate %", "comp_time_ms": "Comp Time (ms)"},
            "rows": [
                {"row": "chinet", "name": "ChiNet", "paper": {"det_rate": 97.35, "comp_time_ms": 192}},
                {"row": "unet", "name": "U-Net", "paper": {"det_rate": 94.2, "comp_time_ms": 82}},
                {"row": "fusenet", "name": "FuseNet", "paper": {"det_rate": 95.2, "comp_time_ms": 125}},
            ],
        }
    }
)


@pytest.fixture
def tracker(tmp_path):
    tracker = Tracker(sqlite_uri(tmp_path), str(tmp_path / "artifacts"))
    exp = tracker.experiment_id("t2")

    def job(row, seed, rate, ms, status="FINISHED", chash=None, scale="cpu"):
        run = tracker.start(
            exp,
            row,
            {"kind": KIND_JOB, "row": row, "seed": str(seed), "scale": scale, "config_hash": chash or f"{row}-{seed}"},
        )
        tracker.log_metrics(run, {"det_rate": rate, "comp_time_ms": ms})
        tracker.end(run, status)

    job("unet", 0, 5.0, 1.0, scale="smoke")  # a smoke run in the same store: not part of the cpu-scale table
    job("unet", 0, 60.0, 10.0, chash="unet-old")  # superseded by a rerun after a config change
    job("unet", 0, 80.0, 10.0)
    job("unet", 1, 82.0, 12.0)
    job("chinet", 0, 90.0, 30.0)
    job("chinet", 1, 0.0, 1.0, status="FAILED", chash="chinet-1")
    job("fusenet", 0, 70.0, 20.0, chash="f")
    job("fusenet", 0, 85.0, 20.0, chash="f")  # a forced rerun: the latest of a config hash counts
    return tracker


def test_summary_follows_paper_order_and_skips_failed_runs(tracker):
    runs = collect(tracker, "t2")
    assert len(runs) == 4
    summary = summarise(runs, TABLE.table)
    assert list(summary["name"]) == ["ChiNet", "U-Net", "FuseNet"]
    chinet = summary.iloc[0]
    assert chinet["n"] == 1 and chinet["det_rate_mean"] == 90.0 and math.isnan(chinet["det_rate_std"])
    unet = summary.iloc[1]
    assert unet["det_rate_mean"] == 81.0 and unet["det_rate_std"] == pytest.approx(math.sqrt(2.0))
    assert summary.iloc[2]["det_rate_mean"] == 85.0


def test_kendall_tau_against_the_paper(tracker):
    summary = summarise(collect(tracker, "t2"), TABLE.table)
    tau, n = kendall(summary, "det_rate")
    # ours: ChiNet 90 > FuseNet 85 > U-Net 81; paper: ChiNet > FuseNet > U-Net
    assert n == 3 and tau == pytest.approx(1.0)


def test_markdown_has_rows_paper_column_bold_best_and_is_reproducible(tracker, tmp_path):
    md, png, *_ = write_table(TABLE, tracker, results_dir=tmp_path / "r1")
    text = md.read_text()
    main, rest = text.split("All metrics:")
    lines = [line for line in main.splitlines() if line.startswith("|")]
    assert len(lines) == 2 + 3 and len(lines[0].strip("|").split("|")) <= 10
    assert "Comp Time (ms) (ours)" in rest and "Comp Time" not in main  # a secondary metric: in "All metrics"
    assert "**90.00**" in text and "**97.35**" in text  # best det rate, ours and paper
    assert "**11.00 ± 1.41**" in text and "**82.00**" in text  # lowest comp time is best
    assert "Kendall τ" in text and "1.00 over 3 rows" in text
    md2, png2, *_ = write_table(TABLE, tracker, results_dir=tmp_path / "r2")
    assert md2.read_bytes() == md.read_bytes()
    assert png2.read_bytes() == png.read_bytes()


def test_rows_without_finished_runs_are_listed_not_tabled(tmp_path):
    tracker = Tracker(sqlite_uri(tmp_path), str(tmp_path / "artifacts"))
    exp = tracker.experiment_id("t2")
    run = tracker.start(exp, "u", {"kind": KIND_JOB, "row": "unet", "seed": "0", "config_hash": "x"})
    tracker.log_metrics(run, {"det_rate": 50.0, "comp_time_ms": 5.0})
    tracker.end(run, "FINISHED")
    md, *_ = write_table(TABLE, tracker, results_dir=tmp_path)
    text = md.read_text()
    assert len([line for line in text.split("All metrics:")[0].splitlines() if line.startswith("|")]) == 3
    assert "Rows without a finished run: ChiNet, FuseNet." in text


@pytest.mark.parametrize(
    "task, evaluators, expected",
    [
        # made before runs recorded their evaluator: the detection and road metrics changed since, the mask AP did not
        (
            "ablate.tasks.detection.DetectionTask",
            [None, None],
            "ablate.metrics.kitti now follows kitti_object_devkit_2017 "
            "(ablate/metrics/__init__.py), and 2 of 2 runs were scored otherwise (no recorded evaluator: 2)",
        ),
        (
            "ablate.tasks.road_bev.RoadTask",
            [None, "kitti_road_devkit"],
            "ablate.metrics.road now follows "
            "kitti_road_devkit (ablate/metrics/__init__.py), and 1 of 2 runs were scored otherwise "
            "(no recorded evaluator: 1)",
        ),
        ("ablate.tasks.instance.InstanceTask", [None, None], None),
        # recorded: another rule (the older devkit, chosen) is named; today's rule on every run says nothing
        (
            "ablate.tasks.detection.DetectionTask",
            ["kitti_object_devkit_2017", "kitti_object_devkit_2d_2012"],
            "and 1 of 2 runs were scored otherwise (kitti_object_devkit_2d_2012: 1)",
        ),
        ("ablate.tasks.detection.DetectionTask", ["kitti_object_devkit_2017"] * 2, None),
    ],
)
def test_footer_says_when_the_metric_changed_since_the_runs(tmp_path, task, evaluators, expected):
    tracker = Tracker(sqlite_uri(tmp_path), str(tmp_path / "artifacts"))
    exp = tracker.experiment_id("t2")
    for seed, evaluator in enumerate(evaluators):
        tags = {"kind": KIND_JOB, "row": "unet", "seed": str(seed), "config_hash": f"unet-{seed}"}
        run = tracker.start(exp, "unet", {**tags, **({"evaluator": evaluator} if evaluator else {})})
        tracker.log_params(run, {"task._target_": task})
        tracker.log_metrics(run, {"det_rate": 50.0 + seed, "comp_time_ms": 5.0})
        tracker.end(run, "FINISHED")
    md, *_ = write_table(TABLE, tracker, results_dir=tmp_path)
    footer = md.read_text().splitlines()[-1]
    if expected is None:
        assert "Metric changed" not in footer
    else:
        assert "**Metric changed since these runs**: " in footer and expected in footer
        assert footer.endswith(
            "rerun them (`force=true`) to compare with the paper. Regenerated by "
            "`python -m ablate.report`; do not edit by hand."
        )


def test_an_ad_hoc_sweep_keeps_the_typed_order_and_has_no_paper_columns(tmp_path):
    """`-m fusion=sum,max,sharpen,smoe`: rows in the order typed (Hydra's job numbers), the first typed is the
    reference, and no paper column or τ line where there are no paper numbers."""
    tracker = Tracker(sqlite_uri(tmp_path), str(tmp_path / "artifacts"))
    exp = tracker.experiment_id("ablate")
    for num, (row, ap) in enumerate(
        [("fusion=sum", 20.0), ("fusion=max", 22.0), ("fusion=sharpen", 21.0), ("fusion=smoe", 23.0)]
    ):
        run = tracker.start(
            exp, row, {"kind": KIND_JOB, "row": row, "seed": "0", "config_hash": row, "job_num": str(num)}
        )
        tracker.log_metrics(run, {"map": ap})
        tracker.end(run, "FINISHED")
    cfg = OmegaConf.create(
        {
            "table": {
                "name": "ablate",
                "title": "Ad-hoc sweep",
                "primary": "map",
                "metrics": {"map": "mask AP"},
                "rows": [],
            }
        }
    )
    text = write_table(cfg, tracker, results_dir=tmp_path)[0].read_text()
    rows = [
        line.split("|")[1].strip() for line in text.split("All metrics:")[0].splitlines() if line.startswith("| fusion")
    ]
    assert rows == ["fusion=sum", "fusion=max", "fusion=sharpen", "fusion=smoe"]
    assert "vs fusion=sum" in text and "reference" in text.splitlines()[4]
    assert "paper" not in text and "Kendall" not in text


def test_a_rows_job_time_is_its_runs_and_a_copied_run_counts_its_sources(tmp_path):
    # the racing sweeper's look estimate weighs rows by these seconds: a copy took milliseconds, its source minutes
    tracker = Tracker(sqlite_uri(tmp_path), str(tmp_path / "artifacts"))
    tags = {"kind": KIND_JOB, "scale": "cpu", "seed": "0"}

    def job(exp, row, start_s, minutes):
        client = MlflowClient(tracker.uri)  # runs with the start and end times of jobs long past
        run = client.create_run(exp, start_time=int(start_s * 1000), tags={**tags, "row": row})
        client.set_terminated(run.info.run_id, "FINISHED", end_time=int((start_s + minutes * 60) * 1000))
        return tracker.get_run(run.info.run_id)

    other, mine = tracker.experiment_id("table_i"), tracker.experiment_id("table_ii")
    source = job(other, "dgfn", 1_000, 19.0)
    job(mine, "ssd", 3_000, 9.0)
    job(mine, "ssd", 4_000, 10.0)
    tracker.copy_run(source, mine, {"row": "dgfn", "seed": "0"})
    assert row_seconds(tracker, job_runs(tracker, "table_ii")) == {"dgfn": 19 * 60.0, "ssd": 9.5 * 60}


def test_a_column_where_every_row_ties_bolds_none_and_one_best_is_bold():
    from ablate.tables.summary import bold_of

    assert np.isnan(bold_of(pd.Series([1.85, 1.85, np.nan]), "max_f"))
    assert bold_of(pd.Series([1.0, 2.0]), "max_f") == 2.0 and bold_of(pd.Series([1.0, 2.0]), "latency_ms") == 1.0
    assert bold_of(pd.Series([3.0]), "max_f") == 3.0  # one row: its value
