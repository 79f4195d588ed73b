"""COCO-style mask and box AP (pycocotools COCOeval) as a torchmetrics ``Metric``.

SMoE (seed 000) §5 reports AP, AP50 and AP75 of instance masks and evaluates "only objects larger than 25 pixels
in height which follows the same principle with KITTI object detection benchmark". Readings chosen here:

* Height threshold. KITTI's devkit ignores a ground truth whose box height is below ``MIN_HEIGHT`` (25 px for the
  moderate/hard levels), so an object counts when ``height >= min_height * image_height / reference_height``
  (25 px at KITTI's 375 px image height, scaled for other input sizes). The height is the GT box height: the
  given ``boxes`` or, if absent, the tight box of the mask.
* Smaller ground truths are not removed but marked ``iscrowd=1``: COCOeval then lets a detection match them
  without counting it as a TP or an FP, and they never count as misses. COCOeval's crowd matching measures a
  detection's overlap with a crowd GT as intersection / detection area, so a detection lying mostly inside a small
  object is ignored, while one that merely covers it remains an FP.
* DontCare. A prediction is dropped at ``update`` when more than ``ignore_overlap`` (default 0.5) of its mask area
  lies inside the image's ``ignore`` region. Ground truths are kept as given.
* Boxes. Given boxes are xyxy in pixel-edge coordinates (a box around pixel columns 3..5 is x1=3, x2=6), the
  convention of pycocotools' ``toBbox``, which supplies the boxes of the masks when none are given.
* Empty cases follow COCOeval: classes with no counted GT are left out of the mean; if no class has a counted GT
  (or nothing was updated) every value is -1. Ground truths with no predictions give 0.

States are flat 1-D tensors per image concatenated with ``dist_reduce_fx="cat"``; masks are kept as compressed
RLE bytes, so the metric works under DDP and costs a few bytes per mask.
"""

from __future__ import annotations

import contextlib
import io
from typing import Any

import numpy as np
import torch
from pycocotools import mask as mask_utils
from pycocotools.coco import COCO
from pycocotools.cocoeval import COCOeval
from torch import Tensor
from torchmetrics import Metric
from torchmetrics.utilities import dim_zero_cat

from ablate.data.difficulty import MIN_HEIGHT, REFERENCE_HEIGHT, counted
from ablate.metrics.accumulate import bits

_STATES = (
    "img_sizes",
    "pred_counts",
    "gt_counts",
    "pred_scores",
    "pred_labels",
    "pred_boxes",
    "pred_rle",
    "pred_rle_len",
    "gt_labels",
    "gt_boxes",
    "gt_crowd",
    "gt_rle",
    "gt_rle_len",
)


def _encode(masks: Tensor) -> tuple[list[dict], Tensor, Tensor]:
    """(N,H,W) bool masks -> (RLEs, concatenated RLE bytes as uint8, byte length per mask)."""
    n, h, w = masks.shape
    if n == 0:
        return [], torch.zeros(0, dtype=torch.uint8), torch.zeros(0, dtype=torch.long)
    arr = np.asfortranarray(masks.detach().cpu().numpy().astype(np.uint8).transpose(1, 2, 0))
    rles = mask_utils.encode(arr)
    raw = b"".join(r["counts"] for r in rles)
    data = torch.frombuffer(bytearray(raw), dtype=torch.uint8)
    return rles, data, torch.tensor([len(r["counts"]) for r in rles], dtype=torch.long)


def _xyxy_to_xywh(boxes: Tensor) -> Tensor:
    boxes = boxes.detach().cpu().double().reshape(-1, 4)
    return torch.cat([boxes[:, :2], boxes[:, 2:] - boxes[:, :2]], dim=1)


