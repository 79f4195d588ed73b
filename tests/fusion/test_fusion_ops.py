"""Each fusion operator against its paper equation on hand-made tensors."""

import math

import pytest
import torch

from ablate.fusion import OPERATORS, build
from ablate.fusion.ops_bifnet import CBF

LOGIT_QUARTER = math.log(0.25 / 0.75)  # sigmoid(LOGIT_QUARTER) = 0.25


def pair(c=2, h=3, w=4, b=2, seed=0):
    g = torch.Generator().manual_seed(seed)
    return [torch.randn(b, c, h, w, generator=g) for _ in range(2)]


def test_sum_mean_max_elementwise():
    fi, fj = pair()
    torch.testing.assert_close(build("sum", 2)([fi, fj]), fi + fj)
    torch.testing.assert_close(build("mean", 2)([fi, fj]), (fi + fj) / 2)
    torch.testing.assert_close(build("max", 2)([fi, fj]), torch.maximum(fi, fj))


def test_concat_is_a_1x1_conv_from_2c_to_c():
    op = build("concat", 2)
    assert op.conv.weight.shape == (2, 4, 1, 1)
    with torch.no_grad():
        op.conv.weight.copy_(torch.cat([torch.eye(2), 2 * torch.eye(2)], 1)[:, :, None, None])
        op.conv.bias.zero_()
    fi, fj = pair()
    torch.testing.assert_close(op([fi, fj]), fi + 2 * fj)


def test_sharpen_known_values_threshold_over_c_h_w():
    # channel 0: f_i + f_j = [4, 4, -1, 2], f_p = [3, 4, 1, 2]; channel 1: f_i + f_j = f_p = 10.
    # t = mean over C, H, W = (9 + 40) / 8 = 6.125: channel 0 all weak (sum), channel 1 all strong (a * f_p).
    fi = torch.tensor([[[[1.0, 4.0], [-2.0, 0.0]], [[10.0] * 2] * 2]])
    fj = torch.tensor([[[[3.0, 0.0], [1.0, 2.0]], [[0.0] * 2] * 2]])
    out = build("sharpen", 2, a=2.0)([fi, fj])
    expected = torch.tensor([[[[4.0, 4.0], [-1.0, 2.0]], [[20.0] * 2] * 2]])
    torch.testing.assert_close(out, expected)


def test_sharpen_threshold_is_per_sample():
    # one channel: sum [4, 4, -1, 2], t = 2.25, f_p = [3, 4, 1, 2] -> [a*3, a*4, -1, 2]
    fi = torch.tensor([[[[1.0, 4.0], [-2.0, 0.0]]]])
    fj = torch.tensor([[[[3.0, 0.0], [1.0, 2.0]]]])
    out = build("sharpen", 1, a=3.0)([torch.cat([fi, 10 * fi]), torch.cat([fj, 10 * fj])])
    first = torch.tensor([[[9.0, 12.0], [-1.0, 2.0]]])
    torch.testing.assert_close(out[0], first)
    torch.testing.assert_close(out[1], 10 * first)  # a batch-wide threshold would make sample 0 all weak


def set_gate(op, bias_per_input):
    """Zero the gate conv and set its bias so the gates are constant."""
    c = op.channels
    with torch.no_grad():
        op.gate.conv.weight.zero_()
        op.gate.conv.bias.copy_(torch.tensor(bias_per_input).repeat_interleave(c))


@pytest.mark.parametrize("name", ["moe_sum", "moe_max", "smoe"])
def test_moe_gate_quarter(name):
    op = build(name, 2)
    assert op.gate.conv.weight.shape == (2, 4, 1, 1)  # SMoE eq. 2: one 1x1 conv, 2C -> C
    set_gate(op, [LOGIT_QUARTER])
    fi, fj = pair()
    out = op([fi, fj])
    wi, wj = 0.25 * fi, 0.75 * fj  # eq. 3: W = 0.25 on f_i, 1 - W on f_j
    t = (wi + wj).mean(dim=(1, 2, 3), keepdim=True)
    fp = torch.maximum(wi, wj)
    expected = {"moe_sum": wi + wj, "moe_max": fp, "smoe": torch.where(fp > t, 2.0 * fp, wi + wj)}[name]
    torch.testing.assert_close(out, expected)
    torch.testing.assert_close(op.last_gates[0], torch.full_like(fi, 0.25))
    torch.testing.assert_close(op.last_gates[1], torch.full_like(fi, 0.75))
    assert not op.last_gates[0].requires_grad


