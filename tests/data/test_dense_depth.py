"""Triangle rasteriser of the dense depth map (SMoE §3.2) against SciPy's linear interpolation, the
independence of results computed with reused work buffers, and the memory those buffers hold."""

import threading

import numpy as np
import pytest
from scipy.interpolate import LinearNDInterpolator
from scipy.spatial import Delaunay

from ablate.data import triangles
from ablate.data.kitti import Calibration, read_image, read_velodyne
from ablate.data.lidar import dense_depth, sparse_depth
from ablate.data.triangles import raster_triangles


def random_sparse(seed: int, shape=(30, 40), n=60) -> np.ndarray:
    rng = np.random.default_rng(seed)
    sp = np.zeros(shape, np.float32)
    lin = rng.choice(shape[0] * shape[1], n, replace=False)
    sp.ravel()[lin] = rng.uniform(2.0, 80.0, n).astype(np.float32)
    return sp


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_raster_matches_scipy_on_its_own_triangles(seed):
    sp = random_sparse(seed)
    h, w = sp.shape
    ys, xs = np.nonzero(sp)
    pts = np.stack([xs, ys], 1).astype(np.float64)
    tri = Delaunay(pts)
    out = np.full(h * w, np.nan)
    count = raster_triangles(pts[tri.simplices].astype(np.float32), sp.ravel(), w, out)
    lin = np.flatnonzero(~np.isnan(out))
    assert count == len(lin)  # a pixel on a shared edge is drawn once
    gy, gx = np.divmod(lin, w)
    ref = LinearNDInterpolator(tri, sp[ys, xs].astype(np.float64))(np.stack([gx, gy], 1))
    np.testing.assert_allclose(out[lin], ref, rtol=0, atol=1e-9)
    # Every pixel centre strictly inside the hull is drawn (boundary pixels may or may not be).
    all_y, all_x = np.mgrid[:h, :w]
    q = np.stack([all_x.ravel(), all_y.ravel()], 1).astype(np.float64)
    strictly = tri.find_simplex(q) >= 0
    for a, b in tri.convex_hull:  # drop pixel centres on a hull edge
        d = pts[b] - pts[a]
        cross = d[0] * (q[:, 1] - pts[a, 1]) - d[1] * (q[:, 0] - pts[a, 0])
        strictly &= np.abs(cross) > 1e-9
    drawn = np.zeros(h * w, bool)
    drawn[lin] = True
    assert drawn[strictly].all()


def test_results_do_not_share_buffers():
    a_in, b_in = random_sparse(3), random_sparse(4)
    a = dense_depth(a_in)
    a_copy = a.copy()
    b = dense_depth(b_in)
    np.testing.assert_array_equal(a, a_copy)  # the second call leaves the first result alone
    assert not np.shares_memory(a, b)
    np.testing.assert_array_equal(dense_depth(a_in), a_copy)  # deterministic
    np.testing.assert_array_equal(a[a_in > 0], a_in[a_in > 0])


def test_tiny_and_collinear_inputs():
    sp = np.zeros((5, 6), np.float32)
    sp[1, 1], sp[1, 3], sp[1, 5] = 4.0, 6.0, 8.0  # collinear: no triangle, nearest fill only
    dd = dense_depth(sp)
    assert dd[4, 0] == 4.0 and dd[0, 5] == 8.0 and dd[3, 3] == 6.0
    sp = np.zeros((3, 3), np.float32)
    sp[0, 0] = 7.0
    assert (dense_depth(sp) == 7.0).all()


def test_blocks_do_not_change_results(monkeypatch):
    """Rasterising in blocks of a few spans, pixels and triangles gives the same bits as in one block."""
    sp = random_sparse(5, shape=(60, 90), n=400)
    sp[3, 2], sp[57, 88], sp[1, 85] = 5.0, 9.0, 70.0  # a few long spans and tall triangles
    whole = dense_depth(sp)
    for name, size in (("SPANS", 7), ("PIXELS", 5), ("TRIANGLES", 3)):
        monkeypatch.setattr(triangles, name, size)
    np.testing.assert_array_equal(dense_depth(sp), whole)


def test_buffers_after_full_resolution_frames(kitti_root):
    """A worker's reused buffers stay under 20 MB after full-resolution KITTI frames (a fresh thread holds only
    what dense_depth kept)."""
    obj = kitti_root / "object" / "training"
    frames = []
    for frame in ("000000", "000001", "000006"):
        shape = read_image(obj / "image_2" / f"{frame}.png").shape[:2]
        assert shape[1] >= 1224 and shape[0] >= 370
        frames.append(
            sparse_depth(
                read_velodyne(obj / "velodyne" / f"{frame}.bin"),
                Calibration.from_file(obj / "calib" / f"{frame}.txt"),
                shape,
            )
        )
    held = []

    def worker():
        for sp in frames:
            dense_depth(sp)
            held.append(triangles.scratch.nbytes())

    t = threading.Thread(target=worker)
    t.start()
    t.join()
    assert len(held) == 3 and max(held) < 20e6, held
