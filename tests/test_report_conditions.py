"""Tables whose rows are test conditions (DGFN Table I), and model tables with paper-only rows read under one
condition (DGFN Table II), from hand-made runs."""

import pytest
from omegaconf import OmegaConf

from ablate.store.tracker import KIND_JOB, Tracker
from ablate.tables import write_table
from tests.stores import sqlite_uri

CONDITIONS = [
    {
        "condition": "full",
        "name": "Full",
        "paper": {"gfu": {"car_easy": 90.0, "car_moderate": 80.0}, "base": {"car_easy": 85.0, "car_moderate": 75.0}},
    },
    {
        "condition": "normal",
        "name": "Normal",
        "paper": {"gfu": {"car_easy": 98.0, "car_moderate": 90.0}, "base": {"car_easy": 93.0, "car_moderate": 87.0}},
    },
    {
        "condition": "camera_blank",
        "name": "RGB blank",
        "paper": {"gfu": {"car_easy": 88.0, "car_moderate": 78.0}, "base": {"car_easy": 86.0, "car_moderate": 74.0}},
    },
    {"condition": "camera_noise", "name": "RGB noise"},
]
TABLE1 = OmegaConf.create(
    {
        "table": {
            "name": "t1",
            "title": "Table I",
            "layout": "conditions",
            "reference": "base",
            "primary": "car_moderate",
            "primary_condition": "full",
            "metrics": {"car_easy": "Easy", "car_moderate": "Moderate"},
            "rows": [{"row": "gfu", "name": "Proposed"}, {"row": "base", "name": "Baseline"}],
            "conditions": CONDITIONS,
            "also": [{"name": "t1_gates", "title": "Gates", "metrics": {"gate_rgb": "w_C"}}],
        },
        "task": {
            "eval_conditions": {"normal": {}, "camera_blank": {"camera": "blank"}, "camera_noise": {"camera": "noise"}}
        },
    }
)
#: per row: {condition: (car_easy, car_moderate)} for seeds 0 and 1 (seed 1: + 2), and the noise severities
OURS = {
    "gfu": {"full": (60, 50), "normal": (80, 70), "camera_blank": (40, 30), "camera_noise": (55, 45)},
    "base": {"full": (50, 40), "normal": (75, 66), "camera_blank": (20, 10), "camera_noise": (45, 35)},
}
CURVE = {"gfu": {"0.5": 60.0, "2": 20.0}, "base": {"0.5": 50.0, "2": 5.0}}


@pytest.fixture
def tracker(tmp_path):
    tracker = Tracker(sqlite_uri(tmp_path), str(tmp_path / "artifacts"))
    for table in ("t1", "t2"):
        exp = tracker.experiment_id(table)
        for row, values in OURS.items():
            for seed in (0, 1):
                run = tracker.start(
                    exp,
                    row,
                    {"kind": KIND_JOB, "row": row, "seed": str(seed), "scale": "smoke", "config_hash": f"{row}-{seed}"},
                )
                metrics = {
                    f"{c}/{m}": v[k] + 2 * seed
                    for c, v in values.items()
                    for k, m in enumerate(("car_easy", "car_moderate"))
                }
                metrics.update({f"camera_noise-s{s}/car_moderate": v + seed for s, v in CURVE[row].items()})
                metrics.update({f"{c}/gate_rgb": 0.5 if row == "gfu" else 1.0 for c in values})
                metrics["car_easy"] = -1.0  # a plain metric of the same name must not shadow the condition's
                tracker.log_metrics(run, metrics)
                tracker.end(run, "FINISHED")
    return tracker


def rows_of(text: str) -> list[list[str]]:
    """The cells of the first table in ``text`` (a rows table's main table), header first."""
    lines = [line for line in text.split("All metrics:")[0].splitlines() if line.startswith("|")]
    return [[cell.strip() for cell in line.strip("|").split("|")] for line in lines[:1] + lines[2:]]


