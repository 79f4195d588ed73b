"""MaskAP against hand-made masks and direct pycocotools COCOeval calls."""

from __future__ import annotations

import contextlib
import io

import numpy as np
import pytest
import torch
from pycocotools import mask as mask_utils
from pycocotools.coco import COCO
from pycocotools.cocoeval import COCOeval

from ablate.metrics.coco import MaskAP

H, W = 75, 100  # threshold scales to 25 * 75 / 375 = 5 px


def rect(x1: int, y1: int, x2: int, y2: int, h: int = H, w: int = W) -> torch.Tensor:
    m = torch.zeros(h, w, dtype=torch.bool)
    m[y1:y2, x1:x2] = True
    return m


def target(*rects: tuple, labels: list[int]) -> dict:
    return {"masks": torch.stack([rect(*r) for r in rects]), "labels": torch.tensor(labels)}


def pred(*rects: tuple, scores: list[float], labels: list[int]) -> dict:
    masks = torch.stack([rect(*r) for r in rects]) if rects else torch.zeros(0, H, W, dtype=torch.bool)
    return {"masks": masks, "scores": torch.tensor(scores), "labels": torch.tensor(labels, dtype=torch.long)}


def coco_stats(images: list[tuple[dict, dict]], iou_type: str) -> np.ndarray:
    """Direct COCOeval on the same masks, the reference the metric must agree with."""
    gt_anns, results, imgs = [], [], []
    for img_id, (p, t) in enumerate(images, start=1):
        imgs.append({"id": img_id, "height": H, "width": W})
        for m, lab in zip(t["masks"], t["labels"]):
            rle = mask_utils.encode(np.asfortranarray(m.numpy().astype(np.uint8)))
            gt_anns.append(
                {
                    "id": len(gt_anns) + 1,
                    "image_id": img_id,
                    "category_id": int(lab),
                    "iscrowd": 0,
                    "segmentation": rle,
                    "area": float(mask_utils.area(rle)),
                    "bbox": mask_utils.toBbox(rle).tolist(),
                }
            )
        for m, s, lab in zip(p["masks"], p["scores"], p["labels"]):
            rle = mask_utils.encode(np.asfortranarray(m.numpy().astype(np.uint8)))
            results.append({"image_id": img_id, "category_id": int(lab), "segmentation": rle, "score": float(s)})
    with contextlib.redirect_stdout(io.StringIO()):
        gt = COCO()
        gt.dataset = {
            "images": imgs,
            "annotations": gt_anns,
            "categories": [{"id": c} for c in sorted({a["category_id"] for a in gt_anns})],
        }
        gt.createIndex()
        ev = COCOeval(gt, gt.loadRes(results), iouType=iou_type)
        ev.evaluate()
        ev.accumulate()
        ev.summarize()
    return ev.stats


def test_perfect_prediction_scores_one():
    t = target((10, 10, 40, 50), (60, 20, 70, 60), labels=[0, 1])
    p = pred((10, 10, 40, 50), (60, 20, 70, 60), scores=[0.9, 0.8], labels=[0, 1])
    metric = MaskAP()
    metric.update([p], [t])
    out = metric.compute()
    for key in ("map", "map_50", "map_75", "bbox_map", "bbox_map_50", "bbox_map_75"):
        assert out[key].item() == pytest.approx(1.0), key


def test_shifted_masks_match_direct_cocoeval():
    images = [
        (
            pred((12, 10, 42, 50), (60, 25, 70, 65), (0, 0, 20, 20), scores=[0.9, 0.6, 0.7], labels=[0, 1, 0]),
            target((10, 10, 40, 50), (60, 20, 70, 60), labels=[0, 1]),
        ),
        (
            pred((50, 30, 90, 70), (5, 5, 25, 30), scores=[0.5, 0.95], labels=[0, 0]),
            target((55, 30, 95, 70), (5, 8, 25, 33), (30, 40, 45, 70), labels=[0, 0, 1]),
        ),
    ]
    metric = MaskAP()
    for p, t in images:
        metric.update([p], [t])
    out = metric.compute()
    segm, bbox = coco_stats(images, "segm"), coco_stats(images, "bbox")
    assert 0.0 < segm[0] < 1.0  # the case is not degenerate
    assert out["map"].item() == pytest.approx(segm[0])
    assert out["map_50"].item() == pytest.approx(segm[1])
    assert out["map_75"].item() == pytest.approx(segm[2])
    assert out["bbox_map"].item() == pytest.approx(bbox[0])
    assert out["bbox_map_75"].item() == pytest.approx(bbox[2])


