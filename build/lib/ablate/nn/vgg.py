"""VGG-16 SSD trunk (Liu et al. SSD300), the per-sensor CNN of DGFN §III-A.

DGFN: "The VGG network is used for the first 15 layers and 8 extra convolutional layers are added"; the
fused maps are conv4_3, conv7 (FC7), conv8_2, conv9_2, conv10_2 and conv11_2, in SSD's notation.

``batch_norm=True`` (not in DGFN or SSD) puts a BatchNorm after every convolution of the trunk, conv6, conv7 and
the extras, as ScratchDet does to train SSD from scratch (Zhu et al., "ScratchDet: Training Single-Shot Object
Detectors from Scratch", CVPR 2019, §3: BatchNorm in the backbone and the head makes the optimisation landscape
smoother and lets the detector train from random weights with a larger learning rate). ``features`` then has
torchvision's ``vgg16_bn`` layout (conv, BN, ReLU), so its state dict loads the same way.
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import Tensor, nn

from ablate.nn.weights import WeightsError, adapt_first_conv, load_checked, read_state_dict

# conv widths of VGG-16 conv1_1 .. conv5_3; "M" a 2x2 max-pool ("C": with ceil_mode, SSD's pool3)
VGG16 = [64, 64, "M", 128, 128, "M", 256, 256, 256, "C", 512, 512, 512, "M", 512, 512, 512]
CONV4_3 = 10  # conv4_3 is the 10th conv of VGG16
# SSD300 extras: (out, kernel, stride, padding), pairs conv8_1/8_2 .. conv11_1/11_2
EXTRAS = [
    (256, 1, 1, 0),
    (512, 3, 2, 1),
    (128, 1, 1, 0),
    (256, 3, 2, 1),
    (128, 1, 1, 0),
    (256, 3, 1, 0),
    (128, 1, 1, 0),
    (256, 3, 1, 0),
]


class BatchNorm2d(nn.BatchNorm2d):
    """BatchNorm that normalises a training batch holding one value per channel (one frame at conv11_2's 1x1 map,
    as the last batch of an epoch can be) with the running statistics instead of failing: one value has no batch
    variance. Every other batch is normalised as by :class:`torch.nn.BatchNorm2d`."""

    def forward(self, x: Tensor) -> Tensor:
        if self.training and x.shape[0] * x.shape[2] * x.shape[3] == 1:
            return nn.functional.batch_norm(
                x, self.running_mean, self.running_var, self.weight, self.bias, False, 0.0, self.eps
            )
        return super().forward(x)


class L2Norm(nn.Module):
    """SSD's channel-wise L2 normalisation of conv4_3 with a learnable per-channel scale (init 20)."""

    def __init__(self, channels: int, scale: float = 20.0) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.full((channels,), scale))

    def forward(self, x: Tensor) -> Tensor:
        return x / x.norm(dim=1, keepdim=True).clamp_min(1e-10) * self.weight[None, :, None, None]


