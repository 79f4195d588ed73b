"""The paper path's check (ablate.capacity.check and its paper_* pieces, `python -m ablate.check_paper`): one
row per task family at the paper's architecture (full widths and depths, the paper's recipes) runs a training and a
test step on a small input, so that a broken paper config fails here; the estimates' arithmetic; a failing row is
reported and fails the command; the paper recipes' steps; the GPU trainers' precision and the paper scale's loader
workers."""

import json
from pathlib import Path

import pytest
import torch

from ablate import hardware
from ablate.capacity import check as paper_check
from ablate.capacity import estimates as paper_estimates
from ablate.capacity import measure as paper_measure
from ablate.capacity import rows as paper_rows
from ablate.config import compose
from ablate.tables import published

#: One row per family: SMoE on frozen ResNet-101 experts (instance), DGFN's two VGG-16 SSD trunks with GFUs
#: (detection), ChiNet (semantic), BiFNet with DST and CBF (road).
FAMILIES = {
    "instance": ("smoe_table1", "smoe_fpn"),
    "detection": ("dgfn_table2", "dgfn"),
    "semantic": ("chinet_table2", "chinet"),
    "road": ("bifnet_table4", "bifnet_dst_cbf"),
}
#: SMoE (Peng et al.), whose §4.3 gives its recipe.
SMOE_TEXT = Path(__file__).resolve().parents[2] / "shared" / "seeds" / "000_af90cf6c69eb2abf.txt"
#: A small input (height x width) that keeps every network's architecture (DGFN resizes to SSD300 whatever it gets).
SIZE = (64, 208)


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    return str(tmp_path_factory.mktemp("paper-data"))


@pytest.mark.parametrize("family", sorted(FAMILIES))
def test_a_paper_row_of_each_family_trains_and_tests_a_step(family, data_dir):
    table, row = FAMILIES[family]
    # one test pass, not one per test condition of the table (DGFN's 15: the conditions are not the architecture)
    overrides = ["task.eval_conditions=null"] if family == "detection" else []
    cfg = paper_rows.measured_config(table, row, overrides=overrides)
    assert cfg.scale.name == "paper" and cfg.scale.width == 1.0
    assert paper_rows.family(cfg) == family
    m = paper_measure.measure(cfg, paper_measure.sample_config(cfg, data_dir, SIZE), steps=100)
    assert m["input"] == list(SIZE)
    assert m["macs"] > 0 and m["activations"] > 0 and m["train_s"] > 0 and m["test_s"] > 0
    assert m["weights"] >= 4 * m["params"]
    # the trainable parameters without a gradient are the ones named unused
    assert m["grads"] <= 4 * m["trainable"] and (m["grads"] == 4 * m["trainable"]) == (not m["unused"]), m["unused"]
    if m["unused"]:  # DDP would stop at step 2 unless told to look for them
        for trainer in ("ddp_gpu", "ddp_cpu"):
            assert compose([f"trainer={trainer}"]).trainer.strategy.find_unused_parameters
    entry = paper_rows.recipe(cfg)
    assert paper_estimates.gpu_memory({**m}, entry["batch"]) > m["weights"] + m["grads"] + m["optimizer_state"]
    if family == "instance":  # SMoE §4.1: ResNet-101 experts, frozen in stage 2 (§4.3)
        assert cfg.model.backbone.depth == 101 and cfg.model.fpn_channels == 256
        assert m["trainable"] < m["params"] / 10 and m["params"] > 90e6
        # the experts run forward only: a step costs 3 x the trainable MACs + 1 x the frozen ones, not 3 x all
        assert entry["frozen"] and 0 < m["macs_frozen"] < m["macs"] and m["feature_bytes"] > 0
        frames = entry["steps"] * entry["batch"]
        hours = paper_estimates.row_hours({**entry, "key": "k"}, {"k": m})
        flops = 2 * (3 * (m["macs"] - m["macs_frozen"]) * frames + m["macs_frozen"] * frames) * entry["seeds"]
        sustained = paper_estimates.GPU.bf16_tflops * 1e12 * paper_estimates.UTILISATION
        # at 64 x 208 the features of the 5985 training and validation frames (3.2 GiB) fit an 80 GB GPU and the
        # cache's 8 GiB: the experts run once per frame, not every step (at 375 x 1242, 112 GiB, they do not)
        assert (
            paper_estimates.cache_share(m, entry) == 1
            and paper_estimates.frozen_frames(m, entry) == entry["fit_frames"]
        )
        assert paper_estimates.cache_share({**m, "feature_bytes": m["feature_bytes"] * 35}, entry) == 0
        assert paper_estimates.row_hours({**entry, "key": "k"}, {"k": {**m, "feature_bytes": 0}}) == pytest.approx(
            flops / sustained / 3600
        )
        assert hours < flops / sustained / 3600 < paper_estimates.gpu_hours(m["macs"], frames, entry["seeds"])
    else:
        assert not entry["frozen"] and m["macs_frozen"] == 0
    if family == "detection":  # two full-width VGG-16 SSD trunks
        assert m["params"] > 45e6
    if family == "semantic":
        assert cfg.scale.unet_widths == [64, 128, 256, 512, 1024]


