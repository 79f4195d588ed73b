"""KITTI road benchmark measures in the metric bird's-eye view (MaxF, AP, PRE, REC) as a torchmetrics ``Metric``.

BiFNet (seed 004) §V-A evaluates with "the evaluation metrics in literature [12]" (Fritsch, Kuehnl, Geiger, "A New
Performance Measure and Evaluation Benchmark for Road Detection Algorithms", ITSC 2013): PRE = TP / (TP + FP),
REC = TP / (TP + FN), MaxF = max over thresholds of the F-measure (beta = 1) and AP, "all calculated in BEV space".

Conformance: by default this follows the KITTI road devkit (``devkit_road``, 2013: ``python/transform2BEV.py``
with ``BirdsEyeView.py``, and ``python/helper.py``) bug for bug; runs record it as evaluator ``kitti_road_devkit``
(:data:`LOOKUPS`, :data:`ablate.metrics.EVALUATORS`). ``lookup="nearest"`` (``kitti_road_nearest_pixel``) keeps
this project's earlier reading of the warp, a deviation from the devkit. Tests (tests/metrics/test_road.py): the
measures against a loop-based reference of ``helper.py`` and counts by hand; the lookup's pixels on a calibration
projected by hand and, on the real frame um_000000, against a transliteration of ``BirdsEyeView``; the BEV cells a
single road pixel lands in.

* BEV grid. Cells of 0.05 m, lateral x in [-10, 10] m (column 0 left), forward z in [6, 46] m (row 0 far), so
  800 x 400 cells; a cell is represented by its centre on the road plane.
* Warp. The devkit does not put a flat plane at a fixed camera height: each frame's calib carries
  ``Tr_cam_to_road``, a rigid transform from the camera to a road frame fitted per frame, whose road plane is
  y = 0 (y down). The homography from road (x, z, 1) to image_2 is columns (0, 2, 3) of
  ``P2 . R0_rect . Tr_cam_to_road^-1`` (:func:`road_homography`). A calib without ``Tr_cam_to_road`` (the object
  benchmark's) may instead give ``camera_height``: a level plane that far below the rectified camera.
* Lookup, ``lookup="devkit"`` (default; ``BirdsEyeView.computeBEVLookUpTable`` and ``transformImage2BEV``): the
  cell centres are cast to float32, projected, and the projection (u, v) is read as 1-based: a cell is kept only
  where 1 <= u <= W and 1 <= v <= H, and takes the pixel (int(v) - 1, int(u) - 1), truncating. Read with 0-based
  pixel centres, that pixel's centre lies 1 to 2 px up and left of the projection (the nearest pixel's within
  0.5 px); the image's first row and column take projections in [1, 2), its last only one exactly on H or W.
* Lookup, ``lookup="nearest"`` (a deviation, kept as an option): the nearest pixel with 0-based pixel centres, as
  :func:`ablate.data.lidar.project_points`; a cell is kept where -0.5 <= u < W - 0.5 (and so for v).
* Either way prediction and ground truth are sampled at the same pixels, and cells left out are don't-care, as in
  the devkit, where their ground truth stays black (void). Both also leave out a cell centre behind the camera,
  which the devkit does not test for; no cell of its grid is behind the camera.
* Thresholds 0/255 .. 255/255; a cell is road at threshold t when ``p >= t`` (``evalExp``). TP / FP / FN are
  summed over all frames before PRE, REC and F are formed (``pxEval_maximizeFMeasure``), never averaged per frame.
* PRE = TP / (TP + FP + 1e-10), F = 2 PRE REC / (PRE + REC + 1e-10); MaxF is the first (lowest-threshold) maximum;
  PRE and REC are reported at that threshold. The devkit drops thresholds with TP = 0 first; that changes neither
  MaxF nor AP, since threshold 0 always has REC = 1 and TP > 0.
* AP is the devkit's 11-point (Pascal VOC) interpolation: the mean over r in ``np.arange(0, 1.1, 0.1)`` (float
  values included, 0.1 * 3 > 0.3) of the highest precision among thresholds with REC >= r.

States are per-threshold TP / FP / FN counts (shape [256], ``dist_reduce_fx="sum"``): memory does not grow with
the number of frames and the metric works under DDP.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor
from torchmetrics import Metric

from ablate.data import DataError
from ablate.data.kitti import Calibration

#: The devkit's BEV: cell size (m), lateral x range and forward z range (m) on the road plane.
BEV_RES, BEV_X, BEV_Z = 0.05, (-10.0, 10.0), (6.0, 46.0)
#: The devkit's 256 thresholds and 11 recall levels.
NUM_THRESHOLDS = 256
AP_RECALLS = np.arange(0.0, 1.1, 0.1)
#: The BEV lookups (:func:`bev_lookup`) and the ``evaluator`` tag of each: the devkit's, and the nearest pixel.
LOOKUPS = {"devkit": "kitti_road_devkit", "nearest": "kitti_road_nearest_pixel"}


def road_homography(calib: Calibration, camera_height: float | None = None) -> np.ndarray:
    """(3,3) homography from road-plane (x, z, 1) to homogeneous image_2 pixels.

    With ``camera_height`` None: the devkit's ``P2 . R0_rect . Tr_cam_to_road^-1`` restricted to road y = 0.
    Otherwise a level road plane ``camera_height`` metres below the rectified camera: (x, z) -> P2 (x, h, z, 1)."""
    if camera_height is not None:
        return calib.P2 @ np.array([[1.0, 0, 0], [0, 0, camera_height], [0, 1, 0], [0, 0, 1]])
    if calib.Tr_cam_to_road is None:
        raise DataError(
            f"{calib.path or 'calibration'}: no Tr_cam_to_road for the road plane; pass "
            f"camera_height to use a level plane below the camera instead"
        )
    rect, road = np.eye(4), np.eye(4)
    rect[:3, :3], road[:3] = calib.R0_rect, calib.Tr_cam_to_road
    return (calib.P2 @ rect @ np.linalg.inv(road))[:, [0, 2, 3]]


def bev_shape(
    res: float = BEV_RES, x_range: Sequence[float] = BEV_X, z_range: Sequence[float] = BEV_Z
) -> tuple[int, int]:
    """(rows, columns) of the BEV grid: rows run along z (far at row 0), columns along x (left at column 0)."""
    return int(round((z_range[1] - z_range[0]) / res)), int(round((x_range[1] - x_range[0]) / res))


def bev_centres(
    res: float = BEV_RES, x_range: Sequence[float] = BEV_X, z_range: Sequence[float] = BEV_Z
) -> tuple[np.ndarray, np.ndarray]:
    """(x, z) road-plane coordinates (m) of every cell centre, each (rows, columns)."""
    rows, cols = bev_shape(res, x_range, z_range)
    return np.meshgrid(x_range[0] + (np.arange(cols) + 0.5) * res, z_range[1] - (np.arange(rows) + 0.5) * res)


def check_lookup(lookup: str) -> str:
    """``lookup`` if it names a BEV lookup, else a ValueError naming the option and the accepted values."""
    if lookup not in LOOKUPS:
        raise ValueError(f"lookup must be one of {sorted(LOOKUPS)}, got {lookup!r}")
    return lookup


def bev_lookup(
    homography: np.ndarray,
    image_shape: tuple[int, int],
    res: float = BEV_RES,
    x_range: Sequence[float] = BEV_X,
    z_range: Sequence[float] = BEV_Z,
    lookup: str = "devkit",
) -> tuple[np.ndarray, np.ndarray]:
    """For each BEV cell (flattened row-major): the flat index of the image pixel it takes, and whether it is kept
    (its centre projects into the image, in front of the camera; index 0 where not).

    ``lookup="devkit"``: ``BirdsEyeView.computeBEVLookUpTable`` / ``transformImage2BEV`` of the road devkit: float32
    cell centres, projection read as 1-based, kept where 1 <= u <= W and 1 <= v <= H, pixel (int(v) - 1,
    int(u) - 1). ``lookup="nearest"``: the nearest pixel with 0-based pixel centres (a deviation from the devkit)."""
    x, z = bev_centres(res, x_range, z_range)
    if check_lookup(lookup) == "devkit":
        x, z = x.astype(np.float32).astype(np.float64), z.astype(np.float32).astype(np.float64)
    hom = np.stack([x.ravel(), z.ravel(), np.ones(x.size)]).T @ np.asarray(homography, np.float64).T
    with np.errstate(divide="ignore", invalid="ignore"):
        u, v = hom[:, 0] / hom[:, 2], hom[:, 1] / hom[:, 2]
    h, w = image_shape
    if lookup == "devkit":
        inside = (u >= 1) & (u <= w) & (v >= 1) & (v <= h)
        col, row = np.floor(np.where(inside, u, 1)) - 1, np.floor(np.where(inside, v, 1)) - 1
    else:
        col, row = np.rint(u), np.rint(v)
        inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    inside &= hom[:, 2] > 0
    return np.where(inside, row * w + col, 0).astype(np.int64), inside


def road_scores(tp: Tensor, fp: Tensor, fn: Tensor) -> dict[str, Tensor]:
    """KITTI road measures from per-threshold counts (each [256], threshold k/255): max_f, ap, pre, rec in percent
    and the threshold of MaxF in [0, 1]. All NaN when no road cell was counted."""
    tp, fp, fn = (torch.as_tensor(c).double().cpu() for c in (tp, fp, fn))
    positives = tp[0] + fn[0]
    if positives <= 0:
        return {k: torch.tensor(float("nan")) for k in ("max_f", "ap", "pre", "rec", "threshold")}
    recall = tp / positives
    precision = tp / (tp + fp + 1e-10)
    f = 2 * precision * recall / (precision + recall + 1e-10)
    best = int(torch.argmax(f))  # the first maximum, as numpy's argmax in the devkit
    ap = torch.stack([precision[recall >= r].max() for r in AP_RECALLS.tolist()]).mean()
    return {
        "max_f": 100 * f[best],
        "ap": 100 * ap,
        "pre": 100 * precision[best],
        "rec": 100 * recall[best],
        "threshold": torch.tensor(best / (NUM_THRESHOLDS - 1), dtype=torch.float64),
    }


def levels(preds: Tensor) -> Tensor:
    """Per cell, how many thresholds k/255 its road probability reaches (0 .. 256): ``preds`` in [0, 1] (float) or
    0..255 (uint8, read as k/255).

    The count is ``torch.bucketize(p, thresholds, right=True)`` over the thresholds ``arange(256) / 255`` in ``p``'s
    dtype, found without the search (a quarter to a third of its time): ``g = floor(255 p)`` is at most one off the last
    threshold ``p`` reaches, and comparing ``p`` with ``g / 255`` and ``(g + 1) / 255``, the same division of the
    same integers as the thresholds', corrects it exactly (tests/metrics/test_road.py checks every threshold and
    its neighbouring floats against the search)."""
    if preds.dtype == torch.uint8:
        return preds.long() + 1
    p = preds.detach().float() if preds.dtype in (torch.float16, torch.bfloat16) else preds.detach()
    low, high = torch.aminmax(p)  # NaN in either fails both tests
    if not (low >= 0 and high <= 1):
        raise ValueError(
            f"RoadMaxF.update: preds must be probabilities in [0, 1], got values in "
            f"[{low.item():.4g}, {high.item():.4g}] (logits?)"
        )
    top = NUM_THRESHOLDS - 1
    guess = (p * top).floor_().clamp_(0, top)  # the last threshold p reaches, give or take one
    level = guess + 1
    level -= (p < guess / top).to(p.dtype)
    level += ((p >= (guess + 1) / top) & (guess < top)).to(p.dtype)
    return level.long()


def level_histograms(level: Tensor, target: Tensor, valid: Tensor) -> Tensor:
    """(B, 2 x 257) int64: per frame of (B,H,W) ``level`` (:func:`levels`), the histogram of its road cells'
    levels, then of its other cells' (cells where ``valid`` is False left out); counted on ``level``'s device, returned
    on the CPU."""
    bins = NUM_THRESHOLDS + 1
    rows = []
    for lv, tg, va in zip(level, target.bool().to(level.device), valid.bool().to(level.device)):
        road, other = lv[tg & va], lv[~tg & va]
        rows.append(torch.cat([torch.bincount(road, minlength=bins), torch.bincount(other, minlength=bins)]))
    return torch.stack(rows).cpu() if rows else torch.zeros(0, 2 * bins, dtype=torch.long)


def frame_histograms(preds: Tensor, target: Tensor, valid: Tensor) -> Tensor:
    """(B, 2 x 257) int64: per BEV frame, the histogram of :func:`levels` over its road cells, then over its other
    cells (don't-care cells left out): per-frame counts from which the frames' per-threshold TP / FP / FN, summed
    over any draw of frames, follow (:func:`ablate.tables.frames.max_f_from_histograms`), and what
    :meth:`RoadMaxF.update` adds given them."""
    return level_histograms(
        levels(_frames(preds, "preds")), _frames(target, "target").bool(), _frames(valid, "valid").bool()
    )


def _frames(x: Tensor, name: str) -> Tensor:
    """(H,W), (B,H,W) or (B,1,H,W) -> (B,H,W)."""
    if x.ndim == 4 and x.shape[1] == 1:
        x = x[:, 0]
    if x.ndim == 2:
        x = x[None]
    if x.ndim != 3:
        raise ValueError(f"RoadMaxF.update: {name} must be (H,W), (B,H,W) or (B,1,H,W), got {tuple(x.shape)}")
    return x


class RoadMaxF(Metric):
    """KITTI road benchmark measures in BEV (Fritsch et al., ITSC 2013; BiFNet §V-A): MaxF, AP, PRE, REC in percent
    and the threshold of MaxF.

    Args:
        res, x_range, z_range: the BEV grid (defaults: the devkit's 0.05 m, x in [-10, 10], z in [6, 46]).
        camera_height: when set, warp with a level road plane this far below the camera instead of each calib's
            ``Tr_cam_to_road`` (for calibrations that lack it).
        lookup: the perspective -> BEV lookup of ``update(..., calib=...)``: ``"devkit"`` (default, the road
            devkit's ``transformImage2BEV``) or ``"nearest"`` (the nearest pixel, a deviation; see the module
            docstring). Its ``evaluator`` tag: :data:`LOOKUPS`.
    """

    full_state_update = False
    is_differentiable = False
    higher_is_better = True

    def __init__(
        self,
        res: float = BEV_RES,
        x_range: Sequence[float] = BEV_X,
        z_range: Sequence[float] = BEV_Z,
        camera_height: float | None = None,
        lookup: str = "devkit",
        **kwargs: Any,
    ) -> None:
        super().__init__(**kwargs)
        try:
            self.lookup = check_lookup(lookup)
        except ValueError as err:
            raise ValueError(f"RoadMaxF: {err}") from None
        if res <= 0 or x_range[1] <= x_range[0] or z_range[1] <= z_range[0]:
            raise ValueError(
                f"RoadMaxF: need res > 0 and increasing ranges, got res={res}, x_range={x_range}, z_range={z_range}"
            )
        if camera_height is not None and camera_height <= 0:
            raise ValueError(f"RoadMaxF: camera_height must be > 0 m, got {camera_height}")
        self.res, self.x_range, self.z_range = float(res), tuple(map(float, x_range)), tuple(map(float, z_range))
        self.camera_height = camera_height
        self.shape = bev_shape(self.res, self.x_range, self.z_range)
        for name in ("tp", "fp", "fn"):
            self.add_state(name, default=torch.zeros(NUM_THRESHOLDS, dtype=torch.long), dist_reduce_fx="sum")

    @property
    def evaluator(self) -> str:
        """The evaluator this metric follows, as a run records it (``ablate.tasks.base.FusionTask.evaluator``)."""
        return LOOKUPS[self.lookup]

    def update(
        self,
        preds: Tensor | None = None,
        target: Tensor | None = None,
        valid: Tensor | None = None,
        calib: Calibration | Sequence[Calibration] | None = None,
        *,
        histograms: Tensor | None = None,
    ) -> None:
        """Add frames. ``preds``: road probability in [0, 1] (float) or 0..255 (uint8, read as k/255); ``target``:
        road mask (bool or 0/1); ``valid``: optional mask, False where the ground truth is don't-care. Each is
        (H,W), (B,H,W) or (B,1,H,W). With ``calib`` (one, or one per frame) they are image_2 perspective images
        and are warped into the BEV grid; without it they must already be on the grid (``self.shape``).

        Or the frames' level histograms alone (``histograms``: :meth:`histograms` or :func:`frame_histograms` of BEV
        frames, (B, 2 x 257), or their sum): the same counts, for a caller that keeps them per frame as well."""
        if histograms is not None:
            if preds is not None or target is not None:
                raise ValueError("RoadMaxF.update: pass preds and target, or histograms, not both")
            return self._add(histograms)
        if preds is None or target is None:
            raise ValueError("RoadMaxF.update: preds and target are needed (or histograms)")
        self._add(self.histograms(preds, target, valid, calib))

    def histograms(
        self,
        preds: Tensor,
        target: Tensor,
        valid: Tensor | None = None,
        calib: Calibration | Sequence[Calibration] | None = None,
    ) -> Tensor:
        """(B, 2 x 257) int64, on the CPU: per frame, the level histograms :meth:`update` adds for these inputs (the
        same inputs, checked alike), for a caller that keeps them per frame and adds them with
        ``update(histograms=...)``."""
        preds, target = _frames(preds, "preds"), _frames(target, "target").to(preds.device)
        valid = torch.ones_like(target, dtype=torch.bool) if valid is None else _frames(valid, "valid").bool()
        if not preds.shape == target.shape == valid.shape:
            raise ValueError(
                f"RoadMaxF.update: preds {tuple(preds.shape)}, target {tuple(target.shape)} and valid "
                f"{tuple(valid.shape)} must have one shape"
            )
        if not ((target == 0) | (target == 1)).all():
            raise ValueError("RoadMaxF.update: target must be a road mask of 0/1 or bool values")
        level = levels(preds)
        target, valid = target.bool(), valid.to(preds.device)
        if calib is not None:
            level, target, valid = self._warp(level, target, valid, calib)
        elif tuple(preds.shape[1:]) != self.shape:
            raise ValueError(
                f"RoadMaxF.update: BEV inputs must be {self.shape} (rows z, columns x), got "
                f"{tuple(preds.shape[1:])}; pass calib for image_2 perspective inputs"
            )
        return level_histograms(level, target, valid)

    def _add(self, histograms: Tensor) -> None:
        """Add the per-threshold counts of frames given as level histograms ((B, 2 x 257) or summed, (514,))."""
        bins = NUM_THRESHOLDS + 1
        if histograms.shape[-1] != 2 * bins:
            raise ValueError(
                f"RoadMaxF.update: histograms must end in {2 * bins} counts, got {tuple(histograms.shape)}"
            )
        total = histograms.reshape(-1, 2 * bins).sum(0).to(self.tp.device)
        tp, fp = (h.flip(0).cumsum(0).flip(0)[1:] for h in (total[:bins], total[bins:]))  # [k]: cells with p >= k/255
        self.tp += tp
        self.fp += fp
        self.fn += tp[0] - tp  # every cell has p >= 0/255, so tp[0] counts all road cells

    def _warp(
        self, level: Tensor, target: Tensor, valid: Tensor, calib: Calibration | Sequence[Calibration]
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Perspective (B,H,W) -> BEV (B,rows,cols) by ``self.lookup``'s pixel of each cell; cells left out are
        don't-care."""
        calibs = [calib] * len(level) if isinstance(calib, Calibration) else list(calib)
        if len(calibs) != len(level):
            raise ValueError(f"RoadMaxF.update: {len(calibs)} calibrations for {len(level)} frames")
        out = []
        for lv, tg, va, cal in zip(level, target, valid, calibs):
            hom = road_homography(cal, self.camera_height)
            index, inside = (
                torch.from_numpy(a).to(lv.device)
                for a in bev_lookup(hom, tuple(lv.shape), self.res, self.x_range, self.z_range, self.lookup)
            )
            out.append([x.flatten()[index].view(self.shape) for x in (lv, tg, va)])
            out[-1][2] &= inside.view(self.shape)
        return tuple(torch.stack(x) for x in zip(*out))

    def compute(self) -> dict[str, Tensor]:
        """max_f, ap, pre, rec (percent) and threshold (in [0, 1]) over all frames; NaN before any road cell."""
        return {k: v.float() for k, v in road_scores(self.tp, self.fp, self.fn).items()}
