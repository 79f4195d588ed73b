"""conf/fusion and conf/stage: one YAML per operator and per stage, composable with Hydra."""

import functools
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import OmegaConf

from ablate.fusion import OPERATORS, STAGES
from ablate.nn import ResNet

CONF = Path(__file__).resolve().parents[2] / "conf"


def test_one_yaml_per_operator_and_stage():
    assert sorted(p.stem for p in (CONF / "fusion").glob("*.yaml")) == sorted(OPERATORS)
    assert sorted(p.stem for p in (CONF / "stage").glob("*.yaml")) == sorted(STAGES)


@pytest.mark.parametrize("name", sorted(OPERATORS))
def test_fusion_yaml_instantiates_a_partial_of_build(name):
    cfg = OmegaConf.load(CONF / "fusion" / f"{name}.yaml")
    assert cfg.name == name
    make = instantiate(cfg)
    assert isinstance(make, functools.partial)
    op = make(channels=4, num_inputs=3)
    assert type(op) is OPERATORS[name]
    assert op([torch.randn(1, 4, 6, 8) for _ in range(3)]).shape == (1, 4, 6, 8)


@pytest.mark.parametrize("stage", STAGES)
def test_groups_compose_into_a_fusion_model(stage, tiny_head, tmp_path):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose(overrides=["+fusion=smoe", f"+stage={stage}"])
    assert cfg.stage.name == stage and cfg.fusion.a == 2.0
    torch.save(ResNet(18, 0.125).state_dict(), tmp_path / "rgb.pth")
    OmegaConf.set_struct(cfg, False)
    cfg.modalities = {"rgb": 3, "dense_depth": 1}
    cfg.model = {
        "_target_": "ablate.fusion.stages.FusionModel",
        "stage": "${stage.name}",
        "single": "${oc.select:stage.modality,null}",
        "modalities": "${modalities}",
        "fusion": "${fusion}",
        "backbone": {"depth": 18, "width": 0.125, "weights": {"rgb": str(tmp_path / "rgb.pth")}},
        "fpn_channels": 8,
    }
    model = instantiate(cfg.model, head=tiny_head)
    assert model.single == ("rgb" if stage == "single" else None)
    if stage != "early":
        loaded = ResNet(18, 0.125, weights=tmp_path / "rgb.pth").conv1.weight
        torch.testing.assert_close(model.encoders["rgb"].conv1.weight, loaded)
    out = model({"rgb": torch.randn(1, 3, 64, 64), "dense_depth": torch.randn(1, 1, 64, 64)})
    assert out["proto"].shape == (1, 4, 8, 8)
