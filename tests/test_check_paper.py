"""The paper path's check (ablate.run.paper_check, `python -m ablate.check_paper`): one row per task family at the
paper's architecture (full widths and depths, the paper's recipes) runs a training and a test step on a small input,
so that a broken paper config fails here; the estimates' arithmetic; a failing row is reported and fails the
command; the GPU trainers' precision and the paper scale's loader workers."""

import json

import pytest
import torch

from ablate import hardware
from ablate.config import compose
from ablate.run import paper_check

#: One row per family: SMoE on frozen ResNet-101 experts (instance), DGFN's two VGG-16 SSD trunks with GFUs
#: (detection), ChiNet (semantic), BiFNet with DST and CBF (road).
FAMILIES = {
    "instance": ("smoe_table1", "smoe_fpn"),
    "detection": ("dgfn_table2", "dgfn"),
    "semantic": ("chinet_table2", "chinet"),
    "road": ("bifnet_table4", "bifnet_dst_cbf"),
}
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
    cfg = paper_check.measured_config(table, row, overrides=overrides)
    assert cfg.scale.name == "paper" and cfg.scale.width == 1.0
    assert paper_check.family(cfg) == family
    m = paper_check.measure(cfg, paper_check.sample_config(cfg, data_dir, SIZE), steps=100)
    assert m["input"] == list(SIZE)
    assert m["macs"] > 0 and m["activations"] > 0 and m["train_s"] > 0 and m["test_s"] > 0
    assert m["weights"] >= 4 * m["params"]
    # the trainable parameters without a gradient are the ones named unused
    assert m["grads"] <= 4 * m["trainable"] and (m["grads"] == 4 * m["trainable"]) == (not m["unused"]), m["unused"]
    if m["unused"]:  # DDP would stop at step 2 unless told to look for them
        for trainer in ("ddp_gpu", "ddp_cpu"):
            assert compose([f"trainer={trainer}"]).trainer.strategy.find_unused_parameters
    entry = paper_check.recipe(cfg)
    assert paper_check.gpu_memory({**m}, entry["batch"]) > m["weights"] + m["grads"] + m["optimizer_state"]
    if family == "instance":  # SMoE §4.1: ResNet-101 experts, frozen in stage 2 (§4.3)
        assert cfg.model.backbone.depth == 101 and cfg.model.fpn_channels == 256
        assert m["trainable"] < m["params"] / 10 and m["params"] > 90e6
    if family == "detection":  # two full-width VGG-16 SSD trunks
        assert m["params"] > 45e6
    if family == "semantic":
        assert cfg.scale.unet_widths == [64, 128, 256, 512, 1024]


def test_recipes_give_the_papers_steps():
    semantic = paper_check.recipe(paper_check.job_config("chinet_table2", "chinet"))
    assert (semantic["batch"], semantic["train_frames"], semantic["steps"]) == (5, 4489, 50 * 898)
    detection = paper_check.recipe(paper_check.job_config("dgfn_table1", "dgfn"))
    assert (detection["batch"], detection["steps"], detection["optimizer"]) == (2, 240000, "SGD")
    road = paper_check.recipe(paper_check.job_config("bifnet_table4", "bifnet_dst_cbf"))
    assert (road["steps"], road["expert_steps"], road["optimizer"]) == (30000, 30000, "Adam")


def test_gpu_hours_are_macs_times_six_flops_a_frame_over_the_sustained_peak():
    gpu = paper_check.Gpu("test", bf16_tflops=100.0, memory_gib=80, source="test")
    # 1e12 MACs x 2 x 3 x 1000 frames x 2 seeds = 1.2e16 FLOPs at 40 TFLOPs sustained = 300 s
    assert paper_check.gpu_hours(10**12, 1000, 2, gpu) == pytest.approx(300 / 3600)
    m = {"weights": 4, "grads": 4, "optimizer_state": 8, "activations": 100}
    assert paper_check.gpu_memory(m, 5) == 16 + 100 * 5 * paper_check.BF16_ACTIVATIONS + paper_check.CUDA_OVERHEAD


def test_a_failing_row_is_reported_with_its_error_and_the_command_fails(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(paper_check, "RESULTS", tmp_path)
    monkeypatch.setattr(paper_check, "experiments", lambda: ["chinet_table3"])
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
    assert "| simo | **FAILED**: RuntimeError: shapes" in md and "| chinet | 0.0 | 1.0 | 2.0 |" in md
    assert "No GPU was available" in md and "H100" in md
    stored = json.loads((tmp_path / "paper_scale.json").read_text())["measured"]
    assert sum("error" in m for m in stored.values()) == 1
    # a later run measures only what failed or is missing
    monkeypatch.setattr(paper_check, "run_isolated", lambda spec, data_dir, overrides=(): figures)
    assert paper_check.main(["row=simo"]) == 0
    assert "simo" in capsys.readouterr().out and "FAILED" not in (tmp_path / "paper_scale.md").read_text()


def test_a_budget_leaves_rows_for_a_later_run(tmp_path, monkeypatch):
    monkeypatch.setattr(paper_check, "RESULTS", tmp_path)
    monkeypatch.setattr(paper_check, "experiments", lambda: ["chinet_table3"])
    monkeypatch.setattr(paper_check, "run_isolated", lambda *a, **k: pytest.fail("over the budget"))
    assert paper_check.main(["budget_min=-1"]) == 0
    assert "not run here: the check's time budget" in (tmp_path / "paper_scale.md").read_text()


@pytest.mark.parametrize("trainer", ["gpu", "ddp_gpu"])
def test_gpu_trainers_train_in_bf16_mixed(trainer):
    assert compose([f"trainer={trainer}", "scale=paper"]).trainer.precision == "bf16-mixed"


def test_paper_loaders_take_one_worker_a_core_up_to_eight():
    assert compose(["scale=paper"]).data.num_workers == min(8, hardware.cores())
    assert hardware.loader_workers(8) == min(8, hardware.cores()) and hardware.loader_workers(1) == 1


def test_paper_loaders_pin_memory_where_cuda_reads_them(tmp_path, monkeypatch):
    from hydra.utils import instantiate

    cfg = paper_check.sample_config(
        compose(["experiment=chinet_table2", "row=unet", "scale=paper"]), str(tmp_path), SIZE
    )
    datamodule = instantiate(cfg.data)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert datamodule.train_dataloader().pin_memory
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert not datamodule.test_dataloader().pin_memory
