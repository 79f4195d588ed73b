"""Dense depth (SMoE §3.2) of full-resolution real KITTI frames: ablate.data.lidar.dense_depth against the plain
SciPy pipeline (Delaunay + LinearNDInterpolator + NearestNDInterpolator), interleaved in the same run.

Prints per frame the median time of each, their ratio and the work buffers dense_depth holds after the frame;
then the median ratio over the frames, the memory a call takes (peak RSS growth over the first calls, traced
peak of one call) and the machine's load average before and after."""

from __future__ import annotations

import os
import resource
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np
from scipy.interpolate import LinearNDInterpolator, NearestNDInterpolator
from scipy.spatial import Delaunay

from ablate.data.kitti import Calibration, read_image, read_velodyne
from ablate.data.lidar import dense_depth, sparse_depth
from ablate.data.triangles import scratch

ROOT = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).resolve().parents[2] / "shared/kitti/object/training"
FRAMES = ("000000", "000001", "000006")
REPS_OURS, REPS_SCIPY = 9, 3


def scipy_dense(sparse: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    h, w = sparse.shape
    ys, xs = np.nonzero(sparse)
    pts, vals = np.stack([xs, ys], 1).astype(np.float64), sparse[ys, xs]
    gy, gx = np.mgrid[:h, :w]
    query = np.stack([gx.ravel(), gy.ravel()], 1)
    linear = LinearNDInterpolator(Delaunay(pts), vals)(query).reshape(h, w)
    out = linear.copy()
    hole = np.isnan(linear)
    out[hole] = NearestNDInterpolator(pts, vals)(query[hole.ravel()])
    return out, ~hole


def timed(fn, arg, times: list[float]):
    t = time.perf_counter()
    res = fn(arg)
    times.append(time.perf_counter() - t)
    return res


def main() -> None:
    load = [os.getloadavg()]
    sparse = {}
    for frame in FRAMES:
        calib = Calibration.from_file(ROOT / "calib" / f"{frame}.txt")
        shape = read_image(ROOT / "image_2" / f"{frame}.png").shape[:2]
        sparse[frame] = sparse_depth(read_velodyne(ROOT / "velodyne" / f"{frame}.bin"), calib, shape)

    # Memory first, before SciPy runs in this process: buffers held after each frame, peak RSS growth.
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    held = {}
    for frame in FRAMES:
        dense_depth(sparse[frame])
        held[frame] = scratch.nbytes() / 1e6
    rss_growth = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0) / 1024
    tracemalloc.start()
    dense_depth(sparse[FRAMES[1]])
    traced_peak = tracemalloc.get_traced_memory()[1] / 1e6
    tracemalloc.stop()

    # Timing: ours and SciPy interleaved over frames and repetitions, medians per frame.
    t_ours = {f: [] for f in FRAMES}
    t_ref = {f: [] for f in FRAMES}
    ours, ref = {}, {}
    for rep in range(REPS_OURS):
        for frame in FRAMES:
            ours[frame] = timed(dense_depth, sparse[frame], t_ours[frame])
            if rep < REPS_SCIPY:
                ref[frame] = timed(scipy_dense, sparse[frame], t_ref[frame])
    load.append(os.getloadavg())

    ratios = []
    for frame in FRAMES:
        sp, (dense_ref, hull) = sparse[frame], ref[frame]
        a, b = np.median(t_ours[frame]), np.median(t_ref[frame])
        ratios.append(b / a)
        diff = np.abs(ours[frame] - dense_ref)[hull]
        print(
            f"{frame} {sp.shape[1]}x{sp.shape[0]} lidar px {int((sp > 0).sum())}: ours {a * 1e3:.1f} ms, "
            f"scipy {b * 1e3:.0f} ms (medians of {REPS_OURS} / {REPS_SCIPY}), ratio {b / a:.1f}x; "
            f"buffers held after the frame {held[frame]:.1f} MB; inside hull |diff| median "
            f"{np.median(diff):.2e} m, mean {diff.mean():.3f} m, p90 {np.percentile(diff, 90):.3f} m"
        )
    print(f"ratio over frames: median {np.median(ratios):.1f}x, min {min(ratios):.1f}x (target >= 10x)")
    print(
        f"memory: peak RSS growth over the first {len(FRAMES)} calls {rss_growth:.1f} MB, traced peak of one call "
        f"(NumPy allocations, buffers already held) {traced_peak:.1f} MB"
    )
    print(
        "load average (1, 5, 15 min) before "
        + " ".join(f"{x:.2f}" for x in load[0])
        + ", after "
        + " ".join(f"{x:.2f}" for x in load[1])
        + f" on {os.cpu_count()} CPUs"
    )


if __name__ == "__main__":
    main()
