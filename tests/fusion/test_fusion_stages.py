"""Every operator x every stage builds and trains one step; stage structure, MACs, experts, errors."""

import functools

import pytest
import torch

from ablate.fusion import OPERATORS, STAGES, FusionModel, build

MODALITIES = {"rgb": 3, "dense_depth": 1}
BACKBONE = {"depth": 18, "width": 0.125}


def inputs(b=2, size=64):
    g = torch.Generator().manual_seed(0)
    return {m: torch.randn(b, c, size, size, generator=g) for m, c in MODALITIES.items()} | {"unused": torch.zeros(1)}


def flat(out):
    return [t for v in out.values() for t in (v if isinstance(v, list) else [v])]


@pytest.mark.parametrize("stage", STAGES)
@pytest.mark.parametrize("op", sorted(OPERATORS))
def test_every_operator_at_every_stage_trains(op, stage, make_model):
    m = make_model(stage, op)
    out = m(inputs())
    assert set(out) == {"cls", "proto"}
    assert [tuple(t.shape) for t in out["cls"]] == [(2, 3, s, s) for s in (8, 4, 2, 1, 1)]
    assert out["proto"].shape == (2, 4, 8, 8)
    sum((t * torch.randn_like(t)).sum() for t in flat(out)).backward()
    dead = [n for n, p in m.named_parameters() if p.grad is None]
    assert not dead, f"no gradient reaches {dead[:5]}"


def test_fusion_points_per_stage(make_model):
    assert make_model("early").fusion_modules() == [] and len(make_model("early").encoders) == 0
    assert make_model("single").fusion_modules() == [] and list(make_model("single").encoders) == ["rgb"]
    assert [f.channels for f in make_model("backbone").fusion_modules()] == [16, 32, 64]  # C3, C4, C5 at width 1/8
    assert [f.channels for f in make_model("fpn").fusion_modules()] == [8] * 5  # P3..P7
    assert [f.channels for f in make_model("late").fusion_modules()] == [3] * 5 + [4]  # one per head output map
    assert make_model("early").encoder.in_channels == 4  # rgb + dense_depth concatenated
    assert list(make_model("fpn").encoders) == ["rgb", "dense_depth"]


def test_fusion_order_is_modality_order(make_model):
    m = make_model("fpn", "lidcamnet")
    with torch.no_grad():
        for op in m.fusion_modules():
            op.alpha.zero_()  # drop the second modality at every level
    x = inputs()
    out = m(x)
    out2 = m(x | {"dense_depth": torch.randn(2, 1, 64, 64)})
    torch.testing.assert_close(flat(out), flat(out2))


def test_late_with_sum_is_two_singles(tiny_head):
    two = {"a": 1, "b": 1}
    late = FusionModel("late", two, functools.partial(build, name="sum"), tiny_head, BACKBONE, 8)
    single = FusionModel("single", two, None, tiny_head, BACKBONE, 8, single="a")
    assert late.num_parameters() == 2 * single.num_parameters()
    shapes = {"a": (1, 64, 64), "b": (1, 64, 64)}
    assert late.macs(shapes) == 2 * single.macs({"a": (1, 64, 64)}) > 0
    assert late.macs({k: (2, *s) for k, s in shapes.items()}) == 2 * late.macs(shapes)


def test_load_expert_copies_and_freezes(make_model):
    expert = make_model("single")
    with torch.no_grad():
        for p in expert.parameters():
            p.add_(1.0)
    fused = make_model("late", "smoe")
    fused.load_expert("rgb", expert)
    for part, theirs in [
        (fused.encoders["rgb"], expert.encoders["rgb"]),
        (fused.fpns["rgb"], expert.fpn),
        (fused.heads["rgb"], expert.head),
    ]:
        for (k, a), b in zip(part.state_dict().items(), theirs.state_dict().values()):
            assert torch.equal(a, b), k
        assert not any(p.requires_grad for p in part.parameters())
    fused.train()
    assert not fused.encoders["rgb"].training and fused.encoders["dense_depth"].training
    assert all(p.requires_grad for p in fused.fusion_modules()[0].parameters())
    with pytest.raises(ValueError, match="stage 'single' model of that modality"):
        fused.load_expert("dense_depth", expert)


def test_errors_name_the_problem(make_model, tiny_head):
    with pytest.raises(ValueError, match="'middle'.*early, backbone, fpn, late, single"):
        make_model("middle")
    with pytest.raises(KeyError, match="missing \\['dense_depth'\\]"):
        make_model("fpn")({"rgb": torch.zeros(1, 3, 64, 64)})
    with pytest.raises(ValueError, match="one of \\['rgb', 'dense_depth'\\]"):
        FusionModel("single", MODALITIES, head=tiny_head, backbone=BACKBONE)
    with pytest.raises(ValueError, match="needs a fusion operator"):
        FusionModel("fpn", MODALITIES, head=tiny_head, backbone=BACKBONE)
    with pytest.raises(ValueError, match="unknown backbone option"):
        FusionModel("early", MODALITIES, head=tiny_head, backbone={"depht": 18})
    with pytest.raises(ValueError, match="needs `head`"):
        FusionModel("early", MODALITIES)
    with pytest.raises(ValueError, match="one H, W"):
        make_model("backbone")({"rgb": torch.zeros(1, 3, 64, 64), "dense_depth": torch.zeros(1, 1, 32, 64)})


@pytest.mark.parametrize("stage", ["backbone", "fpn", "late"])
def test_three_modalities(stage, make_model):
    three = {"rgb": 3, "dense_depth": 1, "dhi_image": 3}
    m = make_model(stage, "smoe", modalities=three)
    assert all(op.num_inputs == 3 for op in m.fusion_modules())
    out = m({k: torch.randn(1, c, 64, 64) for k, c in three.items()})
    assert out["proto"].shape == (1, 4, 8, 8)
