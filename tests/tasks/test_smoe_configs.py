"""SMoE Tables 1 and 2 as experiments: every row composes with Hydra, builds its model and trains a step;
the paper's numbers match the paper's text."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import OmegaConf

from ablate.tables.spec import sweep_params
from ablate.tasks.instance import InstanceTask

REPO = Path(__file__).resolve().parents[2]
CONF = REPO / "conf"
SMOE_TEXT = REPO.parent / "shared" / "seeds" / "000_af90cf6c69eb2abf.txt"
TABLES = ("smoe_table1", "smoe_table2")
# row -> (stage, fusion operator, single modality)
EXPECTED = {
    "smoe_rgb": ("single", "sum", "rgb"),
    "smoe_ddm": ("single", "sum", "ddm_jet"),
    "smoe_sum": ("fpn", "sum", None),
    "smoe_max": ("fpn", "max", None),
    "smoe_sharpen": ("fpn", "sharpen", None),
    "smoe_moe_sum": ("fpn", "moe_sum", None),
    "smoe_moe_max": ("fpn", "moe_max", None),
    "smoe_fpn": ("fpn", "smoe", None),
    "smoe_early": ("early", "smoe", None),
    "smoe_late": ("late", "smoe", None),
    "smoe_backbone": ("backbone", "smoe", None),
}


def table_rows(table: str) -> list[str]:
    return [r.row for r in OmegaConf.load(CONF / "experiment" / f"{table}.yaml").table.rows]


def compose_row(table: str, row: str, *extra: str):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose(
            "config", overrides=[f"experiment={table}", f"row={row}", "scale=smoke", *extra], return_hydra_config=False
        )


@pytest.mark.parametrize("table", TABLES)
def test_sweep_runs_the_table_rows_in_order(table):
    exp = OmegaConf.load(CONF / "experiment" / f"{table}.yaml")
    assert sweep_params({}, [], exp.table)["row"].split(",") == table_rows(table)  # the sweep, from the rows
    assert exp.table.primary == "map"
    assert {"map", "map_50", "map_75", "map_clear", "map_night", "map_rain", "map_glare"} <= set(exp.table.metrics)
    assert all((CONF / "row" / f"{r}.yaml").is_file() for r in table_rows(table))
    assert len(table_rows(table)) == {"smoe_table1": 8, "smoe_table2": 4}[table]


@pytest.mark.parametrize("table,row", [(t, r) for t in TABLES for r in table_rows(t)])
def test_every_row_composes_builds_its_model_and_trains_a_step(table, row):
    cfg = compose_row(table, row)
    stage, op, single = EXPECTED[row]
    assert (cfg.stage.name, cfg.fusion.name, cfg.stage.get("modality")) == (stage, op, single)
    assert cfg.data.conditions == ["clear", "night", "rain_day", "rain_night", "glare"]
    assert list(cfg.targets) == ["instances"] and cfg.task.monitor == "val/map"
    model = instantiate(cfg.model)
    assert model.stage == stage and model.single == single
    if stage != "single":  # the modalities themselves: test_experiment_has_only_the_smoe_modalities_and_metrics
        ops = model.fusion_modules()
        assert (not ops) if stage == "early" else {o.op_name for o in ops} == {op}
    task = instantiate(cfg.task, model=model)
    assert isinstance(task, InstanceTask) and task.groups == ["clear", "night", "rain", "glare"]
    batch = {m: torch.rand(1, c, 64, 64) for m, c in cfg.model.modalities.items()}
    mask = torch.zeros(1, 64, 64, dtype=torch.bool)
    mask[:, 16:48, 8:40] = True
    batch["instances"] = [{"masks": mask, "labels": torch.tensor([0]), "boxes": torch.tensor([[8.0, 16, 40, 48]])}]
    task.log = lambda *a, **k: None
    assert torch.isfinite(task.training_step(batch, 0))


def test_experiment_sets_its_table_and_two_stage_training():
    cfg = compose_row("smoe_table1", "smoe_sum")
    assert cfg.table.name == "smoe_table1" and len(cfg.table.rows) == 8 and cfg.table.primary == "map"
    assert cfg.experts.freeze is True


def test_experiment_has_only_the_smoe_modalities_and_metrics():
    cfg = compose_row("smoe_table1", "smoe_sum")
    assert list(cfg.modalities) == ["rgb", "ddm_jet"] and dict(cfg.model.modalities) == {"rgb": 3, "ddm_jet": 3}
    assert set(cfg.table.metrics) == {"map", "map_50", "map_75", "map_clear", "map_night", "map_rain", "map_glare"}


def paper_table(title: str) -> list[tuple[float, float, float]]:
    """(AP, AP50, AP75) per line of the table headed ``title`` in the SMoE text, in order."""
    text = SMOE_TEXT.read_text(encoding="utf-8")
    block = text[text.index(title) :].split("\n\n", 2)[1]
    lines = [ln for ln in block.splitlines() if re.search(r"\d+\.\d+\s+\d+\.\d+\s+\d+\.\d+\s*$", ln)]
    return [tuple(float(v) for v in ln.split()[-3:]) for ln in lines]


@pytest.mark.parametrize(
    "table,title", [("smoe_table1", "Table 1 Comparison"), ("smoe_table2", "**Table 2** Comparison")]
)
def test_paper_numbers_match_the_paper_text(table, title):
    if not SMOE_TEXT.is_file():
        pytest.skip(f"SMoE text not found at {SMOE_TEXT}")
    rows = OmegaConf.load(CONF / "experiment" / f"{table}.yaml").table.rows
    ours = [(r.paper.map, r.paper.map_50, r.paper.map_75) for r in rows]
    assert ours == paper_table(title)


def test_followup_rows_change_only_epochs_or_freezing_and_share_their_experts():
    from ablate.jobs.experts import expert_config
    from ablate.store import config_hash

    rows = table_rows("smoe_table1_followup")
    cfgs = {r: compose_row("smoe_table1_followup", r, "scale=cpu") for r in rows}
    # (stage-2 epochs, the experts' epochs) per row
    assert {r: (cfgs[r].trainer.max_epochs, cfgs[r].experts.max_epochs) for r in rows} == {
        "smoe_rgb": (4, 10),
        "smoe_rgb_long": (4, 20),
        "smoe_ddm": (4, 10),
        "smoe_ddm_long": (4, 20),
        "smoe_fpn": (4, 10),
        "smoe_fpn_long": (8, 20),
        "smoe_fpn_finetuned": (4, 10),
    }
    assert {r: expert_config(cfgs[r], "rgb").trainer.max_epochs for r in ("smoe_rgb", "smoe_rgb_long")} == {
        "smoe_rgb": 10,
        "smoe_rgb_long": 20,
    }
    assert cfgs["smoe_fpn_finetuned"].experts.freeze is False and cfgs["smoe_fpn_long"].experts.freeze is True
    # the long fused row stands on the long experts, so they are trained once, not twice
    for modality, single in (("rgb", "smoe_rgb_long"), ("ddm_jet", "smoe_ddm_long")):
        assert config_hash(expert_config(cfgs["smoe_fpn_long"], modality)) == config_hash(
            expert_config(cfgs[single], modality)
        )
    # rows shared with Table 1 have Table 1's config hash, so they are reused
    assert config_hash(cfgs["smoe_fpn"]) == config_hash(compose_row("smoe_table1", "smoe_fpn", "scale=cpu"))
