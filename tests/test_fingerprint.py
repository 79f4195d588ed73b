"""A job's fingerprint (ablate.jobs.fingerprint) and the provenance footer that judges runs by it: a rename or a move
keeps every number, a changed loss or data pipeline changes the component it is in, and runs without a
fingerprint fall back to the file check."""

import os
import subprocess
import sys
import tempfile
from pathlib import Path

import pandas as pd
import pytest

import ablate.data.datamodule
import ablate.data.kitti
import ablate.jobs.fingerprint
import ablate.tasks.semantic
from ablate.config import compose
from ablate.jobs.fingerprint import COMPONENTS, compute, decode, differs, encode
from ablate.store.fingerprint import kernel_family
from ablate.tables.provenance import ROOT, provenance


@pytest.fixture(scope="module")
def chinet():
    cfg = compose(["experiment=chinet_table2", "row=chinet"])
    return cfg, compute(cfg)


def test_the_fingerprint_is_numbers_per_component_and_repeats(chinet):
    cfg, fingerprint = chinet
    # every component but the training corruptions', which ChiNet does not train on
    assert list(fingerprint) == list(COMPONENTS[:-1]) and all(len(v) for v in fingerprint.values())
    assert differs(fingerprint, compute(cfg)) is None
    assert differs(fingerprint, decode(encode(fingerprint))) is None


def test_the_jobs_of_one_process_generate_the_frames_once_and_get_a_fresh_processs_numbers(chinet, monkeypatch):
    generated = []
    generate = ablate.data.datamodule.generate
    monkeypatch.setattr(ablate.data.datamodule, "generate", lambda *a, **k: generated.append(a) or generate(*a, **k))
    unet = compose(["experiment=chinet_table2", "row=unet"])
    shared = compute(unet)
    assert not generated  # the frames ChiNet's fingerprint generated in this process
    monkeypatch.setattr(ablate.jobs.fingerprint, "_SCRATCH", {})  # as a fresh process
    assert compute(unet) == shared and len(generated) == 1


def test_a_killed_processs_frames_are_removed_by_the_next_process(monkeypatch):
    gone = subprocess.Popen(["true"])
    gone.wait()
    orphan = Path(tempfile.mkdtemp(prefix=f"{ablate.jobs.fingerprint.SCRATCH_PREFIX}{gone.pid}-"))
    monkeypatch.setattr(ablate.jobs.fingerprint, "_SCRATCH", {})  # as a fresh process
    mine = ablate.jobs.fingerprint.scratch()
    assert not orphan.exists() and mine.is_dir() and mine.name.startswith(f"ablate-fingerprint-{os.getpid()}-")


def test_a_rename_or_a_move_keeps_every_number(chinet, tmp_path, monkeypatch):
    """The task module copied to another package under another name, and the config pointed at it."""
    cfg, fingerprint = chinet
    source = (ROOT / "ablate" / "tasks" / "semantic.py").read_text()
    (tmp_path / "moved_tasks").mkdir()
    (tmp_path / "moved_tasks" / "__init__.py").write_text("")
    (tmp_path / "moved_tasks" / "segmentation.py").write_text(source)
    monkeypatch.syspath_prepend(str(tmp_path))
    moved = cfg.copy()
    moved.task._target_ = "moved_tasks.segmentation." + cfg.task._target_.rsplit(".", 1)[1]
    assert differs(fingerprint, compute(moved)) is None
    sys.modules.pop("moved_tasks.segmentation", None)


def test_a_changed_constant_in_the_loss_is_named(chinet, monkeypatch):
    cfg, fingerprint = chinet
    loss = ablate.tasks.semantic.SemanticTask.loss
    monkeypatch.setattr(ablate.tasks.semantic.SemanticTask, "loss", lambda self, o, b: 1.5 * loss(self, o, b))
    assert differs(fingerprint, compute(cfg)) == "loss"


def test_the_jobs_gradient_clipping_is_in_its_two_steps(chinet):
    cfg, fingerprint = chinet
    clipped = compose(["experiment=chinet_table2", "row=chinet", "++trainer.gradient_clip_val=1e-6"])
    assert differs(fingerprint, compute(clipped)) == "loss"  # Adam's steps shrink once gradients are below its eps


def test_a_changed_constant_in_the_data_pipeline_is_named(chinet, monkeypatch):
    cfg, fingerprint = chinet
    read = ablate.data.kitti.read_image
    monkeypatch.setattr(ablate.data.kitti, "read_image", lambda path: (read(path) * 0.9).astype("uint8"))
    assert differs(fingerprint, compute(cfg)) == "data"


