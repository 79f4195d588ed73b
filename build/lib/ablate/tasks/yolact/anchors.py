"""The anchor layout of the YOLACT head SMoE builds on (seed 000 §4.1, §4.3); the anchor grid, SSD box coding and
matching are the shared ones of :mod:`ablate.tasks.boxes`.

Boxes are in input-image pixels. ``xyxy`` boxes use pixel-edge coordinates (a box around pixel columns 3..5 has
x1=3, x2=6); anchors are ``cxcywh``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ablate.tasks import boxes
from ablate.tasks.boxes import VARIANCES, box_iou, cxcywh_to_xyxy, decode_boxes, encode, match

__all__ = [
    "ANCHOR_SCALES",
    "ASPECT_RATIOS",
    "VARIANCES",
    "Anchors",
    "box_iou",
    "box_region",
    "cxcywh_to_xyxy",
    "decode_boxes",
    "encode",
    "match",
]

#: Anchor sizes in units of each level's stride. YOLACT's 24, 48, 96, 192, 384 px on P3..P7 at its 550 px input
#: are 3 strides each (24 / 8, 48 / 16, ...); tying the size to the stride keeps that layout at any input size.
#: (Sizes taken as fractions of the input height instead shrink below the grid step on small inputs: at 128x416
#: they are 5.6 px on P3's 8 px grid, and only 3% of the generated data's boxes then have an anchor with
#: IoU >= 0.5, against 58% with 3 strides.)
ANCHOR_SCALES = (3.0, 3.0, 3.0, 3.0, 3.0)
#: Width / height ratios of the anchors at every location (issue 5: 1, 1/2, 2).
ASPECT_RATIOS = (1.0, 0.5, 2.0)


class Anchors(boxes.Anchors):
    """YOLACT's anchors (:class:`ablate.tasks.boxes.Anchors` in stride units): on level l an anchor of aspect
    ratio r is ``s_l * d_l * sqrt(r)`` wide and ``s_l * d_l / sqrt(r)`` tall, with ``s_l = scales[l]`` in units of
    the level's stride ``d_l = H / Hl``."""

    def __init__(
        self, scales: tuple[float, ...] = ANCHOR_SCALES, aspect_ratios: tuple[float, ...] = ASPECT_RATIOS
    ) -> None:
        super().__init__(scales, aspect_ratios, relative_to="stride")


def box_region(boxes: Tensor, height: int, width: int) -> Tensor:
    """[n, height, width] bool: pixels whose centre lies in the xyxy box (pixel-edge coordinates, in the pixel
    units of a height x width grid). YOLACT's crop, used on the mask loss and on assembled masks."""
    ys = torch.arange(height, device=boxes.device, dtype=boxes.dtype) + 0.5
    xs = torch.arange(width, device=boxes.device, dtype=boxes.dtype) + 0.5
    x1, y1, x2, y2 = (boxes[:, i, None] for i in range(4))
    in_x = (xs[None] >= x1) & (xs[None] < x2)
    in_y = (ys[None] >= y1) & (ys[None] < y2)
    return in_y[:, :, None] & in_x[:, None, :]
