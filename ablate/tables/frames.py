"""Counts per test frame: what a table needs to count the test set's draw as a source of variance
(:mod:`ablate.tables.twolevel`).

Where a task keeps its test metric's counts per test frame (:attr:`ablate.tasks.base.FusionTask.frame_counts`; the
run's artifact :data:`ablate.store.FRAME_COUNTS`), the metric over any subset of frames follows from the counts
summed over it (:data:`FROM_COUNTS`):

* ChiNet's semantic segmentation keeps each frame's 3 x 3 confusion counts (ground truth by prediction,
  :func:`ablate.tasks.semantic.confusion`); its detection rate and IoUs are ratios of their sums over frames.
* BiFNet's road task keeps, per frame and branch, the histograms of its BEV cells' probability levels over road and
  over other cells (:func:`ablate.metrics.road.frame_histograms`, 514 counts): the per-threshold TP and FP over any
  set of frames follow from their sums, and MaxF from those, as the devkit forms it.

The AP tasks keep, per test frame, their evaluator's matches instead (the run's artifact
:data:`ablate.store.FRAME_DETECTIONS`, :mod:`ablate.metrics.accumulate`): SMoE's mask AP (``map``, COCOeval's
matches) and DGFN's box AP per class and level (``car_moderate`` ..., the KITTI devkit's), from which AP over any set
of frames is re-accumulated (:data:`FROM_DETECTIONS`).

Both are published beside the table's records (``runs/<table>.frames.csv.gz``: run, row, seed, condition, frame,
counts; ``runs/<table>.detections.csv.gz``: run, row, seed and the detection rows), so the intervals render again
from the records alone.
"""

from __future__ import annotations

import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from ablate.metrics.accumulate import COLUMNS, as_arrays, coco_ap, kitti_ap, kitti_ap_drawn
from ablate.store import FRAME_COUNTS, FRAME_DETECTIONS, Tracker
from ablate.tables.records import RUNS_DIR
from ablate.tables.seal import write_csv


def _rate(c: np.ndarray) -> np.ndarray:
    """ChiNet's detection rate (%) from 3 x 3 confusion counts [..., 9]: free-space and object pixels predicted as
    themselves over all free-space and object pixels (:mod:`ablate.tasks.semantic`)."""
    right = c[..., 4] + c[..., 8]
    total = c[..., 3:9].sum(axis=-1)
    return 100.0 * right / np.maximum(total, 1)


def _iou(k: int) -> Callable[[np.ndarray], np.ndarray]:
    def iou(c: np.ndarray) -> np.ndarray:
        tp = c[..., 4 * k]
        union = c[..., 3 * k : 3 * k + 3].sum(axis=-1) + c[..., k::3].sum(axis=-1) - tp
        return 100.0 * tp / np.maximum(union, 1)

    return iou


#: The road devkit's thresholds k/255 (:data:`ablate.metrics.road.NUM_THRESHOLDS`; the tables do not import torch).
NUM_THRESHOLDS = 256


def max_f_from_histograms(c: np.ndarray) -> np.ndarray:
    """MaxF (%) from :func:`frame_histograms` summed over frames ([..., 514]), as :func:`ablate.metrics.road.road_scores` forms it: the
    per-threshold TP and FP are the cells at or above each threshold; NaN without a road cell."""
    bins = NUM_THRESHOLDS + 1
    tp = np.flip(np.cumsum(np.flip(c[..., :bins], -1), -1), -1)[..., 1:]
    fp = np.flip(np.cumsum(np.flip(c[..., bins:], -1), -1), -1)[..., 1:]
    positives = tp[..., :1]
    with np.errstate(invalid="ignore", divide="ignore"):
        recall = tp / positives
        precision = tp / (tp + fp + 1e-10)
        f = 2 * precision * recall / (precision + recall + 1e-10)
    return np.where(positives[..., 0] > 0, 100 * f.max(axis=-1), np.nan)


def _road(c: np.ndarray) -> np.ndarray:
    """BiFNet's MaxF (%) from the first branch's level histograms (:func:`ablate.metrics.road.frame_histograms`): a
    road job keeps each branch's in the order camera, BEV, and its main MaxF is its first branch's."""
    return max_f_from_histograms(c[..., : 2 * (NUM_THRESHOLDS + 1)])


#: Each metric that decomposes over test frames, from its counts summed over frames.
FROM_COUNTS: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "det_rate": _rate,
    "iou_free_space": _iou(1),
    "iou_road_objects": _iou(2),
    "max_f": _road,
    "cam_max_f": _road,  # a row with a camera branch keeps it first
}


def frames_path(results_dir: str | Path, table: str) -> Path:
    """The counts per test frame kept beside a table's records."""
    return Path(results_dir) / RUNS_DIR / f"{table}.frames.csv.gz"


