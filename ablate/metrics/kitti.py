"""KITTI 2D object-detection AP (the KITTI object devkit's ``evaluate_object.cpp`` / ``eval.cpp``) as a
torchmetrics ``Metric``.

DGFN (Kim et al., seed 002) §IV-A evaluates 2D detection of car, pedestrian and cyclist "with three difficulty
levels (easy, moderate, hard) as proposed in the KITTI Benchmark", and §IV-B by "the same evaluation method" as
MV3D and 3DOP (Table II).

Conformance: by default this equals the 2017 KITTI object devkit (``devkit_object``, ``cpp/evaluate_object.cpp``,
released with the 3D and bird's-eye-view benchmarks) bug for bug in 2D; runs record it as evaluator
``kitti_object_devkit_2017`` (:data:`DEVKITS`, :data:`ablate.metrics.EVALUATORS`). ``devkit="2d_2012"`` follows the
older 2D-only devkit (2012, ``cpp/evaluate_object.cpp``), which differs in one rule only: ``cleanData`` there
ignores a ground truth *shorter* than the level's minimum height, where the 2017 one ignores it when *not taller*
(``height <= MIN_HEIGHT``), so a GT exactly 40.00 px tall is not easy, one exactly 25.00 px tall counts at no level.
Published numbers: KITTI's server and devkit since 2017 (and so the AP40 ranking since 2019) use the 2017 rule;
numbers computed before 2017, such as 3DOP's (2015) and, by their dates, MV3D's (2016) that DGFN Table II quotes,
the 2012 one. Only boxes exactly on a threshold tell them apart. Heights are ``y2 - y1`` in float64, as the devkit
takes them from labels read as double, so a label's 25.00 px is not always 25.0 (148.45 - 123.45 is
24.999999999999986: too short under both rules); boxes passed as float32 (``boxes2d`` of ``ablate.data.dataset``)
are rounded first, and about 1 in 6 labels 25.00 px tall then falls on the other side of the threshold. Tests
(tests/metrics/test_kitti.py): cases by hand, boxes at 24.99, 25.00, 25.01, 39.99, 40.00 and 40.01 px under both
rules, and random frames against a loop-by-loop transliteration of ``cleanData``, ``computeStatistics``,
``getThresholds`` and ``eval_class`` with either rule.

This is the devkit's evaluation, per class and level:

* A ground truth counts at a level when its box height > 40 / 25 / 25 px (``devkit="2d_2012"``: >=), occlusion
  <= 0 / 1 / 2 and truncation <= 0.15 / 0.30 / 0.50 (easy / moderate / hard); pixel heights scale with
  ``image_height / 375``. The rules are nested, so a GT counts at every level from its lowest up. The height rule
  is applied to the GT boxes at evaluation, so a ``difficulty`` input (computed with >=, as
  ``Object3D.difficulty_at``) follows the chosen devkit too.
* A detection matches a GT of its class at IoU > 0.7 (Car) or 0.5 (Pedestrian, Cyclist). A match to an ignored
  GT (the neighbouring class, Van for Car and Person_sitting for Pedestrian, or a GT not counted at the level) is
  neither TP nor FP; a counted GT left unmatched is a FN.
* A detection shorter than the level's minimum height is ignored (both devkits: ``height < MIN_HEIGHT``): never a
  FP, though it may absorb a GT as above.
  An unmatched detection with more than its class's overlap of its own area inside a DontCare box is not a FP.
* Thresholds (``getThresholds``): from the sorted TP scores, up to 41 scores whose recalls are closest to
  0, 1/40, ..., 1; precision at each is interpolated as the maximum over itself and the later ones.
  ``ap40`` averages points 1..40 (KITTI since 2019), ``ap11`` points 0, 4, ..., 40 (recall 0, 0.1, ..., 1; KITTI
  before 2019). Values in percent, as the devkit prints them.

Readings where the devkit or the papers leave room:

* DGFN does not say which AP it reports; being of 2018 and compared with MV3D / 3DOP, its tables are ``ap11``.
* ``ap11`` samples the same 41-point curve every 4th point, as the pre-2019 devkit's ``printAp`` did (its
  ``N_SAMPLE_PTS`` was already 41); it is not a separate ``getThresholds`` run with 11 samples.
* The curve assumes many counted GTs (>= 41 for a perfect detector to reach 100): the k-th threshold fills point k
  whatever its recall. With one GT found, ``ap11`` = 100/11 and ``ap40`` = 0. Kept: published numbers use it.
* As in ``cleanData``, a too-short detection is ignored for every class, not only its own.
* Assignment follows ``computeStatistics``: GTs in input order; the threshold pass takes the highest-scoring free
  candidate, the precision pass the highest-IoU one that is not too short (else the first too-short one); first on
  ties. A precision of 0/0 (no TP or FP at a threshold) is taken as 0.
* Scaled heights are compared as floats (the devkit truncates detection heights to int: the same at scale 1).
* A class with no counted GT at a level gives -1 (the devkit prints 0); means over classes leave it out.

States are flat per-image tensors concatenated with ``dist_reduce_fx="cat"``, so the metric works under DDP.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor
from torchmetrics import Metric
from torchmetrics.utilities import dim_zero_cat

from ablate.data.dataset import CLASSES
from ablate.data.difficulty import REFERENCE_HEIGHT, counted
from ablate.metrics.accumulate import N_SAMPLE_PTS, kitti_thresholds

LEVELS = ("easy", "moderate", "hard")
MIN_HEIGHT, MAX_OCCLUSION, MAX_TRUNCATION = (40.0, 25.0, 25.0), (0, 1, 2), (0.15, 0.30, 0.50)
MIN_OVERLAP = {"Car": 0.7, "Pedestrian": 0.5, "Cyclist": 0.5}
NEIGHBOURS = {"Car": "Van", "Pedestrian": "Person_sitting"}
#: Label ids of predictions and targets: the dataset's classes first, then the GT-only KITTI types.
LABEL_NAMES = (*CLASSES, "Van", "Person_sitting", "DontCare")
#: The devkit versions KittiAP follows (``cleanData``'s ground-truth height rule) and the ``evaluator`` tag of each.
DEVKITS = {"2017": "kitti_object_devkit_2017", "2d_2012": "kitti_object_devkit_2d_2012"}
_STATES = (
    "pred_counts",
    "pred_boxes",
    "pred_scores",
    "pred_labels",
    "pred_in_dc",
    "gt_counts",
    "gt_boxes",
    "gt_labels",
    "gt_level",
)


def overlap(a: np.ndarray, b: np.ndarray, union: bool = True) -> np.ndarray:
    """eval.cpp ``boxoverlap`` of xyxy boxes (A,4) x (B,4): intersection over union, or over the area of ``a``."""
    w = np.minimum(a[:, None, 2], b[None, :, 2]) - np.maximum(a[:, None, 0], b[None, :, 0])
    h = np.minimum(a[:, None, 3], b[None, :, 3]) - np.maximum(a[:, None, 1], b[None, :, 1])
    inter = np.where((w > 0) & (h > 0), w * h, 0.0)
    area = lambda x: (x[:, 2] - x[:, 0]) * (x[:, 3] - x[:, 1])  # noqa: E731
    denom = area(a)[:, None] + area(b)[None] - inter if union else np.broadcast_to(area(a)[:, None], inter.shape)
    return np.divide(inter, denom, out=np.zeros_like(inter), where=inter > 0)


thresholds = kitti_thresholds  # eval.cpp ``getThresholds``, where the tables re-accumulate AP too


def assign(ok: np.ndarray, key: np.ndarray, active: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Greedy ``computeStatistics`` assignment at T score thresholds at once. ``ok`` (G,D): candidate pairs;
    ``key`` (G,D): preference (highest first, first on ties); ``active`` (T,D): detections above the threshold.
    Returns the detection of each GT (T,G), -1 for none, and the detections left free (T,D)."""
    free, rows = active.copy(), np.arange(active.shape[0])
    match = np.full((active.shape[0], ok.shape[0]), -1)
    for g in range(ok.shape[0] if ok.shape[1] else 0):
        cand = free & ok[g]
        best = np.where(cand, key[g], -np.inf).argmax(1)
        found = cand[rows, best]
        match[found, g] = best[found]
        free[rows[found], best[found]] = False
    return match, free