class MaskAP(Metric):
    """Mask AP and box AP of instance segmentation, COCO definition (IoU 0.50:0.05:0.95, 101-point PR curve).

    Args:
        min_height: smallest counted GT height in px at ``reference_height`` (SMoE §5, KITTI moderate: 25).
        reference_height: image height the threshold refers to (KITTI: 375).
        ignore_overlap: a prediction with more than this fraction of its area in ``ignore`` is dropped.
        max_detections: detections per image kept by COCOeval (highest scores first).
        class_metrics: also return ``map_per_class`` / ``bbox_map_per_class`` and ``classes``.
    """

    full_state_update = False
    is_differentiable = False
    higher_is_better = True

    def __init__(
        self,
        min_height: float = MIN_HEIGHT,
        reference_height: float = REFERENCE_HEIGHT,
        ignore_overlap: float = 0.5,
        max_detections: int = 100,
        class_metrics: bool = False,
        **kwargs: Any,
    ) -> None:
        super().__init__(**kwargs)
        if reference_height <= 0 or min_height < 0:
            raise ValueError(
                f"MaskAP: need reference_height > 0 and min_height >= 0, got {reference_height}, {min_height}"
            )
        self.min_height, self.reference_height = float(min_height), float(reference_height)
        self.ignore_overlap, self.max_detections = float(ignore_overlap), int(max_detections)
        self.class_metrics = class_metrics
        for name in _STATES:
            self.add_state(name, default=[], dist_reduce_fx="cat")

    def update(self, preds: list[dict[str, Tensor]], targets: list[dict[str, Tensor]]) -> None:
        """Add images. ``preds[i]``: masks (N,H,W) bool, scores (N,), labels (N,), optional boxes (N,4) xyxy.
        ``targets[i]``: masks (M,H,W) bool, labels (M,), optional boxes (M,4) xyxy and ignore (H,W) bool."""
        if len(preds) != len(targets):
            raise ValueError(f"MaskAP.update: {len(preds)} predictions for {len(targets)} targets")
        for pred, target in zip(preds, targets):
            self._add_image(pred, target)

    def _add_image(self, pred: dict[str, Tensor], target: dict[str, Tensor]) -> None:
        for key, d, where in (
            ("masks", pred, "preds"),
            ("scores", pred, "preds"),
            ("labels", pred, "preds"),
            ("masks", target, "targets"),
            ("labels", target, "targets"),
        ):
            if key not in d:
                raise KeyError(f"MaskAP.update: {where} dict lacks '{key}' (has {sorted(d)})")
        gt_masks, masks = target["masks"].bool(), pred["masks"].bool()
        if gt_masks.ndim != 3 or masks.ndim != 3 or gt_masks.shape[1:] != masks.shape[1:]:
            raise ValueError(
                f"MaskAP.update: masks must be (N,H,W) of one image size, got preds "
                f"{tuple(masks.shape)} and targets {tuple(gt_masks.shape)}"
            )
        h, w = gt_masks.shape[1:]
        keep = torch.ones(masks.shape[0], dtype=torch.bool, device=masks.device)
        if "ignore" in target and masks.shape[0]:
            region = target["ignore"].bool().to(masks.device)
            inside = masks[:, region].sum(1, dtype=torch.int32).double()  # int32 sums: 8x faster than bool's
            keep = inside <= self.ignore_overlap * masks.flatten(1).sum(1, dtype=torch.int32).double()
        keep = keep.cpu()
        rles, rle, rle_len = _encode(masks[keep.to(masks.device)])
        boxes = (
            _xyxy_to_xywh(pred["boxes"])[keep]
            if "boxes" in pred
            else torch.as_tensor(mask_utils.toBbox(rles) if rles else np.zeros((0, 4))).double()
        )
        gt_rles, gt_rle, gt_rle_len = _encode(gt_masks)
        gt_boxes = (
            _xyxy_to_xywh(target["boxes"])
            if "boxes" in target
            else torch.as_tensor(mask_utils.toBbox(gt_rles) if gt_rles else np.zeros((0, 4))).double()
        )
        crowd = ~counted(gt_boxes[:, 3], h, self.min_height, self.reference_height)
        self.img_sizes.append(torch.tensor([h, w], dtype=torch.long, device=self.device))
        self.pred_counts.append(torch.tensor([len(rles)], dtype=torch.long, device=self.device))
        self.gt_counts.append(torch.tensor([len(gt_rles)], dtype=torch.long, device=self.device))
        for name, value in (
            ("pred_scores", pred["scores"].detach().cpu().double()[keep]),
            ("pred_labels", pred["labels"].detach().cpu().long()[keep]),
            ("pred_boxes", boxes.flatten()),
            ("pred_rle", rle),
            ("pred_rle_len", rle_len),
            ("gt_labels", target["labels"].detach().cpu().long()),
            ("gt_boxes", gt_boxes.flatten()),
            ("gt_crowd", crowd.long()),
            ("gt_rle", gt_rle),
            ("gt_rle_len", gt_rle_len),
        ):
            getattr(self, name).append(value.to(self.device))

    def _datasets(self) -> tuple[dict, dict]:
        """Rebuild COCO-format GT and detection datasets from the (possibly gathered) states."""
        s = {n: dim_zero_cat(getattr(self, n)).cpu() for n in _STATES}
        sizes, n_pred, n_gt = s["img_sizes"].long().view(-1, 2), s["pred_counts"].long(), s["gt_counts"].long()

        def split(prefix: str) -> list[bytes]:
            data = s[f"{prefix}_rle"].to(torch.uint8).numpy().tobytes()
            ends = np.cumsum(s[f"{prefix}_rle_len"].long().numpy())
            return [data[a:b] for a, b in zip(np.concatenate([[0], ends[:-1]]), ends)]

        images, gt_anns, dt_anns = [], [], []
        cats = set(s["gt_labels"].long().tolist()) | set(s["pred_labels"].long().tolist())
        gt_rle, dt_rle = split("gt"), split("pred")
        gt_boxes, dt_boxes = s["gt_boxes"].double().view(-1, 4), s["pred_boxes"].double().view(-1, 4)
        gi = di = 0
        for img_id, ((h, w), ng, nd) in enumerate(zip(sizes.tolist(), n_gt.tolist(), n_pred.tolist()), start=1):
            images.append({"id": img_id, "height": h, "width": w})
            for j in range(gi, gi + ng):
                rle = {"size": [h, w], "counts": gt_rle[j]}
                gt_anns.append(
                    {
                        "id": j + 1,
                        "image_id": img_id,
                        "category_id": int(s["gt_labels"][j]),
                        "segmentation": rle,
                        "area": float(mask_utils.area(rle)),
                        "bbox": gt_boxes[j].tolist(),
                        "iscrowd": int(s["gt_crowd"][j]),
                    }
                )
            for j in range(di, di + nd):
                rle = {"size": [h, w], "counts": dt_rle[j]}
                dt_anns.append(
                    {
                        "id": j + 1,
                        "image_id": img_id,
                        "category_id": int(s["pred_labels"][j]),
                        "segmentation": rle,
                        "area": float(mask_utils.area(rle)),
                        "bbox": dt_boxes[j].tolist(),
                        "score": float(s["pred_scores"][j]),
                        "iscrowd": 0,
                    }
                )
            gi, di = gi + ng, di + nd
        categories = [{"id": c} for c in sorted(cats)]
        return (
            {"images": images, "annotations": gt_anns, "categories": categories},
            {"images": images, "annotations": dt_anns, "categories": categories},
        )

    def _cocos(self) -> tuple[COCO, COCO]:
        """The ground truth and the detections as indexed COCO datasets (:meth:`_datasets`), silenced."""
        gt_data, dt_data = self._datasets()
        with contextlib.redirect_stdout(io.StringIO()):
            gt, dt = COCO(), COCO()
            gt.dataset, dt.dataset = gt_data, dt_data
            gt.createIndex()
            dt.createIndex()
        return gt, dt

    def _matched(self, gt: COCO, dt: COCO, iou_type: str) -> COCOeval:
        """COCOeval over them with this metric's ``max_detections``, its per-image matching done, silenced."""
        ev = COCOeval(gt, dt, iouType=iou_type)
        ev.params.maxDets = [1, 10, self.max_detections]
        with contextlib.redirect_stdout(io.StringIO()):
            ev.evaluate()
        return ev

    def _evaluate(self, gt: COCO, dt: COCO, iou_type: str) -> tuple[np.ndarray, list[int]]:
        """COCOeval precision [T, R, K] at area 'all' and the last maxDets, silenced."""
        ev = self._matched(gt, dt, iou_type)
        with contextlib.redirect_stdout(io.StringIO()):
            ev.accumulate()
        return ev.eval["precision"][:, :, :, 0, -1], list(ev.params.catIds)

    def frame_rows(self, iou_type: str = "segm") -> list[dict]:
        """What re-accumulating AP over any set of the images needs (:mod:`ablate.metrics.accumulate`), per image in
        update order (``index``) and category: COCOeval's per-image matches of its first ``max_detections``
        detections (kind ``dt``: score, match and ignore bits per IoU threshold) and its ground truths not ignored
        (kind ``gt``). AP from them over every image is :meth:`compute`'s."""
        sizes = self.img_sizes
        if (sizes.numel() if isinstance(sizes, Tensor) else len(sizes)) == 0:
            return []
        ev = self._matched(*self._cocos(), iou_type)
        p, rows = ev.params, []
        n_area, n_img, top = len(p.areaRng), len(p.imgIds), p.maxDets[-1]
        for k, cat in enumerate(p.catIds):
            for i in range(n_img):
                e = ev.evalImgs[k * n_area * n_img + i]  # area "all": the first of p.areaRng
                if e is None:
                    continue
                base = {"index": i, "cls": str(cat), "level": 0}
                npig = int(np.count_nonzero(np.asarray(e["gtIgnore"]) == 0))
                rows.append(base | {"kind": "gt", "score": np.nan, "a": npig, "b": 0})
                match = bits(np.asarray(e["dtMatches"])[:, :top] > 0)
                ignore = bits(np.asarray(e["dtIgnore"])[:, :top].astype(bool))
                for score, m, g in zip(e["dtScores"][:top], match, ignore):
                    rows.append(base | {"kind": "dt", "score": float(score), "a": int(m), "b": int(g)})
        return rows

    def compute(self) -> dict[str, Tensor]:
        """Returns map, map_50, map_75 (masks) and bbox_map, bbox_map_50, bbox_map_75 in 0-1 (-1: no GT)."""
        keys = ("map", "map_50", "map_75")
        sizes = self.img_sizes
        if (sizes.numel() if isinstance(sizes, Tensor) else len(sizes)) == 0:
            return {f"{p}{k}": torch.tensor(-1.0) for p in ("", "bbox_") for k in keys}
        gt, dt = self._cocos()

        def mean(p: np.ndarray) -> float:
            valid = p[p > -1]
            return float(valid.mean()) if valid.size else -1.0

        out: dict[str, Tensor] = {}
        for prefix, iou_type in (("", "segm"), ("bbox_", "bbox")):
            prec, cat_ids = self._evaluate(gt, dt, iou_type)
            for key, p in zip(keys, (prec, prec[0:1], prec[5:6])):  # iouThrs[0] = .50, iouThrs[5] = .75
                out[prefix + key] = torch.tensor(mean(p), dtype=torch.float32)
            if self.class_metrics:
                out[prefix + "map_per_class"] = torch.tensor([mean(prec[:, :, k]) for k in range(len(cat_ids))])
                out["classes"] = torch.tensor(cat_ids, dtype=torch.long)
        return out