def test_within_the_tolerance_is_the_same_and_beyond_it_is_not():
    a = {"data": [1.0, 2.0], "model": [3.0], "loss": [0.5], "schedule": [0.1], "metric": [0.0]}
    assert differs(a, {**a, "model": [3.0 * (1 + 2e-5)]}) is None
    assert differs(a, {**a, "model": [3.0 * (1 + 1e-3)]}) == "model"
    assert differs(a, {**a, "metric": [1e-3]}) == "metric"
    # a component one side lacks is no rounding: it differs on any kernels
    assert differs(a, {**a, "corruptions": [1.0]}, across_kernels=True) == "corruptions"
    assert differs({**a, "loss": [0.5, 0.1]}, a, across_kernels=True) == "loss"


OLD = "8edd5de63f9cb74394c0f2c4dea5b28b3c903f21"  # before the top of ablate became store/tables/run


def runs(fingerprint: str, commit: str = OLD) -> pd.DataFrame:
    return pd.DataFrame(
        [
            {
                "row": "chinet",
                "seed": "0",
                "run_id": "r0",
                "git_commit": commit,
                "targets": "ablate.tasks.semantic.SemanticTask",
                "evaluator": "",
                "fingerprint": fingerprint,
            }
        ]
    )


def test_a_run_without_a_fingerprint_falls_back_to_the_file_check():
    lines = provenance(runs(""), recompute=lambda cfg: {}, config=lambda run_id: None)
    assert any(line.startswith("**Code changed since 8edd5de63f9c**") for line in lines)


def test_a_matching_fingerprint_flags_nothing_and_a_differing_one_names_its_component(chinet):
    _, fingerprint = chinet
    same = provenance(runs(encode(fingerprint)), recompute=lambda cfg: fingerprint, config=lambda run_id: None)
    assert same == [
        "Runs made at commit 8edd5de63f9c (1 runs); the code they build changed since, and the "
        "fingerprints of all 1 rows still match."
    ]
    mixed = pd.concat([runs(encode(fingerprint)), runs(encode(fingerprint), OLD + "-dirty")], ignore_index=True)
    both = provenance(mixed, recompute=lambda cfg: fingerprint, config=lambda run_id: None)
    assert both[0].endswith("the fingerprints of all 1 rows still match.") and both[1].startswith("**Mixed commits**")
    moved = {**fingerprint, "loss": [v * 2 for v in fingerprint["loss"]]}
    flagged = provenance(runs(encode(fingerprint)), recompute=lambda cfg: moved, config=lambda run_id: None)
    assert any("**Numbers may have moved** for row chinet" in line and "loss differs" in line for line in flagged)


def test_a_run_from_a_wheel_says_its_commit_is_unknown():
    lines = provenance(runs("", commit="unknown"))
    assert any("unknown commit (not a git checkout)" in line for line in lines)


def test_a_tuned_rows_recorded_fingerprint_recomputes_equal_from_its_records():
    # the report recomputes a recorded run's fingerprint on the config its row was tuned to (ChiNet Table II's U-Net:
    # lr 0.00087 and a weight decay), not on the recipe's, which would flag every tuned row once its code changed
    from ablate.analysis.reproduce import recorded_config

    runs = pd.read_csv(ROOT / "results" / "runs" / "chinet_table2.csv")
    unet = runs[(runs["row"] == "unet") & (runs["seed"] == 0)].iloc[0]
    cfg = recorded_config(runs, ["experiment=chinet_table2"])(unet["run_id"])
    assert cfg.task.optimizer.lr == pytest.approx(0.0008727)
    assert differs(decode(unet["fingerprint"]), compute(cfg)) is None


def test_across_instruction_sets_rounding_is_not_a_change_but_a_changed_model_still_is(chinet):
    # measured across AVX-512, AVX2 and SSE kernels: the loss after two steps moves up to 9 %, the model's
    # outputs within 3e-4 (ablate.store.fingerprint.ACROSS)
    _, fingerprint = chinet
    rounded = {**fingerprint, "loss": [v * 1.05 for v in fingerprint["loss"]], "metric": fingerprint["metric"]}
    rounded["model"] = [v * (1 + 3e-4) for v in fingerprint["model"]]
    assert differs(fingerprint, rounded) == "model"  # like with like: flagged
    assert differs(fingerprint, rounded, across_kernels=True) is None
    changed = {**fingerprint, "model": [v * 1.01 for v in fingerprint["model"]]}
    assert differs(fingerprint, changed, across_kernels=True) == "model"
    assert differs(fingerprint, {**fingerprint, "data": [v + 1 for v in fingerprint["data"]]}, True) == "data"