def test_a_single_modal_row_trained_as_an_expert_counts_its_tables_seeds():
    (image,) = paper_rows.describe([("bifnet_table4", "bifnet_image")])
    (fused,) = paper_rows.describe([("bifnet_table4", "bifnet_dst_sum")])
    assert image["seeds"] == fused["seeds"] == 3  # scale=paper: the papers' three seeds, every row


def test_recipes_give_the_papers_steps():
    semantic = paper_rows.recipe(paper_rows.job_config("chinet_table2", "chinet"))
    assert (semantic["batch"], semantic["train_frames"], semantic["steps"]) == (5, 4489, 50 * 898)
    detection = paper_rows.recipe(paper_rows.job_config("dgfn_table1", "dgfn"))
    assert (detection["batch"], detection["steps"], detection["optimizer"]) == (2, 240000, "SGD")
    road = paper_rows.recipe(paper_rows.job_config("bifnet_table4", "bifnet_dst_cbf"))
    assert (road["steps"], road["expert_steps"], road["optimizer"]) == (30000, 30000, "Adam")


def test_gpu_hours_are_macs_times_six_flops_a_frame_over_the_sustained_peak():
    gpu = paper_estimates.Gpu("test", bf16_tflops=100.0, memory_gib=80, source="test")
    # 1e12 MACs x 2 x 3 x 1000 frames x 2 seeds = 1.2e16 FLOPs at 40 TFLOPs sustained = 300 s
    assert paper_estimates.gpu_hours(10**12, 1000, 2, gpu) == pytest.approx(300 / 3600)
    # frozen MACs run forward only: (3 x 0.4e12 + 1 x 0.6e12) x 2 x 1000 x 2 = 7.2e15 FLOPs = 180 s
    assert paper_estimates.gpu_hours(10**12, 1000, 2, gpu, frozen=6 * 10**11) == pytest.approx(180 / 3600)
    # where a feature cache holds their features, the experts run once per training and validation frame
    assert paper_estimates.gpu_hours(10**12, 1000, 2, gpu, frozen=6 * 10**11, frozen_frames=100) == pytest.approx(
        (3 * 4e11 * 1000 + 6e11 * 100) * 2 * 2 / 40e12 / 3600
    )
    m = {"weights": 4, "grads": 4, "optimizer_state": 8, "activations": 100}
    assert (
        paper_estimates.gpu_memory(m, 5)
        == 16 + 100 * 5 * paper_estimates.BF16_ACTIVATIONS + paper_estimates.CUDA_OVERHEAD
    )


