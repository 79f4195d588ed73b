"""ResNet trunk: torchvision-equal sizes, C2-C5 strides, width, input channels, local weights."""

import pytest
import torch

from ablate.nn import ResNet, WeightsError

# torchvision resnet{18,34,50,101} parameter counts minus their 1000-class fc layer
TRUNK_PARAMS = {
    18: 11_689_512 - 513_000,
    34: 21_797_672 - 513_000,
    50: 25_557_032 - 2_049_000,
    101: 44_549_160 - 2_049_000,
}


@pytest.mark.parametrize("depth", [18, 34, 50, 101])
def test_parameter_count_matches_torchvision(depth):
    assert sum(p.numel() for p in ResNet(depth).parameters()) == TRUNK_PARAMS[depth]


@pytest.mark.parametrize("depth,expansion", [(18, 1), (50, 4)])
def test_c2_c5_strides_and_channels(depth, expansion):
    net = ResNet(depth, width=0.125, in_channels=6)
    assert net.channels == [c * expansion for c in (8, 16, 32, 64)]
    outs = net(torch.randn(1, 6, 64, 96))
    assert [tuple(o.shape) for o in outs] == [(1, c, 64 // s, 96 // s) for c, s in zip(net.channels, (4, 8, 16, 32))]


def test_bad_options_and_input():
    with pytest.raises(ValueError, match="depth 20.*\\[18, 34, 50, 101\\]"):
        ResNet(20)
    with pytest.raises(ValueError, match="\\[B,1,H,W\\]"):
        ResNet(18, 0.125, in_channels=1)(torch.zeros(1, 3, 32, 32))


def test_weights_round_trip_and_fc_ignored(tmp_path):
    src = ResNet(18, 0.125).eval()
    state = src.state_dict() | {"fc.weight": torch.zeros(10, 64), "fc.bias": torch.zeros(10)}
    torch.save(state, tmp_path / "r18.pth")
    dst = ResNet(18, 0.125, weights=tmp_path / "r18.pth").eval()
    x = torch.randn(1, 3, 64, 64)
    for a, b in zip(src(x), dst(x)):
        torch.testing.assert_close(a, b)


def test_first_conv_adapted_to_other_input_channels(tmp_path):
    rgb = ResNet(18, 0.125).eval()
    torch.save(rgb.state_dict(), tmp_path / "r18.pth")
    grey = ResNet(18, 0.125, in_channels=1, weights=tmp_path / "r18.pth").eval()
    torch.testing.assert_close(grey.conv1.weight, rgb.conv1.weight.sum(1, keepdim=True))
    # In float64, so that only the float32 rounding of the summed kernel (about 1e-7) separates the two;
    # float32 activations also differed by their summation orders, past the default tolerance after 18 layers.
    x = torch.randn(1, 1, 64, 64, dtype=torch.float64)
    grey, rgb = grey.double(), rgb.double()
    out, want = grey(x)[-1], rgb(x.repeat(1, 3, 1, 1))[-1]  # grey in = grey RGB in
    torch.testing.assert_close(out, want, rtol=1e-5, atol=1e-5)


def test_weight_errors_name_the_file(tmp_path):
    with pytest.raises(WeightsError, match="not found: .*missing.pth"):
        ResNet(18, 0.125, weights=tmp_path / "missing.pth")
    torch.save(ResNet(18, 0.25).state_dict(), tmp_path / "wide.pth")
    with pytest.raises(WeightsError, match="wide.pth.*shape mismatch.*width 0.125"):
        ResNet(18, 0.125, weights=tmp_path / "wide.pth")
    torch.save(ResNet(34, 0.125).state_dict(), tmp_path / "r34.pth")
    with pytest.raises(WeightsError, match="r34.pth.*unexpected \\['layer1.2"):
        ResNet(18, 0.125, weights=tmp_path / "r34.pth")
    (tmp_path / "junk.pth").write_bytes(b"not a checkpoint")
    with pytest.raises(WeightsError, match="junk.pth could not be read"):
        ResNet(18, 0.125, weights=tmp_path / "junk.pth")
