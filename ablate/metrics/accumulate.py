"""AP re-accumulated from each test frame's scored detections, over any set of frames (numpy only: the tables read it).

Matching detections to ground truth is per image in both evaluators, so when whole frames are left out or drawn
again, no frame's matches change: only the accumulation over frames does. Each frame keeps what the accumulation
reads (:class:`Entries`, long rows: ``kind``, ``cls``, ``level``, ``score``, ``a``, ``b``, in the evaluator's image
order ``index``), and AP over a set of frames follows from the rows of those frames, in milliseconds:

* **COCO** (:func:`coco_ap`, pycocotools' ``COCOeval.accumulate`` vectorised; SMoE's mask AP, :class:`ablate.metrics.
  coco.MaskAP`): per frame and category, kind ``dt`` rows for its detections (COCOeval's ``evaluateImg``: the
  first ``maxDets`` by score) with ``a`` the bits of the 10 IoU thresholds at which the detection matched a ground
  truth and ``b`` those at which it is ignored (matched a crowd region), and one kind ``gt`` row with ``a`` the
  ground truths not ignored. Per category the detections of the frames are concatenated in image order and sorted
  by score with a stable sort (mergesort, as ``accumulate``), precision is made monotone and read at the 101 recall
  thresholds; AP is the mean over thresholds, recalls and categories of the defined values.
* **KITTI** (:func:`kitti_ap`, the tail of the devkit's ``eval_class``; DGFN's box AP, :class:`ablate.metrics.kitti.
  KittiAP`): per frame, class and level, kind ``gt`` (``a``: counted ground truths), kind ``tp`` rows (the scores
  of the threshold pass's true positives, which ``getThresholds`` reads), and kind ``cut`` rows, one per distinct
  detection score ``u``: ``a`` and ``b`` the frame's change of TP and FP counts when the score threshold drops to
  ``u`` (the precision pass's greedy assignment at each threshold is per image, so each frame's counts are a step
  function of the threshold with steps at its own scores). The thresholds of a set of frames come from its TP
  scores and counted ground truths, and its TP and FP at each from the cut rows at or above it.
"""

from __future__ import annotations

import bisect
from collections.abc import Sequence

import numpy as np

#: COCO's recall thresholds (``Params.recThrs``) and the number of IoU thresholds (0.50:0.05:0.95).
REC_THRS = np.linspace(0.0, 1.0, int(np.round((1.00 - 0.0) / 0.01)) + 1)
IOU_THRS = 10
#: KITTI's sampled recall points (eval.cpp ``N_SAMPLE_PTS``).
N_SAMPLE_PTS = 41


def bits(flags: np.ndarray) -> np.ndarray:
    """[T, D] booleans -> [D] integers, bit t set where flag t is."""
    flags = np.asarray(flags, dtype=bool).reshape(flags.shape[0], -1)
    return (flags.astype(np.int64) << np.arange(flags.shape[0])[:, None]).sum(axis=0)


def unbits(values: np.ndarray, n: int = IOU_THRS) -> np.ndarray:
    """:func:`bits`' inverse: [D] integers -> [n, D] booleans."""
    return (np.asarray(values, dtype=np.int64)[None, :] >> np.arange(n)[:, None]) & 1 == 1


def coco_precision(score: np.ndarray, match: np.ndarray, ignore: np.ndarray, npig: int) -> np.ndarray:
    """COCOeval ``accumulate``'s precision [T, R] of one category from its detections in image order (``score``
    [D]; ``match``, ``ignore`` [T, D] booleans) and its ground truths not ignored; all -1 where there are none."""
    out = -np.ones((match.shape[0], len(REC_THRS)))
    if npig == 0:
        return out
    order = np.argsort(-score, kind="mergesort")
    dtm, dtig = match[:, order], ignore[:, order]
    tps, fps = dtm & ~dtig, ~dtm & ~dtig
    tp, fp = np.cumsum(tps, axis=1).astype(float), np.cumsum(fps, axis=1).astype(float)
    for t in range(match.shape[0]):
        q = np.zeros(len(REC_THRS))
        if tp.shape[1]:
            rc = tp[t] / npig
            pr = tp[t] / (fp[t] + tp[t] + np.spacing(1))
            pr = np.maximum.accumulate(pr[::-1])[::-1]  # accumulate's loop: each precision the max of the later ones
            inds = np.searchsorted(rc, REC_THRS, side="left")
            ok = inds < len(pr)
            q[ok] = pr[inds[ok]]
        out[t] = q
    return out