def test_moe_gate_reads_both_inputs():
    op = build("moe_sum", 1)
    with torch.no_grad():
        op.gate.conv.weight.copy_(torch.tensor([1.0, -1.0]).view(1, 2, 1, 1))
        op.gate.conv.bias.zero_()
    fi, fj = pair(c=1)
    w = torch.sigmoid(fi - fj)
    torch.testing.assert_close(op([fi, fj]), w * fi + (1 - w) * fj)


@pytest.mark.parametrize("name", ["moe_sum", "smoe"])
def test_moe_three_inputs_softmax(name):
    op = build(name, 2, num_inputs=3)
    assert op.gate.conv.weight.shape == (6, 6, 1, 1)
    set_gate(op, [0.0, 0.0, math.log(2.0)])  # softmax -> 0.25, 0.25, 0.5
    f = pair(seed=1) + pair(seed=2)[:1]
    weighted = [0.25 * f[0], 0.25 * f[1], 0.5 * f[2]]
    total = sum(weighted)
    fp = torch.maximum(torch.maximum(weighted[0], weighted[1]), weighted[2])
    t = total.mean(dim=(1, 2, 3), keepdim=True)
    expected = total if name == "moe_sum" else torch.where(fp > t, 2.0 * fp, total)
    torch.testing.assert_close(op(f), expected)
    torch.testing.assert_close(sum(op.last_gates), torch.ones_like(f[0]))


def test_gfu_constant_gates_and_relu():
    op = build("gfu", 2)
    assert [g.weight.shape for g in op.gates] == [(1, 4, 3, 3)] * 2  # DGFN eq. 6-7: 3x3, 2C -> 1
    assert op.joint.weight.shape == (2, 4, 1, 1)  # eq. 9: 1x1, 2C -> C
    with torch.no_grad():
        for g, b in zip(op.gates, [LOGIT_QUARTER, -LOGIT_QUARTER]):
            g.weight.zero_()
            g.bias.fill_(b)
        op.joint.weight.copy_(torch.cat([torch.eye(2), torch.eye(2)], 1)[:, :, None, None])
        op.joint.bias.zero_()
    fi, fj = pair()
    out = op([fi, fj])
    torch.testing.assert_close(out, torch.relu(0.25 * fi + 0.75 * fj))
    assert (out == 0).any()  # the ReLU of eq. 9 acted
    assert op.last_gates[0].shape == (2, 1, 3, 4)


def test_gfu_gate_is_a_padded_3x3_conv_over_both_inputs():
    op = build("gfu", 1)
    with torch.no_grad():
        for g in op.gates:
            g.weight.zero_()
            g.bias.zero_()
        op.gates[0].weight[0, 0, 0, 0] = 1.0  # top-left tap on f_i
        op.gates[1].weight[0, 1, 1, 1] = 1.0  # centre tap on f_j
    fi, fj = pair(c=1)
    op([fi, fj])
    shifted = torch.zeros_like(fi)
    shifted[..., 1:, 1:] = fi[..., :-1, :-1]  # zero padding at the border
    torch.testing.assert_close(op.last_gates[0], torch.sigmoid(shifted))
    torch.testing.assert_close(op.last_gates[1], torch.sigmoid(fj))


def test_gfu_ungated_baseline_is_concat_conv_relu():
    op = build("gfu", 2, gated=False)
    assert len(op.gates) == 0
    with torch.no_grad():
        op.joint.weight.copy_(torch.cat([torch.eye(2), -torch.eye(2)], 1)[:, :, None, None])
        op.joint.bias.zero_()
    fi, fj = pair()
    torch.testing.assert_close(op([fi, fj]), torch.relu(fi - fj))  # DGFN baseline: weight maps fixed to one
    torch.testing.assert_close(op.last_gates[1], torch.ones(2, 1, 3, 4))


def set_cbf_gains(op: CBF, gains):
    with torch.no_grad():
        for mlp, g in zip(op.mlps, gains):
            mlp[-2].weight.zero_()
            mlp[-2].bias.copy_(torch.logit(torch.tensor(g)))


