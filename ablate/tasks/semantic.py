"""Semantic segmentation of free space and road objects, the ChiNet task (John et al., ../shared/seeds/003).

A model returns either two single-channel logit maps ``free_space`` and ``road_objects`` (multilabel: two output
branches with sigmoid + binary cross-entropy, ChiNet §III-A) or one 3-class logit map ``semantic`` (multiclass:
softmax + categorical cross-entropy, ChiNet §III-B, MISO / U-Net / FuseNet). Maps at a lower resolution than the
labels are upsampled bilinearly before the loss.

Metrics (the paper gives no definition of "Det. Rate %", so this is the reading chosen here):
- ``det_rate``: pixel accuracy over the pixels whose ground truth is free space or road object, in percent:
  (free-space pixels predicted free space + object pixels predicted object) / (free-space + object pixels).
  Background pixels do not count, so a model cannot score by predicting background.
- ``iou_free_space`` and ``iou_road_objects``: per-class intersection over union, in percent.
A multilabel prediction becomes a class map as: object where p(object) > 0.5, else free space where
p(free space) > 0.5, else background — the same precedence the labels use.

``class_weights`` (multiclass loss only; ChiNet §III-B says categorical cross-entropy and no weighting, which is the
default ``None``): ``"median_frequency"`` weights class c by median(f) / f_c, f_c its share of the training
split's pixels (median frequency balancing, Eigen & Fergus, ICCV 2015, with the share over all pixels rather than
over the images holding c), counted once at the start of the fit and kept in the checkpoint (``class_weight``);
or a list of 3 weights. The multilabel loss already gives road objects a term of its own. No table row sets it:
tried on the FuseNet seed whose road objects never appeared at the cpu scale (ChiNet Table II, seed 1), it left
their IoU at 0, so class imbalance alone does not explain that seed.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING, Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402
import torch.nn.functional as F  # noqa: E402
from torch import nn  # noqa: E402
from torchmetrics.classification import MulticlassJaccardIndex, MulticlassRecall  # noqa: E402

from ablate.tasks.base import FusionTask  # noqa: E402

if TYPE_CHECKING:
    from matplotlib.figure import Figure

CLASSES = ("background", "free_space", "road_objects")
BRANCHES = ("free_space", "road_objects")


class SegmentationHead(nn.Module):
    """A head for a fusion model's FPN: P3 .. P(2+levels) upsampled to P3's size and summed, a 3x3 conv + ReLU,
    then one 1x1 conv per output branch, as ChiNet's separate free-space and road-object branches."""

    def __init__(
        self, in_channels: int, num_levels: int = 5, levels: int = 3, outputs: tuple[str, ...] = BRANCHES
    ) -> None:
        super().__init__()
        if not 1 <= levels <= num_levels:
            raise ValueError(f"head.levels must be in 1..{num_levels}, got {levels}")
        self.levels = levels
        self.mix = nn.Sequential(nn.Conv2d(in_channels, in_channels, 3, padding=1), nn.ReLU(inplace=True))
        self.branches = nn.ModuleDict({name: nn.Conv2d(in_channels, 1, 1) for name in outputs})
        self.out_channels = {name: 1 for name in outputs}

    def forward(self, features: list[torch.Tensor]) -> dict[str, torch.Tensor]:
        size = features[0].shape[-2:]
        x = features[0]
        for f in features[1 : self.levels]:
            x = x + F.interpolate(f, size=size, mode="bilinear", align_corners=False)
        x = self.mix(x)
        return {name: conv(x) for name, conv in self.branches.items()}


def class_map(outputs: dict[str, torch.Tensor], size: tuple[int, int]) -> torch.Tensor:
    """(B,H,W) int64 class map (0 background, 1 free space, 2 road object) from a model's outputs."""
    if "semantic" in outputs:
        return _up(outputs["semantic"], size).argmax(1)
    free = _up(outputs["free_space"], size)[:, 0] > 0
    obj = _up(outputs["road_objects"], size)[:, 0] > 0
    return torch.where(obj, 2, torch.where(free, 1, 0))


def median_frequency(batches: Iterable[dict[str, Any]]) -> torch.Tensor:
    """Median frequency balancing weights median(f) / f_c from the ``semantic`` labels of ``batches``; a class
    absent from every label gets weight 0 (it has no pixel to weigh)."""
    counts = torch.zeros(len(CLASSES), dtype=torch.float64)
    for batch in batches:
        counts += torch.bincount(batch["semantic"].flatten(), minlength=len(CLASSES))[: len(CLASSES)].double()
    if counts.sum() == 0:
        raise ValueError("task.class_weights=median_frequency: the training split has no labelled pixel")
    freq = counts / counts.sum()
    present = freq > 0
    weight = torch.zeros_like(freq)
    weight[present] = freq[present].median() / freq[present]
    return weight.float()