def coco_ap(rows: dict[str, np.ndarray], keep: np.ndarray | None = None) -> float:
    """Mean AP (0-1) over IoU thresholds, recall thresholds and categories of the rows of a run's frames
    (:func:`as_arrays`) whose frame ``index`` is in ``keep`` (default: every frame); -1 where no category has a
    ground truth that counts."""
    sel = np.ones(len(rows["kind"]), bool) if keep is None else np.isin(rows["index"], keep)
    values = []
    for cls in np.unique(rows["cls"][sel]):
        mine = sel & (rows["cls"] == cls)
        dt, gt = mine & (rows["kind"] == "dt"), mine & (rows["kind"] == "gt")
        npig = int(rows["a"][gt].sum())
        prec = coco_precision(rows["score"][dt], unbits(rows["a"][dt]), unbits(rows["b"][dt]), npig)
        values.append(prec)
    if not values:
        return -1.0
    p = np.stack(values)
    valid = p[p > -1]
    return float(valid.mean()) if valid.size else -1.0


def threshold_positions(count: int, n_gt: int) -> np.ndarray:
    """eval.cpp ``getThresholds``' choice among ``count`` TP scores sorted from the highest: the positions whose
    recalls best approximate 0, 1/40, ..., 1. It reads the positions, never the scores, and its choice at a position
    short of the last does not depend on ``count``: one pass per ``n_gt`` serves every count (:data:`_CHOSEN`), which
    makes AP over many draws of the frames cheap (:func:`kitti_ap_drawn`)."""
    if count <= 0:
        return np.zeros(0, np.int64)
    chosen, done, current = _CHOSEN.get(n_gt, ([], 0, 0.0))
    for i in range(done, count - 1):
        left, right = (i + 1) / n_gt, (i + 2) / n_gt
        if right - current < current - left:
            continue
        chosen.append(i)
        current += 1.0 / (N_SAMPLE_PTS - 1.0)
    _CHOSEN[n_gt] = (chosen, max(done, count - 1), current)
    return np.array([*chosen[: bisect.bisect_left(chosen, count - 1)], count - 1], np.int64)  # the last: always


#: n_gt -> (the positions chosen short of the last, how many positions were decided, getThresholds' ``current``).
_CHOSEN: dict[int, tuple[list[int], int, float]] = {}


def kitti_thresholds(scores: np.ndarray, n_gt: int) -> np.ndarray:
    """eval.cpp ``getThresholds``: the TP scores whose recalls best approximate 0, 1/40, ..., 1."""
    return np.sort(scores)[::-1][threshold_positions(len(scores), n_gt)]


def kitti_precision(
    tp_scores: np.ndarray, n_gt: int, cut: np.ndarray, d_tp: np.ndarray, d_fp: np.ndarray
) -> np.ndarray:
    """The devkit's interpolated precision at its 41 points from the TP scores of the threshold pass, the counted
    ground truths and the frames' cut rows (score ``cut``, TP and FP increments ``d_tp``, ``d_fp``)."""
    order = np.argsort(-cut, kind="mergesort")
    return precision_at(kitti_thresholds(tp_scores, n_gt), cut[order], np.cumsum(d_tp[order]), np.cumsum(d_fp[order]))


def precision_at(t: np.ndarray, s: np.ndarray, ctp: np.ndarray, cfp: np.ndarray) -> np.ndarray:
    """The interpolated precision at the 41 points from the thresholds ``t`` and the cut rows sorted from the highest
    score ``s`` with their cumulative TP and FP counts ``ctp``, ``cfp``."""
    reach = np.searchsorted(-s, -t, side="right")  # the cut rows with score >= t
    tp = np.where(reach > 0, ctp[np.maximum(reach - 1, 0)] if len(s) else 0, 0).astype(float)
    fp = np.where(reach > 0, cfp[np.maximum(reach - 1, 0)] if len(s) else 0, 0).astype(float)
    return interpolated(tp, fp)


def interpolated(tp: np.ndarray, fp: np.ndarray) -> np.ndarray:
    """The devkit's precision at its 41 points from the TP and FP counts at each threshold, made monotone."""
    precision = np.zeros(N_SAMPLE_PTS)
    precision[: len(tp)] = np.divide(tp, tp + fp, out=np.zeros_like(tp), where=tp + fp > 0)
    return np.maximum.accumulate(precision[::-1])[::-1]


def ap_of(precision: np.ndarray, points: int) -> float:
    """AP in percent from the 41 points' precision: the devkit's 11 points (every fourth) or its 40 (all but 0)."""
    return float(100 * precision[::4].sum() / 11 if points == 11 else 100 * precision[1:].sum() / 40)


