"""SMoE's diagnosis of a two-stage instance table, the YOLACT family's part of ``python -m ablate.diagnose``
(:mod:`ablate.analysis.diagnose` finds the checkpoints and the runs): what each trained model finds and where its
gates look, on the test split.

SMoE's claim (seed 000 §5.1, Table 1) is that fusing the RGB and the DDM experts beats both. Whether it can on
given data depends on what the experts know that the other does not: :func:`evaluate` records, per counted
ground-truth object (the AP's objects: >= 25 px tall at KITTI's height, :class:`~ablate.metrics.coco.MaskAP`),
whether a detection of its class, among all the detections AP sees, has mask IoU >= 0.5 with it, and the mean gate
weight on each modality per fusion point (SMoE eq. 2-3: W on f_i = RGB, 1 - W on f_j = DDM), averaged over channels
and positions; :func:`ap_per_condition` the mask AP in clear weather, at night and in glare on the *same* test
frames. The tables and figures of these are :mod:`ablate.tasks.yolact.diagnosis_report`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig

from ablate.data.difficulty import counted
from ablate.metrics.coco import MaskAP
from ablate.tasks.yolact.task import condition_group

IOU = 0.5


def mask_overlaps(a: torch.Tensor, b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(IoU, intersection over a's area) of every mask of ``a`` (N,H,W) with every mask of ``b`` (M,H,W)."""
    fa, fb = a.flatten(1).float(), b.flatten(1).float()
    inter = fa @ fb.T
    area = fa.sum(1, keepdim=True)
    return inter / (area + fb.sum(1) - inter).clamp(min=1), inter / area.clamp(min=1)


def found_objects(pred: dict, target: dict, height: int) -> tuple[np.ndarray, np.ndarray]:
    """(counted, found) per ground-truth object of one image: counted = tall enough for the AP; found = a
    same-class detection with mask IoU >= 0.5."""
    gt, labels = target["masks"].bool(), target["labels"]
    if "boxes" in target:
        tall = (target["boxes"][:, 3] - target["boxes"][:, 1]).cpu()
    else:  # the tight box of the mask, as MaskAP
        rows = gt.any(2)
        tall = torch.tensor([(r.nonzero().max() - r.nonzero().min() + 1).item() if r.any() else 0 for r in rows])
    is_counted = counted(tall.double(), height).numpy()
    found = np.zeros(len(gt), dtype=bool)
    if len(gt) and len(pred["masks"]):
        iou, _ = mask_overlaps(gt, pred["masks"].bool().to(gt.device))
        same = labels.view(-1, 1).to(pred["labels"].device) == pred["labels"].view(1, -1)
        found = ((iou * same.to(iou.device)) >= IOU).any(1).cpu().numpy()
    return is_counted, found


@dataclass
class Evaluation:
    """One checkpoint on the test split: per counted GT object (image, object, group, found), per image x fusion
    point x modality the mean gate, the frame with the most objects of each condition group (image, target,
    prediction) and the first batch holding a night and a glare frame, or else the first batch (for the gate
    figure)."""

    objects: pd.DataFrame
    gates: pd.DataFrame
    showcase: dict = field(default_factory=dict)
    gate_batch: dict | None = None
    task: Any = None


def evaluate(cfg: DictConfig, model: torch.nn.Module, datamodule: Any) -> Evaluation:
    """One trained model of job config ``cfg`` on the test split of ``datamodule`` (:class:`Evaluation`)."""
    model = model.eval()
    task = instantiate(cfg.task, model=model)
    ops = [
        op for op in (model.fusion_modules() if hasattr(model, "fusion_modules") else []) if hasattr(op, "last_gates")
    ]
    names = list(model.modalities)
    objects: list[dict[str, Any]] = []
    gates: list[dict[str, Any]] = []
    showcase: dict[str, Any] = {}
    image, gate_batch = 0, None
    with torch.no_grad():
        for batch in datamodule.test_dataloader():
            inputs = {k: v for k, v in batch.items() if torch.is_tensor(v) and k in names}
            outputs = model(inputs)
            size = task.image_size(batch)
            preds = task.predict(outputs, size)
            conditions = batch.get("condition") or ["?"] * len(preds)
            if gate_batch is None or (
                not {"night", "glare"} <= set(gate_batch["condition"] or []) and {"night", "glare"} <= set(conditions)
            ):
                gate_batch = batch  # the first holding a night and a glare frame, else the first
            for b, (pred, target) in enumerate(zip(preds, task.targets(batch))):
                group = condition_group(conditions[b]) or conditions[b]
                is_counted, found = found_objects(pred, target, size[0])
                objects += [
                    {"image": image + b, "object": i, "group": group, "found": bool(f)}
                    for i, (c, f) in enumerate(zip(is_counted, found))
                    if c
                ]
                for level, op in enumerate(ops):
                    for m, gate in zip(names, op.last_gates or []):
                        gates.append(
                            {
                                "image": image + b,
                                "group": group,
                                "point": level,
                                "modality": m,
                                "gate": float(gate[b].float().mean()),
                            }
                        )
                if group not in showcase or len(target["labels"]) > len(showcase[group][1]["labels"]):
                    shown = batch["rgb"][b] if "rgb" in batch else inputs[names[0]][b]
                    showcase[group] = (shown, target, pred)  # the frame with the most objects of its group
            image += len(preds)
    return Evaluation(pd.DataFrame(objects), pd.DataFrame(gates), showcase, gate_batch, task)


#: The conditions the data checks compare (each applied to the whole test split in turn).
CHECKED_CONDITIONS = ("clear", "night", "glare")


def ap_per_condition(cfg: DictConfig, model: torch.nn.Module) -> dict[str, float]:
    """Mask AP (%) of a trained model on the whole test split under each of :data:`CHECKED_CONDITIONS` in turn."""
    model = model.eval()
    task = instantiate(cfg.task, model=model)
    names = list(model.modalities)
    out = {}
    for condition in CHECKED_CONDITIONS:
        datamodule = instantiate(cfg.data, conditions=[condition])
        datamodule.setup("test")
        metric = MaskAP()
        with torch.no_grad():
            for batch in datamodule.test_dataloader():
                outputs = model({k: v for k, v in batch.items() if torch.is_tensor(v) and k in names})
                metric.update(task.predict(outputs, task.image_size(batch)), task.targets(batch))
        out[condition] = float(metric.compute()["map"]) * 100
    return out
