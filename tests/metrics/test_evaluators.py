"""Which evaluator a task's metrics follow: the ``evaluator`` tag its runs record (ablate.jobs.job) and the report
compares with today's (ablate.metrics.EVALUATORS)."""

from __future__ import annotations

import functools

import pytest
import torch
from torch import nn
from torchmetrics import MeanMetric

from ablate.metrics import EVALUATORS
from ablate.metrics.kitti import KittiAP
from ablate.metrics.road import RoadMaxF
from ablate.tasks.base import FusionTask
from ablate.tasks.detection import DetectionTask, SSDHead

SGD = functools.partial(torch.optim.SGD, lr=0.0)


def task_with(**metrics: nn.Module) -> FusionTask:
    task = FusionTask(nn.Identity(), SGD)
    for name, metric in metrics.items():
        setattr(task, name, metric)
    return task


def test_a_task_names_the_evaluators_of_its_metrics():
    assert task_with(val_ap=KittiAP(), test_ap=KittiAP()).evaluator == "kitti_object_devkit_2017"
    both = task_with(test_ap=KittiAP(devkit="2d_2012"), test_road=nn.ModuleDict({"cam": RoadMaxF(lookup="nearest")}))
    assert both.evaluator == "kitti_object_devkit_2d_2012, kitti_road_nearest_pixel"
    assert task_with(test_gates=MeanMetric()).evaluator is None  # no metric names one: no tag


def test_todays_evaluators_are_the_metrics_defaults():
    assert EVALUATORS == {"ablate.metrics.kitti": KittiAP().evaluator, "ablate.metrics.road": RoadMaxF().evaluator}


class Detector(nn.Module):
    """Just a detection head: what DetectionTask reads at construction."""

    modalities = {"rgb": 3}

    def __init__(self):
        super().__init__()
        self.head = SSDHead(8, num_levels=2, aspect_ratios=[[2], [2]])


def test_detection_task_passes_metric_options_to_kitti_ap():
    assert DetectionTask(Detector(), SGD).evaluator == "kitti_object_devkit_2017"
    old = DetectionTask(Detector(), SGD, metric={"devkit": "2d_2012"})
    assert old.test_ap.devkit == old.val_ap.devkit == "2d_2012" and old.evaluator == "kitti_object_devkit_2d_2012"
    with pytest.raises(ValueError, match=r"task.metric: unknown option\(s\) \['lookup'\]"):
        DetectionTask(Detector(), SGD, metric={"lookup": "devkit"})
    with pytest.raises(ValueError, match="devkit must be one of"):
        DetectionTask(Detector(), SGD, metric={"devkit": "2012"})
