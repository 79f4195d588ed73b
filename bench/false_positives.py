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

``--surfaces`` (generated data only) adds what the background false positives lie on: each frame's scene is cast
again from its seed (:func:`ablate.data.generate.render_frame`'s steps), every pixel named by its surface (sky, road,
road in shadow, lane marking, border, facade, furniture, object), and each background false positive's mask split
over them (its shares summing to 1), beside the share of the frames' pixels each surface covers; then the background
false positives per test condition.
"""

from __future__ import annotations

import argparse
import statistics
from collections import Counter

import numpy as np
import torch
from hydra.utils import instantiate

from ablate.analysis.diagnose import checkpoint
from ablate.config import compose
from ablate.data.difficulty import counted
from ablate.jobs.experts import load_model
from ablate.tasks.yolact.diagnose import mask_overlaps

KINDS = ("ignored", "duplicate", "wrong class", "localisation", "background")
SURFACES = ("sky", "road", "road in shadow", "lane marking", "border", "facade", "furniture", "object")


def surface_map(seed: int, index: int, height: int, width: int, furniture: bool) -> np.ndarray:
    """(H, W) index into :data:`SURFACES` of what each pixel of generated frame ``index`` shows (its scene cast again
    as :func:`ablate.data.generate.render_frame` casts it)."""
    from ablate.data.generate import camera_cast
    from ablate.data.raycast import BORDER, BOX, ROAD, SKY
    from ablate.data.shade import ground_shadow, lane_marking
    from ablate.data.synth import FACADE, FURNITURE

    _, scene, _, _, hit = camera_cast(seed, index, height, width, furniture)
    kind, box, point = hit["kind"], hit["box"], hit["point"]
    part = np.where(kind == BOX, scene["part"][np.maximum(box, 0)], -1)
    owner = np.where(kind == BOX, scene["owner"][np.maximum(box, 0)], -1)
    shadow, contact = ground_shadow(scene, point, (kind == ROAD) | (kind == BORDER))
    out = np.full(len(kind), SURFACES.index("road"))
    out[kind == SKY] = SURFACES.index("sky")
    out[(kind == ROAD) & (shadow | contact)] = SURFACES.index("road in shadow")
    out[lane_marking(scene, hit)] = SURFACES.index("lane marking")
    out[kind == BORDER] = SURFACES.index("border")
    out[(kind == BOX) & (part == FACADE)] = SURFACES.index("facade")
    out[(kind == BOX) & (part == FURNITURE)] = SURFACES.index("furniture")
    out[(kind == BOX) & (owner >= 0)] = SURFACES.index("object")
    return out.reshape(height, width)


def shares(mask: torch.Tensor, surface: np.ndarray) -> np.ndarray:
    """The share of ``mask``'s pixels on each of :data:`SURFACES` (summing to 1; zeros for an empty mask)."""
    counts = np.bincount(surface[mask.numpy()], minlength=len(SURFACES)).astype(float)
    return counts / max(counts.sum(), 1.0)


def ledger(pred: dict, target: dict, height: int, found: list[int] | None = None) -> list[tuple[float, str]]:
    """(score, kind) of every detection of one image; kind is "tp", one of :data:`KINDS`; plus ("miss") per counted
    ground truth left unmatched, with score nan. ``found``, where given, gets the index in ``pred`` of each
    detection of the ledger, in its order."""
    gt, labels = target["masks"].bool(), target["labels"]
    tall = target["boxes"][:, 3] - target["boxes"][:, 1]
    is_counted = counted(tall.double(), height) if len(gt) else torch.zeros(0, dtype=torch.bool)
    masks, scores, classes = pred["masks"].bool(), pred["scores"], pred["labels"]
    order = torch.argsort(scores, descending=True)
    iou, inside = mask_overlaps(masks, gt) if len(gt) and len(masks) else (None, None)
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
        if found is not None:
            found.append(d)
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


class Surfaces:
    """Background false positives split over :data:`SURFACES`, the frames' pixels over them, and the background
    false positives per test condition."""

    def __init__(self, synth: dict) -> None:
        self.synth = synth
        self.on = np.zeros(len(SURFACES))
        self.pixels = np.zeros(len(SURFACES))
        self.by_condition: Counter[str] = Counter()
        self.frames: Counter[str] = Counter()

    def add(
        self,
        frame: str,
        condition: str,
        size: tuple[int, int],
        pred: dict,
        rows: list[tuple[float, str]],
        found: list[int],
    ) -> None:
        surface = surface_map(int(self.synth["seed"]), int(frame), *size, bool(self.synth.get("furniture")))
        self.pixels += np.bincount(surface.ravel(), minlength=len(SURFACES))
        self.frames[condition] += 1
        for (_, kind), d in zip(rows, found):
            if kind == "background":
                self.on += shares(pred["masks"][d].bool(), surface)
                self.by_condition[condition] += 1

    def lines(self) -> list[str]:
        on, px = self.on / max(self.on.sum(), 1e-9), self.pixels / max(self.pixels.sum(), 1e-9)
        per = ", ".join(f"{c} {n / self.frames[c]:.1f}" for c, n in sorted(self.by_condition.items()))
        return [
            "  background FPs on: "
            + ", ".join(f"{n} {100 * a:.1f}% (pixels {100 * b:.1f}%)" for n, a, b in zip(SURFACES, on, px)),
            f"  background FPs per test frame, by condition: {per}",
        ]


def run(
    overrides: list[str], row: str, seed: int, surfaces: bool = False
) -> tuple[list[tuple[float, str]], Surfaces | None]:
    cfg = compose([*overrides, f"row={row}", f"seed={seed}"])
    model = load_model(cfg, checkpoint(cfg, str(cfg.table.name), row)).eval()
    task = instantiate(cfg.task, model=model)
    datamodule = instantiate(cfg.data)
    datamodule.prepare_data()
    datamodule.setup("test")
    names = list(model.modalities)
    out: list[tuple[float, str]] = []
    tally = None
    if surfaces:
        import json
        from pathlib import Path

        synth = json.loads((Path(datamodule.datasets["test"].split_dir) / "synth.json").read_text())
        tally = Surfaces(synth)
    with torch.no_grad():
        for batch in datamodule.test_dataloader():
            size = task.image_size(batch)
            preds = task.predict(model({k: v for k, v in batch.items() if k in names}), size)
            for i, (pred, target) in enumerate(zip(preds, task.targets(batch))):
                found: list[int] = []
                rows = ledger(pred, target, size[0], found)
                out += rows
                if tally is not None:
                    tally.add(batch["frame"][i], batch["condition"][i], size, pred, rows, found)
    return out, tally


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("overrides", nargs="*")
    parser.add_argument("--rows", nargs="+", default=["smoe_rgb", "smoe_ddm"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0])
    parser.add_argument("--surfaces", action="store_true", help="what the background FPs lie on (generated data)")
    args = parser.parse_args()
    print("| row | seed | TP | misses | " + " | ".join(KINDS) + " | FP above the median TP: " + ", ".join(KINDS) + " |")
    print("|" + "---|" * (4 + 2 * len(KINDS)))
    for row in args.rows:
        for seed in args.seeds:
            rows, tally = run(args.overrides, row, seed, args.surfaces)
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
            for line in tally.lines() if tally is not None else []:
                print(line)


if __name__ == "__main__":
    main()
