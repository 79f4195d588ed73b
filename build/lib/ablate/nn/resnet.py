"""ResNet-18/34/50/101 (He et al.) in plain torch, returning C2-C5, with a width multiplier and any input channels.

Parameter names follow torchvision's ResNet (``conv1``, ``bn1``, ``layer1.0.conv1``, ``...downsample.0``), so a
torchvision ImageNet state dict saved to a local file loads at width 1.0 (its ``fc.`` keys are ignored).
"""

from __future__ import annotations

from pathlib import Path

from torch import Tensor, nn

from ablate.nn.weights import WeightsError, adapt_first_conv, load_checked, read_state_dict


class BasicBlock(nn.Module):
    """Two 3x3 convs with a residual connection (ResNet-18/34)."""

    expansion = 1

    def __init__(self, in_ch: int, width: int, stride: int = 1) -> None:
        super().__init__()
        out = width * self.expansion
        self.conv1 = nn.Conv2d(in_ch, width, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(width)
        self.conv2 = nn.Conv2d(width, out, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(out)
        self.relu = nn.ReLU(inplace=True)
        self.downsample = _shortcut(in_ch, out, stride)

    def forward(self, x: Tensor) -> Tensor:
        y = self.relu(self.bn1(self.conv1(x)))
        y = self.bn2(self.conv2(y))
        return self.relu(y + (x if self.downsample is None else self.downsample(x)))


class Bottleneck(nn.Module):
    """1x1 - 3x3 (stride here, as torchvision's v1.5) - 1x1 convs with a residual connection (ResNet-50/101)."""

    expansion = 4

    def __init__(self, in_ch: int, width: int, stride: int = 1) -> None:
        super().__init__()
        out = width * self.expansion
        self.conv1 = nn.Conv2d(in_ch, width, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(width)
        self.conv2 = nn.Conv2d(width, width, 3, stride, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(width)
        self.conv3 = nn.Conv2d(width, out, 1, bias=False)
        self.bn3 = nn.BatchNorm2d(out)
        self.relu = nn.ReLU(inplace=True)
        self.downsample = _shortcut(in_ch, out, stride)

    def forward(self, x: Tensor) -> Tensor:
        y = self.relu(self.bn1(self.conv1(x)))
        y = self.relu(self.bn2(self.conv2(y)))
        y = self.bn3(self.conv3(y))
        return self.relu(y + (x if self.downsample is None else self.downsample(x)))


def _shortcut(in_ch: int, out: int, stride: int) -> nn.Sequential | None:
    if stride == 1 and in_ch == out:
        return None
    return nn.Sequential(nn.Conv2d(in_ch, out, 1, stride, bias=False), nn.BatchNorm2d(out))


DEPTHS: dict[int, tuple[type[nn.Module], tuple[int, int, int, int]]] = {
    18: (BasicBlock, (2, 2, 2, 2)),
    34: (BasicBlock, (3, 4, 6, 3)),
    50: (Bottleneck, (3, 4, 6, 3)),
    101: (Bottleneck, (3, 4, 23, 3)),
}


class ResNet(nn.Module):
    """ResNet trunk without the classifier: ``forward(x [B,in_channels,H,W]) -> [C2, C3, C4, C5]``.

    C2..C5 have strides 4, 8, 16, 32 and ``channels[k]`` channels. ``width`` scales every stage width
    (64, 128, 256, 512 at 1.0; at least 1 channel each). ``weights``: a local state dict file; when
    ``in_channels`` differs from the file's first conv (ImageNet: 3), that conv is adapted by
    ``weights.adapt_first_conv``.
    """

    def __init__(
        self, depth: int = 18, width: float = 1.0, in_channels: int = 3, weights: str | Path | None = None
    ) -> None:
        super().__init__()
        if depth not in DEPTHS:
            raise ValueError(f"unknown ResNet depth {depth}; valid: {sorted(DEPTHS)}")
        if width <= 0 or in_channels < 1:
            raise ValueError(
                f"ResNet needs width > 0 and in_channels >= 1, got width={width}, in_channels={in_channels}"
            )
        block, counts = DEPTHS[depth]
        self.depth, self.width, self.in_channels = depth, width, in_channels
        widths = [max(1, round(w * width)) for w in (64, 128, 256, 512)]
        self.conv1 = nn.Conv2d(in_channels, widths[0], 7, 2, 3, bias=False)
        self.bn1 = nn.BatchNorm2d(widths[0])
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(3, 2, 1)
        ch = widths[0]
        for i, (w, n) in enumerate(zip(widths, counts)):
            blocks = []
            for j in range(n):
                blocks.append(block(ch, w, stride=2 if (j == 0 and i > 0) else 1))
                ch = w * block.expansion
            setattr(self, f"layer{i + 1}", nn.Sequential(*blocks))
        self.channels: list[int] = [w * block.expansion for w in widths]
        self._init()
        if weights is not None:
            self.load(weights)

    def _init(self) -> None:
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)

    def load(self, path: str | Path) -> None:
        """Load a local state dict (torchvision names; ``fc.`` ignored), adapting the first conv's input channels."""
        state = read_state_dict(path, ignore=("fc.",))
        w = state.get("conv1.weight")
        if w is not None and w.dim() == 4 and w.shape[1] != self.in_channels and w.shape[0] == self.conv1.out_channels:
            state["conv1.weight"] = adapt_first_conv(w, self.in_channels)
        try:
            load_checked(self, state, path)
        except WeightsError as err:
            raise WeightsError(f"{err} (ResNet-{self.depth}, width {self.width})") from None

    def forward(self, x: Tensor) -> list[Tensor]:
        if x.dim() != 4 or x.shape[1] != self.in_channels:
            raise ValueError(f"ResNet built for [B,{self.in_channels},H,W] input, got {tuple(x.shape)}")
        x = self.maxpool(self.relu(self.bn1(self.conv1(x))))
        c2 = self.layer1(x)
        c3 = self.layer2(c2)
        c4 = self.layer3(c3)
        return [c2, c3, c4, self.layer4(c4)]
