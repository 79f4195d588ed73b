"""DGFN's 2D object detection task as a LightningModule (Kim et al., seed 002 §IV): SSD's loss, KITTI AP.

Batches are the data module's dicts: modality tensors [B, C, H, W], ``boxes2d`` (one dict per image: ``boxes``
[N, 4] xyxy px, ``labels`` [N] 0 Car / 1 Pedestrian / 2 Cyclist / 3 Van / 4 Person_sitting / 5 DontCare,
``difficulty`` [N] 0 easy / 1 moderate / 2 hard / -1 none at the data's height), ``frame`` and ``condition``.

Metrics, in percent (:class:`~ablate.metrics.kitti.KittiAP`: the KITTI devkit's 2D AP, Car at IoU 0.7,
Pedestrian and Cyclist at 0.5): ``{stage}/{class}_{level}`` (``car_easy``, ``car_moderate``, ``car_hard``,
``pedestrian_easy``, ...) 11-point, as the KITTI devkit of DGFN's time computed it (the paper does not say; see
``ablate.metrics.kitti``); ``{class}_{level}_ap40`` 40-point; ``ap11`` and ``ap40`` the mean over the evaluated
classes at moderate. A class with no counted ground truth is logged as NaN. At test, ``gate_<modality>``: the
mean weight map of the first fusion point (conv4_3) over the test frames, DGFN Fig. 4 (1 for the baseline, whose
weights are fixed to one). With ``eval_conditions`` every test metric is logged once per condition,
``test/<condition>/<metric>`` (:class:`~ablate.tasks.base.FusionTask`).
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, cast

import torch
from torch import nn
from torchmetrics import MeanMetric

from ablate.metrics.kitti import LEVELS, KittiAP
from ablate.tasks.base import FusionTask
from ablate.tasks.ssd import CLASSES
from ablate.tasks.ssd.decode import decode
from ablate.tasks.ssd.figures import draw_detections
from ablate.tasks.ssd.loss import SSDLoss
from ablate.tasks.yolact.figures import draw_gates
from ablate.tasks.yolact.task import select, task_head

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from ablate.tasks.conditions import EvalConditions

_DECODE_OPTIONS = tuple(
    p for p in inspect.signature(decode).parameters if p not in ("outputs", "image_size", "anchors")
)
_LOSS_OPTIONS = tuple(p for p in inspect.signature(SSDLoss).parameters if p not in ("anchors", "num_classes"))
_METRIC_OPTIONS = ("devkit", "min_overlap")


class DetectionTask(FusionTask):
    """SSD-style detection over any model whose head has ``anchors`` and ``num_classes``
    (:class:`~ablate.tasks.ssd.head.SSDHead`: on DGFN's VGG maps or a FusionModel's FPN).

    ``loss``: options of :class:`SSDLoss`; ``decode``: options of :func:`decode`; ``classes``: the classes
    evaluated (KITTI names among the head's); ``metric``: options of :class:`KittiAP` (``devkit``: ``"2017"``, its
    default, or ``"2d_2012"``; ``min_overlap``). ``train_corruptions``, ``eval_*``: see
    :class:`~ablate.tasks.base.FusionTask`.
    """

    def __init__(
        self,
        model: nn.Module,
        optimizer: Callable[..., torch.optim.Optimizer],
        scheduler: Callable[..., Any] | None = None,
        monitor: str = "val/ap11",
        loss: dict | None = None,
        decode: dict | None = None,
        classes: list[str] | tuple[str, ...] = ("Car", "Pedestrian"),
        figure_frames: int = 4,
        metric: dict | None = None,
        **conditions: Any,
    ) -> None:
        super().__init__(model, optimizer, scheduler, monitor, **conditions)
        head = task_head(model)
        if getattr(head, "anchors", None) is None or getattr(head, "num_classes", None) is None:
            raise ValueError(
                f"DetectionTask needs a detection head with `anchors` and `num_classes` (head="
                f"ablate.tasks.detection.SSDHead); got {type(head).__name__}"
            )
        assert head is not None  # it has anchors
        self.anchors, self.num_classes = head.anchors, int(head.num_classes)
        for option, given, valid in (
            ("task.loss", loss, _LOSS_OPTIONS),
            ("task.decode", decode, _DECODE_OPTIONS),
            ("task.metric", metric, _METRIC_OPTIONS),
        ):
            if bad := sorted(set(given or {}) - set(valid)):
                raise ValueError(f"{option}: unknown option(s) {bad}; valid: {list(valid)}")
        self.criterion = SSDLoss(self.anchors, self.num_classes, **dict(loss or {}))
        self.decode_options = dict(decode or {})
        self.classes = tuple(classes)
        if bad := [c for c in self.classes if c not in CLASSES[: self.num_classes]]:
            raise ValueError(f"task.classes: {bad} not among the head's classes {list(CLASSES[: self.num_classes])}")
        self.figure_frames = figure_frames
        self.val_ap, self.test_ap = (KittiAP(self.classes, **dict(metric or {})) for _ in range(2))
        fused = hasattr(model, "fusion_modules") and model.fusion_modules()
        if fused:
            self.test_gates = nn.ModuleDict({m: MeanMetric() for m in model.modalities})

    @staticmethod
    def targets(batch: dict) -> list[dict[str, torch.Tensor]]:
        if "boxes2d" not in batch:
            raise KeyError("DetectionTask needs batch['boxes2d']: set `targets: [boxes2d]` in the task config")
        return batch["boxes2d"]

    def predict(self, outputs: dict, image_size: tuple[int, int]) -> list[dict[str, torch.Tensor]]:
        """Per image ``boxes``, ``scores``, ``labels`` from the raw outputs (this task's anchors and options)."""
        return decode(outputs, image_size, self.anchors, **self.decode_options)

    def training_step(self, batch: dict, batch_idx: int) -> torch.Tensor:
        targets = self.targets(batch)
        losses = self.criterion(self(batch), targets, self.image_size(batch))
        loss = self.check_finite(losses["total"])
        self.log("train/loss", loss, prog_bar=True, batch_size=len(targets))
        for key in ("cls", "box"):
            self.log(f"train/loss_{key}", losses[key].detach(), batch_size=len(targets))
        return loss

    def _eval_step(self, batch: dict, stage: str) -> None:
        outputs, targets, size = self(batch), self.targets(batch), self.image_size(batch)
        self.log(f"{stage}/loss", self.criterion(outputs, targets, size)["total"], batch_size=len(targets))
        metric = getattr(self, f"{stage}_ap")
        metric.image_height = float(size[0])  # KITTI's pixel heights scale with the evaluated frames' height
        metric.update(self.predict(outputs, size), targets)
        if stage == "test" and "frame" in batch:
            self.keep_frame_names(list(batch["frame"]))
        gates = getattr(self, f"{stage}_gates", None)
        if gates is not None:
            op = self.model.fusion_modules()[0]
            for m, g in zip(self.model.modalities, op.last_gates):
                gates[m].update(g.float().mean((1, 2, 3)))

    def _eval_end(self, stage: str) -> None:
        metric = getattr(self, f"{stage}_ap")
        if metric.update_count:
            values = metric.compute()
            for cls in self.classes:
                for level in LEVELS:
                    name = f"{stage}/{cls.lower()}_{level}"
                    self.log(name, _percent(values[f"{cls}/{level}/ap11"]))
                    self.log(f"{name}_ap40", _percent(values[f"{cls}/{level}/ap40"]))
            self.log(f"{stage}/ap11", _percent(values["ap11"]), prog_bar=True)
            self.log(f"{stage}/ap40", _percent(values["ap40"]))
            if stage == "test":  # each class's matches per frame: the tables resample the test set from them
                for cls in self.classes:
                    for level in LEVELS:
                        rows = metric.frame_rows(cls, level)
                        self.keep_frame_rows([r | {"metric": f"{cls.lower()}_{level}"} for r in rows])
        metric.reset()
        for m, mean in (getattr(self, f"{stage}_gates", None) or {}).items():
            if mean.update_count:
                self.log(f"{stage}/gate_{m}", mean.compute())
            mean.reset()

    def figure(self, batch: dict, score: float = 0.5) -> Figure:
        """Ground-truth and predicted boxes (score >= ``score``) over the camera image of the first frames."""
        n = min(self.figure_frames, len(self.targets(batch)))
        sub = select(batch, list(range(n)))
        preds = self.predict(self.forward_eval(sub), self.image_size(sub))
        key = "rgb" if "rgb" in sub else next(iter(self.model.modalities))
        return draw_detections(
            sub[key],
            sub["boxes2d"],
            [{k: v.cpu() for k, v in p.items()} for p in preds],
            sub.get("condition"),
            self.num_classes,
            score,
        )

    def gate_figure(self, batch: dict) -> Figure | None:
        """DGFN Fig. 5: the weight maps of the first fusion point (conv4_3) over each input, for the first frame
        under every named test condition (the first frames when there are none). None without a gated fusion."""
        ops = self.model.fusion_modules() if hasattr(self.model, "fusion_modules") else []
        if not ops or not getattr(ops[0], "gated", True):
            return None
        plan: list[tuple[str | None, int]]
        if self.eval_conditions:
            plan = [(name, 0) for name in self.eval_conditions.base]
        else:
            plan = [(None, i) for i in range(min(2, len(self.targets(batch))))]
        images: dict[str, list[torch.Tensor]]
        gates: dict[str, list[torch.Tensor]]
        images, gates = {m: [] for m in self.model.modalities}, {m: [] for m in self.model.modalities}
        for name, i in plan:
            sub = select(batch, [i])
            # a named frame of the plan comes from eval_conditions
            sub = cast("EvalConditions", self.eval_conditions).apply(sub, name) if name else sub
            self.forward_eval(sub)
            for m, g in zip(self.model.modalities, ops[0].last_gates):
                images[m].append(sub[m].cpu())
                gates[m].append(g.mean(1).cpu())
        captions = (
            cast("list[str]", [name for name, _ in plan])  # the plan of eval_conditions names every frame
            if self.eval_conditions
            else [batch["condition"][i] for _, i in plan]
            if batch.get("condition")
            else None
        )
        return draw_gates(
            {m: torch.cat(v) for m, v in images.items()}, [torch.cat(g) for g in gates.values()], captions
        )


def _percent(value: torch.Tensor) -> torch.Tensor:
    """KittiAP's percent; its -1 (no counted ground truth) as NaN."""
    return value if value >= 0 else torch.tensor(float("nan"))
