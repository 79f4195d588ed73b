"""LiDAR representations: sparse and dense depth maps (SMoE §3.2), jet colouring, DHI image (DGFN §III-B)
and BEV raster (BiFNet §V-A)."""
from __future__ import annotations

import threading

import cv2
import numpy as np

from ablate.data import DataError
from ablate.data.kitti import Calibration
from ablate.data.triangles import KEY, raster_triangles, scratch

LIDAR_HEIGHT = 1.73
"""Height of KITTI's velodyne above the road (m); heights in DHI and BEV are measured from the road plane."""


def project_points(points: np.ndarray, calib: Calibration, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Project points into image_2 and keep the nearest per pixel.

    Returns (pixel index into the flattened (H,W) image, index of the winning point), one entry per hit pixel.
    Pixel (row v, column u) is the one whose centre is nearest to the projection (DGFN §III-B: quantize to the
    nearest integer); points with depth <= 0 (behind the camera) are dropped."""
    h, w = shape
    uv, depth = calib.velo_to_image(points[:, :3])
    idx = np.flatnonzero(depth > 0)
    u = np.rint(uv[idx, 0])
    v = np.rint(uv[idx, 1])
    keep = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    idx, u, v = idx[keep], u[keep].astype(np.int64), v[keep].astype(np.int64)
    lin = v * w + u
    order = np.lexsort((depth[idx], lin))
    lin_sorted = lin[order]
    first = np.ones(len(order), bool)
    first[1:] = lin_sorted[1:] != lin_sorted[:-1]
    return lin_sorted[first], idx[order][first]


def sparse_depth(points: np.ndarray, calib: Calibration, shape: tuple[int, int]) -> np.ndarray:
    """(H,W) float32 depth (z in the rectified camera frame, metres) of the nearest point per pixel; 0 = no return."""
    lin, idx = project_points(points, calib, shape)
    _, depth = calib.velo_to_image(points[idx, :3])
    out = np.zeros(shape[0] * shape[1], np.float32)
    out[lin] = depth
    return out.reshape(shape)


def _nearest_fill(seeds: np.ndarray, lut: np.ndarray, dist: np.ndarray, labels: np.ndarray, out: np.ndarray) -> None:
    """out = lut[label of the nearest seed (zero pixel of `seeds`)], labels numbering the seeds row-major from 1."""
    cv2.distanceTransformWithLabels(seeds, cv2.DIST_L2, 5, dst=dist, labels=labels, labelType=cv2.DIST_LABEL_PIXEL)
    np.take(lut, labels.ravel(), out=out, mode="wrap")  # labels are in range; "wrap" skips a buffered copy


def dense_depth(sparse: np.ndarray) -> np.ndarray:
    """Dense depth map (DDM), SMoE §3.2: Delaunay triangulation of the LiDAR pixels, linear interpolation inside
    the triangles, nearest-neighbour fill outside the convex hull.

    Reading: the triangulation is over the LiDAR pixel centres (integer (column, row)), OpenCV's incremental
    Delaunay (``cv2.Subdiv2D``); where several Delaunay triangulations exist (four or more co-circular pixel
    centres, common on the pixel grid) OpenCV's choice is kept, so values there may differ from SciPy/Qhull's.
    Triangles are rasterised by ablate.data.triangles.raster_triangles (pixel centres on the bottom/right hull
    boundary count as outside). Outside the triangles every pixel takes the depth of its nearest LiDAR pixel by
    ``cv2.distanceTransformWithLabels`` (5x5 L2 mask: nearest up to that mask's distance approximation), computed
    in a second thread while the main one triangulates. LiDAR pixels keep their sparse value exactly.
    Returns (H,W) float32, positive and finite everywhere; deterministic."""
    sparse = np.asarray(sparse, np.float32)
    h, w = sparse.shape
    if max(h, w) >= KEY:
        raise DataError(f"dense_depth: image {w}x{h} too large (each side must be < {KEY})")
    flat = sparse.ravel()
    seeds = scratch("dense.seeds", (h, w), np.uint8)
    lidar = np.greater(sparse, 0, out=seeds.view(bool))
    lin_seed = np.flatnonzero(lidar)
    if len(lin_seed) == 0:
        raise DataError("dense_depth: the sparse depth map has no LiDAR return (all zeros)")
    np.logical_not(lidar, out=lidar)  # seeds: 0 at the LiDAR pixels, 1 elsewhere
    ys, xs = np.divmod(lin_seed, w)
    depth = flat[lin_seed]
    lut = np.concatenate([[0], depth]).astype(np.float32)
    out = np.empty(h * w, np.float32)
    fill = threading.Thread(target=_nearest_fill, args=(seeds, lut, scratch("dense.dist", (h, w), np.float32),
                                                         scratch("dense.labels", (h, w), np.int32), out))
    fill.start()
    try:
        tri = None
        if len(ys) >= 3:
            sub = cv2.Subdiv2D((-1, -1, w + 2, h + 2))
            order = np.argsort(xs.astype(np.uint16), kind="stable")  # column-major insertion keeps OpenCV's
            # point location walk short
            sub.insert(np.stack([xs[order], ys[order]], 1).astype(np.float32))
            tri = np.asarray(sub.getTriangleList(), np.float32).reshape(-1, 3, 2)  # () when all collinear
            if len(tri) and tri.min() < 0:  # drop the triangles on Subdiv2D's outer virtual vertices (each has a
                # coordinate < 0); getTriangleList of OpenCV 4 leaves them out already
                real = np.ones(len(tri), bool)
                for k in range(3):
                    real &= (tri[:, k, 0] >= 0) & (tri[:, k, 0] < w) & (tri[:, k, 1] >= 0) & (tri[:, k, 1] < h)
                tri = tri[real]
    finally:
        fill.join()
    if tri is not None:
        raster_triangles(tri, flat, w, out)  # the triangles overwrite the nearest fill inside the hull
    out[lin_seed] = depth
    out = out.reshape(h, w)
    np.maximum(out, depth.min(), out=out)  # interpolation cannot leave the range of its vertices
    return out


def jet(depth: np.ndarray, max_depth: float = 80.0) -> np.ndarray:
    """Jet colourisation of a depth map (SMoE §3.2, Fig. 2): (H,W,3) uint8 RGB, near = red, far = blue,
    depth clipped to [0, max_depth]."""
    scaled = np.clip(np.asarray(depth, np.float32) / max_depth, 0.0, 1.0)
    gray = np.round(255.0 * (1.0 - scaled)).astype(np.uint8)
    return cv2.cvtColor(cv2.applyColorMap(gray, cv2.COLORMAP_JET), cv2.COLOR_BGR2RGB)


def dhi_image(points: np.ndarray, calib: Calibration, shape: tuple[int, int], max_x: float = 80.0,
              max_z: float = 6.0, max_r: float = 0.7, lidar_height: float = LIDAR_HEIGHT) -> np.ndarray:
    """Depth-height-intensity image, DGFN §III-B eq. (2)-(4): ``val = 255 (1 - min[v / max_v, 1])`` for
    v = x (velodyne forward distance), z (height) and r (reflectance), at the nearest point of each pixel.

    Height reference: the DGFN range z in [0, max_z] only makes sense above the road, so z is measured from the
    road plane, ``z = z_velo + lidar_height`` (KITTI's velodyne sits 1.73 m up), clipped below at 0.
    Pixels with no return are 0 in every channel. Returns (H,W,3) uint8."""
    lin, idx = project_points(points, calib, shape)
    p = points[idx]
    ref = np.stack([p[:, 0] / max_x, (p[:, 2] + lidar_height) / max_z, p[:, 3] / max_r], 1)
    val = 255.0 * (1.0 - np.minimum(np.clip(ref, 0.0, None), 1.0))
    out = np.zeros((shape[0] * shape[1], 3), np.uint8)
    out[lin] = np.round(val).astype(np.uint8)
    return out.reshape(shape[0], shape[1], 3)


def bev_grid(x_range: tuple[float, float] = (6.0, 46.0), y_range: tuple[float, float] = (-10.0, 10.0),
             cell: float = 0.5) -> tuple[int, int]:
    """(Hb, Wb) of the BEV raster: rows run along x (far at row 0), columns along y (left at column 0)."""
    return int(round((x_range[1] - x_range[0]) / cell)), int(round((y_range[1] - y_range[0]) / cell))


def bev_cells(points: np.ndarray, x_range=(6.0, 46.0), y_range=(-10.0, 10.0), cell: float = 0.5):
    """Flat BEV cell index of each point inside the ranges, and the mask of those points."""
    hb, wb = bev_grid(x_range, y_range, cell)
    row = np.floor((x_range[1] - points[:, 0]) / cell).astype(np.int64)
    col = np.floor((y_range[1] - points[:, 1]) / cell).astype(np.int64)
    keep = (row >= 0) & (row < hb) & (col >= 0) & (col < wb)
    return row[keep] * wb + col[keep], keep


def bev_image(points: np.ndarray, x_range: tuple[float, float] = (6.0, 46.0),
              y_range: tuple[float, float] = (-10.0, 10.0), cell: float = 0.5,
              lidar_height: float = LIDAR_HEIGHT) -> np.ndarray:
    """BEV raster, BiFNet §V-A: 0.5 m cells holding max, min and mean height, then max, min and mean intensity of
    the points in each cell; 0 where a cell is empty. Height is above the road (z_velo + lidar_height).
    Default ranges are the KITTI road benchmark's BEV (x 6-46 m ahead, y 10 m either side).
    Returns (6,Hb,Wb) float32."""
    hb, wb = bev_grid(x_range, y_range, cell)
    lin, keep = bev_cells(points, x_range, y_range, cell)
    z = points[keep, 2].astype(np.float64) + lidar_height
    r = points[keep, 3].astype(np.float64)
    n = hb * wb
    count = np.bincount(lin, minlength=n)
    out = np.zeros((6, n), np.float64)
    for k, v in ((0, z), (3, r)):
        mx = np.full(n, -np.inf)
        mn = np.full(n, np.inf)
        np.maximum.at(mx, lin, v)
        np.minimum.at(mn, lin, v)
        out[k], out[k + 1] = mx, mn
        out[k + 2] = np.bincount(lin, weights=v, minlength=n) / np.maximum(count, 1)
    out[:, count == 0] = 0.0
    return out.reshape(6, hb, wb).astype(np.float32)
