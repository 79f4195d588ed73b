"""bf16 against fp32 parity (ablate.tables.parity, `python -m ablate.report --parity`): runs of the two precisions
pair by seed, the verdict follows the paired CI, sections of other rows survive a rewrite, and a row without both
precisions is one error."""

import pytest
from omegaconf import OmegaConf

from ablate.report import main as report
from ablate.store.tracker import KIND_JOB, Tracker
from ablate.tables.parity import parity, write_parity
from tests.stores import sqlite_uri

TABLE = OmegaConf.create(
    {
        "name": "t2",
        "title": "Table II",
        "primary": "det_rate",
        "metrics": {"det_rate": "Det. Rate %", "iou": "IoU %"},
        "rows": [{"row": "chinet", "name": "ChiNet"}, {"row": "unet", "name": "U-Net"}],
    }
)


def store(tmp_path, bf16_rates, fp32_rates=(90.0, 91.0, 92.0), row="chinet"):
    tracker = Tracker(sqlite_uri(tmp_path), str(tmp_path / "artifacts"))
    exp = tracker.experiment_id("t2")
    for precision, rates in (("32-true", fp32_rates), ("bf16-mixed", bf16_rates)):
        for seed, rate in enumerate(rates):
            tags = {"kind": KIND_JOB, "row": row, "seed": str(seed), "scale": "cpu", "precision": precision}
            tags |= {"config_hash": f"{precision}-{seed}", "cpu": "Test CPU", "threads": "1", "git_commit": "abc"}
            run = tracker.start(exp, row, tags)
            tracker.log_metrics(run, {"det_rate": rate, "iou": rate - 10})
            tracker.end(run, "FINISHED")
    return tracker


def test_same_values_up_to_noise_are_no_cost(tmp_path):
    found = parity(store(tmp_path, (90.2, 90.8, 92.1)), TABLE, "chinet")
    assert found.seeds == ["0", "1", "2"]
    assert found.delta("det_rate").delta == pytest.approx(0.0333, abs=1e-3)
    assert "Not separable from seed noise; a cost above 0.48 is ruled out at 95 %." in found.verdict()
    text = write_parity(found, tmp_path / "parity.md").read_text()
    assert "| **Det. Rate %** | 91.00 ± 1.00 | 91.03 ± 0.97 |" in text
    assert "seed 0: 90.00 → 90.20" in text and "Test CPU, 1 thread(s) per job" in text


def test_a_consistent_loss_is_called_a_cost(tmp_path):
    found = parity(store(tmp_path, (88.0, 89.1, 89.9)), TABLE, "chinet")
    assert found.verdict().startswith("**bf16 costs Det. Rate % beyond seed noise**")


def test_seeds_that_spread_twice_as_wide_are_named_though_the_mean_holds(tmp_path):
    verdict = parity(store(tmp_path, (88.0, 91.0, 94.0)), TABLE, "chinet").verdict()
    assert "Not separable from seed noise" in verdict
    assert "**bf16's seeds spread 3.0x as wide** (Det. Rate % std 3.00 against 1.00)" in verdict
    assert "spread" not in parity(store(tmp_path / "b", (90.5, 91.0, 92.5)), TABLE, "chinet").verdict()


def test_a_rewrite_replaces_its_own_section_only(tmp_path):
    path = tmp_path / "parity.md"
    write_parity(parity(store(tmp_path / "a", (90.0, 91.0, 92.0), row="unet"), TABLE, "unet"), path)
    write_parity(parity(store(tmp_path / "b", (80.0, 81.0, 82.0)), TABLE, "chinet"), path)
    write_parity(parity(store(tmp_path / "c", (90.5, 91.0, 92.0)), TABLE, "chinet"), path)
    text = path.read_text()
    assert text.count("parity:t2/chinet:begin") == 1 and text.count("parity:t2/unet:begin") == 1
    assert "seed 0: 90.00 → 90.50" in text and "→ 80.00" not in text


def test_a_row_with_one_precision_only_is_one_error(tmp_path, capsys, monkeypatch):
    tracker = Tracker(sqlite_uri(tmp_path), str(tmp_path / "artifacts"))
    run = tracker.start(tracker.experiment_id("chinet_table2"), "c", {"kind": KIND_JOB, "row": "chinet"})
    tracker.set_tags(run, {"seed": "0", "scale": "cpu", "precision": "32-true", "config_hash": "x"})
    tracker.log_metrics(run, {"det_rate": 90.0})
    tracker.end(run, "FINISHED")
    monkeypatch.chdir(tmp_path)
    uri = f"logger.tracking_uri=sqlite:///{tmp_path / 'mlflow.db'}"
    assert report(["--parity", "experiment=chinet_table2", "row=chinet", uri]) == 1
    errors = [line for line in capsys.readouterr().err.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "parity of chinet_table2 row 'chinet' needs FINISHED runs in both 32-true" in errors[0]
    assert "32-true (1 seeds)" in errors[0] and not (tmp_path / "results").exists()
