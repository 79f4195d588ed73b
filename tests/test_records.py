"""Run records: a published table's runs as a CSV beside it, from which the table renders again with no store, byte
for byte; a table without records is left as it is."""

from __future__ import annotations

import filecmp
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
from omegaconf import OmegaConf

from ablate.store.tracker import KIND_JOB, Tracker
from ablate.tables import render_records, write_table
from ablate.tables.records import read_records, records_path, to_records
from tests.scaleout import REPO

CFG = OmegaConf.create(
    {
        "table": {
            "name": "t2",
            "title": "Table II",
            "primary": "det_rate",
            "reference": "unet",
            "seeds": {"looks": [3], "alpha": 0.05, "correction": "bonferroni", "budget_min": None},
            "metrics": {"det_rate": "Det. Rate %", "latency_ms": "Comp Time (ms)"},
            "rows": [
                {"row": "chinet", "name": "ChiNet", "paper": {"det_rate": 97.35, "latency_ms": 192}},
                {"row": "unet", "name": "U-Net", "paper": {"det_rate": 94.2, "latency_ms": 82}},
            ],
        }
    }
)


def store(tmp_path: Path) -> Tracker:
    """A store with a table's runs: two rows, three seeds, a missing metric, and the tags a job records."""
    tracker = Tracker(f"sqlite:///{tmp_path / 'mlflow.db'}", str(tmp_path / "artifacts"))
    exp = tracker.experiment_id("t2")
    for row, base in (("chinet", 96.0), ("unet", 94.0)):
        for seed in range(3):
            tags = {"kind": KIND_JOB, "row": row, "seed": str(seed), "scale": "cpu", "config_hash": f"{row}{seed}"}
            tags |= {"cpu": "AMD EPYC", "cpu_isa": "avx2", "precision": "32-true", "threads": "1", "sweep_id": "s"}
            run = tracker.start(exp, row, tags)
            metrics = {"det_rate": base + 0.1 * seed + 1 / 3, "test/det_rate": base}
            if not (row == "unet" and seed == 2):  # the side-by-side latency of the row, on all but one run
                ms = 12.5 + seed
                metrics |= {"latency_ms": ms, "latency_q1_ms": ms - 1, "latency_q3_ms": ms + 1}
                metrics |= {"latency_load": 0.5, "latency_cores": 2.0, "params_m": 1.25, "macs_g": 0.5}
            tracker.log_metrics(run, metrics)
            for epoch in range(3):  # a history: validation once per epoch, the training loss per step
                tracker.log_metrics(run, {"val/det_rate": base - 3 + epoch + 0.1 * seed}, step=10 * (epoch + 1))
                for step in range(10 * epoch + 1, 10 * epoch + 11):
                    tracker.log_metrics(run, {"train/loss": 2.0 - 0.5 * epoch + 0.01 * step}, step=step)
            tracker.end(run, "FINISHED")
    return tracker


def test_records_keep_every_run_the_table_uses_and_read_back_as_they_were(tmp_path: Path) -> None:
    tracker = store(tmp_path)
    written = write_table(CFG, tracker, results_dir=tmp_path / "a", publish=True)
    path = records_path(tmp_path / "a", "t2")
    assert written[0] == path and path.exists()
    records = read_records(path)
    assert len(records) == 6 and set(records["row"]) == {"chinet", "unet"}
    assert records["seed"].dtype != "int64" and records["det_rate"].dtype == float  # tags stay text
    assert {"table", "status", "config_hash", "git_commit", "made_cpu", "cpu_isa", "seconds"} <= set(records.columns)
    assert not any(c.startswith(("val/", "test/")) for c in records.columns)  # no history, no second names
    unet2 = records[(records["row"] == "unet") & (records["seed"] == "2")]
    assert math.isnan(unet2["latency_ms"].iloc[0])  # a missing metric reads back as missing
    chinet0 = records[(records["row"] == "chinet") & (records["seed"] == "0")]
    assert chinet0["det_rate"].iloc[0] == 96.0 + 1 / 3  # the float, exactly
    again = to_records(records, "t2")
    pd.testing.assert_frame_equal(again.reset_index(drop=True), records)


def test_a_table_renders_from_its_records_with_no_store_byte_for_byte(tmp_path: Path) -> None:
    tracker = store(tmp_path)
    from_store = write_table(CFG, tracker, results_dir=tmp_path / "a", publish=True)
    shutil.copytree(tmp_path / "a" / "runs", tmp_path / "b" / "runs")  # a fresh clone: the records alone
    from_records = render_records(CFG, tmp_path / "b")
    rendered = [p for p in from_store if p.parent.name != "runs"]
    assert from_records is not None and [p.name for p in from_records] == [p.name for p in rendered]
    assert "t2_curves.png" in [p.name for p in from_records]  # the learning curves, from the curves kept beside
    for a, b in zip(rendered, from_records):
        assert filecmp.cmp(a, b, shallow=False), f"{b.name} differs from the table rendered from the store"
    assert render_records(CFG, tmp_path / "c") is None  # no records: nothing rendered