class VGG16SSD(nn.Module):
    """``forward(x) -> [conv4_3, conv7, conv8_2, conv9_2, conv10_2, conv11_2]`` (conv4_3 after L2Norm).

    ``features`` holds conv1_1..conv5_3 with torchvision's indices, so a torchvision VGG-16 state dict
    (``features.*``; its ``classifier.*`` ignored) loads into it; conv6/conv7/extras then keep their
    initialisation. A file with every key of this module loads in full. pool5 is 3x3 stride 1, conv6 a
    3x3 conv with dilation 6 (fc6 as conv), conv7 a 1x1 conv (fc7 as conv). conv10_2 and conv11_2 are
    unpadded 3x3 convs as in SSD300, so the input must be about 260 px or more on each side.
    ``width`` scales every channel count; ``in_channels`` is free (the first conv is adapted when loading).
    ``batch_norm``: a BatchNorm after every conv (ScratchDet; see the module docstring).
    """

    def __init__(
        self, in_channels: int = 3, width: float = 1.0, weights: str | Path | None = None, batch_norm: bool = False
    ) -> None:
        super().__init__()
        if width <= 0 or in_channels < 1:
            raise ValueError(
                f"VGG16SSD needs width > 0 and in_channels >= 1, got width={width}, in_channels={in_channels}"
            )
        self.in_channels, self.width, self.batch_norm = in_channels, width, batch_norm
        s = lambda c: max(1, round(c * width))  # noqa: E731
        norm = (lambda c: BatchNorm2d(c)) if batch_norm else (lambda c: nn.Identity())  # noqa: E731
        layers: list[nn.Module] = []
        ch, convs = in_channels, 0
        for v in VGG16:
            if v in ("M", "C"):
                layers.append(nn.MaxPool2d(2, 2, ceil_mode=v == "C"))
            else:
                layers += (
                    [nn.Conv2d(ch, s(v), 3, padding=1)]
                    + ([BatchNorm2d(s(v))] if batch_norm else [])
                    + [nn.ReLU(inplace=True)]
                )
                ch, convs = s(v), convs + 1
                if convs == CONV4_3:
                    self.conv4_3 = len(layers) - 1  # its ReLU's index: 22 as in vgg16().features, 32 in vgg16_bn()
        self.features = nn.Sequential(*layers)
        self.l2norm = L2Norm(s(512))
        self.pool5 = nn.MaxPool2d(3, 1, 1)
        self.conv6 = nn.Conv2d(ch, s(1024), 3, padding=6, dilation=6)
        self.conv7 = nn.Conv2d(s(1024), s(1024), 1)
        self.bn6, self.bn7 = norm(s(1024)), norm(s(1024))
        ch = s(1024)
        self.extras = nn.ModuleList()
        self.extras_bn = nn.ModuleList()
        for out, k, stride, pad in EXTRAS:
            self.extras.append(nn.Conv2d(ch, s(out), k, stride, pad))
            self.extras_bn.append(norm(s(out)))
            ch = s(out)
        self.channels: list[int] = [s(512), s(1024)] + [s(e[0]) for e in EXTRAS[1::2]]
        if weights is not None:
            self.load(weights)

    def load(self, path: str | Path) -> None:
        """Load a local state dict: this whole module, or torchvision VGG-16 ``features.*`` into ``features``."""
        state = read_state_dict(path, ignore=("classifier.",))
        w = state.get("features.0.weight")
        if w is not None and w.dim() == 4 and w.shape[1] != self.in_channels:
            state["features.0.weight"] = adapt_first_conv(w, self.in_channels)
        full = any(k.startswith("conv6.") for k in state)
        target = self if full else self.features
        if not full:
            state = {k[len("features.") :]: v for k, v in state.items() if k.startswith("features.")}
        try:
            load_checked(target, state, path)
        except WeightsError as err:
            raise WeightsError(f"{err} (VGG16SSD, width {self.width})") from None

    def forward(self, x: Tensor) -> list[Tensor]:
        if x.dim() != 4 or x.shape[1] != self.in_channels:
            raise ValueError(f"VGG16SSD built for [B,{self.in_channels},H,W] input, got {tuple(x.shape)}")
        x = self.features[: self.conv4_3 + 1](x)
        outs = [self.l2norm(x)]
        x = self.features[self.conv4_3 + 1 :](x)
        x = torch.relu(self.bn7(self.conv7(torch.relu(self.bn6(self.conv6(self.pool5(x)))))))
        outs.append(x)
        for i, (conv, bn) in enumerate(zip(self.extras, self.extras_bn)):
            if conv.padding == (0, 0) and min(x.shape[-2:]) < conv.kernel_size[0]:
                raise ValueError(
                    f"input {tuple(outs[0].shape[-2:])} at conv4_3 is too small for the SSD300 extras: "
                    f"{tuple(x.shape[-2:])} before an unpadded 3x3 conv; use inputs of ~260 px or more"
                )
            x = torch.relu(bn(conv(x)))
            if i % 2 == 1:
                outs.append(x)
        return outs
