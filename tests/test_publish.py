"""Trying never overwrites what is published: a sweep writes its table, records and figure into its own folder and
onto its parent run; only ``publish=true`` (or ``python -m ablate.report``, from the records) writes under
``results/`` and the README's summary."""

from __future__ import annotations

import filecmp
import shutil
from pathlib import Path

from tests.scaleout import REPO, SERIAL, ablate, output, runs

#: TINY without publish=true: as a user tries things
TRY = [
    "scale=smoke",
    "data.synth.frames=20",
    "trainer.enable_progress_bar=false",
    "comp_time.repeats=2",
    "logger.log_figures=false",
]


def published(where: Path) -> dict[str, bytes]:
    """The published files under ``where``: results/ and the README."""
    files = [where / "README.md", *sorted((where / "results").rglob("*"))]
    return {str(p.relative_to(where)): p.read_bytes() for p in files if p.is_file()}


def test_a_smoke_sweep_and_an_ad_hoc_sweep_on_other_data_leave_the_published_results_alone(tmp_path: Path) -> None:
    shutil.copytree(REPO / "results", tmp_path / "results")  # a clone's published tables
    shutil.copy(REPO / "README.md", tmp_path / "README.md")
    before = published(tmp_path)
    paper = ablate(tmp_path, "-m", "experiment=chinet_table2", *TRY, SERIAL)
    assert paper.returncode == 0, output(paper)
    adhoc = ablate(tmp_path, "-m", "task=semantic", "model=unet,fusenet", "data.synth.seed=7", *TRY, SERIAL)
    assert adhoc.returncode == 0, output(adhoc)
    assert published(tmp_path) == before  # not a byte of results/ or the README changed
    sweeps = sorted((tmp_path / "multirun").glob("*/*"))
    assert len(sweeps) == 2
    for sweep, table in zip(sweeps, ("chinet_table2", "ablate")):
        assert (sweep / f"{table}.md").is_file() and (sweep / f"{table}.png").is_file()
        assert (sweep / "runs" / f"{table}.csv").is_file()  # the sweep's own records
    client, parents = runs(f"sqlite:///{tmp_path / 'mlflow.db'}", "chinet_table2", kind="sweep")
    parent = parents[0]  # worth opening: named after its table, carrying it and each row's mean
    assert {"chinet_table2.md", "chinet_table2.csv"} <= {a.path for a in client.list_artifacts(parent.info.run_id)}
    assert parent.info.run_name.startswith("chinet_table2 scale=smoke")
    assert {"det_rate/chinet", "det_rate/unet", "det_rate/fusenet"} <= set(parent.data.metrics)
    _, jobs = runs(f"sqlite:///{tmp_path / 'mlflow.db'}", "chinet_table2")
    job = jobs[0]  # MLflow's conventions: its UI's Source, Version and User; the rate per step; the log; clean params
    assert {"mlflow.source.name", "mlflow.source.git.commit", "mlflow.user"} <= set(job.data.tags)
    assert "lr-Adam" in job.data.metrics and "det_rate" in job.data.metrics and "test/det_rate" not in job.data.metrics
    assert {"logs/ablate.log", "logs/overrides.yaml"} <= {
        a.path for a in client.list_artifacts(job.info.run_id, "logs")
    }
    assert len(job.data.params) <= 62 and not any(k.startswith(("table.", "logger.")) for k in job.data.params)
    (dataset,) = [d.dataset for d in job.inputs.dataset_inputs]  # the data it trained on: synth-<hash>, its frames
    assert dataset.name.startswith("synth-") and '"train": 12' in dataset.profile and dataset.digest


def test_publish_true_writes_the_records_and_the_table_under_results(tmp_path: Path) -> None:
    out = ablate(tmp_path, "-m", "experiment=chinet_table2", "row=unet,fusenet", *TRY, SERIAL, "publish=true")
    assert out.returncode == 0, output(out)
    sweep = next((tmp_path / "multirun").glob("*/*"))
    for name in ("chinet_table2.md", "chinet_table2.png", "runs/chinet_table2.csv", "runs/chinet_table2.frames.csv.gz"):
        assert filecmp.cmp(sweep / name, tmp_path / "results" / name, shallow=False), name
    # the counts per test frame beside the records: the verdicts' interval over the seeds and the test frames
    assert (
        "The verdicts and Δ read the interval over seeds and test frames"
        in (tmp_path / "results" / "chinet_table2.md").read_text()
    )
    again = ablate(tmp_path, "-m", "experiment=chinet_table2", "row=unet,fusenet", *TRY, SERIAL)  # as `make run`
    assert again.returncode == 0, output(again)
    assert published(tmp_path)["results/chinet_table2.md"] == (tmp_path / "results" / "chinet_table2.md").read_bytes()
    newest = max((tmp_path / "multirun").glob("*/*"))
    beside = (newest / "chinet_table2_vs_published.md").read_text()
    assert "| U-Net |" in beside and "| FuseNet |" in beside and "Your rows beside the published" in output(again)