def kitti_ap(
    rows: dict[str, np.ndarray], cls: str, level: int, points: int = 11, keep: np.ndarray | None = None
) -> float:
    """AP in percent (``points`` 11 or 40) of ``cls`` at ``level`` from a run's rows (:func:`as_arrays`) of the frames
    in ``keep`` (default: all); -1 with no counted ground truth (as :meth:`ablate.metrics.kitti.KittiAP._ap`)."""
    sel = (rows["cls"] == cls) & (rows["level"] == level)
    if keep is not None:
        sel &= np.isin(rows["index"], keep)
    n_gt = int(rows["a"][sel & (rows["kind"] == "gt")].sum())
    if n_gt == 0:
        return -1.0
    cut = sel & (rows["kind"] == "cut")
    precision = kitti_precision(
        rows["score"][sel & (rows["kind"] == "tp")], n_gt, rows["score"][cut], rows["a"][cut], rows["b"][cut]
    )
    return ap_of(precision, points)


def kitti_ap_drawn(
    rows: dict[str, np.ndarray], cls: str, level: int, frame: np.ndarray, drawn: np.ndarray, points: int = 11
) -> np.ndarray:
    """:func:`kitti_ap` over many draws of the frames at once: ``frame`` [rows] is each row's frame (a column of
    ``drawn``), ``drawn`` [draws, frames] how many times a draw holds each frame; [draws] values, -1 where a draw has
    no counted ground truth. Each equals :func:`kitti_ap` of the drawn frames' rows, each repeated as often as its
    frame is drawn: the counted ground truths are a sum over the frames; the thresholds depend only on how many TP
    scores lie at or above each (:func:`threshold_positions`) and are TP scores, so each frame's TP and FP counts at
    every TP score, counted once, give every draw's by one product. The counts are integers, exact in floats: the same
    values whatever the order of tied scores or of the sums."""
    sel = (rows["cls"] == cls) & (rows["level"] == level)
    f, kind, score, a, b = frame[sel], rows["kind"][sel], rows["score"][sel], rows["a"][sel], rows["b"][sel]
    gt, tp, cut = kind == "gt", kind == "tp", kind == "cut"
    counts, n_frames = drawn.astype(float), drawn.shape[1]
    n_gt = counts @ np.bincount(f[gt], weights=a[gt], minlength=n_frames)
    by_tp = np.argsort(-score[tp], kind="mergesort")
    v = score[tp][by_tp]  # the TP scores from the highest
    reps = np.cumsum(counts[:, f[tp][by_tp]], axis=1)  # per draw, how many TP scores lie at or above each
    levels = np.unique(v)[::-1]  # each TP score once, from the highest: the thresholds any draw can have
    rank = np.searchsorted(-levels, -score[cut], side="left")  # a cut row counts at every threshold from this one
    at = np.zeros((2, len(levels) + 1, n_frames))
    np.add.at(at, (0, rank, f[cut]), a[cut])
    np.add.at(at, (1, rank, f[cut]), b[cut])
    tp_at, fp_at = (counts @ np.cumsum(x[:-1], axis=0).T for x in at)  # [draws, thresholds]
    of_v = np.searchsorted(-levels, -v, side="left")
    out = np.full(len(counts), -1.0)
    for d in np.flatnonzero(n_gt > 0):
        count = int(reps[d, -1]) if len(v) else 0
        k = of_v[np.searchsorted(reps[d], threshold_positions(count, int(n_gt[d])), side="right")]
        out[d] = ap_of(interpolated(tp_at[d, k], fp_at[d, k]), points)
    return out


COLUMNS = ("index", "kind", "cls", "level", "score", "a", "b")


def as_arrays(rows: Sequence[dict] | dict[str, Sequence]) -> dict[str, np.ndarray]:
    """Rows (dicts of :data:`COLUMNS`, or columns) as numpy columns: index, level, a, b integers; score float;
    kind, cls text."""
    if not isinstance(rows, dict):
        rows = {c: [r.get(c) for r in rows] for c in COLUMNS}
    out = {c: np.asarray(rows[c]) for c in COLUMNS}
    for c in ("index", "level", "a", "b"):
        out[c] = np.nan_to_num(np.asarray(out[c], dtype=float), nan=0).astype(np.int64)
    out["score"] = np.nan_to_num(np.asarray(out["score"], dtype=float), nan=0.0)
    out["kind"], out["cls"] = out["kind"].astype(str), out["cls"].astype(str)
    return out
