"""The test set as a source of variance (ablate.tables.frames): the metrics recomputed from counts per test frame,
and the two-level bootstrap over seeds and frames against the seeds alone."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import torch
from torchmetrics.classification import MulticlassJaccardIndex, MulticlassRecall

from ablate.tables.frames import FROM_COUNTS, frame_tests, rejudge, resampled_differences
from ablate.tables.racing import RacePlan, race
from ablate.tables.verdicts import DIFFERENT, UNDECIDED
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


def frames_of(lead: np.ndarray, n_seeds: int = 5, n_frames: int = 40, seed: int = 0) -> pd.DataFrame:
    """Counts per frame of two rows: ``b`` right on 900 of each frame's 1000 free-space pixels, ``a`` on 900 plus
    ``lead[frame]``, both moved by a seed's own luck (shared by the rows) and a little noise of their own."""
    rng = np.random.default_rng(seed)
    out = []
    for s in range(n_seeds):
        luck = rng.integers(-20, 21)
        for row, extra in (("a", lead), ("b", np.zeros(n_frames))):
            for f in range(n_frames):
                right = int(900 + luck + extra[f] + rng.integers(-2, 3))  # free space predicted free space
                counts = {f"c{i}": 0 for i in range(9)} | {"c3": 1000 - right, "c4": right}  # the rest: background
                out.append({"row": row, "seed": s, "condition": "", "frame": f"{f:06d}", **counts})
    return pd.DataFrame(out)


def per_seed_rates(frames: pd.DataFrame) -> dict[str, pd.Series]:
    columns = [f"c{i}" for i in range(9)]
    sums = frames.groupby(["row", "seed"])[columns].sum()
    return {r: pd.Series(FROM_COUNTS["det_rate"](sums.loc[r].to_numpy(dtype=float)), index=range(5)) for r in "ab"}


TABLE = {"primary": "det_rate", "rope": None}


def judged(frames: pd.DataFrame):
    from omegaconf import OmegaConf

    state = race(per_seed_rates(frames), ["a", "b"], "b", RacePlan((5,)))
    return state, rejudge(state, frames, OmegaConf.create(TABLE))


def test_a_lead_on_a_few_frames_is_a_seed_difference_but_not_one_the_test_set_carries() -> None:
    lead = np.zeros(40)
    lead[:2] = 60.0  # a better on 2 frames of 40, by the same margin whatever the seed
    seeds, both = judged(frames_of(lead))
    (c,) = seeds.comparisons.values()
    assert c.kind == DIFFERENT  # the seeds agree: a paired t-test over them rejects
    (f,) = both.comparisons.values()
    assert f.frames and f.kind == UNDECIDED and f.lo <= 0.0 <= f.hi  # another draw of frames may not have them


def test_a_lead_on_every_frame_is_carried_by_both() -> None:
    seeds, both = judged(frames_of(np.full(40, 3.0)))
    assert [c.kind for c in seeds.comparisons.values()] == [DIFFERENT]
    (f,) = both.comparisons.values()
    assert f.kind == DIFFERENT and f.lo > 0 and f.delta == pytest.approx(0.3, abs=0.05)


def test_the_bootstrap_p_values_read_the_resamples_against_zero_and_delta() -> None:
    diffs = np.linspace(-0.1, 0.9, 1001)
    p_diff, p_beyond, p_equiv = frame_tests(0.4, diffs, rope=0.5)
    assert p_diff == pytest.approx(2 * 101 / 1001, abs=1e-3)
    assert p_beyond == pytest.approx(601 / 1001, abs=1e-3) and p_equiv == pytest.approx(401 / 1001, abs=1e-3)
    a = np.ones((3, 10, 9))
    observed, resampled = resampled_differences(a, a, FROM_COUNTS["det_rate"], resamples=50)
    assert observed == 0.0 and np.all(resampled == 0.0)


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