def from_store(tracker: Tracker, runs: pd.DataFrame) -> pd.DataFrame:
    """The counts per test frame of each of ``runs`` that has them (a reused run: its source's), long: run_id, row,
    seed, condition, frame, c0 .. ; empty where no run has them."""
    counts = _from_store(tracker, runs, FRAME_COUNTS, _read)
    return counts.fillna(0) if len(counts) else counts


def _from_store(
    tracker: Tracker, runs: pd.DataFrame, artifact: str, read: Callable[[Path], pd.DataFrame]
) -> pd.DataFrame:
    """``artifact`` of each of ``runs`` that logged it (a reused run: its source's), read by ``read``, each row
    prefixed with its run's run_id, row and seed; empty where no run has it."""
    parts = []
    for _, run in runs.iterrows():
        source = str(run.get("reused_from") or "") or str(run["run_id"])
        if artifact not in tracker.list_artifacts(source, str(Path(artifact).parent)):
            continue
        with tempfile.TemporaryDirectory() as folder:
            kept = read(Path(tracker.download_artifact(source, artifact, folder)))
        ids = pd.DataFrame({"run_id": run["run_id"], "row": run["row"], "seed": run["seed"]}, index=kept.index)
        parts.append(pd.concat([ids, kept], axis=1))  # one concat: 514 columns inserted one by one fragment
    return pd.concat(parts, ignore_index=True) if parts else pd.DataFrame()


def _write(kept: pd.DataFrame, path: Path) -> Path | None:
    """``kept`` as gzipped CSV at ``path`` (the same bytes for the same rows), sealed
    (:func:`ablate.tables.seal.write_csv`); None where it is empty."""
    return write_csv(kept, path) if not kept.empty else None


def write_frames(frames: pd.DataFrame, results_dir: str | Path, table: str) -> Path | None:
    """``runs/<table>.frames.csv.gz``; None where there are no counts."""
    return _write(frames, frames_path(results_dir, table))


def read_frames(results_dir: str | Path, table: str) -> pd.DataFrame:
    """The counts kept beside a table's records (empty where there are none)."""
    path = frames_path(results_dir, table)
    return _read(path) if path.exists() else pd.DataFrame()


def _read(path: Path) -> pd.DataFrame:
    """Counts per frame from a CSV: frames and conditions as text (no condition: ""), counts a row lacks (a road row
    with one branch beside one with two) as 0."""
    frames = pd.read_csv(path, dtype={"frame": str, "condition": str})
    frames["condition"] = frames["condition"].fillna("")
    return frames.fillna(0)


def counts_by_run(frames: pd.DataFrame, condition: str = "") -> dict[tuple[str, int], pd.DataFrame]:
    """Each (row, seed)'s counts under ``condition`` ([frames, k] as floats, sorted and indexed by frame name), by
    (row, seed): one pass over a table's counts (filtering them again for each run took most of a report's time)."""
    sel = frames[frames["condition"].astype(str) == condition]
    columns = [c for c in frames.columns if c.startswith("c") and c[1:].isdigit()]
    names, counts = sel["frame"].astype(str).to_numpy(), sel[columns].to_numpy(dtype=float)
    runs: dict[tuple[str, int], list[int]] = {}
    for i, key in enumerate(zip(sel["row"].astype(str), pd.to_numeric(sel["seed"]).astype(int), strict=True)):
        runs.setdefault(key, []).append(i)
    out = {}
    for key, at in runs.items():
        order = np.asarray(at)[np.argsort(names[at], kind="stable")]
        out[key] = pd.DataFrame(counts[order], index=pd.Index(names[order], name="frame"), columns=columns)
    return out


def _mask_ap(rows: dict[str, np.ndarray], keep: np.ndarray | None = None) -> float:
    """SMoE's mask AP (percent) from one run's COCOeval rows (:func:`ablate.metrics.accumulate.coco_ap`)."""
    value = coco_ap(rows, keep)
    return 100.0 * value if value >= 0 else float("nan")


def _box_ap(rows: dict[str, np.ndarray], keep: np.ndarray | None = None) -> float:
    """DGFN's 11-point box AP (percent) of the rows' class and level (:func:`ablate.metrics.accumulate.kitti_ap`)."""
    if not len(rows["kind"]):
        return float("nan")
    value = kitti_ap(rows, str(rows["cls"][0]), int(rows["level"][0]), 11, keep)
    return value if value >= 0 else float("nan")


#: Each AP metric whose runs keep their detections per test frame: the metric over any set of frames from them.
BOX_AP = tuple(f"{c}_{lv}" for c in ("car", "pedestrian", "cyclist") for lv in ("easy", "moderate", "hard"))
FROM_DETECTIONS: dict[str, Callable[[dict[str, np.ndarray], np.ndarray | None], float]] = {
    "map": _mask_ap,
    **dict.fromkeys(BOX_AP, _box_ap),
}


def detections_path(results_dir: str | Path, table: str) -> Path:
    """The detections per test frame kept beside a table's records."""
    return Path(results_dir) / RUNS_DIR / f"{table}.detections.csv.gz"