def confusion(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(B, 9) int64: each frame's 3 x 3 confusion counts, ground truth by prediction, row-major (``[t * 3 + p]``):
    what ``det_rate`` and the IoUs are computed from (:data:`ablate.tables.frames.FROM_COUNTS`), so that a table can
    resample the test frames."""
    n = len(CLASSES)
    index = (target.long() * n + pred.long()).flatten(1)
    return torch.stack([torch.bincount(i, minlength=n * n) for i in index.cpu()])


def _up(x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    return x if x.shape[-2:] == tuple(size) else F.interpolate(x, size=size, mode="bilinear", align_corners=False)


class SemanticTask(FusionTask):
    """Free space + road objects with ChiNet's losses and the metrics above."""

    def __init__(
        self,
        model: nn.Module,
        optimizer: Callable[..., torch.optim.Optimizer],
        scheduler: Callable[..., Any] | None = None,
        monitor: str = "val/det_rate",
        figure_frames: int = 4,
        class_weights: str | list[float] | None = None,
    ) -> None:
        super().__init__(model, optimizer, scheduler, monitor)
        self.figure_frames = figure_frames
        if class_weights not in (None, "median_frequency") and (
            isinstance(class_weights, str) or len(class_weights) != len(CLASSES)
        ):
            raise ValueError(
                f"task.class_weights: 'median_frequency', a list of {len(CLASSES)} weights or null; "
                f"got {class_weights!r}"
            )
        self.class_weights = class_weights
        if class_weights is not None:  # filled at the start of the fit, or from a checkpoint
            given = [float(w) for w in class_weights] if not isinstance(class_weights, str) else [0.0] * 3
            self.register_buffer("class_weight", torch.tensor(given))
        for stage in ("val", "test"):
            setattr(self, f"{stage}_rate", MulticlassRecall(num_classes=3, average="micro", ignore_index=0))
            setattr(self, f"{stage}_iou", MulticlassJaccardIndex(num_classes=3, average="none"))

    def on_fit_start(self) -> None:
        super().on_fit_start()
        if self.class_weights == "median_frequency" and not bool(self.class_weight.any()):
            self.class_weight.copy_(median_frequency(self.trainer.datamodule.train_dataloader()))

    def loss(self, outputs: dict[str, torch.Tensor], batch: dict) -> torch.Tensor:
        """BCE per output branch (multilabel, ChiNet), or cross-entropy over 3 classes (multiclass variants),
        weighted by ``class_weight`` when the task has one."""
        size = batch["semantic"].shape[-2:]
        if "semantic" in outputs:
            weight = getattr(self, "class_weight", None)
            return F.cross_entropy(_up(outputs["semantic"], size), batch["semantic"], weight=weight)
        return sum(F.binary_cross_entropy_with_logits(_up(outputs[name], size), batch[name]) for name in BRANCHES)

    def training_step(self, batch: dict, batch_idx: int) -> torch.Tensor:
        loss = self.check_finite(self.loss(self(batch), batch))
        self.log("train/loss", loss, prog_bar=True, batch_size=batch["semantic"].shape[0])
        return loss

    def _eval_step(self, batch: dict, stage: str) -> None:
        outputs = self(batch)
        target = batch["semantic"]
        pred = class_map(outputs, target.shape[-2:])
        getattr(self, f"{stage}_rate").update(pred, target)
        getattr(self, f"{stage}_iou").update(pred, target)
        if stage == "test" and "frame" in batch:
            self.keep_frame_counts(list(batch["frame"]), confusion(pred, target))
        self.log(f"{stage}/loss", self.loss(outputs, batch), batch_size=target.shape[0])

    def _eval_end(self, stage: str) -> None:
        rate, iou = getattr(self, f"{stage}_rate"), getattr(self, f"{stage}_iou")
        self.log(f"{stage}/det_rate", 100.0 * rate.compute(), prog_bar=True)
        ious = iou.compute()
        for i, name in enumerate(CLASSES[1:], start=1):
            self.log(f"{stage}/iou_{name}", 100.0 * ious[i])
        rate.reset()
        iou.reset()

    @torch.no_grad()
    def figure(self, batch: dict) -> Figure:
        """Input intensity, ground truth and prediction for the first frames; red free space, blue objects
        (the colours of ChiNet Fig. 4)."""
        self.model.eval()
        n = min(self.figure_frames, batch["semantic"].shape[0])
        sub = {k: v[:n] for k, v in batch.items() if torch.is_tensor(v)}
        device = next(self.model.parameters()).device
        pred = class_map(self.model({k: v.to(device) for k, v in sub.items()}), sub["semantic"].shape[-2:]).cpu()
        image = sub["rgb"] if "rgb" in sub else sub.get("intensity", next(iter(sub.values())))
        fig, axes = plt.subplots(n, 3, figsize=(12, 1.4 * n + 0.6), squeeze=False)
        colours = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 0, 1]], dtype=torch.float32)
        for i in range(n):
            img = image[i].permute(1, 2, 0).float().clamp(0, 1)
            img = img.expand(-1, -1, 3) if img.shape[-1] == 1 else img
            for ax, (title, labels) in zip(
                axes[i], (("input", None), ("ground truth", sub["semantic"][i]), ("prediction", pred[i]))
            ):
                shown = img if labels is None else 0.5 * img + 0.5 * colours[labels]
                ax.imshow(shown.numpy())
                ax.set_axis_off()
                if i == 0:
                    ax.set_title(title)
        fig.tight_layout()
        return fig
