"""Dense depth (SMoE §3.2) of full-resolution real KITTI frames: ablate.data.lidar.dense_depth against the plain
SciPy pipeline (Delaunay + LinearNDInterpolator + NearestNDInterpolator), in the same run. Prints figures."""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
from scipy.interpolate import LinearNDInterpolator, NearestNDInterpolator
from scipy.spatial import Delaunay

from ablate.data.kitti import Calibration, read_image, read_velodyne
from ablate.data.lidar import dense_depth, sparse_depth

ROOT = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).resolve().parents[2] / "shared/kitti/object/training"


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


def best_of(fn, arg, n):
    times = []
    for _ in range(n):
        t = time.perf_counter()
        res = fn(arg)
        times.append(time.perf_counter() - t)
    return min(times), res


def main() -> None:
    ratios = []
    for frame in ("000000", "000001", "000006"):
        calib = Calibration.from_file(ROOT / "calib" / f"{frame}.txt")
        shape = read_image(ROOT / "image_2" / f"{frame}.png").shape[:2]
        sparse = sparse_depth(read_velodyne(ROOT / "velodyne" / f"{frame}.bin"), calib, shape)
        t_ours, ours = best_of(dense_depth, sparse, 5)
        t_ref, (ref, hull) = best_of(scipy_dense, sparse, 2)
        diff = np.abs(ours - ref)[hull]
        ratios.append(t_ref / t_ours)
        print(f"{frame} {shape[1]}x{shape[0]} lidar px {int((sparse > 0).sum())}: ours {t_ours * 1e3:.1f} ms, "
              f"scipy {t_ref * 1e3:.0f} ms, speed-up {t_ref / t_ours:.1f}x; inside hull |diff| median "
              f"{np.median(diff):.2e} m, mean {diff.mean():.3f} m, p90 {np.percentile(diff, 90):.3f} m")
    print(f"speed-up over frames: min {min(ratios):.1f}x, median {np.median(ratios):.1f}x (target >= 10x)")


if __name__ == "__main__":
    main()
