"""Instance segmentation task of SMoE (seed 000 §4-5): a YOLACT-style head on the fused FPN P3..P7.

The pieces live in :mod:`ablate.tasks.yolact`:

* :class:`YolactHead` — Protonet on P3 and a prediction head shared across levels (class, box, tanh coefficients).
* :class:`Anchors` — aspect ratios 1, 1/2, 2; sizes a fixed fraction of the input height per level.
* :class:`YolactLoss` — SMoE eq. 7 with SSD matching (IoU >= 0.5 positive, < 0.4 negative) and OHEM 3:1.
* :func:`decode` — Fast NMS and mask assembly into :class:`~ablate.metrics.coco.MaskAP`'s input format.
* :class:`InstanceTask` — the LightningModule: loss, mask AP overall and per condition group, figures.

Classes follow the SMoE annotation (§3.1): car and pedestrian, labels 0 and 1.
"""

from __future__ import annotations

from ablate.tasks.yolact import CLASSES
from ablate.tasks.yolact.anchors import ANCHOR_SCALES, ASPECT_RATIOS, VARIANCES, Anchors, match
from ablate.tasks.yolact.head import YolactHead
from ablate.tasks.yolact.loss import YolactLoss
from ablate.tasks.yolact.nms import assemble_masks, decode, fast_nms
from ablate.tasks.yolact.task import CONDITION_GROUPS, SMOE_CONDITIONS, InstanceTask, condition_group, task_head

__all__ = [
    "ANCHOR_SCALES",
    "ASPECT_RATIOS",
    "CLASSES",
    "CONDITION_GROUPS",
    "SMOE_CONDITIONS",
    "VARIANCES",
    "Anchors",
    "InstanceTask",
    "YolactHead",
    "YolactLoss",
    "assemble_masks",
    "condition_group",
    "decode",
    "fast_nms",
    "match",
    "task_head",
]
