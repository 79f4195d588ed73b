"""Test conditions and training corruptions on batches, and the task base's test per condition with pooling."""

import functools
from collections import Counter

import lightning as L
import pytest
import torch
from torch import nn
from torch.utils.data import DataLoader
from torchmetrics import MeanMetric

from ablate.data.datamodule import collate
from ablate.tasks.base import FusionTask
from ablate.tasks.conditions import EvalConditions, TrainCorruptions, corrupt, parse_spec

DGFN_CHOICES = [
    {},
    [{"camera": "blank"}, {"lidar": "blank"}],
    [{"camera": "occlusion"}, {"lidar": "occlusion"}],
    {"camera": "noise"},
    {"camera": "illumination"},
]
CONDITIONS = {
    "normal": {},
    "camera_blank": {"camera": "blank"},
    "lidar_blank": {"lidar": "blank"},
    "camera_occlusion": {"camera": "occlusion"},
}


def batch(n: int = 4, rgb: float = 0.5, dhi: float = 0.25) -> dict:
    return collate(
        [
            {"frame": f"{i:06d}", "rgb": torch.full((3, 16, 24), rgb), "dhi": torch.full((3, 16, 24), dhi)}
            for i in range(n)
        ]
    )


def test_specs_are_checked_and_name_the_option():
    assert parse_spec({"camera": "night", "dhi": "blank"}, "x") == {"camera": "night", "dhi": "blank"}
    with pytest.raises(ValueError, match=r"task.eval_conditions.a: 'noise' applies to the camera only"):
        EvalConditions({"a": {"lidar": "noise"}})
    with pytest.raises(ValueError, match="unknown target 'radar'"):
        parse_spec({"radar": "blank"}, "x")
    with pytest.raises(ValueError, match="unknown corruption 'fog' for 'dhi'"):
        parse_spec({"dhi": "fog"}, "x")
    with pytest.raises(ValueError, match="without '-s'"):
        EvalConditions({"lidar-sparse": {"lidar": "blank"}})
    with pytest.raises(ValueError, match="task.eval_pooled: 'normal' is also a condition"):
        EvalConditions(CONDITIONS, pooled="normal")


def test_conditions_hit_their_sensor_alike_for_every_model_and_not_others():
    ec = EvalConditions(CONDITIONS, severities=[0.5, 2.0], pooled="full", seed=3)
    # blank has no severity: no variants for it
    assert ec.names == [*CONDITIONS, "camera_occlusion-s0.5", "camera_occlusion-s2"] and ec.base == list(CONDITIONS)
    b = batch()
    assert ec.apply(b, "normal") is b
    blank = ec.apply(b, "camera_blank")
    assert not blank["rgb"].any() and torch.equal(blank["dhi"], b["dhi"])
    occl = ec.apply(b, "camera_occlusion")
    holes = (occl["rgb"][:, 0] == 0).sum((1, 2))
    assert (holes > 0).all() and len(set(holes.tolist())) > 1  # every frame its own box
    assert torch.equal(ec.apply(b, "camera_occlusion")["rgb"], occl["rgb"])  # the same box for every model
    bigger = (ec.apply(b, "camera_occlusion-s2")["rgb"][:, 0] == 0).sum((1, 2))
    assert (bigger >= holes).all() and (bigger > holes).any()
    other_seed = EvalConditions(CONDITIONS, seed=4).apply(b, "camera_occlusion")
    assert not torch.equal(other_seed["rgb"], occl["rgb"])
    camera_only = {k: v for k, v in b.items() if k != "dhi"}  # a camera-only model's batch under a LiDAR condition
    assert torch.equal(ec.apply(camera_only, "lidar_blank")["rgb"], b["rgb"])


def test_training_draws_five_choices_equally_and_the_sensor_50_50():
    tc = TrainCorruptions(DGFN_CHOICES, seed=0)
    drawn = Counter(tuple(sorted(tc.draw(step)[0].items())) for step in range(5000))
    choice = Counter(
        {
            "none": drawn[()],
            "blank": drawn[(("camera", "blank"),)] + drawn[(("lidar", "blank"),)],
            "occlusion": drawn[(("camera", "occlusion"),)] + drawn[(("lidar", "occlusion"),)],
            "noise": drawn[(("camera", "noise"),)],
            "illumination": drawn[(("camera", "illumination"),)],
        }
    )
    assert sum(choice.values()) == 5000 and all(900 <= c <= 1100 for c in choice.values()), choice
    camera_share = drawn[(("camera", "blank"),)] / choice["blank"]
    assert 0.44 <= camera_share <= 0.56
    assert tc.draw(17)[0] == TrainCorruptions(DGFN_CHOICES, seed=0).draw(17)[0]  # a resumed run draws alike
    with pytest.raises(ValueError, match="task.train_corruptions.choices: give at least one"):
        TrainCorruptions([])


