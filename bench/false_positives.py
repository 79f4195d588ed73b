"""What an instance expert's detections hit, on the test split: the ledger behind a mask AP (SMoE's experts,
docs/recipes.md#the-modalities-balance).

    PYTHONPATH=. python bench/false_positives.py experiment=smoe_table1_followup [key=value ...]
        [--rows smoe_rgb smoe_ddm] [--seeds 0 1]

Run where the experts' checkpoints are (``checkpoints/``, as ``python -m ablate.diagnose`` needs them). Per image,
the detections in falling score are matched greedily to the counted ground truths of their class at mask IoU >= 0.5
(as COCOeval at IoU 0.5); each other detection is, in this order:

- **ignored**: at least half of it inside a ground truth too small to count or a DontCare region (the AP ignores it);
- **duplicate**: IoU >= 0.5 with a ground truth of its class already matched;
- **wrong class**: IoU >= 0.5 with a ground truth of the other class;
- **localisation**: IoU 0.1-0.5 with some ground truth (a poor mask of a real object);
- **background**: IoU < 0.1 with every ground truth (a road, facade, shadow or furniture taken for an object).

Printed per row and seed: true positives, misses, and each kind of false positive, counted over all detections and
over those scoring above the median true positive (the ones that cost AP50 most).
"""

from __future__ import annotations

import argparse
import statistics
from collections import Counter

import torch
from hydra.utils import instantiate

from ablate.analysis.diagnose import checkpoint
from ablate.config import compose
from ablate.data.difficulty import counted
from ablate.jobs.experts import load_model

KINDS = ("ignored", "duplicate", "wrong class", "localisation", "background")


def ious(a: torch.Tensor, b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(IoU, intersection over a's area) of every mask of ``a`` (N,H,W) with every mask of ``b`` (M,H,W)."""
    fa, fb = a.flatten(1).float(), b.flatten(1).float()
    inter = fa @ fb.T
    area = fa.sum(1, keepdim=True)
    return inter / (area + fb.sum(1) - inter).clamp(min=1), inter / area.clamp(min=1)


def ledger(pred: dict, target: dict, height: int) -> list[tuple[float, str]]:
    """(score, kind) of every detection of one image; kind is "tp", one of :data:`KINDS`; plus ("miss") per counted
    ground truth left unmatched, with score nan."""
    gt, labels = target["masks"].bool(), target["labels"]
    tall = target["boxes"][:, 3] - target["boxes"][:, 1]
    is_counted = counted(tall.double(), height) if len(gt) else torch.zeros(0, dtype=torch.bool)
    masks, scores, classes = pred["masks"].bool(), pred["scores"], pred["labels"]
    order = torch.argsort(scores, descending=True)
    iou, inside = ious(masks, gt) if len(gt) and len(masks) else (None, None)
    ignore = target.get("ignore")
    in_ignore = (  # at least half of each detection inside the DontCare region
        (masks & ignore.bool()).flatten(1).sum(1) >= 0.5 * masks.flatten(1).sum(1)
        if ignore is not None and len(masks)
        else torch.zeros(len(masks), dtype=torch.bool)
    )
    matched = torch.zeros(len(gt), dtype=torch.bool)
    out: list[tuple[float, str]] = []
    for d in order.tolist():
        score = float(scores[d])
        if iou is None:
            out.append((score, "ignored" if in_ignore[d] else "background"))
            continue
        same = labels == classes[d]
        free = same & is_counted & ~matched & (iou[d] >= 0.5)
        if free.any():
            k = int(torch.where(free, iou[d], torch.full_like(iou[d], -1)).argmax())
            matched[k] = True
            out.append((score, "tp"))
        elif (~is_counted & (inside[d] >= 0.5)).any() or in_ignore[d]:
            out.append((score, "ignored"))
        elif (same & matched & (iou[d] >= 0.5)).any():
            out.append((score, "duplicate"))
        elif (~same & (iou[d] >= 0.5)).any():
            out.append((score, "wrong class"))
        elif (iou[d] >= 0.1).any():
            out.append((score, "localisation"))
        else:
            out.append((score, "background"))
    out += [(float("nan"), "miss")] * int((is_counted & ~matched).sum())
    return out


def run(overrides: list[str], row: str, seed: int) -> list[tuple[float, str]]:
    cfg = compose([*overrides, f"row={row}", f"seed={seed}"])
    model = load_model(cfg, checkpoint(cfg, str(cfg.table.name), row)).eval()
    task = instantiate(cfg.task, model=model)
    datamodule = instantiate(cfg.data)
    datamodule.prepare_data()
    datamodule.setup("test")
    names = list(model.modalities)
    out: list[tuple[float, str]] = []
    with torch.no_grad():
        for batch in datamodule.test_dataloader():
            size = task.image_size(batch)
            preds = task.predict(model({k: v for k, v in batch.items() if k in names}), size)
            for pred, target in zip(preds, task.targets(batch)):
                out += ledger(pred, target, size[0])
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("overrides", nargs="*")
    parser.add_argument("--rows", nargs="+", default=["smoe_rgb", "smoe_ddm"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0])
    args = parser.parse_args()
    print("| row | seed | TP | misses | " + " | ".join(KINDS) + " | FP above the median TP: " + ", ".join(KINDS) + " |")
    print("|" + "---|" * (4 + 2 * len(KINDS)))
    for row in args.rows:
        for seed in args.seeds:
            rows = run(args.overrides, row, seed)
            tp = [s for s, k in rows if k == "tp"]
            median = statistics.median(tp) if tp else float("inf")
            every = Counter(k for _, k in rows)
            high = Counter(k for s, k in rows if k in KINDS and s > median)
            print(
                f"| {row} | {seed} | {every['tp']} | {every['miss']} | "
                + " | ".join(str(every[k]) for k in KINDS)
                + " | "
                + " | ".join(str(high[k]) for k in KINDS)
                + " |"
            )


if __name__ == "__main__":
    main()