def detections_from_store(tracker: Tracker, runs: pd.DataFrame) -> pd.DataFrame:
    """The detections per test frame of each of ``runs`` that kept them (a reused run: its source's), long: run_id,
    row, seed, frame, condition, metric and :data:`ablate.metrics.accumulate.COLUMNS`; empty where none did."""
    return _from_store(tracker, runs, FRAME_DETECTIONS, _read_detections)


def verdict_metric(table: Any) -> tuple[str, str]:
    """(metric, condition) whose frames a table's verdicts resample (``table``: its spec,
    :func:`ablate.tables.spec.table_spec`): its primary metric under its ``primary_condition`` ("" where it has
    none), or the two halves of a conditions table's flattened primary ``<condition>/<metric>``."""
    primary, condition = str(table.primary), str(table.get("primary_condition") or "")
    if "/" in primary:
        condition, primary = primary.split("/", 1)
    return primary, condition


def verdicts_read(detections: pd.DataFrame, metric: str, condition: str) -> pd.DataFrame:
    """The rows of ``detections`` that a table's verdicts read (:func:`verdict_metric`): its primary metric under its
    primary condition. A job keeps every metric under every test input (a DGFN job: 16 inputs by 6 class-levels,
    about 1 M rows); a table publishes the one pair its intervals are drawn from, 2-5 % of them."""
    if detections.empty:
        return detections
    keep = (detections["metric"] == metric) & (detections["condition"].fillna("").astype(str) == condition)
    return detections[keep].reset_index(drop=True)


def write_detections(detections: pd.DataFrame, results_dir: str | Path, table: str) -> Path | None:
    """``runs/<table>.detections.csv.gz``; None where there are none."""
    return _write(detections, detections_path(results_dir, table))


def read_detections(results_dir: str | Path, table: str) -> pd.DataFrame:
    """The detections kept beside a table's records (empty where there are none)."""
    path = detections_path(results_dir, table)
    return _read_detections(path) if path.exists() else pd.DataFrame()


def _read_detections(path: Path | str) -> pd.DataFrame:
    rows = pd.read_csv(path, dtype={"frame": str, "condition": str, "metric": str, "kind": str, "cls": str})
    rows["condition"] = rows["condition"].fillna("")
    return rows


def detections_by_run(
    detections: pd.DataFrame, metric: str, condition: str = ""
) -> dict[tuple[str, int], pd.DataFrame]:
    """Each (row, seed)'s rows of ``metric`` under ``condition``, in the order its evaluator wrote them, by (row,
    seed): one pass over a table's detections."""
    d = detections
    sel = d[(d["metric"] == metric) & (d["condition"].astype(str) == condition)]
    groups = sel.groupby([sel["row"], pd.to_numeric(sel["seed"])], sort=False)
    return {(str(row), int(seed)): one for (row, seed), one in groups}


#: The draws of the test frames behind an AP metric's frames' term (:mod:`ablate.tables.twolevel`): how many, and
#: the seed of the one stream every table and race uses (the same records give the same intervals).
AP_DRAWS, AP_DRAWS_SEED = 1000, 0


def frame_draws(count: int, draws: int = AP_DRAWS, seed: int = AP_DRAWS_SEED) -> np.ndarray:
    """[draws, count] indices into a table's sorted frame names: each row ``count`` frames drawn with replacement."""
    return np.random.default_rng(seed).integers(0, count, size=(draws, count))


def ap_resampled(rows: pd.DataFrame, metric: str, frames: list[str], draws: np.ndarray) -> np.ndarray:
    """``metric`` of one run's rows over each draw of ``frames`` ([draws] values): a frame drawn k times counts k
    times (its rows repeated, in image order), a frame the run lacks adds nothing; NaN where a draw holds no ground
    truth that counts. A box AP takes every draw at once from the rows' counts (:func:`ablate.metrics.accumulate.
    kitti_ap_drawn`); a mask AP repeats each draw's rows."""
    arrays = as_arrays({c: rows[c].to_numpy() for c in COLUMNS})
    frame = pd.Index(frames).get_indexer(rows["frame"].astype(str).to_numpy())  # -1: a frame no draw holds
    drawn = np.zeros((len(draws), len(frames) + 1), np.int64)  # the last column: -1's, never drawn
    np.add.at(drawn, (np.arange(len(draws))[:, None], draws), 1)
    if metric in BOX_AP and len(rows):
        ap = kitti_ap_drawn(arrays, str(arrays["cls"][0]), int(arrays["level"][0]), frame, drawn, 11)
        return np.where(ap >= 0, ap, np.nan)
    compute, positions = FROM_DETECTIONS[metric], np.arange(len(rows))
    out = np.empty(len(draws))
    for i, per_frame in enumerate(drawn):
        idx = np.repeat(positions, per_frame[frame])  # the rows of the draw's frames, each as often, in row order
        out[i] = compute({c: v[idx] for c, v in arrays.items()}, None)
    return out