def test_the_report_leaves_tables_without_records_as_they_are(tmp_path: Path) -> None:
    # as on a fresh clone: the published tables and summaries, no store, and (today) no records for this table
    shutil.copytree(REPO / "results", tmp_path / "results", ignore=shutil.ignore_patterns("runs"))
    shutil.copy(REPO / "README.md", tmp_path / "README.md")
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    env.pop("MLFLOW_TRACKING_URI", None)
    out = subprocess.run(
        [sys.executable, "-m", "ablate.report", "experiment=chinet_table2"],
        capture_output=True, text=True, timeout=300, cwd=tmp_path, env=env,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert "chinet_table2: no run records yet" in out.stdout
    assert not (tmp_path / "mlflow.db").exists()  # no store was made or read
    changed = [
        str(p.relative_to(tmp_path))
        for p in [tmp_path / "README.md", *(tmp_path / "results").rglob("*")]
        if p.is_file() and not filecmp.cmp(p, REPO / p.relative_to(tmp_path), shallow=False)
    ]
    assert changed == [], changed


def test_the_tables_numbers_are_a_csv_and_a_booktabs_latex_table_equal_to_its_markdown(tmp_path: Path) -> None:
    write_table(CFG, store(tmp_path), results_dir=tmp_path / "a", publish=True)
    numbers = pd.read_csv(tmp_path / "a" / "t2.csv").set_index("row")
    chinet = [96.0 + 0.1 * s + 1 / 3 for s in range(3)]
    assert numbers.loc["chinet", "det_rate_mean"] == pytest.approx(sum(chinet) / 3, abs=1e-12)
    assert numbers.loc["chinet", "n"] == 3 and numbers.loc["chinet", "det_rate_paper"] == 97.35
    assert numbers.loc["chinet", "reference"] == "unet" and numbers.loc["chinet", "delta"] == pytest.approx(2.0)
    assert numbers.loc["chinet", "verdict"] in ("better", "worse", "equivalent", "different", "undecided")
    assert math.isnan(numbers.loc["unet", "delta"])
    markdown = (tmp_path / "a" / "t2.md").read_text()
    for row, values in numbers.iterrows():  # the CSV's numbers are the markdown's, unrounded
        assert f"{values['det_rate_mean']:.2f} ± {values['det_rate_std']:.2f}" in markdown, row
    tex = (tmp_path / "a" / "t2.tex").read_text()
    assert "\\toprule" in tex and "\\bottomrule" in tex and "Det. Rate \\%" in tex
    assert "ChiNet & \\bfseries 96.43 $\\pm$ 0.10" in tex  # the best of its column in bold


def test_the_published_runs_load_into_a_local_store_once_marked_as_imported(tmp_path: Path) -> None:
    from ablate.tables import collect
    from ablate.tables.records import IMPORTED, load_records

    write_table(CFG, store(tmp_path), results_dir=tmp_path / "a", publish=True)
    local = Tracker(f"sqlite:///{tmp_path / 'local.db'}", str(tmp_path / "local-artifacts"))
    path = records_path(tmp_path / "a", "t2")
    assert load_records(local, path) == 6 and load_records(local, path) == 0  # once
    loaded = local.runs(str(local.find_experiment("t2")))
    assert len(loaded) == 6 and all(r.info.status == "FINISHED" for r in loaded)
    chinet0 = next(r for r in loaded if r.data.tags["row"] == "chinet" and r.data.tags["seed"] == "0")
    assert chinet0.data.metrics["det_rate"] == 96.0 + 1 / 3 and chinet0.data.tags["cpu_isa"] == "avx2"
    assert chinet0.data.tags["kind"] == "imported" and chinet0.data.tags[IMPORTED].endswith(
        "t2.csv#" + chinet0.data.tags["recorded_run_id"]
    )
    assert collect(local, "t2").empty  # not this store's jobs: no table here counts them, no job skips on them


def test_the_learning_curves_are_kept_per_epoch_beside_the_records(tmp_path: Path) -> None:
    from ablate.tables.curves import curves_path, read_curves

    write_table(CFG, store(tmp_path), results_dir=tmp_path / "a", publish=True)
    curves = read_curves(curves_path(tmp_path / "a", "t2"))
    one = curves[(curves["row"] == "chinet") & (curves["seed"] == "1")]
    val = one[one["metric"] == "val/det_rate"].set_index("epoch")["value"]
    loss = one[one["metric"] == "train/loss"].set_index("epoch")["value"]
    assert list(val.index) == [0, 1, 2] and val[2] == pytest.approx(96.0 - 3 + 2 + 0.1)
    # epoch 1's steps are 11..20, up to its validation at step 20: the mean of 1.5 + 0.01 * step over them
    assert list(loss.index) == [0, 1, 2] and loss[1] == pytest.approx(1.5 + 0.01 * 15.5)
    assert len(curves) == 6 * 2 * 3  # per run, two metrics, three epochs: no per-step history


def test_the_results_summary_reads_a_tables_numbers_as_it_read_its_markdown(tmp_path: Path) -> None:
    from ablate.tables import table_spec
    from ablate.tables.index import summarise_numbers, summarise_table

    write_table(CFG, store(tmp_path), results_dir=tmp_path / "a", publish=True)
    spec = table_spec(CFG)
    from_numbers = summarise_numbers(spec, pd.read_csv(tmp_path / "a" / "t2.csv"))
    from_markdown = summarise_table(spec, (tmp_path / "a" / "t2.md").read_text())
    assert from_numbers == from_markdown and from_numbers.ours == "ChiNet"


def test_the_footers_wall_time_starts_where_a_job_began_training_its_experts(tmp_path: Path) -> None:
    from ablate.tables.collect import made_lines

    tracker = store(tmp_path)
    exp = tracker.experiment_id("t2")
    tags = {"kind": KIND_JOB, "row": "chinet", "seed": "3", "scale": "cpu", "config_hash": "chinet3", "sweep_id": "s"}
    run = tracker.start(exp, "chinet", tags | {"cpu": "AMD EPYC", "precision": "32-true", "threads": "1"})
    began = tracker.get_run(run).info.start_time - 20 * 60000  # its experts took 20 min before its run
    tracker.set_tags(run, {"job_started": str(began)})
    tracker.log_metrics(run, {"det_rate": 96.5})
    tracker.end(run, "FINISHED")
    write_table(CFG, tracker, results_dir=tmp_path / "a", publish=True)
    records = read_records(records_path(tmp_path / "a", "t2"))
    assert records["job_started"].min() == began  # kept in the records, to the millisecond
    assert "wall time 20 min over 1 sweep(s), 20 min of job time" in made_lines(records)[0]
    # records written before the column: the runs' own spans, as those tables were rendered
    assert "wall time 0 min over 1 sweep(s), 0 min of job time" in made_lines(records.drop(columns="job_started"))[0]
    # a CPU run names no GPU, and records from before the GPU's column read the same
    assert set(records["made_gpu"]) == {""}
    assert made_lines(records)[0].startswith("Made on AMD EPYC, precision 32-true, 1 thread(s) per job;")
    assert made_lines(records.drop(columns="made_gpu")) == made_lines(records)
    on_gpu = made_lines(records.assign(made_gpu="NVIDIA H200"))[0]
    assert on_gpu.startswith("Made on AMD EPYC with NVIDIA H200, precision 32-true, 1 thread(s) per job;"), on_gpu


def test_a_run_copied_from_another_table_starts_when_it_is_copied(tmp_path: Path) -> None:
    tracker = Tracker(f"sqlite:///{tmp_path / 'mlflow.db'}", str(tmp_path / "artifacts"))
    tags = {"kind": KIND_JOB, "row": "unet", "seed": "0", "sweep_id": "a", "job_started": "1000"}  # long ago
    source = tracker.start(tracker.experiment_id("t1"), "unet", tags)
    tracker.end(source, "FINISHED")
    copy = tracker.get_run(tracker.copy_run(tracker.get_run(source), tracker.experiment_id("t2"), {"table": "t2"}))
    assert "job_started" not in copy.data.tags and "sweep_id" not in copy.data.tags  # its own sweep's wall time


def test_a_committed_table_of_many_metrics_renders_its_numbers_again_without_a_pandas_warning(tmp_path: Path) -> None:
    # DGFN Table I: 58 metrics (8 test inputs, 3 difficulties, AP11/AP40, gates); its numbers were built a column at
    # a time, and pandas warned of a fragmented frame 41 times at the end of every sweep and report
    import warnings

    from ablate.config import compose

    records = REPO / "results" / "runs"
    shutil.copytree(records, tmp_path / "runs", ignore=lambda _, names: [n for n in names if "dgfn_table1." not in n])
    with warnings.catch_warnings():
        warnings.simplefilter("error", pd.errors.PerformanceWarning)
        written = render_records(compose(["experiment=dgfn_table1"]), tmp_path)
    assert written is not None and (tmp_path / "dgfn_table1.csv") in written
    assert filecmp.cmp(tmp_path / "dgfn_table1.csv", REPO / "results" / "dgfn_table1.csv", shallow=False)


def test_each_paper_table_is_named_as_its_experiment_and_the_summary_composes_only_the_published_ones(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A sweep that publishes one table rewrites the summary of the tables under its results folder: it composes
    those (:func:`ablate.tables.published.with_tables`), found by their experiment's file name."""
    from ablate.config import compose
    from ablate.tables import published, table_spec

    for name in published.experiments():
        assert table_spec(compose([f"experiment={name}"])).name == name
    monkeypatch.chdir(tmp_path)
    assert published.with_tables() == []
    (tmp_path / "results").mkdir()
    for name in ("chinet_table3", "mine"):  # a table that is no paper's is in no summary
        (tmp_path / "results" / f"{name}.md").write_text("| a |\n")
    assert published.with_tables() == ["chinet_table3"]
