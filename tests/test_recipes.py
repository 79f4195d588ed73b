"""conf/recipe: each task's optimiser and epochs per scale, chosen by `${task}_${scale}` in the defaults list."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.errors import MissingConfigException

REPO = Path(__file__).resolve().parents[1]
CONF = REPO / "conf"


def compose_with(*overrides: str, conf: Path = CONF):
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        return compose("config", overrides=list(overrides))


def test_the_default_job_is_smoes_fpn_fusion_with_two_stage_training():
    cfg = compose_with()
    assert cfg.task._target_ == "ablate.tasks.instance.InstanceTask"
    assert (cfg.stage.name, list(cfg.modalities)) == ("fpn", ["rgb", "ddm_jet"])
    assert cfg.experts.freeze is True


# paper: epochs unbounded (-1), SMoE §4.3's 80k steps bound both stages (tests/test_check_paper.py)
@pytest.mark.parametrize("scale,epochs,expert_epochs", [("smoke", 1, None), ("cpu", 4, 10), ("paper", -1, None)])
def test_instance_recipe_is_smoes_sgd_at_paper_scale_and_adam_below(scale, epochs, expert_epochs):
    cfg = compose_with(f"scale={scale}")
    opt = cfg.task.optimizer
    if scale == "paper":  # SMoE §4.3
        assert (opt._target_, opt.lr, opt.momentum, opt.weight_decay) == ("torch.optim.SGD", 0.001, 0.9, 0.0005)
    else:
        assert opt._target_ == "torch.optim.Adam" and opt.lr == 0.001 and "momentum" not in opt
    assert cfg.task.scheduler.power == 0.9 and cfg.trainer.max_epochs == epochs
    assert cfg.experts.get("max_epochs") == expert_epochs  # None: the experts train as long as stage 2


@pytest.mark.parametrize("scale,lr,epochs", [("smoke", 0.001, 1), ("cpu", 0.001, 2), ("paper", 0.01, 50)])
def test_chinet_tables_keep_chinets_adam(scale, lr, epochs):
    cfg = compose_with("experiment=chinet_table2", f"scale={scale}")
    opt = cfg.task.optimizer
    assert cfg.task._target_ == "ablate.tasks.semantic.SemanticTask" and cfg.experts is None
    assert (opt._target_, opt.lr, list(opt.betas)) == ("torch.optim.Adam", lr, [0.9, 0.999])
    assert cfg.task.scheduler is None and cfg.trainer.max_epochs == epochs


def test_command_line_overrides_beat_the_recipe():
    cfg = compose_with("trainer.max_epochs=2", "task.optimizer.lr=0.01")
    assert cfg.trainer.max_epochs == 2 and cfg.task.optimizer.lr == 0.01


def test_a_new_scale_without_a_recipe_names_the_missing_recipe(tmp_path):
    conf = tmp_path / "conf"
    shutil.copytree(CONF, conf)
    (conf / "scale" / "gpu.yaml").write_text((CONF / "scale" / "paper.yaml").read_text().replace("paper", "gpu"))
    with pytest.raises(MissingConfigException, match="recipe/instance_gpu"):
        compose_with("scale=gpu", conf=conf)


@pytest.mark.parametrize("scale,dropout", [("smoke", 0.0), ("cpu", 0.0), ("paper", 0.2)])
@pytest.mark.parametrize("row", ["chinet", "unet", "fusenet", "simo", "miso", "iimo"])
def test_chinet_family_dropout_is_the_papers_at_paper_scale_and_off_on_the_cpu(row, scale, dropout):
    cfg = compose_with("experiment=chinet_table2", f"row={row}", f"scale={scale}")
    assert cfg.model.variant == row and cfg.model.dropout == dropout
    assert (
        list(cfg.model.widths)
        == {"smoke": [8, 16, 32], "cpu": [16, 32, 64, 128], "paper": [64, 128, 256, 512, 1024]}[scale]
    )


def test_a_chinet_model_outside_the_semantic_recipe_keeps_the_papers_dropout():
    assert compose_with("model=chinet").model.dropout == 0.2


@pytest.mark.parametrize("scale,batch_norm", [("smoke", True), ("cpu", True), ("paper", False)])
@pytest.mark.parametrize("row", ["dgfn", "dgfn_baseline", "ssd_rgb", "ssd_dhi"])
def test_detection_trunks_get_batch_norm_only_below_paper_scale(row, scale, batch_norm):
    cfg = compose_with("experiment=dgfn_table2", f"row={row}", f"scale={scale}")
    assert cfg.model.batch_norm is batch_norm
