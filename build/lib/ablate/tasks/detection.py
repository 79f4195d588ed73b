"""2D object detection of DGFN (Kim et al., seed 002 §III-IV): an SSD head with GFU fusion at the six SSD maps.

The pieces live in :mod:`ablate.tasks.ssd`; what SSD shares with YOLACT (anchors, box coding, matching, NMS) in
:mod:`ablate.tasks.boxes`:

* :class:`SSDHead` — SSD's per-map predictors and default boxes (SSD eq. 4 scales, SSD300's aspect ratios).
* :class:`DGFN` — one VGG-16 SSD trunk per sensor, a fusion operator (GFU, eq. 5-9) at each SSD map, the head.
* :class:`SSDLoss` — SSD eq. 1-3: matching, hard negative mining 3:1, softmax + smooth L1; KITTI ignore regions.
* :func:`decode` — SSD inference: per-class greedy NMS into :class:`~ablate.metrics.kitti.KittiAP`'s format.
* :class:`DetectionTask` — the LightningModule: loss, KITTI AP (easy / moderate / hard), GFU weight figures.
"""

from __future__ import annotations

from ablate.tasks.ssd import CLASSES
from ablate.tasks.ssd.decode import decode
from ablate.tasks.ssd.head import SSD300_RATIOS, SSDHead, ssd_ratios, ssd_scales
from ablate.tasks.ssd.loss import SSDLoss
from ablate.tasks.ssd.model import DGFN
from ablate.tasks.ssd.task import DetectionTask

__all__ = [
    "CLASSES",
    "DGFN",
    "SSD300_RATIOS",
    "DetectionTask",
    "SSDHead",
    "SSDLoss",
    "decode",
    "ssd_ratios",
    "ssd_scales",
]
