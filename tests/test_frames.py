"""Counts per test frame (ablate.tables.frames): the metrics recomputed exactly from them."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torchmetrics.classification import MulticlassJaccardIndex, MulticlassRecall

from ablate.tables.frames import FROM_COUNTS
from ablate.tasks.semantic import confusion


def test_the_semantic_metrics_are_recomputed_exactly_from_the_counts_per_frame() -> None:
    gen = torch.Generator().manual_seed(0)
    target = torch.randint(0, 3, (5, 16, 24), generator=gen)
    pred = torch.where(
        torch.rand(5, 16, 24, generator=gen) < 0.7, target, torch.randint(0, 3, (5, 16, 24), generator=gen)
    )
    counts = confusion(pred, target).numpy().astype(float)
    assert counts.shape == (5, 9) and counts.sum() == target.numel()
    total = counts.sum(axis=0)
    rate = MulticlassRecall(num_classes=3, average="micro", ignore_index=0)(pred, target)
    iou = MulticlassJaccardIndex(num_classes=3, average="none")(pred, target)
    assert FROM_COUNTS["det_rate"](total) == pytest.approx(100 * float(rate))
    assert FROM_COUNTS["iou_free_space"](total) == pytest.approx(100 * float(iou[1]))
    assert FROM_COUNTS["iou_road_objects"](total) == pytest.approx(100 * float(iou[2]))


def test_the_road_max_f_is_recomputed_exactly_from_the_level_histograms_per_frame() -> None:
    from ablate.metrics.road import RoadMaxF, frame_histograms
    from ablate.tables.frames import max_f_from_histograms

    gen = torch.Generator().manual_seed(1)
    shape = (3, 800, 400)  # BEV frames on the devkit's grid (rows z, columns x)
    target = torch.rand(shape, generator=gen) < 0.3
    preds = (0.3 * target + 0.7 * torch.rand(shape, generator=gen)).clamp(0, 1)  # overlapping: MaxF under 100
    valid = torch.rand(shape, generator=gen) < 0.9
    metric = RoadMaxF()
    metric.update(preds, target, valid)
    per_frame = frame_histograms(preds, target, valid).numpy().astype(float)
    assert per_frame.shape == (3, 514)
    expected = float(metric.compute()["max_f"])  # float32
    assert expected < 95 and max_f_from_histograms(per_frame.sum(axis=0)) == pytest.approx(expected, rel=1e-6)
    assert np.isnan(max_f_from_histograms(np.zeros(514)))  # no road cell
