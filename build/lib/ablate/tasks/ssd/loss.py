"""SSD's training objective (Liu et al. 2016 §2.2, eq. 1-3), which DGFN adopts with SSD's "matching strategy, hard
negative mining, and loss function" (seed 002 §IV-A)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ablate.tasks.boxes import VARIANCES, Anchors, box_inside, cxcywh_to_xyxy, encode, flatten_levels, match


class SSDLoss(nn.Module):
    """SSD eq. 1: ``L = (L_conf + alpha L_loc) / N``, N the matched default boxes of the batch; L = 0 when N = 0.

    * Matching (§2.2): each GT to the default box of best IoU, then every default box with IoU >= ``iou`` (0.5)
      to its best GT (:func:`ablate.tasks.boxes.match` with no neutral zone).
    * Ignore regions: GT boxes labelled ``>= num_classes`` (``boxes2d``'s KITTI Van, Person_sitting and DontCare)
      are never matched, and a default box with at least ``ignore_inside`` (half) of its area inside one is left
      out of the negatives. Reading: SSD has no ignore regions; this follows KITTI's evaluation, which neither
      rewards nor penalises a detection of a Van as a Car, of a Person_sitting as a Pedestrian, or in a DontCare
      area.
    * L_conf (eq. 3): softmax cross-entropy over K + 1 classes on the positives and the hard negatives: per image
      the negatives of highest background loss, at most ``neg_pos_ratio`` (3) per positive ("Hard negative
      mining"); an image without positives adds none (SSD's implementation).
    * L_loc (eq. 2): smooth L1 between predicted and encoded GT offsets of the positives (SSD's implementation
      divides the offsets by the variances 0.1, 0.2; :func:`ablate.tasks.boxes.encode`).

    ``forward(outputs, targets, image_size)``: ``outputs`` the head's ``cls`` and ``box`` maps; ``targets`` one dict
    per image with ``boxes`` (G, 4) xyxy pixels and ``labels`` (G,); returns ``cls``, ``box`` and ``total``.
    """

    def __init__(
        self,
        anchors: Anchors,
        num_classes: int,
        alpha: float = 1.0,
        neg_pos_ratio: int = 3,
        iou: float = 0.5,
        ignore_inside: float = 0.5,
        variances: tuple[float, float] = VARIANCES,
    ) -> None:
        super().__init__()
        if not 0 < iou <= 1 or not 0 < ignore_inside <= 1:
            raise ValueError(f"task.loss: iou and ignore_inside must be in (0, 1], got {iou}, {ignore_inside}")
        self.anchors, self.num_classes = anchors, num_classes
        self.alpha, self.neg_pos_ratio, self.iou = alpha, neg_pos_ratio, iou
        self.ignore_inside, self.variances = ignore_inside, variances

    def assign(self, boxes: Tensor, labels: Tensor, anchors: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Per anchor: its class target (0 background, c + 1 class c), its state (1 positive, 0 negative,
        -1 ignored) and the index of its GT among the real ones; and which GTs are real (not ignore regions)."""
        real = labels < self.num_classes
        idx, state = match(boxes[real], anchors, self.iou, self.iou)
        conf = torch.zeros_like(idx)
        conf[state == 1] = labels[real][idx[state == 1]] + 1
        if (~real).any():
            inside = box_inside(cxcywh_to_xyxy(anchors), boxes[~real]).max(1).values
            state[(state == 0) & (inside >= self.ignore_inside)] = -1
        return conf, state, idx, real

    def forward(self, outputs: dict, targets: list[dict[str, Tensor]], image_size: tuple[int, int]) -> dict:
        counts = self.anchors.num_per_level
        cls = flatten_levels(outputs["cls"], outputs["cls"][0].shape[1] // counts[0])
        loc = flatten_levels(outputs["box"], 4)
        if len(targets) != cls.shape[0]:
            raise ValueError(f"SSDLoss: {len(targets)} targets for a batch of {cls.shape[0]}")
        anchors = self.anchors(image_size, [tuple(m.shape[-2:]) for m in outputs["cls"]], cls.device)
        if anchors.shape[0] != cls.shape[1]:
            raise ValueError(
                f"SSDLoss: {cls.shape[1]} predicted boxes for {anchors.shape[0]} default boxes; "
                "the loss needs the head's anchors"
            )
        cls_sum, box_sum, num_pos = cls.sum() * 0, loc.sum() * 0, 0  # zeros that keep the outputs in the graph
        for b, t in enumerate(targets):
            boxes, labels = t["boxes"].to(loc.dtype).reshape(-1, 4), t["labels"].long().reshape(-1)
            conf, state, idx, real = self.assign(boxes, labels, anchors)
            pos = state == 1
            n_pos = int(pos.sum())
            if n_pos == 0:
                continue
            ce = F.cross_entropy(cls[b], conf, reduction="none")
            rank = torch.where(state == 0, ce.detach(), torch.full_like(ce, -1.0))
            n_neg = min(self.neg_pos_ratio * n_pos, int((state == 0).sum()))
            cls_sum = cls_sum + ce[pos].sum() + ce[rank.topk(n_neg).indices].sum()
            gt = boxes[real][idx[pos]]
            box_sum = box_sum + F.smooth_l1_loss(loc[b][pos], encode(gt, anchors[pos], self.variances), reduction="sum")
            num_pos += n_pos
        n = max(num_pos, 1)
        losses = {"cls": cls_sum / n, "box": box_sum / n}
        losses["total"] = losses["cls"] + self.alpha * losses["box"]
        return losses