def test_a_failing_row_is_reported_with_its_error_and_the_command_fails(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(published, "RESULTS", tmp_path)
    monkeypatch.setattr(paper_rows, "experiments", lambda: ["chinet_table3"])
    figures = {
        "params": 10,
        "trainable": 10,
        "macs": 10**9,
        "forward_s": 1.0,
        "train_s": 2.0,
        "test_s": 1.0,
        "data_s": 0.1,
        "activations": 2**20,
        "weights": 40,
        "grads": 40,
        "optimizer_state": 80,
        "input": [375, 1242],
        "peak_rss": 2**30,
    }

    def fake(spec, data_dir, overrides=()):
        if spec[1] == "simo":
            raise RuntimeError("shapes [1, 64, 47, 156] and [1, 64, 46, 155] do not match")
        return figures

    monkeypatch.setattr(paper_check, "run_isolated", fake)
    assert paper_check.main([]) == 1
    out = capsys.readouterr().out
    assert "chinet_table3/simo" in out and "FAILED: RuntimeError: shapes" in out and "1 row(s) failed" in out
    md = (tmp_path / "paper_scale.md").read_text()
    assert "| simo | **FAILED**: RuntimeError: shapes" in md and "| chinet | 0.0 | 0.0 | 1.0 | — | 2.0 |" in md
    assert "No GPU was available" in md and "H100" in md and paper_check.cpu_name() in md
    stored = json.loads((tmp_path / "paper_scale.json").read_text())["measured"]
    assert sum("error" in m for m in stored.values()) == 1
    # a later run measures only what failed or is missing
    monkeypatch.setattr(paper_check, "run_isolated", lambda spec, data_dir, overrides=(): figures)
    assert paper_check.main(["row=simo"]) == 0
    assert "simo" in capsys.readouterr().out and "FAILED" not in (tmp_path / "paper_scale.md").read_text()


def test_a_budget_leaves_rows_for_a_later_run(tmp_path, monkeypatch):
    monkeypatch.setattr(published, "RESULTS", tmp_path)
    monkeypatch.setattr(paper_rows, "experiments", lambda: ["chinet_table3"])
    monkeypatch.setattr(paper_check, "run_isolated", lambda *a, **k: pytest.fail("over the budget"))
    assert paper_check.main(["budget_min=-1"]) == 0
    assert "not run here: the check's time budget" in (tmp_path / "paper_scale.md").read_text()


def test_gpu_measurements_stand_beside_the_estimates_with_their_ratio_and_divergence(tmp_path, monkeypatch):
    monkeypatch.setattr(published, "RESULTS", tmp_path)
    monkeypatch.setattr(paper_rows, "experiments", lambda: ["chinet_table3"])
    monkeypatch.setattr(paper_check, "run_isolated", lambda *a, **k: pytest.fail("over the budget"))
    gpu = [
        {
            "row": "chinet_table2:chinet",
            "precision": "bf16",
            "device": "NVIDIA H200",
            "torch": "2.11",
            "batch": 5,
            "distinct_frames": 5,
            "step_s": 0.2,
            "estimated_step_s": 0.05,
            "peak_allocated_gib": 21.9,
            "estimated_mem_gib": 17.8,
            "loss_first": 1.3,
            "loss_last": 0.3,
            "overrides": [],
        },
        {
            "row": "smoe_table1:smoe_rgb",
            "precision": "fp32",
            "device": "NVIDIA H200",
            "batch": 8,
            "step_s": None,
            "loss_first": 46.0,
            "loss_last": 1.3e7,
            "overrides": [],
            "deterministic": True,
            "diverged": "step 3: loss 1.3e+07 from 46 (first large output: conv1)",
        },
    ]
    (tmp_path / "paper_scale_gpu.json").write_text(json.dumps(gpu))
    sweep = {"kind": "row", "command": "python -m ablate row=chinet scale=paper trainer=gpu", "gpu": "NVIDIA H200"}
    sweep |= {"date": "2026-11-28", "steps": 300, "steps_per_epoch": 36, "step_s": 0.278, "test_s": 95.0}
    sweep |= {"metrics": {"det_rate": 94.24}, "gpu_training": {}, "gpu_test": {}}
    (tmp_path / "paper_scale_sweeps.json").write_text(json.dumps([sweep]))
    assert paper_check.main(["budget_min=-1"]) == 0
    md = (tmp_path / "paper_scale.md").read_text()
    assert "**Whole commands were run on a GPU**" in md and md.rstrip().endswith("Test metrics: det_rate 94.24.")
    assert "`python -m ablate row=chinet scale=paper trainer=gpu`" in md and "0.278 s a step" in md
    assert "No GPU was available" not in md and "## Measured on a GPU" in md and "NVIDIA H200 (torch 2.11" in md
    assert (
        "| chinet_table2:chinet | bf16 | — | 5 | 5 | 0.200 | 0.050 | 4.0x | 21.9 | 17.8 | 1.3 -> 0.3 | trains |" in md
    )
    assert "| deterministic |" in md and "**diverged** at step 3: loss 1.3e+07 from 46 |" in md
    assert "a measured step takes 4.0x to 4.0x the estimated one" in md
    assert "- smoe_table1:smoe_rgb (fp32): step 3: loss 1.3e+07 from 46 (first large output: conv1)" in md


@pytest.mark.parametrize("name", ["paper_scale.json", "paper_scale_gpu.json"])
def test_a_truncated_figures_file_is_one_error_naming_it(name, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(published, "RESULTS", tmp_path)
    monkeypatch.setattr(paper_check, "run_isolated", lambda *a, **k: pytest.fail("nothing runs"))
    (tmp_path / name).write_text('{"measured": {"a": ')
    assert paper_check.main(["reuse=true"]) == 2
    out = capsys.readouterr().out
    assert out.startswith(f"error: {tmp_path / name} is not valid JSON") and "Traceback" not in out


@pytest.mark.parametrize("trainer", ["gpu", "ddp_gpu"])
def test_gpu_trainers_train_in_bf16_mixed(trainer):
    assert compose([f"trainer={trainer}", "scale=paper"]).trainer.precision == "bf16-mixed"


def test_paper_loaders_take_one_worker_a_core_up_to_eight():
    assert compose(["scale=paper"]).data.num_workers == min(8, hardware.cores())
    assert hardware.loader_workers(8) == min(8, hardware.cores()) and hardware.loader_workers(1) == 1


def test_paper_loaders_pin_memory_where_cuda_reads_them(tmp_path, monkeypatch):
    from hydra.utils import instantiate

    cfg = paper_measure.sample_config(
        compose(["experiment=chinet_table2", "row=unet", "scale=paper"]), str(tmp_path), SIZE
    )
    datamodule = instantiate(cfg.data)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert datamodule.train_dataloader().pin_memory
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert not datamodule.test_dataloader().pin_memory


def test_table_hours_count_the_frozen_experts_forward_and_each_expert_once_per_steps(monkeypatch):
    entries = paper_rows.describe(paper_rows.plan(["smoe_table1_followup"]))
    by_row = {e["row"]: e for e in entries}
    expert_key, fused_key = by_row["smoe_rgb"]["key"], by_row["smoe_fpn"]["key"]
    assert by_row["smoe_fpn"]["frozen"] and not by_row["smoe_fpn_finetuned"]["frozen"]
    m = {"macs": 10**11, "weights": 4 * 10**8, "feature_bytes": 0}
    measured = {k: m for e in entries for k in (e["key"], *e["experts"].values())}
    measured[fused_key] = {**m, "macs": 2 * 10**11, "macs_frozen": 15 * 10**10}
    fpn = by_row["smoe_fpn"]
    frames = fpn["steps"] * fpn["batch"]
    assert paper_estimates.row_hours(fpn, measured) == pytest.approx(
        paper_estimates.gpu_hours(5 * 10**10, frames, 3) + paper_estimates.gpu_hours(15 * 10**10, frames, 3) / 3
    )
    # a row on frozen experts whose frozen MACs are not counted is not counted at all
    assert paper_estimates.row_hours(fpn, {**measured, fused_key: {**m, "macs": 2 * 10**11}}) is None
    # the experts of the fused rows are the single-modal rows (recipe's and twice the epochs): not counted again
    total, missing = paper_estimates.table_hours(entries, measured)
    assert not missing and total == pytest.approx(sum(paper_estimates.row_hours(e, measured) for e in entries))
    # in a table without its single-modal rows, each expert is counted once per number of steps it trains
    fused = [by_row[r] for r in ("smoe_fpn", "smoe_fpn_long", "smoe_fpn_finetuned")]
    total, _ = paper_estimates.table_hours(fused, measured)
    experts = sum(
        paper_estimates.gpu_hours(10**11, steps * fpn["batch"], 3) for steps in {e["expert_steps"] for e in fused}
    )
    assert len({e["expert_steps"] for e in fused}) == 2 and expert_key in fpn["experts"].values()
    assert total == pytest.approx(sum(paper_estimates.row_hours(e, measured) for e in fused) + 2 * experts)


def test_frozen_macs_are_the_frozen_parts_off_the_gradient_path():
    from torch import nn

    model = nn.Sequential(nn.Linear(8, 8), nn.Linear(8, 8), nn.Linear(8, 8))
    for i in (0, 2):
        model[i].requires_grad_(False)
    assert paper_measure.frozen_parts(model) == [model[0], model[2]]
    with paper_measure.FrozenMacs(model) as frozen:
        model(torch.zeros(2, 8))
    # the first layer's input needs no gradient: forward only; the last one's does: backward runs through it
    assert frozen.macs == 2 * 8 * 8


def test_smoes_paper_recipe_trains_both_stages_80k_steps_at_batch_8():
    """SMoE §4.3: "We train the networks for 80k iterations with a batch size of 8 ... poly learning rate" (eq. 6,
    i the iteration): the experts (stage 1) and the fusion network on them (stage 2) alike."""
    import lightning as L

    from ablate.jobs.experts import expert_config, needed

    if SMOE_TEXT.is_file():
        assert "80k iterations with a batch size of 8" in SMOE_TEXT.read_text(encoding="utf-8")
    for table in ("smoe_table1", "smoe_table2"):
        for row in paper_rows.table_rows(table):
            cfg = paper_rows.job_config(table, row)
            got = paper_rows.recipe(cfg)
            assert (got["batch"], got["steps"], got["expert_steps"], got["optimizer"]) == (8, 80000, 80000, "SGD")
            assert (cfg.trainer.max_epochs, cfg.trainer.max_steps) == (-1, 80000), row
            for modality in needed(cfg):
                assert expert_config(cfg, modality).trainer.max_steps == 80000
    # the poly schedule's i_max is the trainer's steps (ablate.tasks.base.FusionTask.configure_optimizers), stepped
    # per iteration: 80k, not the epochs' batches
    trainer = L.Trainer(max_epochs=cfg.trainer.max_epochs, max_steps=cfg.trainer.max_steps, logger=False)
    assert trainer.estimated_stepping_batches == 80000
    assert cfg.task.scheduler._target_ == "ablate.tasks.base.poly_lr" and cfg.task.scheduler.power == 0.9


def test_long_rows_train_twice_the_recipes_steps_at_every_scale():
    from omegaconf import OmegaConf

    from ablate.jobs.experts import expert_config
    from ablate.store import config_hash

    def cfg(row, scale):
        return compose(["experiment=smoe_table1_followup", f"row={row}", f"scale={scale}"])

    for scale in ("smoke", "cpu", "paper"):
        long, base = cfg("smoe_fpn_long", scale), cfg("smoe_fpn", scale)
        # in optimiser steps, of both stages: the epochs' at smoke and cpu, max_steps at paper
        steps = [paper_rows.recipe(c) for c in (long, base)]
        assert steps[0]["steps"] == 2 * steps[1]["steps"] and steps[0]["expert_steps"] == 2 * steps[1]["expert_steps"]
        for single in ("smoe_rgb", "smoe_ddm"):
            modality = cfg(single, scale).stage.modality
            experts = [expert_config(c, modality) for c in (cfg(f"{single}_long", scale), long, base)]
            trained = [paper_rows.recipe(e)["steps"] for e in experts]
            assert trained[0] == trained[1] == 2 * trained[2]
            # the long fused row stands on the long single-modal rows' experts: trained once
            assert config_hash(experts[0]) == config_hash(experts[1])
    # at the paper's recipe: twice SMoE §4.3's 80k steps at batch 8, each stage
    paper = paper_rows.recipe(paper_rows.job_config("smoe_table1_followup", "smoe_fpn_long"))
    assert (paper["steps"], paper["expert_steps"], paper["batch"]) == (160000, 160000, 8)
    # at the cpu scale the jobs are those of before the epochs followed the scale: the resolved config is the base
    # row's with the epochs alone changed (experts 20, stage 2 8), so its config hash and its experts' are kept
    for row, base, epochs in (
        ("smoe_fpn_long", "smoe_fpn", (8, 20)),
        ("smoe_rgb_long", "smoe_rgb", (4, 20)),
        ("smoe_ddm_long", "smoe_ddm", (4, 20)),
    ):
        got, want = (OmegaConf.to_container(cfg(r, "cpu"), resolve=True) for r in (row, base))
        want["trainer"]["max_epochs"], want["experts"]["max_epochs"] = epochs
        got.pop("table"), want.pop("table")
        assert got == want


def test_reuse_counts_only_the_missing_frozen_macs_and_keeps_the_steps(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(published, "RESULTS", tmp_path)
    monkeypatch.setattr(paper_rows, "experiments", lambda: ["smoe_table2"])
    monkeypatch.setattr(paper_check, "run_isolated", lambda *a, **k: pytest.fail("reuse=true times no step"))
    entries = paper_rows.describe(paper_rows.plan())
    figures = {
        "params": 10**8,
        "trainable": 10**7,
        "macs": 2 * 10**11,
        "train_s": 20.0,
        "test_s": 5.0,
        "activations": 2**28,
        "weights": 4 * 10**8,
        "grads": 4 * 10**7,
        "optimizer_state": 4 * 10**7,
        "peak_rss": 2**32,
        "where": "elsewhere",
        "cpu": "Another CPU (2 cores, avx2)",
    }
    stored = {k: dict(figures) for e in entries for k in (e["key"], *e["experts"].values())}
    stale = {"model": "a config no row has today"}
    (tmp_path / "paper_scale.json").write_text(json.dumps({"measured": {**stored, json.dumps(stale): figures}}))
    counted = []

    def count(spec, data_dir, overrides=()):
        counted.append(spec[1])
        return {"macs": 2 * 10**11, "macs_frozen": 15 * 10**10, "feature_bytes": 20 * 2**20}

    monkeypatch.setattr(paper_check, "count_isolated", count)
    assert paper_check.main(["reuse=true"]) == 0
    assert sorted(counted) == ["smoe_backbone", "smoe_fpn", "smoe_late"]  # the rows on frozen experts, once each
    md = (tmp_path / "paper_scale.md").read_text()
    assert "one training and one test step each on Another CPU (2 cores, avx2): not the CPU" in md
    assert f"counted afterwards on {paper_check.cpu_name()}" in md and "| 150.0 | 20.0 |" in md
    assert "smoe_late, smoe_backbone, smoe_fpn: 20.0 MiB a frame, 117 GiB against" in md and "off, the experts" in md
    # stored: the step's figures as they were, the count beside them; a second run counts nothing
    again = json.loads((tmp_path / "paper_scale.json").read_text())["measured"]
    fpn = again[next(e["key"] for e in entries if e["row"] == "smoe_fpn")]
    assert fpn["train_s"] == 20.0 and fpn["cpu"] == figures["cpu"] and fpn["macs_frozen"] == 15 * 10**10
    assert again[json.dumps(stale)] == figures  # a measurement of another config is kept, not lost
    monkeypatch.setattr(paper_check, "count_isolated", lambda *a, **k: pytest.fail("counted twice"))
    assert paper_check.main(["reuse=true"]) == 0


def test_a_count_that_fails_is_its_rows_error_and_the_other_rows_are_counted(monkeypatch):
    # each count runs in a process of its own: whatever it raises (the model's, the data's) is that row's result
    entries = [
        {"frozen": True, "key": k, "spec": ("smoe_table1", row, None)} for k, row in (("a", "fpn"), ("b", "late"))
    ]
    measured = {k: {"where": f"smoe_table1/{k}", "macs": 10} for k in ("a", "b")}

    def count(spec, data_dir, overrides=()):
        if spec[1] == "fpn":
            raise KeyError("conv9")
        return {"macs": 10, "macs_frozen": 4, "feature_bytes": 2**20}

    monkeypatch.setattr(paper_check, "count_isolated", count)
    out = paper_check.recount(entries, measured, echo=lambda _: None)
    assert out["a"]["count_error"] == "KeyError: 'conv9'" and "macs_frozen" not in out["a"]
    assert out["b"]["macs_frozen"] == 4 and "count_error" not in out["b"]
