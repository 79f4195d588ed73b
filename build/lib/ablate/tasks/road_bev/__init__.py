"""BiFNet's road segmentation in camera space and in BEV (Li et al., seed 004).

* :class:`RoadNet` — per-modality ResNet + FPN branches, fused by the bidirectional module (DST -> DT -> operator,
  :mod:`ablate.fusion.bidirectional`, :mod:`ablate.fusion.space`) or directly in camera space (LidCamNet, PLARD).
* :class:`RoadLoss` — focal loss in camera space + lambda x focal loss in BEV (eq. 13).
* :class:`MetricBev` — both spaces warped to the KITTI road devkit's metric BEV, for
  :class:`~ablate.metrics.road.RoadMaxF`.
* :class:`RoadTask` — the LightningModule: loss, MaxF / AP / PRE / REC per branch, figures.
"""

from ablate.tasks.road_bev.evaluate import MetricBev
from ablate.tasks.road_bev.loss import RoadLoss, focal_loss
from ablate.tasks.road_bev.model import RoadNet
from ablate.tasks.road_bev.task import RoadTask

__all__ = ["MetricBev", "RoadLoss", "RoadNet", "RoadTask", "focal_loss"]
