"""SSD's convolutional predictors and default boxes (SSD, Liu et al. 2016 §2.1-2.2; DGFN §III-A detects "as done
in the SSD" on its fused maps)."""

from __future__ import annotations

from collections.abc import Sequence

from torch import Tensor, nn

from ablate.tasks.boxes import Anchors

#: SSD300's aspect ratios beyond 1 per map (conv4_3, conv7, conv8_2 .. conv11_2): each a_r adds a_r and 1 / a_r;
#: "for conv4_3, conv10_2 and conv11_2, we only associate 4 default boxes at each feature map location -- omitting
#: aspect ratios of 1/3 and 3" (SSD §3.1).
SSD300_RATIOS = ((2,), (2, 3), (2, 3), (2, 3), (2,), (2,))


def ssd_scales(num_levels: int, s_min: float = 0.2, s_max: float = 0.9, first: float | None = 0.1) -> tuple:
    """SSD eq. 4, ``s_k = s_min + (s_max - s_min)(k - 1)/(m - 1)``, k = 1..m. With ``first``, the first map (conv4_3)
    gets that scale and eq. 4 spans the other m - 1 maps, as SSD300 does ("we set default box with scale 0.1 on
    conv4_3", SSD §3.1): 0.1, 0.2, 0.375, 0.55, 0.725, 0.9 for six maps."""
    m = num_levels - (first is not None)
    rest = [s_min + (s_max - s_min) * k / max(m - 1, 1) for k in range(m)]
    return tuple(([first] if first is not None else []) + rest)


def ssd_ratios(extra: Sequence[float]) -> tuple[float, ...]:
    """SSD's aspect ratios of one map from its a_r beyond 1: (1, a_1, 1 / a_1, a_2, 1 / a_2, ...)."""
    return (1.0, *[x for r in extra for x in (float(r), 1.0 / float(r))])


class SSDHead(nn.Module):
    """Per map a 3x3 conv to A_l (K + 1) class scores and a 3x3 conv to A_l 4 box offsets (SSD §2.1).

    ``forward(list[Tensor[B, C_l, H_l, W_l]]) -> {"cls": [B, A_l (K + 1), H_l, W_l] per map, "box": [B, A_l 4, H_l,
    W_l] per map}``; channel ``a (K + 1) + c`` scores class c of box a, c = 0 background, class c of the targets
    (0 Car, 1 Pedestrian, 2 Cyclist) is logit channel c + 1. ``in_channels``: one count for every map (a FusionModel's
    FPN) or one per map (DGFN's VGG maps). ``aspect_ratios``: SSD's a_r beyond 1 per map; default SSD300's for six
    maps, (2, 3) on every map otherwise. Default boxes (:attr:`anchors`): SSD eq. 4 scales (:func:`ssd_scales`)
    relative to the image, plus the extra box sqrt(s_k s_{k+1}) of ratio 1.
    """

    def __init__(
        self,
        in_channels: int | Sequence[int],
        num_levels: int = 6,
        num_classes: int = 3,
        aspect_ratios: Sequence[Sequence[float]] | None = None,
        s_min: float = 0.2,
        s_max: float = 0.9,
        first_scale: float | None = 0.1,
    ) -> None:
        super().__init__()
        channels = [int(in_channels)] * num_levels if isinstance(in_channels, int) else [int(c) for c in in_channels]
        if len(channels) != num_levels:
            raise ValueError(f"SSDHead: {len(channels)} in_channels for num_levels={num_levels}")
        extra = aspect_ratios or (SSD300_RATIOS if num_levels == 6 else ((2, 3),) * num_levels)
        if len(extra) != num_levels:
            raise ValueError(f"head.aspect_ratios: {len(extra)} lists for {num_levels} maps")
        self.num_levels, self.num_classes = num_levels, num_classes
        self.anchors = Anchors(
            ssd_scales(num_levels, s_min, s_max, first_scale),
            [ssd_ratios(r) for r in extra],
            relative_to="image",
            extra=True,
        )
        a = self.anchors.num_per_level
        self.cls = nn.ModuleList(nn.Conv2d(c, n * (num_classes + 1), 3, padding=1) for c, n in zip(channels, a))
        self.box = nn.ModuleList(nn.Conv2d(c, n * 4, 3, padding=1) for c, n in zip(channels, a))
        self.out_channels = {"cls": [n * (num_classes + 1) for n in a], "box": [n * 4 for n in a]}
        for m in self.modules():  # SSD §3.1: new layers initialised with the "xavier" method
            if isinstance(m, nn.Conv2d):
                nn.init.xavier_uniform_(m.weight)
                nn.init.zeros_(m.bias)

    def forward(self, features: list[Tensor]) -> dict[str, list[Tensor]]:
        if len(features) != self.num_levels:
            raise ValueError(f"SSDHead: expected {self.num_levels} maps, got {len(features)}")
        return {
            "cls": [conv(f) for conv, f in zip(self.cls, features)],
            "box": [conv(f) for conv, f in zip(self.box, features)],
        }
