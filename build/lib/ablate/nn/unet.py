"""U-Net building blocks (Ronneberger et al.), used by the ChiNet family (John et al.)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn


class ConvBlock(nn.Sequential):
    """Two 3x3 'same' convs, each followed by BatchNorm and ReLU; then Dropout2d(dropout) if dropout > 0."""

    def __init__(self, in_ch: int, out_ch: int, dropout: float = 0.0) -> None:
        if not 0.0 <= dropout < 1.0:
            raise ValueError(f"ConvBlock dropout must be in [0, 1), got {dropout}")
        layers: list[nn.Module] = []
        for c in (in_ch, out_ch):
            layers += [nn.Conv2d(c, out_ch, 3, padding=1, bias=False), nn.BatchNorm2d(out_ch), nn.ReLU(inplace=True)]
        if dropout > 0:
            layers.append(nn.Dropout2d(dropout))
        super().__init__(*layers)
        self.in_ch, self.out_ch = in_ch, out_ch


class Encoder(nn.Module):
    """A ConvBlock per width, a 2x2 max-pool between consecutive blocks.

    ``forward(x) -> list of skip features``, one per width (each taken before the pool that follows it),
    the deepest last; the i-th has ``widths[i]`` channels and stride 2**i. ``channels`` is ``widths``.
    """

    def __init__(self, in_ch: int, widths: list[int], dropout: float = 0.0) -> None:
        super().__init__()
        if not widths:
            raise ValueError("Encoder needs at least one width")
        self.channels: list[int] = list(widths)
        self.blocks = nn.ModuleList(
            ConvBlock(c, w, dropout) for c, w in zip([in_ch] + self.channels[:-1], self.channels)
        )
        self.pool = nn.MaxPool2d(2)

    def forward(self, x: Tensor) -> list[Tensor]:
        skips = []
        for i, block in enumerate(self.blocks):
            x = block(x if i == 0 else self.pool(x))
            skips.append(x)
        return skips


class DecoderBlock(nn.Module):
    """``forward(x, skip)``: upsample x to skip's size (x2 when sizes halve; ``mode`` nearest or bilinear),
    concatenate [x, skip] on channels, then a ConvBlock(in_ch + skip_ch -> out_ch)."""

    def __init__(self, in_ch: int, skip_ch: int, out_ch: int, dropout: float = 0.0, mode: str = "nearest") -> None:
        super().__init__()
        if mode not in ("nearest", "bilinear"):
            raise ValueError(f"DecoderBlock mode must be 'nearest' or 'bilinear', got {mode!r}")
        self.mode = mode
        self.block = ConvBlock(in_ch + skip_ch, out_ch, dropout)

    def forward(self, x: Tensor, skip: Tensor) -> Tensor:
        kw = {"align_corners": False} if self.mode == "bilinear" else {}
        x = F.interpolate(x, size=skip.shape[-2:], mode=self.mode, **kw)
        return self.block(torch.cat([x, skip], 1))
