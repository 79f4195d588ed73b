"""The test set as a source of variance: each comparison's interval over the seeds *and* the test frames.

A table's test split is one draw of frames; a difference smaller than what another draw would move does not carry
to new data (Bouthillier et al. 2021, "Accounting for variance in machine learning benchmarks", MLSys: data
sampling is a larger source of variance than the seed in most of their benchmarks). Where a task keeps its test
metric's counts per test frame (:attr:`ablate.tasks.base.FusionTask.frame_counts`; the run's artifact
:data:`ablate.store.FRAME_COUNTS`), the table resamples both.

**Counts.** ChiNet's semantic segmentation keeps each frame's 3 x 3 confusion counts (ground truth by prediction,
:func:`ablate.tasks.semantic.confusion`); its detection rate and IoUs are ratios of their sums over frames. BiFNet's
road task keeps, per frame and branch, the histograms of its BEV cells' probability levels over road and over
other cells (:func:`ablate.metrics.road.frame_histograms`, 514 counts): the per-threshold TP and FP over any draw
of frames follow from their sums, and MaxF from those, as the devkit forms it. Each metric is recomputed exactly
from the counts (:data:`FROM_COUNTS`). The AP tasks (SMoE's mask AP, DGFN's 11-point box AP) keep none: AP over a
resample needs each frame's scored detections matched again, which this module does not do. The counts are published beside the table's records
(``runs/<table>.frames.csv.gz``: run, row, seed, condition, frame, counts), so the intervals render again from the
records alone.

**Two-level paired bootstrap** (:func:`resampled_differences`): each of :data:`RESAMPLES` resamples draws the seeds
with replacement (the same seeds for both rows: paired) and, independently, the test frames with replacement (the
same frames for every seed and both rows: the rows are tested on one test set); each (row, seed) metric is computed
from its counts summed over the drawn frames, and the difference is the mean over the drawn seeds. The two levels
are the two sources of variance: the seeds' (training) and the frames' (the test set's draw). The interval is the
resamples' percentile interval; the p-values are the shares of resamples on the other side of 0, of ±δ
(:func:`frame_tests`).

**Verdicts** (:func:`rejudge`): each comparison of the race is judged again at the look where it ended, with these
p-values in place of the t-tests over seeds, the same levels and the same correction over the table's comparisons
(:mod:`ablate.tables.verdicts`). The race itself stopped on the seeds alone (the sweeper does not read the frames);
the table's verdicts, its forest plot and its numbers use the seeds-and-frames interval where the runs have counts,
and the footer says so.
"""

from __future__ import annotations

import math
import tempfile
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
from omegaconf import DictConfig

from ablate.store import FRAME_COUNTS, Tracker
from ablate.tables.racing import RaceState
from ablate.tables.records import RUNS_DIR
from ablate.tables.verdicts import BETTER, EQUIVALENT, WORSE, rejected, verdict

#: Resamples of the two-level bootstrap.
RESAMPLES = 2000


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
    parts = []
    for _, run in runs.iterrows():
        source = str(run.get("reused_from") or "") or str(run["run_id"])
        if FRAME_COUNTS not in tracker.list_artifacts(source, str(Path(FRAME_COUNTS).parent)):
            continue
        with tempfile.TemporaryDirectory() as folder:
            path = tracker.download_artifact(source, FRAME_COUNTS, folder)
            counts = _read(path)
        ids = pd.DataFrame({"run_id": run["run_id"], "row": run["row"], "seed": run["seed"]}, index=counts.index)
        parts.append(pd.concat([ids, counts], axis=1))  # one concat: 514 columns inserted one by one fragment
    return pd.concat(parts, ignore_index=True).fillna(0) if parts else pd.DataFrame()


def write_frames(frames: pd.DataFrame, results_dir: str | Path, table: str) -> Path | None:
    """``runs/<table>.frames.csv.gz``; None where there are no counts."""
    if frames.empty:
        return None
    path = frames_path(results_dir, table)
    path.parent.mkdir(parents=True, exist_ok=True)
    frames.to_csv(path, index=False, lineterminator="\n", compression={"method": "gzip", "mtime": 0})
    return path


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


def counts(frames: pd.DataFrame, row: str, seeds: list[int], condition: str = "") -> np.ndarray:
    """[seeds, frames, k] counts of ``row`` for ``seeds`` under ``condition``, frames in one order for every row."""
    sel = frames[(frames["row"] == row) & (frames["condition"].astype(str) == condition)]
    columns = [c for c in frames.columns if c.startswith("c") and c[1:].isdigit()]
    out = []
    for seed in seeds:
        one = sel[pd.to_numeric(sel["seed"]) == seed].sort_values("frame")
        out.append(one[columns].to_numpy(dtype=float))
    return np.stack(out)