class KittiAP(Metric):
    """KITTI 2D detection AP per class and difficulty, 11- and 40-point (see the module docstring).

    Args:
        classes: evaluated classes, each in ``label_names`` and in ``MIN_OVERLAP`` or ``min_overlap``.
        label_names: KITTI type of each label id; GT-only types (Van, Person_sitting, DontCare) follow the
            dataset's classes, so ``boxes2d`` labels are valid as they are.
        image_height: height of the evaluated images; the pixel thresholds scale with it / 375.
        min_overlap: per-class IoU overrides of KITTI's (Car 0.7, Pedestrian 0.5, Cyclist 0.5).
        devkit: ``"2017"`` (default): a GT counts at a level when taller than its minimum height, as the 2017
            object devkit's ``cleanData``; ``"2d_2012"``: when at least that tall, as the older 2D devkit (numbers
            published before 2017). See the module docstring.
    """

    full_state_update = False
    is_differentiable = False
    higher_is_better = True

    def __init__(
        self,
        classes: Sequence[str] = CLASSES,
        label_names: Sequence[str] = LABEL_NAMES,
        image_height: float = REFERENCE_HEIGHT,
        min_overlap: dict[str, float] | None = None,
        devkit: str = "2017",
        **kwargs: Any,
    ) -> None:
        super().__init__(**kwargs)
        if devkit not in DEVKITS:
            raise ValueError(f"KittiAP: devkit must be one of {sorted(DEVKITS)}, got {devkit!r}")
        self.devkit = devkit
        self.classes, self.label_names = tuple(classes), tuple(label_names)
        self.min_overlap = {**MIN_OVERLAP, **(min_overlap or {})}
        for c in self.classes:
            if c not in self.label_names or c not in self.min_overlap:
                raise ValueError(
                    f"KittiAP: class {c!r} must be in label_names {self.label_names} and have a "
                    f"min_overlap (known: {sorted(self.min_overlap)})"
                )
        if image_height <= 0:
            raise ValueError(f"KittiAP: image_height must be > 0, got {image_height}")
        self.image_height = float(image_height)
        for name in _STATES:
            self.add_state(name, default=[], dist_reduce_fx="cat")

    @property
    def evaluator(self) -> str:
        """The evaluator this metric follows, as a run records it (``ablate.tasks.base.FusionTask.evaluator``)."""
        return DEVKITS[self.devkit]

    def gt_tall_enough(self, heights: np.ndarray, level: int) -> np.ndarray:
        """Which GT box heights (px) are tall enough to count at ``level`` under ``self.devkit``'s ``cleanData``."""
        minimum = MIN_HEIGHT[level] * self.image_height / REFERENCE_HEIGHT
        return heights > minimum if self.devkit == "2017" else heights >= minimum

    def _id(self, name: str) -> int:
        return self.label_names.index(name) if name in self.label_names else -1

    def update(self, preds: list[dict[str, Tensor]], targets: list[dict[str, Tensor]]) -> None:
        """Add images. ``preds[i]``: boxes (N,4) xyxy px, scores (N,), labels (N,). ``targets[i]``: boxes (M,4),
        labels (M,) (DontCare regions, Vans and Person_sittings among them, by their ``label_names`` ids) and
        either difficulty (M,): 0 easy, 1 moderate, 2 hard, -1 none, as ``Object3D.difficulty_at(image_height /
        375)`` and ``boxes2d`` give it, or occluded (M,) 0-3 and truncated (M,) 0-1 of the label file."""
        if len(preds) != len(targets):
            raise ValueError(f"KittiAP.update: {len(preds)} predictions for {len(targets)} targets")
        for pred, target in zip(preds, targets):
            for key, d, where in (
                ("boxes", pred, "preds"),
                ("scores", pred, "preds"),
                ("labels", pred, "preds"),
                ("boxes", target, "targets"),
                ("labels", target, "targets"),
            ):
                if key not in d:
                    raise KeyError(f"KittiAP.update: {where} dict lacks '{key}' (has {sorted(d)})")
            if "difficulty" not in target and not {"occluded", "truncated"} <= set(target):
                raise KeyError(
                    f"KittiAP.update: targets need 'difficulty' or 'occluded' and 'truncated' (has {sorted(target)})"
                )
            self._add_image(pred, target)

    def _add_image(self, pred: dict[str, Tensor], target: dict[str, Tensor]) -> None:
        arr = lambda x, dt=np.float64: torch.as_tensor(x).detach().cpu().numpy().astype(dt)  # noqa: E731
        boxes, scores, labels = arr(pred["boxes"]).reshape(-1, 4), arr(pred["scores"]), arr(pred["labels"], np.int64)
        gt_boxes, gt_labels = arr(target["boxes"]).reshape(-1, 4), arr(target["labels"], np.int64)
        for lab, where in ((labels, "preds"), (gt_labels, "targets")):
            bad = lab[(lab < 0) | (lab >= len(self.label_names))]
            if bad.size:
                raise ValueError(f"KittiAP.update: {where} label {int(bad[0])} is not an index of {self.label_names}")
        if "difficulty" in target:
            level = arr(target["difficulty"], np.int64)
        else:
            height, occ, trunc = gt_boxes[:, 3] - gt_boxes[:, 1], arr(target["occluded"]), arr(target["truncated"])
            ok = np.stack(
                [
                    counted(height, self.image_height, MIN_HEIGHT[k])
                    & (occ <= MAX_OCCLUSION[k])
                    & (trunc <= MAX_TRUNCATION[k])
                    for k in range(3)
                ],
                1,
            )
            level = np.where(ok.any(1), ok.argmax(1), -1)
        dc = gt_labels == self._id("DontCare")
        thr = np.array([self.min_overlap.get(self.label_names[k], np.inf) for k in labels])
        in_dc = (overlap(boxes, gt_boxes[dc], union=False) > thr[:, None]).any(1)
        for name, value in (
            ("pred_counts", [len(boxes)]),
            ("pred_boxes", boxes.ravel()),
            ("pred_scores", scores),
            ("pred_labels", labels),
            ("pred_in_dc", in_dc.astype(np.int64)),
            ("gt_counts", [int((~dc).sum())]),
            ("gt_boxes", gt_boxes[~dc].ravel()),
            ("gt_labels", gt_labels[~dc]),
            ("gt_level", level[~dc]),
        ):
            getattr(self, name).append(torch.as_tensor(np.asarray(value)).to(self.device))

    def _images(self) -> list[tuple[np.ndarray, ...]]:
        """Per image: det boxes, scores, labels, in_dc; GT boxes, labels, levels; and their IoU (M,N)."""
        s = {n: dim_zero_cat(getattr(self, n)).cpu().numpy() for n in _STATES}
        s["pred_boxes"], s["gt_boxes"] = s["pred_boxes"].reshape(-1, 4), s["gt_boxes"].reshape(-1, 4)
        s["pred_in_dc"] = s["pred_in_dc"].astype(bool)

        def per_image(keys: tuple[str, ...], counts: str) -> Iterator[tuple[np.ndarray, ...]]:
            cuts = np.cumsum(s[counts].astype(np.int64))[:-1]
            return zip(*(np.split(s[k], cuts) for k in keys))

        dets = per_image(("pred_boxes", "pred_scores", "pred_labels", "pred_in_dc"), "pred_counts")
        gts = per_image(("gt_boxes", "gt_labels", "gt_level"), "gt_counts")
        return [(*d, *g, overlap(g[0], d[0])) for d, g in zip(dets, gts)]

    def _prepared(self, images: list, cls: str, level: int) -> list[tuple[Any, ...]]:
        """Per image, what ``eval_class`` reads of ``cls`` at ``level``: the candidate pairs, the precision pass's
        preference, which GTs count, which detections are too short, the scores, which detections may be FPs, the
        threshold pass's TP scores and the counted GTs."""
        cid, nid, thr = self._id(cls), self._id(NEIGHBOURS.get(cls, "")), self.min_overlap[cls]
        prepared = []
        for boxes, scores, labels, in_dc, gt_boxes, gt_labels, gt_level, iou in images:
            small = ~counted(boxes[:, 3] - boxes[:, 1], self.image_height, MIN_HEIGHT[level])
            det, gt = (labels == cid) | small, (gt_labels == cid) | (gt_labels == nid)
            tall = self.gt_tall_enough(gt_boxes[gt, 3] - gt_boxes[gt, 1], level)
            counts = (gt_labels[gt] == cid) & (gt_level[gt] >= 0) & (gt_level[gt] <= level) & tall
            iou_, small_, scores_ = iou[gt][:, det], small[det], scores[det]
            fp_able = ~small_ & (labels[det] == cid) & ~in_dc[det]
            ok, to_small = iou_ > thr, np.append(small_, False)  # to_small[match]: matched a too-short det
            match, _ = assign(ok, np.broadcast_to(scores_, ok.shape), np.ones((1, len(scores_)), bool))
            tp = (match[0] >= 0) & counts & ~to_small[match[0]]
            key = np.where(small_, -1.0, iou_)
            prepared.append((ok, key, counts, to_small, scores_, fp_able, scores_[match[0][tp]], int(counts.sum())))
        return prepared

    @staticmethod
    def _counts(image: tuple[Any, ...], t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The precision pass's TP and FP of one image at the score thresholds ``t``."""
        ok, key, counts, to_small, scores_, fp_able = image[:6]
        match, free = assign(ok, key, scores_[None] >= t[:, None])
        return ((match >= 0) & counts & ~to_small[match]).sum(1), (free & fp_able).sum(1)

    def _ap(self, images: list, cls: str, level: int) -> tuple[float, float]:
        """(ap11, ap40) in percent of ``cls`` at ``level``, -1 with no counted GT (eval.cpp ``eval_class``)."""
        prepared = self._prepared(images, cls, level)
        n_gt = int(sum(p[7] for p in prepared))
        if n_gt == 0:
            return -1.0, -1.0
        t = thresholds(np.concatenate([p[6] for p in prepared]), n_gt)
        tp, fp = np.zeros(len(t)), np.zeros(len(t))
        for image in prepared:
            a, b = self._counts(image, t)
            tp += a
            fp += b
        precision = np.zeros(N_SAMPLE_PTS)
        precision[: len(t)] = np.divide(tp, tp + fp, out=np.zeros_like(tp), where=tp + fp > 0)
        precision = np.maximum.accumulate(precision[::-1])[::-1]
        return 100 * precision[::4].sum() / 11, 100 * precision[1:].sum() / 40

    def frame_rows(self, cls: str, level: int) -> list[dict]:
        """What re-accumulating ``cls``'s AP at ``level`` over any set of the images needs, per image in update
        order (:mod:`ablate.metrics.accumulate`: kind ``gt``, ``tp`` and ``cut`` rows; ``index`` the image)."""
        n = self.pred_counts
        if not (n.numel() if isinstance(n, Tensor) else len(n)):
            return []
        k = LEVELS.index(level) if isinstance(level, str) else int(level)
        rows: list[dict] = []
        for index, image in enumerate(self._prepared(self._images(), cls, k)):
            base = {"index": index, "cls": cls, "level": k}
            rows.append(base | {"kind": "gt", "score": np.nan, "a": image[7], "b": 0})
            rows += [base | {"kind": "tp", "score": float(s), "a": 0, "b": 0} for s in image[6]]
            cuts = np.unique(image[4])[::-1]
            if len(cuts):
                tp, fp = self._counts(image, cuts)
                d_tp, d_fp = np.diff(tp, prepend=0), np.diff(fp, prepend=0)
                rows += [
                    base | {"kind": "cut", "score": float(u), "a": int(a), "b": int(b)}
                    for u, a, b in zip(cuts, d_tp, d_fp)
                    if a or b
                ]
        return rows

    def compute(self) -> dict[str, Tensor]:
        """``{class}/{level}/ap11`` and ``/ap40`` in percent (-1: no counted GT); ``{level}/ap11`` and ``/ap40``:
        mean over classes; ``ap11`` and ``ap40``: that mean at moderate, KITTI's ranking level."""
        n = self.pred_counts
        images = self._images() if (n.numel() if isinstance(n, Tensor) else len(n)) else None
        out: dict[str, float] = {}
        for k, level in enumerate(LEVELS):
            for cls in self.classes:
                ap = self._ap(images, cls, k) if images else (-1.0, -1.0)
                out[f"{cls}/{level}/ap11"], out[f"{cls}/{level}/ap40"] = ap
            for kind in ("ap11", "ap40"):
                valid = [out[f"{c}/{level}/{kind}"] for c in self.classes if out[f"{c}/{level}/{kind}"] >= 0]
                out[f"{level}/{kind}"] = float(np.mean(valid)) if valid else -1.0
        out["ap11"], out["ap40"] = out["moderate/ap11"], out["moderate/ap40"]
        return {k: torch.tensor(v, dtype=torch.float32) for k, v in out.items()}
