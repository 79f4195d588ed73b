"""YOLACT training loss, SMoE (seed 000) §4.3 eq. 7: L = L_cls + alpha L_box + beta L_mask."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ablate.tasks.boxes import VARIANCES, encode, flatten_levels, match
from ablate.tasks.yolact.anchors import Anchors, box_region


class YolactLoss(nn.Module):
    """SMoE eq. 7 on the raw maps of :class:`~ablate.tasks.yolact.head.YolactHead` (or their fusion).

    * L_cls: softmax cross-entropy over K + 1 classes on the positives and on the hardest negatives (OHEM,
      ``neg_pos_ratio`` : 1, ranked by their background loss), summed and divided by the number of positives in
      the batch. Neutral anchors (neg_iou <= IoU < pos_iou) are left out. Reading for an image without GT: it
      contributes its ``neg_pos_ratio`` hardest negatives (as if it had one positive), so empty frames still
      teach the background class.
    * L_box: smooth-L1 (beta 1) between predicted and SSD-encoded GT offsets of the positives, / positives.
    * L_mask: per positive, the pixel-wise BCE of sigmoid(proto @ coef) against the GT mask (resized to the
      prototype resolution, > 0.5) summed inside the GT box and divided by the box area in prototype pixels (so
      each instance weighs the same whatever its size), then averaged over the instances. At most ``max_masks``
      positives per image are used (a random subset, as in YOLACT).

    Defaults alpha = 1.5, beta = 6.125 are YOLACT's weights; SMoE does not state its own.
    ``forward(outputs, targets, image_size)``: targets are one dict per image with ``boxes`` (G, 4) xyxy pixels,
    ``labels`` (G,) in [0, K) and ``masks`` (G, H, W); returns ``cls``, ``box``, ``mask`` and ``total``.
    """

    def __init__(
        self,
        anchors: Anchors | None = None,
        alpha: float = 1.5,
        beta: float = 6.125,
        neg_pos_ratio: int = 3,
        pos_iou: float = 0.5,
        neg_iou: float = 0.4,
        variances: tuple[float, float] = VARIANCES,
        max_masks: int = 100,
    ) -> None:
        super().__init__()
        if not 0 < neg_iou <= pos_iou <= 1:
            raise ValueError(f"YolactLoss: need 0 < neg_iou <= pos_iou <= 1, got {neg_iou}, {pos_iou}")
        self.anchors = anchors or Anchors()
        self.alpha, self.beta, self.neg_pos_ratio = alpha, beta, neg_pos_ratio
        self.pos_iou, self.neg_iou, self.variances, self.max_masks = pos_iou, neg_iou, variances, max_masks

    def forward(self, outputs: dict, targets: list[dict[str, Tensor]], image_size: tuple[int, int]) -> dict:
        proto = outputs["proto"]
        a = self.anchors.num_per_location
        cls = flatten_levels(outputs["cls"], outputs["cls"][0].shape[1] // a)
        loc = flatten_levels(outputs["box"], 4)
        coef = flatten_levels(outputs["coef"], proto.shape[1])
        if len(targets) != cls.shape[0]:
            raise ValueError(f"YolactLoss: {len(targets)} targets for a batch of {cls.shape[0]}")
        anchors = self.anchors(image_size, [tuple(m.shape[-2:]) for m in outputs["cls"]], cls.device)
        # zero-valued terms that keep every output in the graph when a batch has no positives
        cls_sum, box_sum, mask_sum = cls.sum() * 0, loc.sum() * 0, (coef.sum() + proto.sum()) * 0
        num_pos = num_masks = 0
        for b, t in enumerate(targets):
            boxes = t["boxes"].to(loc.dtype).reshape(-1, 4)
            labels = t["labels"].long().reshape(-1)
            idx, state = match(boxes, anchors, self.pos_iou, self.neg_iou)
            pos = state == 1
            n_pos = int(pos.sum())
            conf_t = torch.zeros_like(idx)
            conf_t[pos] = labels[idx[pos]] + 1
            ce = F.cross_entropy(cls[b], conf_t, reduction="none")
            rank = torch.where(state == 0, ce.detach(), torch.full_like(ce, -1.0))
            n_neg = min(self.neg_pos_ratio * max(n_pos, 1), int((state == 0).sum()))
            cls_sum = cls_sum + ce[pos].sum() + ce[rank.topk(n_neg).indices].sum()
            if n_pos == 0:
                continue
            num_pos += n_pos
            box_sum = box_sum + F.smooth_l1_loss(
                loc[b][pos], encode(boxes[idx[pos]], anchors[pos], self.variances), reduction="sum"
            )
            pos_idx = pos.nonzero().squeeze(1)
            if n_pos > self.max_masks:
                pos_idx = pos_idx[torch.randperm(n_pos, device=pos_idx.device)[: self.max_masks]]
            mask_sum = mask_sum + self._mask_loss(
                proto[b], coef[b][pos_idx], t["masks"], boxes, idx[pos_idx], image_size
            )
            num_masks += len(pos_idx)
        losses = {
            "cls": cls_sum / max(num_pos, 1),
            "box": box_sum / max(num_pos, 1),
            "mask": mask_sum / max(num_masks, 1),
        }
        losses["total"] = losses["cls"] + self.alpha * losses["box"] + self.beta * losses["mask"]
        return losses

    @staticmethod
    def _mask_loss(
        proto: Tensor, coef: Tensor, gt_masks: Tensor, gt_boxes: Tensor, gt_idx: Tensor, image_size: tuple[int, int]
    ) -> Tensor:
        """Sum over instances of the box-cropped, box-area-normalised BCE (SMoE eq. 7, L_mask)."""
        hp, wp = proto.shape[-2:]
        logits = torch.einsum("khw,nk->nhw", proto, coef)
        gt = F.interpolate(gt_masks[None].to(proto.dtype), (hp, wp), mode="bilinear", align_corners=False)[0]
        gt = (gt > 0.5).to(proto.dtype)[gt_idx]
        scale = torch.tensor([wp / image_size[1], hp / image_size[0]] * 2, device=proto.device, dtype=proto.dtype)
        region = box_region(gt_boxes[gt_idx] * scale, hp, wp).to(proto.dtype)
        bce = F.binary_cross_entropy_with_logits(logits, gt, reduction="none")
        return ((bce * region).sum((1, 2)) / region.sum((1, 2)).clamp(min=1)).sum()
