"""The ChiNet family (ChiNet Table I): outputs, branches and where the skips go."""

import pytest
import torch

from ablate.nn.chinet import VARIANTS, build

MODALITIES = {"intensity": 1, "dense_depth": 1}


def _inputs(h=32, w=48):
    return {"intensity": torch.rand(2, 1, h, w), "dense_depth": torch.rand(2, 1, h, w)}


@pytest.mark.parametrize("variant", VARIANTS)
def test_every_variant_runs_forward_and_backward(variant):
    model = build(variant, MODALITIES, [4, 8, 16])
    out = model(_inputs())
    expected = {"free_space": 1, "road_objects": 1} if variant in ("chinet", "simo", "iimo") else {"semantic": 3}
    assert {k: v.shape[1] for k, v in out.items()} == expected
    assert all(v.shape[-2:] == (32, 48) for v in out.values())
    sum(v.sum() for v in out.values()).backward()
    assert all(p.grad is not None for p in model.parameters() if p.requires_grad)


def test_chinet_decoders_take_both_encoders_and_iimo_ignores_depth():
    chinet = build("chinet", MODALITIES, [4, 8, 16])
    assert len(chinet.encoders) == 2 and len(chinet.decoders) == 2
    # each decoder level concatenates [upsampled, intensity skip, depth skip]: 16 + 2 * 8 input channels
    assert chinet.decoders["free_space"].blocks[0].block[0].in_channels == 2 * 16 + 2 * 8
    iimo = build("iimo", MODALITIES, [4, 8, 16])
    x = _inputs()
    a = iimo(x)["free_space"]
    x["dense_depth"] = torch.rand_like(x["dense_depth"])
    assert torch.equal(
        iimo.eval()(x)["free_space"], iimo.eval()(_inputs() | {"intensity": x["intensity"]})["free_space"]
    )
    assert a.shape == (2, 1, 32, 48)


def test_unknown_variant_names_the_valid_ones():
    with pytest.raises(ValueError, match="unknown ChiNet variant 'chinet2'.*fusenet"):
        build("chinet2", MODALITIES, [4, 8])