def test_your_seeds_are_placed_in_the_published_rows_prediction_interval() -> None:
    from omegaconf import OmegaConf

    from ablate.analysis.compare import UNMEASURED, compare

    table = OmegaConf.create({"primary": "det_rate", "rows": [{"row": "unet", "name": "U-Net"}]})
    shared = {"row": "unet", "made_cpu": "AMD EPYC", "made_precision": "32-true", "made_threads": "1"}
    import pandas as pd

    ours = pd.DataFrame([{**shared, "cpu_isa": "avx2", "det_rate": v} for v in (95.0, 99.5)])
    theirs = pd.DataFrame([{**shared, "cpu_isa": "avx512f", "det_rate": v} for v in (94.0, 95.0, 96.0)])
    text = compare(ours, theirs, table)
    line = last_row(text)
    # the table did not measure how far other numerics move a run: said under it
    assert text.splitlines()[-1] == UNMEASURED
    # published: mean 95, s = 1, n = 3: 95 ± 4.30 · 1 · sqrt(4/3) = [90.03, 99.97]
    assert line.startswith("| U-Net | 97.25 (2) | 95.00 (3) | [90.03, 99.97] | 2 of 2 |"), line
    assert "ISA: avx512f -> avx2" in line and "CPU" not in line and "tuned config" not in line
    # a published row raced on its tuned config, yours on the recipe: said, with the published values
    tuned = '{"task.optimizer.lr": 0.0008727, "task.optimizer.weight_decay": null}'
    line = last_row(compare(ours, theirs.assign(tuned_config=tuned), table))
    assert line.endswith("; tuned config: lr=0.0008727, weight_decay=default -> the recipe |"), line
    # the same values given on the command line: the config hashes per seed are the published ones
    hashed = {"seed": [0, 1], "config_hash": ["a0", "a1"]}
    mine = ours.assign(**hashed)
    line = compare(mine, theirs.assign(tuned_config=tuned, seed=[0, 1, 2], config_hash=["a0", "a1", "a2"]), table)
    assert last_row(line).endswith("; same config |") and "tuned config" not in line
    line = compare(mine.assign(config_hash=["b0", "b1"]), theirs.assign(seed=[0, 1, 2], config_hash="a"), table)
    assert last_row(line).endswith("; another config (its hash differs from the published one's at the same seed) |")
    # yours at scale=smoke on the published tuned config (it records only what it set beyond the recipe): the scale
    # is named, not a tuned config it did not differ in
    smoke = mine.assign(config_hash=["b0", "b1"], scale="smoke", tuned_config="")
    line = compare(smoke, theirs.assign(tuned_config=tuned, seed=[0, 1, 2], config_hash="a", scale="cpu"), table)
    assert last_row(line).endswith("; another scale: cpu -> smoke |") and "recipe" not in line, line
    # yours trained on a GPU, the published rows on the CPU (records from before the column name none)
    line = last_row(compare(ours.assign(made_gpu="NVIDIA H200"), theirs, table))
    assert "GPU: none -> NVIDIA H200" in line, line
    assert "GPU" not in last_row(compare(ours.assign(made_gpu=""), theirs, table))
    # a table that measured how far other numerics move a run (table.kernels_run): yours on another ISA are placed
    # in the interval with that shift's variance added; yours on the published numerics in the interval without it
    measured = OmegaConf.merge(table, {"kernels_run": {"sd": 3.0, "seeds": 3}})
    header, *_, line = compare(ours, theirs, measured).splitlines()
    assert "Published 95 % PI for a new seed, with other numerics' sd 3 (3 seeds)" in header, header
    assert UNMEASURED not in compare(ours, theirs, measured)
    assert line.startswith("| U-Net | 97.25 (2) | 95.00 (3) | [85.92, 104.08] | 2 of 2 |"), line
    same = ours.assign(cpu_isa="avx512f")
    header, *_, line = compare(same, theirs, measured).splitlines()
    assert "other numerics" not in header and "| [90.03, 99.97] | 2 of 2 | none |" in line, line
    assert UNMEASURED not in compare(same, theirs, table)


def last_row(text: str) -> str:
    """The last row of a markdown table in ``text``."""
    return [line for line in text.splitlines() if line.startswith("|")][-1]
