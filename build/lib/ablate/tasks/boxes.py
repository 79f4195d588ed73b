"""Boxes shared by the detection heads (YOLACT, SSD): anchors, SSD box coding, SSD matching, NMS.

Boxes are in input-image pixels. ``xyxy`` boxes use pixel-edge coordinates (a box around pixel columns 3..5 has
x1=3, x2=6); anchors are ``cxcywh``. Head maps [B, A*D, Hl, Wl] flatten to [B, N, D] in :class:`Anchors` order
(:func:`flatten_levels`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import cast

import numpy as np
import torch
from torch import Tensor

#: SSD's encoding variances (centre, size), from its implementation.
VARIANCES = (0.1, 0.2)
UNITS = ("stride", "image")


class Anchors:
    """Anchor (default) boxes on every cell of each level, for an input of size (H, W) and levels [(Hl, Wl), ...].

    Centres: ``((j + .5) W / Wl, (i + .5) H / Hl)`` on cell (i, j) (SSD eq. 4's ((i + .5) / |f_k|, ...) in pixels).
    Sizes, for the scale ``s_l`` of level l and an aspect ratio r (width / height):

    * ``relative_to="stride"`` (YOLACT): a square of ``s_l`` strides, side ``d = s_l H / Hl``, reshaped to
      ``w = d sqrt(r)``, ``h = d / sqrt(r)``;
    * ``relative_to="image"`` (SSD eq. 4, normalised coordinates): ``w = s_l W sqrt(r)``, ``h = s_l H / sqrt(r)``.
      On an input warped to a square, as SSD300's, these are the paper's boxes; mapped back to the image they keep
      its aspect.

    ``aspect_ratios``: one tuple for every level, or one tuple per level. ``extra``: SSD's additional box of ratio 1
    and scale ``sqrt(s_l s_{l+1})`` after each level's others; past the last level the scales' last step goes on
    (``s_{m+1} = 2 s_m - s_{m-1}``, 1.05 after SSD300's 0.88). Order: level, row i, column j, box.
    """

    def __init__(
        self,
        scales: Sequence[float],
        aspect_ratios: Sequence[float] | Sequence[Sequence[float]],
        relative_to: str = "stride",
        extra: bool = False,
    ) -> None:
        per_level = (
            [tuple(r) for r in cast("Sequence[Sequence[float]]", aspect_ratios)]
            if aspect_ratios and isinstance(aspect_ratios[0], Sequence)
            else [tuple(cast("Sequence[float]", aspect_ratios))] * len(scales)
        )
        if not scales or min(scales) <= 0 or any(not r or min(r) <= 0 for r in per_level):
            raise ValueError(f"Anchors: scales and aspect_ratios must be positive, got {scales}, {aspect_ratios}")
        if len(per_level) != len(scales):
            raise ValueError(f"Anchors: {len(per_level)} aspect-ratio lists for {len(scales)} levels")
        if relative_to not in UNITS:
            raise ValueError(f"Anchors: relative_to must be one of {UNITS}, got {relative_to!r}")
        self.scales, self.ratios = tuple(float(s) for s in scales), [tuple(map(float, r)) for r in per_level]
        self.aspect_ratios = self.ratios[0] if len(set(self.ratios)) == 1 else tuple(self.ratios)
        self.relative_to, self.extra = relative_to, bool(extra)
        self._cache: dict[tuple, Tensor] = {}

    @property
    def num_per_level(self) -> list[int]:
        """Boxes per location on each level."""
        return [len(r) + self.extra for r in self.ratios]

    @property
    def num_per_location(self) -> int:
        """Boxes per location, when every level has the same number."""
        counts = set(self.num_per_level)
        if len(counts) != 1:
            raise ValueError(f"Anchors: the boxes per location vary by level ({self.num_per_level}); use num_per_level")
        return counts.pop()

    def shapes(self, image_size: tuple[int, int], level_sizes: list[tuple[int, int]]) -> list[Tensor]:
        """Per level, the [A, 2] (w, h) of its boxes in pixels."""
        h, w = image_size
        nxt = self.scales[-1] + (self.scales[-1] - self.scales[-2] if len(self.scales) > 1 else 0.0)
        out = []
        for k, ((hl, _), s, ratios) in enumerate(zip(level_sizes, self.scales, self.ratios)):
            bw, bh = (s * h / hl,) * 2 if self.relative_to == "stride" else (s * w, s * h)
            wh = [(bw * math.sqrt(r), bh / math.sqrt(r)) for r in ratios]
            if self.extra:
                prime = math.sqrt(s * (self.scales[k + 1] if k + 1 < len(self.scales) else nxt)) / s
                wh.append((bw * prime, bh * prime))
            out.append(torch.tensor(wh, dtype=torch.float32))
        return out

    def __call__(
        self, image_size: tuple[int, int], level_sizes: list[tuple[int, int]], device: torch.device | str = "cpu"
    ) -> Tensor:
        """[N, 4] anchors (cx, cy, w, h) in pixels, N = sum_l Hl * Wl * A_l."""
        if len(level_sizes) != len(self.scales):
            raise ValueError(f"Anchors: {len(level_sizes)} levels given but {len(self.scales)} scales configured")
        key = (tuple(image_size), tuple(map(tuple, level_sizes)), str(device))
        if key not in self._cache:
            h, w = image_size
            per_level = []
            for (hl, wl), sizes in zip(level_sizes, self.shapes(image_size, level_sizes)):
                cy = (torch.arange(hl, dtype=torch.float32) + 0.5) * h / hl
                cx = (torch.arange(wl, dtype=torch.float32) + 0.5) * w / wl
                cy, cx = torch.meshgrid(cy, cx, indexing="ij")
                centres = torch.stack([cx, cy], -1)[:, :, None, :].expand(hl, wl, len(sizes), 2)
                per_level.append(torch.cat([centres, sizes.expand_as(centres)], -1).reshape(-1, 4))
            self._cache[key] = torch.cat(per_level).to(device)
        return self._cache[key]


def flatten_levels(maps: list[Tensor], depth: int) -> Tensor:
    """Per-level maps [B, A_l*depth, Hl, Wl] -> [B, sum_l Hl*Wl*A_l, depth], in :class:`Anchors` order."""
    return torch.cat([m.permute(0, 2, 3, 1).reshape(m.shape[0], -1, depth) for m in maps], 1)


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


def box_inside(a: Tensor, b: Tensor) -> Tensor:
    """Share of each xyxy box of ``a`` [A, 4] lying inside each box of ``b`` [B, 4]: intersection / area(a)."""
    lt = torch.maximum(a[:, None, :2], b[None, :, :2])
    rb = torch.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = (rb - lt).clamp(min=0).prod(-1)
    return inter / (a[:, 2:] - a[:, :2]).clamp(min=0).prod(-1)[:, None].clamp(min=1e-9)


def encode(boxes: Tensor, anchors: Tensor, variances: tuple[float, float] = VARIANCES) -> Tensor:
    """SSD encoding (SSD eq. 2, with its implementation's variances) of xyxy boxes against cxcywh anchors:
    ((c - c_a) / (v0 wh_a), log(wh / wh_a) / v1)."""
    wh = (boxes[..., 2:] - boxes[..., :2]).clamp(min=1e-6)
    centre = (boxes[..., :2] + boxes[..., 2:]) / 2
    return torch.cat(
        [
            (centre - anchors[..., :2]) / (variances[0] * anchors[..., 2:]),
            torch.log(wh / anchors[..., 2:]) / variances[1],
        ],
        -1,
    )


def decode_boxes(loc: Tensor, anchors: Tensor, variances: tuple[float, float] = VARIANCES) -> Tensor:
    """Inverse of :func:`encode`: offsets [..., 4] -> xyxy boxes in pixels."""
    centre = anchors[..., :2] + loc[..., :2] * variances[0] * anchors[..., 2:]
    wh = anchors[..., 2:] * torch.exp(loc[..., 2:] * variances[1])
    return cxcywh_to_xyxy(torch.cat([centre, wh], -1))


def match(gt_boxes: Tensor, anchors: Tensor, pos_iou: float = 0.5, neg_iou: float = 0.4) -> tuple[Tensor, Tensor]:
    """SSD matching (SSD §2.2). Returns, per anchor, the index of its best GT and its state: 1 positive
    (IoU >= pos_iou), 0 negative (IoU < neg_iou), -1 neutral (in between, left out of the class loss). Each GT's
    best anchor is forced positive and assigned to that GT (GTs later in the list win when two share a best
    anchor). ``neg_iou == pos_iou`` is SSD's own rule: no neutral anchors."""
    n = anchors.shape[0]
    if gt_boxes.shape[0] == 0:
        return torch.zeros(n, dtype=torch.long, device=anchors.device), torch.zeros(
            n, dtype=torch.long, device=anchors.device
        )
    iou = box_iou(gt_boxes, cxcywh_to_xyxy(anchors))  # [G, N]
    best_iou, best_gt = iou.max(0)
    for g, a in enumerate(iou.argmax(1).tolist()):
        best_iou[a], best_gt[a] = 2.0, g
    state = torch.full((n,), -1, dtype=torch.long, device=anchors.device)
    state[best_iou >= pos_iou] = 1
    state[best_iou < neg_iou] = 0
    return best_gt, state


def fast_nms(
    boxes: Tensor,
    scores: Tensor,
    iou_threshold: float = 0.5,
    score_threshold: float = 0.05,
    top_k: int = 200,
    max_detections: int = 100,
) -> tuple[Tensor, Tensor, Tensor]:
    """YOLACT's Fast NMS (Bolya et al. 2019, §3.4), per class in matrix form.

    ``boxes`` [N, 4] xyxy, ``scores`` [N, C] (one column per foreground class). For each class the ``top_k``
    boxes are sorted by score; the upper triangle of their IoU matrix gives, per box, the largest IoU with any
    higher-scoring box of that class, and a box is kept when that IoU is <= ``iou_threshold`` and its score is
    > ``score_threshold``. Unlike greedy NMS, an already suppressed box still suppresses the boxes below it.
    Returns (box index, class, score) of at most ``max_detections`` kept boxes, highest score first.
    """
    k = min(top_k, boxes.shape[0])
    s, idx = scores.t().sort(1, descending=True)  # [C, N]
    s, idx = s[:, :k], idx[:, :k]
    iou = box_iou(boxes[idx], boxes[idx]).triu_(diagonal=1)  # [C, k, k]
    iou_max = iou.max(1).values if k else s
    keep = (iou_max <= iou_threshold) & (s > score_threshold)
    classes = torch.arange(scores.shape[1], device=scores.device)[:, None].expand_as(keep)[keep]
    s, order = s[keep].sort(descending=True)
    order = order[:max_detections]
    return idx[keep][order], classes[order], s[:max_detections]


def nms(boxes: Tensor, scores: Tensor, iou_threshold: float) -> Tensor:
    """Greedy NMS (SSD's inference, §3): boxes in order of descending score; each box still kept suppresses
    every later box whose IoU with it exceeds ``iou_threshold``. Returns the kept indices, highest score first
    (ties: lower index first)."""
    order = torch.sort(scores, descending=True, stable=True).indices
    iou = box_iou(boxes[order].float(), boxes[order].float()).cpu().numpy()
    keep = np.ones(len(order), bool)
    for i in range(len(order)):
        if keep[i]:
            keep[i + 1 :] &= iou[i, i + 1 :] <= iou_threshold
    return order[torch.from_numpy(keep).to(order.device)]