class Toy(FusionTask):
    """Logs the mean camera and LiDAR input of its test frames; records what each training batch looked like."""

    def __init__(self, **conditions):
        super().__init__(nn.Linear(1, 1), functools.partial(torch.optim.SGD, lr=0.0), **conditions)
        self.test_rgb, self.test_dhi = MeanMetric(), MeanMetric()
        self.seen: list[tuple[int, bool, bool]] = []

    def training_step(self, b, i):
        self.seen.append((self.global_step, bool(b["rgb"].any()), bool(b["dhi"].any())))
        return self.model(b["rgb"].mean((1, 2, 3))[:, None]).sum()

    def _eval_step(self, b, stage):
        self.test_rgb.update(b["rgb"].mean((1, 2, 3)))
        self.test_dhi.update(b["dhi"].mean((1, 2, 3)))
        self.log(f"{stage}/frames", float(len(b["frame"])), reduce_fx="sum")

    def _eval_end(self, stage):
        for name in ("rgb", "dhi"):
            metric = getattr(self, f"{stage}_{name}")
            self.log(f"{stage}/{name}", metric.compute())
            metric.reset()


def loader(n: int = 6) -> DataLoader:
    b = batch(n)
    samples = [{k: v[i] for k, v in b.items()} for i in range(n)]
    return DataLoader(samples, batch_size=3, collate_fn=collate)


def trainer(**kw) -> L.Trainer:
    return L.Trainer(
        logger=False, enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False, **kw
    )


def test_a_task_is_tested_once_per_condition_and_pooled():
    task = Toy(eval_conditions=CONDITIONS, eval_severities=[0.5], eval_pooled="full")
    (res,) = trainer().test(task, loader(), verbose=False)
    assert res["test/normal/rgb"] == pytest.approx(0.5) and res["test/normal/dhi"] == pytest.approx(0.25)
    assert res["test/camera_blank/rgb"] == 0.0 and res["test/camera_blank/dhi"] == pytest.approx(0.25)
    assert res["test/lidar_blank/rgb"] == pytest.approx(0.5) and res["test/lidar_blank/dhi"] == 0.0
    assert 0.3 < res["test/camera_occlusion/rgb"] < res["test/camera_occlusion-s0.5/rgb"] < 0.5  # smaller boxes
    # Full pools the four named conditions (not the severity variants): every frame under each
    expected = (0.5 + 0.0 + 0.5 + res["test/camera_occlusion/rgb"]) / 4
    assert res["test/full/rgb"] == pytest.approx(expected)
    assert res["test/normal/frames"] == 6.0 and "test/full/frames" not in res
    assert not any(k in res for k in ("test/rgb", "test/frames"))
    (plain,) = trainer().test(Toy(), loader(), verbose=False)  # no conditions: the task logs as it always did
    assert set(plain) == {"test/rgb", "test/dhi", "test/frames"}


def test_training_batches_carry_the_corruption_drawn_for_their_weight_update():
    tc = {"choices": [[{"camera": "blank"}, {"lidar": "blank"}]], "seed": 5}
    task = Toy(train_corruptions=tc)
    trainer(max_steps=8, limit_val_batches=0).fit(task, loader(24))
    draws = TrainCorruptions(**tc)
    assert [
        (step, "camera" not in draws.draw(step)[0], "lidar" not in draws.draw(step)[0]) for step in range(8)
    ] == task.seen
    assert {rgb for _, rgb, _ in task.seen} == {True, False}  # both sensors were blanked in 8 updates
    (res,) = trainer().test(task, loader(), verbose=False)  # testing sees the data as it is
    assert res["test/rgb"] == pytest.approx(0.5)


def test_a_task_without_test_metrics_cannot_take_conditions():
    class Bare(Toy):
        def __init__(self, **kw):
            super().__init__(**kw)
            del self.test_rgb, self.test_dhi

    with pytest.raises(TypeError, match="keeps no test metrics as `test_\\*` modules"):
        trainer().test(Bare(eval_conditions=CONDITIONS), loader(), verbose=False)


def test_corrupt_leaves_the_input_batch_alone():
    b = batch()
    out = corrupt(b, {"camera": "blank"}, (0,))
    assert b["rgb"].all() and not out["rgb"].any() and out["dhi"] is b["dhi"]