def test_small_objects_are_neither_missed_nor_false_positives():
    # 4 px tall object at H=75: below 5 px -> ignored; the big one is found exactly.
    t = target((10, 10, 40, 50), (70, 10, 80, 14), labels=[0, 0])
    missed = pred((10, 10, 40, 50), scores=[0.9], labels=[0])
    found = pred((70, 10, 80, 14), (10, 10, 40, 50), scores=[0.99, 0.9], labels=[0, 0])
    for p in (missed, found):
        metric = MaskAP()
        metric.update([p], [t])
        assert metric.compute()["map"].item() == pytest.approx(1.0)
    counted = MaskAP(min_height=0.0)  # same input, small object counted: the miss costs recall
    counted.update([missed], [t])
    assert counted.compute()["map"].item() < 0.6


def test_height_threshold_scales_with_image_height():
    # a 10 px tall object: counted at H=75 (threshold 5 px), ignored at H=375 (threshold 25 px)
    for h, expected in ((75, 0.0), (375, -1.0)):
        t = {"masks": rect(10, 10, 40, 20, h=h)[None], "labels": torch.tensor([0])}
        p = {
            "masks": torch.zeros(0, h, W, dtype=torch.bool),
            "scores": torch.zeros(0),
            "labels": torch.zeros(0, dtype=torch.long),
        }
        metric = MaskAP()
        metric.update([p], [t])
        assert metric.compute()["map"].item() == expected


def test_predictions_in_dontcare_region_are_dropped():
    t = target((10, 10, 40, 50), labels=[0])
    t["ignore"] = rect(60, 0, 100, 75)
    p = pred((70, 20, 90, 60), (10, 10, 40, 50), scores=[0.95, 0.9], labels=[0, 0])
    metric = MaskAP()
    metric.update([p], [t])
    assert metric.compute()["map"].item() == pytest.approx(1.0)
    # only 40 % inside the region: kept, and as the top-scoring FP it lowers AP
    p_half = pred((44, 20, 69, 60), (10, 10, 40, 50), scores=[0.95, 0.9], labels=[0, 0])
    metric = MaskAP()
    metric.update([p_half], [t])
    assert metric.compute()["map"].item() < 1.0


def _two_images() -> list[tuple[dict, dict]]:
    return [
        (pred((12, 10, 42, 50), scores=[0.9], labels=[0]), target((10, 10, 40, 50), labels=[0])),
        (pred((5, 5, 25, 30), (60, 20, 70, 60), scores=[0.4, 0.8], labels=[1, 1]), target((5, 8, 25, 33), labels=[1])),
    ]


def test_two_updates_equal_one_update_with_both_images():
    (p1, t1), (p2, t2) = _two_images()
    a, b = MaskAP(class_metrics=True), MaskAP(class_metrics=True)
    a.update([p1], [t1])
    a.update([p2], [t2])
    b.update([p1, p2], [t1, t2])
    out_a, out_b = a.compute(), b.compute()
    assert out_a.keys() == out_b.keys()
    for key in out_a:
        assert torch.equal(out_a[key], out_b[key]), key
    assert out_a["classes"].tolist() == [0, 1]


def test_gathered_state_equals_updates_from_every_rank():
    """Emulates a 2-process all_gather in which both ranks saw the same images."""
    (p1, t1), (p2, t2) = _two_images()
    synced, local = MaskAP(), MaskAP()
    synced.update([p1, p2], [t1, t2])
    synced._sync_dist(lambda t, group=None: [t, t])  # what Metric.sync runs under DDP
    assert isinstance(synced.pred_rle, torch.Tensor)
    local.update([p1, p2, p1, p2], [t1, t2, t1, t2])
    out_s, out_l = synced.compute(), local.compute()
    for key in out_s:
        assert out_s[key].item() == pytest.approx(out_l[key].item()), key


def test_empty_cases():
    with pytest.warns(UserWarning, match="before the ``update``"):
        assert MaskAP().compute()["map"].item() == -1.0
    no_preds = MaskAP()
    no_preds.update([pred(scores=[], labels=[])], [target((10, 10, 40, 50), labels=[0])])
    assert no_preds.compute()["map"].item() == 0.0
    no_gt = MaskAP()
    no_gt.update(
        [pred((10, 10, 40, 50), scores=[0.5], labels=[0])],
        [{"masks": torch.zeros(0, H, W, dtype=torch.bool), "labels": torch.zeros(0, dtype=torch.long)}],
    )
    assert no_gt.compute()["bbox_map"].item() == -1.0


def test_missing_key_is_named():
    with pytest.raises(KeyError, match="scores"):
        MaskAP().update(
            [{"masks": torch.zeros(0, H, W), "labels": torch.zeros(0)}], [target((10, 10, 40, 50), labels=[0])]
        )
