"""Figures of whole commands on a GPU: ``bench/gpu_sweeps.py`` reads them from a job's log and nvidia-smi's samples,
and ``results/paper_scale.md`` lists them (:func:`ablate.capacity.sweeps.sweeps_section`)."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

from ablate.capacity.sweeps import sweeps_section

BENCH = Path(__file__).resolve().parent.parent / "bench" / "gpu_sweeps.py"


def bench():
    spec = importlib.util.spec_from_file_location("gpu_sweeps", BENCH)
    assert spec and spec.loader
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_a_rows_step_time_test_time_and_gpu_figures_are_read_from_its_log_and_nvidia_smi(tmp_path: Path) -> None:
    log = tmp_path / "job.log"
    log.write_text(
        "[10:00:00][ablate.jobs.job] Numerics: precision bf16-mixed\n"
        "[10:00:20][ablate.jobs.progress_lines] epoch 1/50, step 10/40, loss 0.5, about 1 min left\n"
        "[10:00:30][ablate.jobs.progress_lines] epoch 2/50, step 20/40, loss 0.4, about 1 min left\n"  # warm-up above
        "[10:00:35][ablate.jobs.progress_lines] epoch 3/50, step 30/40, loss 0.3, about 0.1 min left\n"
        "[10:00:41][ablate.jobs.progress_lines] epoch 4/50, step 40/40, loss 0.2, about 0.0 min left\n"
        "[10:01:41][ablate.jobs.job] FINISHED chinet seed 0: det_rate=94.24, loss=0.1609\n"
    )
    smi = tmp_path / "smi.csv"
    lines = [
        f"2026/11/28 10:00:{s:02d}.100, {80 if s < 41 else 2} %, {20480 if s < 41 else 10240} MiB" for s in range(60)
    ]
    smi.write_text("\n".join(lines) + "\n")
    out = tmp_path / "sweeps.json"
    command = "python -m ablate experiment=chinet_table2 row=chinet scale=paper trainer=gpu"
    args = ["row", "--train-log", str(log), "--smi", str(smi), "--gpu", "NVIDIA H200", "--command", command]
    assert bench().main([*args, "--json", str(out)]) == 0
    (entry,) = json.loads(out.read_text())
    assert entry["steps"] == 40 and entry["steps_per_epoch"] == 10
    assert entry["step_s"] == 0.55  # the median of 0.5 and 0.6 s a step, the warm-up's 1 s left out
    assert entry["test_s"] == 60.0 and entry["metrics"] == {"det_rate": 94.24, "loss": 0.1609}
    assert entry["gpu_training"]["util_mean"] == 80 and entry["gpu_training"]["mem_max_gib"] == 20.0
    assert entry["gpu_test"]["util_max"] == 2 and entry["gpu_test"]["mem_max_gib"] == 10.0
    # the same command again replaces its entry
    assert bench().main([*args, "--json", str(out)]) == 0
    assert len(json.loads(out.read_text())) == 1
    section = "\n".join(sweeps_section(json.loads(out.read_text())))
    assert section.startswith("## Through `python -m ablate` on a GPU")
    assert "40 training steps, 10 an epoch: 0.550 s a step" in section and "Its test took 60 s" in section


def test_a_tables_verdicts_are_listed_beside_the_published_ones() -> None:
    entry = {
        "kind": "table", "table": "t2", "command": "python -m ablate -m experiment=t2 trainer=gpu",
        "gpu": "NVIDIA H200", "cpu": "Xeon", "precision": "bf16-mixed", "date": "2026-11-28", "jobs": 9,
        "at_a_time": 9, "job_s": [38.1, 26.5, 51.7], "wall_s": 59, "command_s": 204, "plan_job_s": None,
        "gpu_jobs": {}, "beside_published": [],
        "verdicts": {"A vs B": "different, of uncertain practical size (n = 3, Δ +0.93)", "A vs C": "undecided (n = 3)"},
        "published_verdicts": {"A vs B": "undecided (n = 5, Δ +1.09)", "A vs C": "undecided (n = 5)"},
    }  # fmt: skip
    section = sweeps_section([entry])
    assert "| A vs B | different, of uncertain practical size (n = 3, Δ +0.93) | undecided (n = 5, Δ +1.09) | no |" in (
        section
    )
    assert "| A vs C | undecided (n = 3) | undecided (n = 5) | yes |" in section
    assert sweeps_section([]) == []