def test_rows_are_conditions_columns_model_by_metric_with_the_paper_and_tau(tracker, tmp_path):
    paths = write_table(TABLE1, tracker, results_dir=tmp_path / "r")
    text = (tmp_path / "r" / "t1.md").read_text()
    table = rows_of(text.split("Per model")[0])
    header, body = table[0], table[1:]
    assert header[:4] == ["Test input", "Proposed: Easy (ours)", "Proposed: Easy (paper)", "Proposed: Moderate (ours)"]
    assert "Baseline: Moderate (paper)" in header
    assert [r[0] for r in body] == ["Full", "Normal", "RGB blank", "RGB noise", "Kendall τ vs paper (n)"]
    col = {name: [r[header.index(name)] for r in body] for name in header}
    assert col["Proposed: Easy (ours)"][:4] == [
        "**61.00 ± 1.41**",
        "**81.00 ± 1.41**",
        "**41.00 ± 1.41**",
        "**56.00 ± 1.41**",
    ]
    assert col["Baseline: Easy (ours)"][1] == "76.00 ± 1.41" and col["Baseline: Easy (paper)"][1] == "93.00"
    assert col["Proposed: Easy (paper)"][3] == "—"  # no paper number for noise here
    # ours orders Full, Normal, RGB blank as the paper does: tau 1 over the 3 conditions with both
    assert col["Proposed: Easy (ours)"][4] == "1.00 (3)" and col["Baseline: Moderate (ours)"][4] == "1.00 (3)"
    assert "Per model, on Moderate (Full):" in text and "Δ Moderate (Full) vs Baseline [95% CI]" in text
    assert "+10.00" in text  # Proposed - Baseline on Moderate (Full), paired over the two seeds
    assert "Latency (ms): not measured yet" in text
    assert sorted(p.name for p in paths) == ["t1.csv", "t1.md", "t1.png", "t1.tex", "t1_gates.md", "t1_robustness.png"]
    gates = rows_of((tmp_path / "r" / "t1_gates.md").read_text())
    assert gates[0] == ["Test input", "Proposed: w_C (ours)", "Baseline: w_C (ours)"]
    assert gates[1] == ["Full", "0.50 ± 0.00", "1.00 ± 0.00"] and len(gates) == 1 + 4  # no paper: no τ row
    again = write_table(TABLE1, tracker, results_dir=tmp_path / "r2")
    assert [p.read_bytes() for p in again] == [p.read_bytes() for p in paths]


def test_robustness_curves_run_from_the_normal_input_through_the_severities(tracker):
    from ablate.tables import collect, table_spec
    from ablate.tables.conditions import curves

    table = table_spec(TABLE1)
    data = curves(collect(tracker, "t1"), table, dict(TABLE1.task.eval_conditions))
    assert list(data) == ["camera_noise"]
    gfu = data["camera_noise"]["gfu"]
    assert sorted(gfu) == [0.0, 0.5, 1.0, 2.0]
    assert [gfu[s].mean() for s in sorted(gfu)] == [71.0, 60.5, 46.0, 20.5]


def test_a_conditions_table_names_its_missing_pieces(tracker, tmp_path):
    bad = OmegaConf.merge(TABLE1, {"table": {"primary_condition": "fog"}})
    with pytest.raises(ValueError, match="table.primary_condition: 'fog' is not one of the table's conditions"):
        write_table(bad, tracker, results_dir=tmp_path)
    with pytest.raises(ValueError, match="table.layout: 'columns'"):
        write_table(OmegaConf.merge(TABLE1, {"table": {"layout": "columns"}}), tracker, results_dir=tmp_path)


TABLE2 = OmegaConf.create(
    {
        "table": {
            "name": "t2",
            "title": "Table II",
            "reference": "gfu",
            "primary": "car_moderate",
            "primary_condition": "normal",
            "metrics": {"car_easy": "Easy", "car_moderate": "Moderate"},
            "text_columns": {"data": "Data"},
            "rows": [
                {"row": "base", "name": "SSD", "data": "Mono", "paper": {"car_easy": 90.0, "car_moderate": 87.0}},
                {
                    "row": "3dop",
                    "name": "3DOP",
                    "data": "Stereo",
                    "paper_only": True,
                    "paper": {"car_easy": 94.0, "car_moderate": 89.0},
                },
                {"row": "ssd_dhi", "name": "SSD", "data": "Lidar", "paper": {"car_easy": 89.0, "car_moderate": 77.0}},
                {"row": "gfu", "name": "DGFN", "data": "Lidar+Mono", "paper": {"car_easy": 98.0, "car_moderate": 90.0}},
            ],
        }
    }
)


def test_a_model_table_reads_one_condition_and_lists_paper_only_rows(tracker, tmp_path):
    md, *_ = write_table(TABLE2, tracker, results_dir=tmp_path)
    text = md.read_text()
    table = rows_of(text)
    header, body = table[0], table[1:]
    # the main table: the primary difficulty only; Easy goes below, under "All metrics"
    assert header[:4] == ["Row", "Data", "Moderate (ours)", "Moderate (paper)"] and len(header) <= 10
    assert [(r[0], r[1]) for r in body] == [("SSD", "Mono"), ("3DOP", "Stereo"), ("DGFN", "Lidar+Mono")]
    assert body[1][2] == "—" and body[1][3] == "89.00" and body[1][-1] == "paper only"
    rest = [
        [c.strip() for c in line.strip("|").split("|")]
        for line in text.split("All metrics:")[1].splitlines()
        if line.startswith("| ")
    ]
    assert rest[0][:3] == ["Row", "Easy (ours)", "Easy (paper)"]
    assert rest[1][1] == "76.00 ± 1.41" and rest[3][1] == "**81.00 ± 1.41**"  # the "normal" condition's values
    assert "Rows without a finished run: SSD." in text  # ssd_dhi; 3DOP is the paper's only
    assert "1.00 over 2 rows" in text