def resampled_differences(
    a: np.ndarray, b: np.ndarray, metric: Callable[[np.ndarray], np.ndarray], resamples: int = RESAMPLES, seed: int = 0
) -> tuple[float, np.ndarray]:
    """The observed mean difference of ``metric`` between rows ``a`` and ``b`` ([seeds, frames, k] counts, paired
    by seed and frame) and its :data:`RESAMPLES` two-level bootstrap resamples (see the module)."""
    rng = np.random.default_rng(seed)
    n_seeds, n_frames = a.shape[0], a.shape[1]
    observed = float((metric(a.sum(axis=1)) - metric(b.sum(axis=1))).mean())
    frame_w = rng.multinomial(n_frames, np.full(n_frames, 1.0 / n_frames), size=resamples).astype(float)
    seed_w = rng.multinomial(n_seeds, np.full(n_seeds, 1.0 / n_seeds), size=resamples).astype(float) / n_seeds
    per_seed = metric(np.einsum("rf,sfk->rsk", frame_w, a)) - metric(np.einsum("rf,sfk->rsk", frame_w, b))
    return observed, (per_seed * seed_w).sum(axis=1)


def frame_tests(observed: float, diffs: np.ndarray, rope: float | None) -> tuple[float, float, float]:
    """Bootstrap p-values (p_diff, p_beyond, p_equiv) of :class:`ablate.tables.verdicts.PairedTests`' tests: the
    shares of resamples on the other side of 0 (doubled: two-sided), of δ on the side of the observed mean, and
    the larger share beyond -δ or δ."""
    p_diff = min(1.0, 2.0 * min(float((diffs <= 0).mean()), float((diffs >= 0).mean())))
    if rope is None:
        return p_diff, math.nan, math.nan
    beyond = float((diffs <= rope).mean()) if observed > 0 else float((diffs >= -rope).mean())
    equiv = max(float((diffs <= -rope).mean()), float((diffs >= rope).mean()))
    return p_diff, beyond, equiv


def rejudge(state: RaceState, frames: pd.DataFrame, table: DictConfig) -> RaceState | None:
    """``state`` with each comparison judged again on its seeds-and-frames interval (see the module); None where
    the runs have no counts for the table's primary metric."""
    key = str(table.primary)
    if frames.empty or key not in FROM_COUNTS:
        return None
    condition = str(table.get("primary_condition") or "")
    plan, levels = state.plan, state.plan.levels()
    judged = {}
    for look in sorted({c.look for c in state.comparisons.values()}):
        at = [(k, c) for k, c in state.comparisons.items() if c.look == look and c.n >= 1]  # 1: over frames alone
        seeds = list(range(plan.looks[look - 1]))
        tests = []
        for _, c in at:
            a, b = counts(frames, c.a, seeds[: c.n], condition), counts(frames, c.b, seeds[: c.n], condition)
            if a.shape != b.shape or a.shape[1] == 0:
                return None  # a run without counts, or rows tested on other frames: no interval over frames
            observed, diffs = resampled_differences(a, b, FROM_COUNTS[key])
            tests.append((observed, diffs, frame_tests(observed, diffs, plan.rope)))
        claims = [rejected([t[2][i] for t in tests], levels[look - 1], plan.multiplicity) for i in (1, 2, 0)]
        for i, (k, c) in enumerate(at):
            observed, diffs, _ = tests[i]
            kind = verdict(claims[0][i], claims[1][i], claims[2][i], observed)
            lo, hi = np.quantile(diffs, [levels[look - 1], 1 - levels[look - 1]])
            done = kind in (BETTER, WORSE, EQUIVALENT)
            p_diff = tests[i][2][0]
            judged[k] = replace(
                c, kind=kind, lo=float(lo), hi=float(hi), delta=observed, p=p_diff, decided=done, frames=True
            )
    return replace(state, comparisons={k: judged.get(k, c) for k, c in state.comparisons.items()})


def judged(state: RaceState, runs: pd.DataFrame, table: DictConfig) -> RaceState:
    """The race's state as a table reports it: judged again on the seeds-and-frames interval where ``runs`` carry
    counts per test frame (``runs.attrs["frames"]``, put there by the table's writer), else as the race left it."""
    frames = runs.attrs.get("frames")
    again = rejudge(state, frames, table) if isinstance(frames, pd.DataFrame) else None
    return again if again is not None else state
