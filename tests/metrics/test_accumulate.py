"""AP re-accumulated from each frame's scored detections (ablate.metrics.accumulate) equals the evaluators' own AP:
pycocotools' COCOeval (MaskAP) and the KITTI devkit-conformant KittiAP, over every frame and over any subset."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from ablate.data.dataset import CLASSES
from ablate.metrics.accumulate import as_arrays, bits, coco_ap, kitti_ap, kitti_ap_drawn, unbits
from ablate.metrics.coco import MaskAP
from ablate.metrics.kitti import LEVELS, KittiAP
from tests.metrics.test_kitti import image, random_frames

H, W = 60, 80


def random_instances(seed: int, n_images: int = 25) -> list[tuple[dict, dict]]:
    """Frames of 0-4 rectangular objects of 2 classes (some small: crowd), each detected 0-2 times with jitter,
    plus false positives; scores with ties."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n_images):
        gts, labels, dets, scores, dlabels = [], [], [], [], []
        for _ in range(rng.integers(0, 5)):
            x, y = rng.integers(0, W - 20), rng.integers(0, H - 20)
            w, h = rng.integers(3, 20), rng.integers(3, 20)
            m = torch.zeros(H, W, dtype=torch.bool)
            m[y : y + h, x : x + w] = True
            gts.append(m)
            labels.append(int(rng.integers(0, 2)))
            for _ in range(rng.integers(0, 3)):
                dx, dy = rng.integers(-3, 4, 2)
                d = torch.zeros(H, W, dtype=torch.bool)
                d[max(0, y + dy) : y + h + dy, max(0, x + dx) : x + w + dx] = True
                dets.append(d)
                scores.append(float(np.round(rng.random(), 2)))
                dlabels.append(labels[-1] if rng.random() < 0.9 else 1 - labels[-1])
        for _ in range(rng.integers(0, 3)):
            d = torch.zeros(H, W, dtype=torch.bool)
            x, y = rng.integers(0, W - 10), rng.integers(0, H - 10)
            d[y : y + 8, x : x + 8] = True
            dets.append(d)
            scores.append(float(np.round(rng.random(), 2)))
            dlabels.append(int(rng.integers(0, 2)))
        target = {
            "masks": torch.stack(gts) if gts else torch.zeros(0, H, W, dtype=torch.bool),
            "labels": torch.tensor(labels, dtype=torch.long),
        }
        pred = {
            "masks": torch.stack(dets) if dets else torch.zeros(0, H, W, dtype=torch.bool),
            "scores": torch.tensor(scores),
            "labels": torch.tensor(dlabels, dtype=torch.long),
        }
        out.append((pred, target))
    return out


def mask_ap(images: list[tuple[dict, dict]]) -> MaskAP:
    metric = MaskAP()
    for p, t in images:
        metric.update([p], [t])
    return metric


def test_bits_round_trip() -> None:
    flags = np.random.default_rng(0).random((10, 7)) < 0.5
    assert np.array_equal(unbits(bits(flags)), flags)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_coco_ap_from_the_frames_equals_cocoeval_over_every_frame_and_any_subset(seed: int) -> None:
    images = random_instances(seed)
    rows = as_arrays(mask_ap(images).frame_rows("segm"))
    whole = mask_ap(images).compute()["map"].item()
    assert 0.0 < whole < 1.0  # not degenerate
    assert coco_ap(rows) == pytest.approx(whole, abs=1e-6)
    keep = np.random.default_rng(seed).choice(len(images), size=len(images) // 2, replace=False)
    subset = mask_ap([images[i] for i in sorted(keep)]).compute()["map"].item()
    assert coco_ap(rows, keep=keep) == pytest.approx(subset, abs=1e-6)
    left_out = [i for i in range(len(images)) if i != 3]
    assert coco_ap(rows, keep=np.array(left_out)) == pytest.approx(
        mask_ap([images[i] for i in left_out]).compute()["map"].item(), abs=1e-6
    )


def kitti_metric(frames: list) -> KittiAP:
    metric = KittiAP()
    for g, d in frames:
        p, t = image(g, d)
        metric.update([p], [t])
    return metric


@pytest.mark.parametrize("seed", [0, 3, 5])
def test_kitti_ap_from_the_frames_equals_the_devkit_conformant_evaluator(seed: int) -> None:
    frames = random_frames(seed, on_thresholds=0.2 if seed == 5 else 0.0)
    metric = kitti_metric(frames)
    logged = {k: v.item() for k, v in metric.compute().items()}  # float32, as a run logs it
    keep = np.random.default_rng(seed).choice(len(frames), size=len(frames) - 7, replace=False)
    other = kitti_metric([frames[i] for i in sorted(keep)])
    inner = 0
    for cls in CLASSES:
        for k, level in enumerate(LEVELS):
            rows = as_arrays(metric.frame_rows(cls, k))
            whole, part = metric._ap(metric._images(), cls, k), other._ap(other._images(), cls, k)
            for i, points in enumerate((11, 40)):
                assert kitti_ap(rows, cls, k, points) == pytest.approx(whole[i], abs=1e-9)
                assert kitti_ap(rows, cls, k, points) == pytest.approx(logged[f"{cls}/{level}/ap{points}"], rel=1e-6)
                assert kitti_ap(rows, cls, k, points, keep=keep) == pytest.approx(part[i], abs=1e-9)
            inner += 0 < whole[1] < 100
    assert inner >= 5


@pytest.mark.parametrize("seed", [0, 5])
def test_kitti_ap_over_draws_of_the_frames_equals_it_on_the_drawn_frames_rows_repeated(seed: int) -> None:
    # the frames' bootstrap (ablate.tables.twolevel) takes 1000 draws at once from weights: every draw must give the
    # AP of its frames' rows repeated as often as drawn, to the bit (the same records, the same verdicts)
    frames = random_frames(seed, on_thresholds=0.2 if seed == 5 else 0.0)
    metric = kitti_metric(frames)
    draws = np.random.default_rng(seed).integers(0, len(frames), size=(40, len(frames)))
    draws[0] = 0  # one frame drawn every time: its few thresholds
    per_frame = np.stack([np.bincount(d, minlength=len(frames)) for d in draws])
    compared = 0
    for cls in CLASSES:
        for k in range(len(LEVELS)):
            rows = as_arrays(metric.frame_rows(cls, k))
            for points in (11, 40):
                drawn = kitti_ap_drawn(rows, cls, k, rows["index"], per_frame, points)
                for d, times in enumerate(per_frame):
                    idx = np.repeat(np.arange(len(rows["index"])), times[rows["index"]])
                    assert drawn[d] == kitti_ap({c: v[idx] for c, v in rows.items()}, cls, k, points)
                    compared += 0 < drawn[d] < 100
    assert compared >= 100