def test_cbf_structure_and_constant_gains():
    op = build("cbf", 2, joint=False)
    assert [type(m).__name__ for m in op.mlps[0]] == ["Linear", "ReLU", "Linear", "ReLU", "Linear", "Sigmoid"]
    set_cbf_gains(op, [[0.25, 0.5], [0.75, 0.1]])
    fi, fj = pair()
    gi, gj = torch.tensor([0.25, 0.5]).view(1, 2, 1, 1), torch.tensor([0.75, 0.1]).view(1, 2, 1, 1)
    torch.testing.assert_close(op([fi, fj]), gi * fi + gj * fj)  # BiFNet eq. 11, summed


def test_cbf_joint_mlp_sees_all_inputs():
    op = build("cbf", 2)
    assert op.mlps[0][0].in_features == 4 and op.mlps[0][-2].out_features == 4
    set_cbf_gains(op, [[0.2, 0.4, 0.6, 0.8]])
    fi, fj = pair()
    expected = torch.tensor([0.2, 0.4]).view(1, 2, 1, 1) * fi + torch.tensor([0.6, 0.8]).view(1, 2, 1, 1) * fj
    torch.testing.assert_close(op([fi, fj]), expected)


def test_cbf_descriptor_is_global_average_pooling():
    op = build("cbf", 2)
    fj = pair()[1]
    spike = torch.zeros(2, 2, 3, 4)
    spike[..., 1, 2] = 12.0  # mean 1, max 12
    flat = torch.ones(2, 2, 3, 4)  # mean 1, max 1
    op([spike, fj])
    gains = op.last_gates
    op([flat, fj])
    torch.testing.assert_close(op.last_gates, gains)  # BiFNet eq. 9: average, not max, pooling
    op([flat + 1.0, fj])  # another mean changes the gains
    assert not torch.allclose(op.last_gates[0], gains[0])


def test_lidcamnet_one_scalar_on_lidar():
    op = build("lidcamnet", 2)
    assert [p.numel() for p in op.parameters()] == [1]
    with torch.no_grad():
        op.alpha.fill_(0.5)
    fi, fj = pair()
    torch.testing.assert_close(op([fi, fj]), fi + 0.5 * fj)
    assert build("lidcamnet", 2, num_inputs=3).alpha.numel() == 2


def test_plard_one_weight_per_position():
    op = build("plard", 2, size=(3, 4))
    assert op.weight.shape == (1, 1, 3, 4)
    w = torch.arange(12.0).view(1, 1, 3, 4) / 10
    with torch.no_grad():
        op.weight.copy_(w)
    fi, fj = pair()
    torch.testing.assert_close(op([fi, fj]), fi + w * fj)
    torch.testing.assert_close(op.last_gates[1], w)


def test_plard_resamples_its_map_to_other_sizes():
    op = build("plard", 2, size=(3, 4))
    with torch.no_grad():
        op.weight.fill_(0.3)
    fi, fj = pair(h=7, w=5)
    torch.testing.assert_close(op([fi, fj]), fi + 0.3 * fj)


@pytest.mark.parametrize("name", sorted(OPERATORS))
@pytest.mark.parametrize("n", [2, 3])
def test_shapes_and_gradients(name, n):
    torch.manual_seed(0)  # a ReLU MLP on random inputs can be dead for one draw: one draw for every order of tests
    op = build(name, 4, num_inputs=n)
    f = [torch.randn(2, 4, 6, 10, requires_grad=True) for _ in range(n)]
    out = op(f)
    assert out.shape == (2, 4, 6, 10)
    (out * torch.randn_like(out)).sum().backward()
    for p_name, p in op.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, f"{name}: no gradient reaches {p_name}"
    assert any(x.grad.abs().sum() > 0 for x in f)


def test_errors_name_the_problem():
    with pytest.raises(ValueError, match="'nope'.*cbf, concat, gfu"):
        build("nope", 4)
    with pytest.raises(TypeError, match="'sum' has no option a"):
        build("sum", 4, a=2.0)
    with pytest.raises(ValueError, match="num_inputs must be >= 2"):
        build("gfu", 4, num_inputs=1)
    with pytest.raises(ValueError, match="built for 2 inputs, got 3"):
        build("sum", 4)(pair(c=4) + pair(c=4)[:1])
    with pytest.raises(ValueError, match="one shape"):
        build("max", 2)([torch.zeros(1, 2, 3, 3), torch.zeros(1, 2, 3, 4)])