def test_a_run_recorded_on_avx512_is_compared_across_kernels_where_today_runs_others(chinet, monkeypatch):
    _, fingerprint = chinet
    one = runs(encode(fingerprint)).assign(cpu_isa="avx2 avx512f avx512_bf16")
    moved = {**fingerprint, "loss": [v * 1.05 for v in fingerprint["loss"]]}
    monkeypatch.setattr("ablate.hardware.kernels", lambda: "AVX2; oneDNN AVX2")
    lines = provenance(one, recompute=lambda cfg: moved, config=lambda run_id: None)
    assert not any("Numbers may have moved" in line for line in lines) and lines[0].endswith("rows still match.")
    monkeypatch.setattr("ablate.hardware.kernels", lambda: "AVX512")
    lines = provenance(one, recompute=lambda cfg: moved, config=lambda run_id: None)
    assert any("**Numbers may have moved** for row chinet" in line and "loss differs" in line for line in lines)


def test_the_same_instruction_set_on_another_cpu_is_other_kernels_and_the_same_cpu_is_not(chinet, monkeypatch):
    # ATen's AVX-512 kernels on an Intel Xeon model 106 and on the AMD EPYC model 17 of the records: oneDNN and the
    # BLAS block and dispatch by the CPU, and BiFNet's image row's loss moved 6.7e-4 there (ablate.store.fingerprint)
    from ablate.hardware import Cpu

    _, fingerprint = chinet
    one = runs(encode(fingerprint)).assign(
        cpu_isa="avx2 avx512f avx512_bf16", cpu_kernels="AVX512", made_cpu="AMD EPYC (family 25, model 17)"
    )
    moved = {**fingerprint, "loss": [v * (1 + 7e-4) for v in fingerprint["loss"]]}
    monkeypatch.setattr("ablate.hardware.kernels", lambda: "AVX512")
    for chip, flagged in (("Intel(R) Xeon(R) Processor @ 2.80GHz (family 6, model 106)", False),
                          ("AMD EPYC 9R14 (family 25, model 17)", True)):  # fmt: skip
        monkeypatch.setattr("ablate.hardware.cpu", lambda chip=chip: Cpu(chip, frozenset({"avx2", "avx512f"})))
        lines = provenance(one, recompute=lambda cfg: moved, config=lambda run_id: None)
        assert any("Numbers may have moved" in line and "loss differs" in line for line in lines) == flagged, chip
    changed = {**fingerprint, "model": [v * 1.01 for v in fingerprint["model"]]}  # on any CPU: a change
    lines = provenance(one, recompute=lambda cfg: changed, config=lambda run_id: None)
    assert any("**Numbers may have moved** for row chinet" in line and "model differs" in line for line in lines)
    assert kernel_family("AVX512", cpu="AMD EPYC (family 25, model 17)") == "AVX512 on AMD family 25 model 17"
    assert kernel_family("", "avx2", "AMD EPYC") == "AVX2"  # a name without its family and model: the ISA alone


def test_how_a_blanked_sensors_trunk_trains_is_in_the_fingerprint_and_an_older_record_is_flagged():
    # DGFN trains on a blanked sensor one update in ten; the two updates of the loss component draw none, so only
    # the corruption steps see that a blanked trunk now normalises with its running statistics
    cfg = compose(["experiment=dgfn_table1", "row=dgfn", "scale=smoke"])
    fingerprint = compute(cfg)
    before = compute(compose(["experiment=dgfn_table1", "row=dgfn", "scale=smoke", "model.blank_running_stats=false"]))
    assert differs(fingerprint, before) == "corruptions"
    older = {name: v for name, v in fingerprint.items() if name != "corruptions"}  # recorded before the component
    lines = provenance(runs(encode(older)), recompute=lambda cfg: fingerprint, config=lambda run_id: None)
    assert any(
        line.startswith("**Numbers may have moved** for row chinet")
        and "predates the corruptions component that today's code computes" in line
        for line in lines
    )


def test_the_report_computes_a_row_shared_by_tables_once_and_another_seed_again(monkeypatch):
    # ChiNet Tables II-V all hold the ChiNet row: its lowest seed is one config hash in each, one fingerprint
    import ablate.analysis.report as report

    calls = []
    monkeypatch.setattr(report, "_fingerprints", {})
    monkeypatch.setattr(ablate.jobs.fingerprint, "compute", lambda cfg: calls.append(cfg.seed) or {"data": [1.0]})
    shared = [compose([f"experiment={t}", "row=chinet", "seed=0"]) for t in ("chinet_table2", "chinet_table3")]
    got = [report.fingerprint(cfg) for cfg in shared]
    got[0]["data"].append(2.0)  # a caller changing what it got changes no other caller's
    assert report.fingerprint(shared[1]) == {"data": [1.0]} and calls == [0]
    report.fingerprint(compose(["experiment=chinet_table2", "row=chinet", "seed=1"]))
    assert calls == [0, 1]
