"""Anchors, SSD box encoding and SSD-style matching of the YOLACT head SMoE builds on (seed 000 §4.1, §4.3).

Boxes are in input-image pixels. ``xyxy`` boxes use pixel-edge coordinates (a box around pixel columns 3..5 has
x1=3, x2=6); anchors are ``cxcywh``.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

#: Anchor sizes in units of each level's stride. YOLACT's 24, 48, 96, 192, 384 px on P3..P7 at its 550 px input
#: are 3 strides each (24 / 8, 48 / 16, ...); tying the size to the stride keeps that layout at any input size.
#: (Sizes taken as fractions of the input height instead shrink below the grid step on small inputs: at 128x416
#: they are 5.6 px on P3's 8 px grid, and only 3% of the generated data's boxes then have an anchor with
#: IoU >= 0.5, against 58% with 3 strides.)
ANCHOR_SCALES = (3.0, 3.0, 3.0, 3.0, 3.0)
#: Width / height ratios of the anchors at every location (issue 5: 1, 1/2, 2).
ASPECT_RATIOS = (1.0, 0.5, 2.0)
#: SSD's encoding variances (centre, size).
VARIANCES = (0.1, 0.2)


class Anchors:
    """Anchor boxes for an input of size (H, W) and FPN levels of sizes [(H3, W3), ..., (H7, W7)].

    On level l an anchor of aspect ratio r is ``s_l * d_l * sqrt(r)`` wide and ``s_l * d_l / sqrt(r)`` tall, with
    ``s_l = scales[l]`` in units of the level's stride ``d_l = H / Hl``, centred on each cell
    ``((j + .5) W / Wl, (i + .5) H / Hl)``.
    Order: level, row i, column j, ratio — the order of a head map [B, A*D, Hl, Wl] permuted to [B, Hl, Wl, A, D].
    """

    def __init__(self, scales: tuple[float, ...] = ANCHOR_SCALES,
                 aspect_ratios: tuple[float, ...] = ASPECT_RATIOS) -> None:
        if not scales or not aspect_ratios or min(scales) <= 0 or min(aspect_ratios) <= 0:
            raise ValueError(f"Anchors: scales and aspect_ratios must be positive, got {scales}, {aspect_ratios}")
        self.scales, self.aspect_ratios = tuple(scales), tuple(aspect_ratios)
        self._cache: dict[tuple, Tensor] = {}

    @property
    def num_per_location(self) -> int:
        return len(self.aspect_ratios)

    def __call__(self, image_size: tuple[int, int], level_sizes: list[tuple[int, int]],
                 device: torch.device | str = "cpu") -> Tensor:
        """[N, 4] anchors (cx, cy, w, h) in pixels, N = sum_l Hl * Wl * A."""
        if len(level_sizes) != len(self.scales):
            raise ValueError(f"Anchors: {len(level_sizes)} levels given but {len(self.scales)} scales configured")
        key = (tuple(image_size), tuple(map(tuple, level_sizes)), str(device))
        if key not in self._cache:
            h, w = image_size
            per_level = []
            for (hl, wl), s in zip(level_sizes, self.scales):
                cy = (torch.arange(hl, dtype=torch.float32) + 0.5) * h / hl
                cx = (torch.arange(wl, dtype=torch.float32) + 0.5) * w / wl
                cy, cx = torch.meshgrid(cy, cx, indexing="ij")
                size = s * h / hl
                sizes = torch.tensor([[size * math.sqrt(r), size / math.sqrt(r)] for r in self.aspect_ratios])
                centres = torch.stack([cx, cy], -1)[:, :, None, :].expand(hl, wl, len(self.aspect_ratios), 2)
                per_level.append(torch.cat([centres, sizes.expand_as(centres)], -1).reshape(-1, 4))
            self._cache[key] = torch.cat(per_level).to(device)
        return self._cache[key]


def cxcywh_to_xyxy(b: Tensor) -> Tensor:
    return torch.cat([b[..., :2] - b[..., 2:] / 2, b[..., :2] + b[..., 2:] / 2], -1)


def box_iou(a: Tensor, b: Tensor) -> Tensor:
    """IoU of xyxy boxes, [..., A, 4] x [..., B, 4] -> [..., A, B] (leading dims broadcast)."""
    lt = torch.maximum(a[..., :, None, :2], b[..., None, :, :2])
    rb = torch.minimum(a[..., :, None, 2:], b[..., None, :, 2:])
    inter = (rb - lt).clamp(min=0).prod(-1)
    area_a = (a[..., 2:] - a[..., :2]).clamp(min=0).prod(-1)
    area_b = (b[..., 2:] - b[..., :2]).clamp(min=0).prod(-1)
    return inter / (area_a[..., :, None] + area_b[..., None, :] - inter).clamp(min=1e-9)


def encode(boxes: Tensor, anchors: Tensor, variances: tuple[float, float] = VARIANCES) -> Tensor:
    """SSD encoding of xyxy boxes against cxcywh anchors: ((c - c_a) / (v0 w_a), log(wh / wh_a) / v1)."""
    wh = (boxes[..., 2:] - boxes[..., :2]).clamp(min=1e-6)
    centre = (boxes[..., :2] + boxes[..., 2:]) / 2
    return torch.cat([(centre - anchors[..., :2]) / (variances[0] * anchors[..., 2:]),
                      torch.log(wh / anchors[..., 2:]) / variances[1]], -1)


def decode_boxes(loc: Tensor, anchors: Tensor, variances: tuple[float, float] = VARIANCES) -> Tensor:
    """Inverse of :func:`encode`: offsets [..., 4] -> xyxy boxes in pixels."""
    centre = anchors[..., :2] + loc[..., :2] * variances[0] * anchors[..., 2:]
    wh = anchors[..., 2:] * torch.exp(loc[..., 2:] * variances[1])
    return cxcywh_to_xyxy(torch.cat([centre, wh], -1))


def match(gt_boxes: Tensor, anchors: Tensor, pos_iou: float = 0.5, neg_iou: float = 0.4) -> tuple[Tensor, Tensor]:
    """SSD matching. Returns, per anchor, the index of its best GT and its state: 1 positive (IoU >= pos_iou),
    0 negative (IoU < neg_iou), -1 neutral (in between, left out of the class loss). Each GT's best anchor is forced
    positive and assigned to that GT (GTs later in the list win when two share a best anchor)."""
    n = anchors.shape[0]
    if gt_boxes.shape[0] == 0:
        return torch.zeros(n, dtype=torch.long, device=anchors.device), torch.zeros(n, dtype=torch.long,
                                                                                    device=anchors.device)
    iou = box_iou(gt_boxes, cxcywh_to_xyxy(anchors))  # [G, N]
    best_iou, best_gt = iou.max(0)
    for g, a in enumerate(iou.argmax(1).tolist()):
        best_iou[a], best_gt[a] = 2.0, g
    state = torch.full((n,), -1, dtype=torch.long, device=anchors.device)
    state[best_iou >= pos_iou] = 1
    state[best_iou < neg_iou] = 0
    return best_gt, state


def box_region(boxes: Tensor, height: int, width: int) -> Tensor:
    """[n, height, width] bool: pixels whose centre lies in the xyxy box (pixel-edge coordinates, in the pixel
    units of a height x width grid). YOLACT's crop, used on the mask loss and on assembled masks."""
    ys = torch.arange(height, device=boxes.device, dtype=boxes.dtype) + 0.5
    xs = torch.arange(width, device=boxes.device, dtype=boxes.dtype) + 0.5
    x1, y1, x2, y2 = (boxes[:, i, None] for i in range(4))
    in_x = (xs[None] >= x1) & (xs[None] < x2)
    in_y = (ys[None] >= y1) & (ys[None] < y2)
    return in_y[:, :, None] & in_x[:, None, :]
