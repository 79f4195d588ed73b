"""YOLACT-style feature pyramid (Lin et al. FPN as used by YOLACT, Bolya et al. 2019): C3-C5 -> P3-P7."""

from __future__ import annotations

import torch.nn.functional as F
from torch import Tensor, nn


class FPN(nn.Module):
    """``forward([C3, C4, C5]) -> [P3, P4, P5, P6, P7]``, every level with ``out_channels`` channels.

    As in YOLACT: 1x1 lateral convs; top-down pathway by bilinear upsampling to the finer level's size and
    addition; a 3x3 conv + ReLU on each of P3-P5; P6 and P7 by 3x3 stride-2 convs (no ReLU), P6 from P5 and
    P7 from P6. ``num_downsample`` sets how many stride-2 levels follow P5 (2 gives P6, P7).
    """

    def __init__(self, in_channels: list[int], out_channels: int = 256, num_downsample: int = 2) -> None:
        super().__init__()
        if len(in_channels) < 1 or out_channels < 1 or num_downsample < 0:
            raise ValueError(
                f"FPN needs in_channels (one per input level), out_channels >= 1, num_downsample >= 0; "
                f"got {in_channels}, {out_channels}, {num_downsample}"
            )
        self.in_channels, self.out_channels = list(in_channels), out_channels
        self.lateral = nn.ModuleList(nn.Conv2d(c, out_channels, 1) for c in in_channels)
        self.pred = nn.ModuleList(nn.Conv2d(out_channels, out_channels, 3, padding=1) for _ in in_channels)
        self.downsample = nn.ModuleList(nn.Conv2d(out_channels, out_channels, 3, 2, 1) for _ in range(num_downsample))
        self.num_levels = len(in_channels) + num_downsample

    def forward(self, features: list[Tensor]) -> list[Tensor]:
        if len(features) != len(self.lateral) or any(f.shape[1] != c for f, c in zip(features, self.in_channels)):
            raise ValueError(
                f"FPN built for inputs with channels {self.in_channels}, got {[tuple(f.shape) for f in features]}"
            )
        outs: list[Tensor] = [None] * len(features)
        x = None
        for j in range(len(features) - 1, -1, -1):
            lat = self.lateral[j](features[j])
            x = lat if x is None else lat + F.interpolate(x, size=lat.shape[-2:], mode="bilinear", align_corners=False)
            outs[j] = x
        outs = [F.relu(pred(o)) for pred, o in zip(self.pred, outs)]
        for down in self.downsample:
            outs.append(down(outs[-1]))
        return outs
