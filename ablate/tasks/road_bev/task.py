"""BiFNet's road segmentation task as a LightningModule (Li et al., seed 004 §IV-C loss, §V-A metrics).

Batches are the data module's dicts: the modalities (``rgb`` and ``bev``, or two camera-space ones), the targets
``free_space`` (image road mask), ``road_valid``, ``road_bev``, ``road_bev_valid`` and the geometry ``calib``,
``height_image``, ``height_bev``, ``lidar_points`` (:mod:`ablate.fusion.geometry`).

Metrics (KITTI road devkit measures in the metric BEV, :class:`~ablate.metrics.road.RoadMaxF`, in percent), per
branch the model has: ``cam_max_f``, ``cam_ap``, ``cam_pre``, ``cam_rec`` from the camera-space output and
``bev_max_f``, ... from the BEV output, both warped to the devkit's grid (:class:`MetricBev`); and ``max_f``, ``ap``,
``pre``, ``rec``: the prediction, the camera-space branch when the model has one ("the output of the camera space
branch is the final result for testing", Fig. 4), else the BEV branch (the BEV-only row).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import torch
from torch import nn

from ablate.fusion.geometry import BevGrid
from ablate.metrics.road import RoadMaxF
from ablate.tasks.base import FusionTask
from ablate.tasks.road_bev.evaluate import MetricBev
from ablate.tasks.road_bev.figures import draw_gains, draw_roads
from ablate.tasks.road_bev.loss import RoadLoss, upsample

if TYPE_CHECKING:
    from matplotlib.figure import Figure

MEASURES = ("max_f", "ap", "pre", "rec")
BRANCHES = {"cam": "road_cam", "bev": "road_bev"}


class RoadTask(FusionTask):
    """Road probability in camera space and in BEV with BiFNet's loss (:class:`RoadLoss`, ``loss`` its options)
    and the KITTI road measures. ``grid``: the BEV raster the model predicts on (``data.bev``)."""

    def __init__(
        self,
        model: nn.Module,
        optimizer: Callable[..., torch.optim.Optimizer],
        scheduler: Callable[..., Any] | None = None,
        monitor: str = "val/max_f",
        loss: dict | None = None,
        grid: dict | None = None,
        figure_frames: int = 4,
        **options: Any,
    ) -> None:
        super().__init__(model, optimizer, scheduler, monitor, **options)
        loss = dict(loss or {})
        if unknown := sorted(set(loss) - {"alpha", "gamma", "lam"}):
            raise ValueError(f"task.loss: unknown option(s) {unknown}; valid: alpha, gamma, lam")
        self.criterion = RoadLoss(**loss)
        self.warp = MetricBev(BevGrid.from_config(grid))
        self.figure_frames = figure_frames
        for stage in ("val", "test"):
            setattr(self, f"{stage}_road", nn.ModuleDict({b: RoadMaxF() for b in BRANCHES}))

    def training_step(self, batch: dict, batch_idx: int) -> torch.Tensor:
        parts = self.criterion(self(batch), batch)
        loss = self.check_finite(parts["loss"])
        size = len(batch["frame"]) if "frame" in batch else 1
        self.log("train/loss", loss, prog_bar=True, batch_size=size)
        for name in ("loss_cam", "loss_bev"):
            self.log(f"train/{name}", parts[name], batch_size=size)
        return loss

    def probabilities(self, outputs: dict, batch: dict) -> dict[str, torch.Tensor]:
        """Per branch the model has: road probability [B,H,W] at the resolution of that space's ground truth."""
        out = {}
        if "road_cam" in outputs:
            out["cam"] = torch.sigmoid(upsample(outputs["road_cam"], batch["free_space"].shape[-2:]))[:, 0]
        if "road_bev" in outputs:
            size = batch["road_bev"].shape[-2:] if "road_bev" in batch else self.warp.grid.shape
            out["bev"] = torch.sigmoid(upsample(outputs["road_bev"], size))[:, 0]
        return out

    def _eval_step(self, batch: dict, stage: str) -> None:
        outputs = self(batch)
        calibs = batch["calib"]
        target, inside = self.warp.camera(batch["free_space"], calibs)
        valid = inside & (self.warp.camera(batch["road_valid"], calibs)[0] > 0.5 if "road_valid" in batch else inside)
        metrics = getattr(self, f"{stage}_road")
        kept = []
        for branch, prob in self.probabilities(outputs, batch).items():
            warped = self.warp.camera(prob, calibs)[0] if branch == "cam" else self.warp.lidar(prob, calibs)
            counts = metrics[branch].histograms(warped.clamp(0, 1), target > 0.5, valid)  # per frame, checked as update
            metrics[branch].update(histograms=counts)
            if stage == "test" and "frame" in batch:
                kept.append(counts)
        if kept:  # per frame, each branch's histograms in BRANCHES' order: the counts its MaxF resamples from
            self.keep_frame_counts(list(batch["frame"]), torch.cat(kept, dim=1))
        self.log(f"{stage}/loss", self.criterion(outputs, batch)["loss"], batch_size=len(calibs))

    def _eval_end(self, stage: str) -> None:
        metrics = getattr(self, f"{stage}_road")
        main = None
        for branch in BRANCHES:
            metric = metrics[branch]
            if metric.update_count == 0:
                continue
            scores = metric.compute()
            for k in MEASURES:
                self.log(f"{stage}/{branch}_{k}", scores[k], prog_bar=(k == "max_f"))
            main = main if main is not None else scores  # the camera branch first
        if main is not None:
            for k in MEASURES:
                self.log(f"{stage}/{k}", main[k])
        for metric in metrics.values():
            metric.reset()

    @torch.no_grad()
    def figure(self, batch: dict) -> Figure:
        """Image, ground truth and predicted road probability in camera space and in BEV for the first frames."""
        n = min(self.figure_frames, len(batch["frame"]) if "frame" in batch else 1)
        sub = {k: v[:n] for k, v in batch.items() if torch.is_tensor(v)}
        device = next(self.model.parameters()).device
        was_training = self.model.training
        self.model.eval()
        try:
            probs = self.probabilities(self.model({k: v.to(device) for k, v in sub.items()}), sub)
        finally:
            self.model.train(was_training)
        return draw_roads(sub, {k: v.cpu() for k, v in probs.items()})

    @torch.no_grad()
    def gate_figure(self, batch: dict) -> Figure | None:
        """CBF's gains per channel (camera and LiDAR input) at every fusion point, mean over the first frames; None
        for a model without CBF gains."""
        fusion: list[nn.Module] = getattr(self.model, "fusion_modules", lambda: [])()
        if not fusion:
            return None
        self.figure(batch)  # one forward pass fills each operator's last gains
        return draw_gains(fusion, getattr(self.model, "levels", ()))
