"""YOLACT-style instance head on an FPN (P3..P7), the prediction head of SMoE (seed 000 §4.1, Fig. 4)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ablate.tasks.yolact.anchors import ANCHOR_SCALES, ASPECT_RATIOS, Anchors


def _xavier(module: nn.Module) -> None:
    """SMoE §4.3: Xavier initialisation for the layers that are not the pre-trained backbone."""
    for m in module.modules():
        if isinstance(m, nn.Conv2d):
            nn.init.xavier_uniform_(m.weight)
            nn.init.zeros_(m.bias)


class Protonet(nn.Module):
    """YOLACT's Protonet on P3: three 3x3 conv + ReLU, x2 bilinear upsampling, 3x3 conv + ReLU, 1x1 conv to k
    prototypes + ReLU. Output [B, k, 2 H3, 2 W3] (a quarter of the input resolution for a stride-8 P3)."""

    def __init__(self, in_channels: int, num_prototypes: int, channels: int | None = None) -> None:
        super().__init__()
        c = channels or in_channels
        self.pre = nn.Sequential(
            *[
                m
                for i in range(3)
                for m in (nn.Conv2d(in_channels if i == 0 else c, c, 3, padding=1), nn.ReLU(inplace=True))
            ]
        )
        self.post = nn.Sequential(
            nn.Conv2d(c, c, 3, padding=1), nn.ReLU(inplace=True), nn.Conv2d(c, num_prototypes, 1), nn.ReLU()
        )

    def forward(self, p3: Tensor) -> Tensor:
        x = F.interpolate(self.pre(p3), scale_factor=2, mode="bilinear", align_corners=False)
        return self.post(x)


class YolactHead(nn.Module):
    """Protonet + a prediction head shared across P3..P7.

    ``forward(list[Tensor] P3..P7, each [B, C, Hl, Wl]) -> dict`` of raw maps, kept as [B, C, H, W] so late fusion
    can combine them elementwise:

    * ``proto``: [B, k, 2 H3, 2 W3] prototypes (ReLU),
    * ``cls``: per level [B, A (K + 1), Hl, Wl] class logits, channel ``a (K + 1) + c``, c = 0 background,
    * ``box``: per level [B, A 4, Hl, Wl] SSD offsets (see :func:`~ablate.tasks.yolact.anchors.encode`),
    * ``coef``: per level [B, A k, Hl, Wl] mask coefficients (tanh).

    ``out_channels`` gives the channel count of each map; ``anchors`` is the matching :class:`Anchors`.
    Class c of the targets (0 <= c < num_classes, e.g. 0 car, 1 pedestrian) is logit channel c + 1.
    """

    def __init__(
        self,
        in_channels: int,
        num_levels: int = 5,
        num_classes: int = 2,
        num_prototypes: int = 32,
        aspect_ratios: tuple[float, ...] = ASPECT_RATIOS,
        anchor_scales: tuple[float, ...] = ANCHOR_SCALES,
        proto_channels: int | None = None,
    ) -> None:
        super().__init__()
        if len(anchor_scales) != num_levels:
            raise ValueError(f"YolactHead: {len(anchor_scales)} anchor_scales for num_levels={num_levels}")
        self.num_levels, self.num_classes, self.num_prototypes = num_levels, num_classes, num_prototypes
        self.anchors = Anchors(anchor_scales, aspect_ratios)
        a = self.anchors.num_per_location
        self.protonet = Protonet(in_channels, num_prototypes, proto_channels)
        self.upfeature = nn.Sequential(nn.Conv2d(in_channels, in_channels, 3, padding=1), nn.ReLU(inplace=True))
        self.cls = nn.Conv2d(in_channels, a * (num_classes + 1), 3, padding=1)
        self.box = nn.Conv2d(in_channels, a * 4, 3, padding=1)
        self.coef = nn.Conv2d(in_channels, a * num_prototypes, 3, padding=1)
        self.out_channels: dict[str, int | list[int]] = {
            "proto": num_prototypes,
            "cls": [a * (num_classes + 1)] * num_levels,
            "box": [a * 4] * num_levels,
            "coef": [a * num_prototypes] * num_levels,
        }
        _xavier(self)

    def forward(self, features: list[Tensor]) -> dict[str, Tensor | list[Tensor]]:
        if len(features) != self.num_levels:
            raise ValueError(f"YolactHead: expected {self.num_levels} FPN levels (P3..), got {len(features)}")
        out: dict[str, Tensor | list[Tensor]] = {"proto": self.protonet(features[0]), "cls": [], "box": [], "coef": []}
        for f in features:
            x = self.upfeature(f)
            out["cls"].append(self.cls(x))
            out["box"].append(self.box(x))
            out["coef"].append(torch.tanh(self.coef(x)))
        return out
