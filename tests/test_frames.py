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


def test_the_counts_split_by_run_in_one_pass_are_each_runs_own() -> None:
    """:func:`counts_by_run` (one pass, what the frames' variance reads) gives each (row, seed) exactly its own
    counts under the condition, as floats, rows sorted by frame whatever order the records list them in, and leaves
    out a condition's other runs."""
    import pandas as pd

    from ablate.tables.frames import counts_by_run

    gen = np.random.default_rng(0)
    rows = [
        {"row": row, "seed": seed, "frame": f"{frame:06d}", "condition": cond, "c0": gen.integers(9), "c1": 1}
        for row in ("a", "b")
        for seed in (0, 1, 2)
        for cond in ("", "night")
        for frame in gen.permutation(5)
        if not (row == "b" and seed == 2 and cond == "")
    ]
    frames = pd.DataFrame(rows).sample(frac=1.0, random_state=1).reset_index(drop=True)
    split = counts_by_run(frames, "")
    assert sorted(split) == [("a", 0), ("a", 1), ("a", 2), ("b", 0), ("b", 1)]
    for (row, seed), counts in split.items():
        own = frames[(frames["row"] == row) & (frames["seed"] == seed) & (frames["condition"] == "")]
        own = own.sort_values("frame").set_index("frame")[["c0", "c1"]].astype(float)
        pd.testing.assert_frame_equal(counts, own)
        assert list(counts.index) == [f"{i:06d}" for i in range(5)] and list(counts.columns) == ["c0", "c1"]
    assert len(counts_by_run(frames, "night")) == 6
