"""YOLACT-style FPN, VGG-16 SSD trunk and U-Net blocks."""

import pytest
import torch

from ablate.nn import FPN, VGG16SSD, ConvBlock, DecoderBlock, Encoder, WeightsError


def c3_c5(b=1):
    return [torch.randn(b, c, 64 // s, 96 // s) for c, s in ((16, 8), (32, 16), (64, 32))]


def test_fpn_levels_p3_to_p7():
    torch.manual_seed(0)
    fpn = FPN([16, 32, 64], 8)
    outs = fpn(c3_c5())
    assert [tuple(o.shape) for o in outs] == [(1, 8, 8, 12), (1, 8, 4, 6), (1, 8, 2, 3), (1, 8, 1, 2), (1, 8, 1, 1)]
    assert [d.stride for d in fpn.downsample] == [(2, 2)] * 2 and fpn.num_levels == 5
    assert (outs[0] >= 0).all() and (outs[3] < 0).any()  # ReLU on P3-P5, none after the stride-2 convs


def test_fpn_top_down_pathway():
    fpn = FPN([16, 32, 64], 8).eval()
    feats = c3_c5()
    base = fpn(feats)
    moved_c5 = fpn(feats[:2] + [feats[2] + 1.0])
    moved_c3 = fpn([feats[0] + 1.0] + feats[1:])
    assert not torch.allclose(moved_c5[0], base[0])  # C5 reaches P3 top-down
    torch.testing.assert_close(moved_c3[2], base[2])  # C3 never reaches P5


def test_vgg16_ssd_sizes_and_parameters():
    full = VGG16SSD()
    assert sum(p.numel() for p in full.features.parameters()) == 14_714_688  # torchvision vgg16().features
    assert full.channels == [512, 1024, 512, 256, 256, 256]
    net = VGG16SSD(in_channels=3, width=0.125)
    outs = net(torch.randn(1, 3, 300, 300))
    sizes = [o.shape[-1] for o in outs]
    assert sizes == [38, 19, 10, 5, 3, 1]  # SSD300: conv4_3, conv7, conv8_2 .. conv11_2
    assert [o.shape[1] for o in outs] == net.channels
    torch.testing.assert_close(outs[0].norm(dim=1), torch.full((1, 38, 38), 20.0))  # L2Norm at init scale
    with pytest.raises(ValueError, match="too small for the SSD300 extras"):
        net(torch.randn(1, 3, 128, 128))


def test_vgg16_ssd_with_batch_norm_has_vgg16_bn_layout_and_the_same_maps():
    full = VGG16SSD(batch_norm=True)
    assert sum(p.numel() for p in full.features.parameters()) == 14_723_136  # torchvision vgg16_bn().features
    conv4_3 = full.features[full.conv4_3 - 2]
    assert isinstance(conv4_3, torch.nn.Conv2d) and conv4_3.out_channels == 512 and full.conv4_3 == 32
    assert isinstance(full.features[full.conv4_3], torch.nn.ReLU)
    assert sum(isinstance(m, torch.nn.BatchNorm2d) for m in full.modules()) == 13 + 2 + 8  # trunk, conv6-7, extras
    net = VGG16SSD(width=0.125, batch_norm=True)
    outs = net(torch.randn(2, 3, 300, 300))
    assert [o.shape[-1] for o in outs] == [38, 19, 10, 5, 3, 1] and [o.shape[1] for o in outs] == net.channels
    assert not any("bn" in k for k in VGG16SSD(width=0.125).state_dict())  # without it: the old checkpoints' keys
    one = net.train()(torch.randn(1, 3, 300, 300))  # conv11_2 is 1x1: one value per channel, running stats there
    assert one[-1].shape == (1, net.channels[-1], 1, 1) and torch.isfinite(one[-1]).all()


def test_vgg16_loads_torchvision_features(tmp_path):
    src = VGG16SSD(width=0.125)
    state = {f"features.{k}": v for k, v in src.features.state_dict().items()} | {
        "classifier.0.weight": torch.zeros(2, 2)
    }
    torch.save(state, tmp_path / "vgg16.pth")
    dhi = VGG16SSD(in_channels=1, width=0.125, weights=tmp_path / "vgg16.pth")
    torch.testing.assert_close(dhi.features[2].weight, src.features[2].weight)
    torch.testing.assert_close(dhi.features[0].weight, src.features[0].weight.sum(1, keepdim=True))
    with pytest.raises(WeightsError, match="vgg16.pth.*width 0.25"):
        VGG16SSD(width=0.25, weights=tmp_path / "vgg16.pth")


def test_conv_block_layers():
    block = ConvBlock(3, 8, dropout=0.1)
    kinds = [type(m).__name__ for m in block]
    assert kinds == ["Conv2d", "BatchNorm2d", "ReLU", "Conv2d", "BatchNorm2d", "ReLU", "Dropout2d"]
    assert all(m.kernel_size == (3, 3) and m.padding == (1, 1) for m in block if isinstance(m, torch.nn.Conv2d))
    assert "Dropout2d" not in [type(m).__name__ for m in ConvBlock(3, 8)]
    assert block(torch.randn(2, 3, 15, 17)).shape == (2, 8, 15, 17)


def test_encoder_skips_and_decoder():
    enc = Encoder(4, [8, 16, 32])
    assert enc.channels == [8, 16, 32]
    skips = enc(torch.randn(1, 4, 30, 44))
    assert [tuple(s.shape) for s in skips] == [(1, 8, 30, 44), (1, 16, 15, 22), (1, 32, 7, 11)]
    for mode in ("nearest", "bilinear"):
        dec = DecoderBlock(32, 16, 16, mode=mode)
        assert dec(skips[2], skips[1]).shape == (1, 16, 15, 22)  # odd size: upsampled to the skip's size
    with pytest.raises(ValueError, match="'bicubic'"):
        DecoderBlock(32, 16, 16, mode="bicubic")
