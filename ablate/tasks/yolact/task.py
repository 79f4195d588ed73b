"""SMoE's instance segmentation task as a LightningModule (seed 000 §4.3 training, §5 evaluation).

Batches are the data module's dicts: modality tensors [B, C, H, W], ``instances`` (one dict per image: ``masks``
[N, H, W] bool, ``labels`` [N] 0 car / 1 pedestrian, ``boxes`` [N, 4] xyxy px), optional ``ignore`` [B, H, W]
bool (KITTI DontCare) and ``condition`` (one name per image).

Metrics, in percent like SMoE Tables 1-2: ``{val,test}/map``, ``map_50``, ``map_75`` (mask AP, COCO definition,
objects >= 25 px tall at KITTI's height, :class:`~ablate.metrics.coco.MaskAP`) and ``bbox_map``. At test, mask AP
per condition group as well (``test/map_clear``, ``test/map_night``, ``test/map_rain``, ``test/map_glare``): rain
pools SMoE's light rain day and light rain night (§3.3); a group is logged only when the test set holds it. A
value COCOeval leaves undefined (no counted ground truth) is logged as NaN.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import torch
from torch import nn

from ablate.metrics.coco import MaskAP
from ablate.tasks.base import FusionTask
from ablate.tasks.yolact.anchors import Anchors
from ablate.tasks.yolact.figures import draw_gates, draw_instances
from ablate.tasks.yolact.loss import YolactLoss
from ablate.tasks.yolact.nms import decode

if TYPE_CHECKING:
    from matplotlib.figure import Figure

#: Condition groups of the per-condition columns; members are ablate.data condition names (SMoE §3.3).
CONDITION_GROUPS: dict[str, tuple[str, ...]] = {
    "clear": ("clear",),
    "night": ("night",),
    "rain": ("rain_day", "rain_night"),
    "glare": ("glare",),
}
#: The Complex KITTI conditions, spread equally over the data (SMoE §3.3).
SMOE_CONDITIONS = ("clear", "night", "rain_day", "rain_night", "glare")
_DECODE_OPTIONS = tuple(
    p for p in inspect.signature(decode).parameters if p not in ("outputs", "image_size", "anchors")
)


def condition_group(condition: str) -> str | None:
    """The group of ``CONDITION_GROUPS`` a data condition belongs to, or None."""
    return next((g for g, members in CONDITION_GROUPS.items() if condition in members), None)


def task_head(model: nn.Module) -> nn.Module | None:
    """A fusion model's task head: ``model.head``, or for late fusion the first of ``model.heads`` (one per
    modality, all built by the same head partial, so they share their anchor layout)."""
    if isinstance(getattr(model, "head", None), nn.Module):
        return model.head
    heads = getattr(model, "heads", None)
    return next(iter(heads.values())) if isinstance(heads, nn.ModuleDict) and len(heads) else None


def select(batch: dict, index: list[int]) -> dict:
    """The frames ``index`` of a batch: tensors and per-image lists indexed alike, other values kept."""
    out = {}
    for key, value in batch.items():
        if torch.is_tensor(value) and value.ndim:
            out[key] = value[index]
        elif isinstance(value, (list, tuple)):
            out[key] = [value[i] for i in index]
        else:
            out[key] = value
    return out


def gate_frames(
    conditions: list[str] | None, batch_size: int, wanted: tuple[str, ...] = ("night", "glare"), count: int = 2
) -> list[int]:
    """Indices of the first frame of each ``wanted`` condition present, filled up with the first frames."""
    conditions = list(conditions or [])
    picked = [conditions.index(c) for c in wanted if c in conditions]
    picked += [i for i in range(batch_size) if i not in picked]
    return picked[: min(count, batch_size)]


class InstanceTask(FusionTask):
    """YOLACT-style instance segmentation with SMoE eq. 7 (:class:`YolactLoss`) and mask AP.

    ``loss``: keyword options of :class:`YolactLoss`; ``decode``: keyword options of :func:`decode` (score and
    NMS thresholds, detections per image). Anchors come from the model's head (:func:`task_head`), so loss and
    decoding use the layout the head was built with. ``conditions``: the data's conditions; each must belong to a
    group of ``CONDITION_GROUPS`` (default: the five of SMoE §3.3).
    """

    def __init__(
        self,
        model: nn.Module,
        optimizer: Callable[..., torch.optim.Optimizer],
        scheduler: Callable[..., Any] | None = None,
        monitor: str = "val/map",
        loss: dict | None = None,
        decode: dict | None = None,
        conditions: list[str] | None = None,
        figure_frames: int = 4,
    ) -> None:
        super().__init__(model, optimizer, scheduler, monitor)
        head = task_head(model)
        self.anchors: Anchors = getattr(head, "anchors", None) or Anchors()
        self.criterion = YolactLoss(anchors=self.anchors, **dict(loss or {}))
        self.decode_options = dict(decode or {})
        if bad := sorted(set(self.decode_options) - set(_DECODE_OPTIONS)):
            raise ValueError(f"task.decode: unknown option(s) {bad}; valid: {list(_DECODE_OPTIONS)}")
        conditions = list(SMOE_CONDITIONS if conditions is None else conditions)
        if bad := [c for c in conditions if condition_group(c) is None]:
            valid = [c for members in CONDITION_GROUPS.values() for c in members]
            raise ValueError(f"task.conditions: no condition group for {bad}; valid: {valid}")
        self.groups = [g for g, members in CONDITION_GROUPS.items() if set(members) & set(conditions)]
        self.figure_frames = figure_frames
        self.val_map, self.test_map = MaskAP(), MaskAP()
        self.test_group_map = nn.ModuleDict({f"map_{g}": MaskAP() for g in self.groups})  # "clear" is a method name

    # -- batch access ---------------------------------------------------------------------------------------
    @staticmethod
    def targets(batch: dict) -> list[dict[str, torch.Tensor]]:
        """Per image ``masks``, ``labels``, ``boxes`` and, when the batch has it, ``ignore``."""
        if "instances" not in batch:
            raise KeyError("InstanceTask needs batch['instances']: set `targets: [instances]` in the task config")
        out = [dict(t) for t in batch["instances"]]
        if "ignore" in batch:
            for t, ignore in zip(out, batch["ignore"]):
                t["ignore"] = ignore
        return out

    def predict(self, outputs: dict, image_size: tuple[int, int]) -> list[dict[str, torch.Tensor]]:
        """Per image ``masks``, ``scores``, ``labels``, ``boxes`` from the model's raw outputs (FastNMS with this
        task's anchors and ``decode`` options)."""
        return decode(outputs, image_size, anchors=self.anchors, **self.decode_options)

    # -- loops ----------------------------------------------------------------------------------------------
    def training_step(self, batch: dict, batch_idx: int) -> torch.Tensor:
        losses = self.criterion(self(batch), self.targets(batch), self.image_size(batch))
        loss = self.check_finite(losses["total"])
        size = len(batch["instances"])
        self.log("train/loss", loss, prog_bar=True, batch_size=size)
        for key in ("cls", "box", "mask"):
            self.log(f"train/loss_{key}", losses[key].detach(), batch_size=size)
        return loss

    def _eval_step(self, batch: dict, stage: str) -> None:
        outputs, targets, size = self(batch), self.targets(batch), self.image_size(batch)
        self.log(f"{stage}/loss", self.criterion(outputs, targets, size)["total"], batch_size=len(targets))
        preds = self.predict(outputs, size)
        getattr(self, f"{stage}_map").update(preds, targets)
        if stage == "test":
            if "frame" in batch:
                self.keep_frame_names(list(batch["frame"]))
            for pred, target, condition in zip(preds, targets, batch.get("condition") or [None] * len(preds)):
                group = condition_group(condition) if condition is not None else None
                if f"map_{group}" in self.test_group_map:
                    self.test_group_map[f"map_{group}"].update([pred], [target])

    def _eval_end(self, stage: str) -> None:
        metric = getattr(self, f"{stage}_map")
        if metric.update_count:
            values = metric.compute()
            for key in ("map", "map_50", "map_75", "bbox_map"):
                self.log(f"{stage}/{key}", _percent(values[key]), prog_bar=key == "map")
            if stage == "test":  # the mask AP's matches per frame: the tables resample the test set from them
                self.keep_frame_rows([r | {"metric": "map"} for r in metric.frame_rows("segm")])
        metric.reset()
        if stage == "test":
            for key, m in self.test_group_map.items():
                if m.update_count:
                    self.log(f"test/{key}", _percent(m.compute()["map"]))
                m.reset()

    # -- figures --------------------------------------------------------------------------------------------
    def _forward_frames(self, batch: dict, index: list[int]) -> tuple[dict, dict]:
        """Run the model in eval mode on frames ``index``; returns (their sub-batch, raw outputs)."""
        sub = select(batch, index)
        return sub, self.forward_eval(sub)

    def figure(self, batch: dict, score: float = 0.5) -> Figure:
        """Ground truth and predicted masks (score >= ``score``) over the RGB of the first frames, as SMoE Fig. 6."""
        n = min(self.figure_frames, len(batch["instances"]))
        sub, outputs = self._forward_frames(batch, list(range(n)))
        preds = self.predict(outputs, self.image_size(sub))
        return draw_instances(
            _display_image(sub, self.model),
            sub["instances"],
            [{k: v.cpu() for k, v in p.items()} for p in preds],
            sub.get("condition"),
            score,
        )

    def gate_figure(self, batch: dict) -> Figure | None:
        """Gate maps of the first gated fusion op (finest fusion point) on a night and a glare frame, when the
        batch holds them (else the first frames), upsampled over each input (SMoE §4.2 eq. 2-3, DGFN Fig. 5).
        Each gate is averaged over channels. None when the model has no gated fusion op."""
        ops = self.model.fusion_modules() if hasattr(self.model, "fusion_modules") else []
        if not ops:
            return None
        index = gate_frames(batch.get("condition"), len(batch["instances"]))
        sub, _ = self._forward_frames(batch, index)
        op = next((op for op in ops if op.last_gates is not None), None)
        if op is None:
            return None
        images = {m: sub[m] for m in self.model.modalities}
        return draw_gates(images, [g.mean(1).cpu() for g in op.last_gates], sub.get("condition"))


def _percent(value: torch.Tensor) -> torch.Tensor:
    """MaskAP's 0-1 value in percent; its -1 (undefined) as NaN."""
    return 100.0 * value if value >= 0 else torch.tensor(float("nan"))


def _display_image(batch: dict, model: nn.Module) -> torch.Tensor:
    """The frames to draw on: ``rgb`` if present, else the model's first modality."""
    key = (
        "rgb"
        if "rgb" in batch
        else next(
            iter(
                getattr(model, "modalities", None)
                or [k for k, v in batch.items() if torch.is_tensor(v) and v.ndim == 4]
            )
        )
    )
    return batch[key].detach().cpu()
