"""LiDAR representations: sparse and dense depth maps (SMoE §3.2), jet colouring, DHI image (DGFN §III-B),
BEV raster (BiFNet §V-A), and the dense heights per pixel and per BEV cell of BiFNet's DST (§IV-A1, §IV-A2)."""

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
    fill = threading.Thread(
        target=_nearest_fill,
        args=(seeds, lut, scratch("dense.dist", (h, w), np.float32), scratch("dense.labels", (h, w), np.int32), out),
    )
    fill.start()
    try:
        tri = None
        if len(ys) >= 3:
            sub = cv2.Subdiv2D((-1, -1, w + 2, h + 2))
            order = np.argsort(xs.astype(np.uint16), kind="stable")  # column-major insertion keeps OpenCV's
            # point location walk short
            # an (N,2) float32 array is a vector of points to OpenCV; its stubs only know Sequence[Sequence[float]]
            sub.insert(np.stack([xs[order], ys[order]], 1).astype(np.float32))  # type: ignore[call-overload]
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


def dhi_image(
    points: np.ndarray,
    calib: Calibration,
    shape: tuple[int, int],
    max_x: float = 80.0,
    max_z: float = 6.0,
    max_r: float = 0.7,
    lidar_height: float = LIDAR_HEIGHT,
) -> np.ndarray:
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


def bev_grid(
    x_range: tuple[float, float] = (6.0, 46.0), y_range: tuple[float, float] = (-10.0, 10.0), cell: float = 0.5
) -> tuple[int, int]:
    """(Hb, Wb) of the BEV raster: rows run along x (far at row 0), columns along y (left at column 0)."""
    return int(round((x_range[1] - x_range[0]) / cell)), int(round((y_range[1] - y_range[0]) / cell))


def bev_cells(
    points: np.ndarray,
    x_range: tuple[float, float] = (6.0, 46.0),
    y_range: tuple[float, float] = (-10.0, 10.0),
    cell: float = 0.5,
) -> tuple[np.ndarray, np.ndarray]:
    """Flat BEV cell index of each point inside the ranges, and the mask of those points."""
    hb, wb = bev_grid(x_range, y_range, cell)
    row = np.floor((x_range[1] - points[:, 0]) / cell).astype(np.int64)
    col = np.floor((y_range[1] - points[:, 1]) / cell).astype(np.int64)
    keep = (row >= 0) & (row < hb) & (col >= 0) & (col < wb)
    return row[keep] * wb + col[keep], keep


def bev_image(
    points: np.ndarray,
    x_range: tuple[float, float] = (6.0, 46.0),
    y_range: tuple[float, float] = (-10.0, 10.0),
    cell: float = 0.5,
    lidar_height: float = LIDAR_HEIGHT,
) -> np.ndarray:
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


#: DST's height upsampling (BiFNet §IV-A1, §IV-A2): window radius (px) of the perspective neighbourhood, azimuth
#: width (degrees) of a column of the range-image arrangement, and points closer than MIN_RANGE (m) dropped.
HEIGHT_WINDOW, AZIMUTH_RES, MIN_RANGE = 4, 0.2, 2.0


def perspective_height(
    points: np.ndarray, calib: Calibration, shape: tuple[int, int], window: int = HEIGHT_WINDOW
) -> np.ndarray:
    """Dense LiDAR height per image pixel, BiFNet §IV-A1 eq. (2): the projected points in a (2 window + 1)^2
    neighbourhood of the pixel, weighted by 1 / (1 + their distance in pixels) and normalised by the sum of the
    weights (eq. (2)'s normalisation parameter). Reading where the text lost its symbols: the weight decays with the
    image distance between the pixel and the neighbour's projection (the nearest point per pixel,
    :func:`project_points`); a pixel with no projected point in its window takes the height of the nearest one.
    Height is z in the velodyne frame (m), as the paper's "height of this pixel in LiDAR coordinate".
    Returns (H,W) float32."""
    if window < 0:
        raise DataError(f"perspective_height: window must be >= 0 px, got {window}")
    h, w = shape
    lin, idx = project_points(points, calib, shape)
    if len(lin) == 0:
        raise DataError("perspective_height: no LiDAR point projects into the image")
    sparse: np.ndarray
    mask: np.ndarray
    sparse, mask = np.zeros(h * w, np.float32), np.zeros(h * w, np.float32)
    sparse[lin], mask[lin] = points[idx, 2], 1.0
    sparse, mask = sparse.reshape(h, w), mask.reshape(h, w)
    r = np.arange(-window, window + 1, dtype=np.float32)
    kernel = 1.0 / (1.0 + np.hypot(r[:, None], r[None, :]))
    num = cv2.filter2D(sparse, cv2.CV_32F, kernel, borderType=cv2.BORDER_CONSTANT)
    den = cv2.filter2D(mask, cv2.CV_32F, kernel, borderType=cv2.BORDER_CONSTANT)
    out: np.ndarray = np.empty(h * w, np.float32)
    seeds = (mask == 0).astype(np.uint8)  # 0 at the LiDAR pixels
    _nearest_fill(
        seeds,
        np.concatenate([[0], sparse.ravel()[np.flatnonzero(mask.ravel())]]).astype(np.float32),
        np.empty((h, w), np.float32),
        np.empty((h, w), np.int32),
        out,
    )
    out = out.reshape(h, w)
    near = den > 1e-6
    out[near] = num[near] / den[near]
    return out


def bev_height(
    points: np.ndarray,
    x_range: tuple[float, float] = (6.0, 46.0),
    y_range: tuple[float, float] = (-10.0, 10.0),
    cell: float = 0.5,
    azimuth_res: float = AZIMUTH_RES,
    min_range: float = MIN_RANGE,
) -> np.ndarray:
    """Dense LiDAR height per BEV cell, BiFNet §IV-A2 eq. (3)-(4), on the grid of :func:`bev_image`.

    The points are arranged as MV3D's front view (Chen et al. [6]): column = floor(atan2(y, x) / azimuth_res), the
    lasers stacked in it. A cell's centre falls in one column (the nearest non-empty one when its own is empty);
    its neighbours there (eq. (3)) are the points just nearer and just farther in horizontal distance
    sqrt(x^2 + y^2), and its height (eq. (4)) their heights interpolated linearly in horizontal distance (the one
    neighbour's height before the nearest or beyond the farthest point). Height is z in the velodyne frame (m).
    Returns (Hb,Wb) float32."""
    if azimuth_res <= 0:
        raise DataError(f"bev_height: azimuth_res must be > 0 degrees, got {azimuth_res}")
    hb, wb = bev_grid(x_range, y_range, cell)
    pts = np.asarray(points, np.float64)
    dist = np.hypot(pts[:, 0], pts[:, 1])
    keep = dist > min_range
    if not keep.any():
        raise DataError(f"bev_height: no LiDAR point beyond {min_range} m")
    res = np.deg2rad(azimuth_res)
    col, dist, z = np.floor(np.arctan2(pts[keep, 1], pts[keep, 0]) / res).astype(np.int64), dist[keep], pts[keep, 2]
    order = np.lexsort((dist, col))
    col, dist, z = col[order], dist[order], z[order]
    x, y = np.meshgrid(
        x_range[1] - (np.arange(hb) + 0.5) * cell, y_range[1] - (np.arange(wb) + 0.5) * cell, indexing="ij"
    )
    cdist, ccol = np.hypot(x, y).ravel(), np.floor(np.arctan2(y, x) / res).astype(np.int64).ravel()
    filled = np.unique(col)
    k = np.clip(np.searchsorted(filled, ccol), 1, max(len(filled) - 1, 1))
    lower, upper = filled[k - 1], filled[np.minimum(k, len(filled) - 1)]
    ccol = np.where(np.abs(ccol - lower) <= np.abs(upper - ccol), lower, upper)
    start, end = np.searchsorted(col, ccol, "left"), np.searchsorted(col, ccol, "right")
    span = dist.max() + 1.0  # (column, distance) as one sortable key
    i = np.searchsorted(col * span + dist, ccol * span + cdist)  # first point of the column at or beyond the cell
    right, left = np.clip(i, start, end - 1), np.clip(i - 1, start, end - 1)
    gap = dist[right] - dist[left]
    t = np.where(gap > 1e-9, (cdist - dist[left]) / np.where(gap > 1e-9, gap, 1.0), 0.0)
    return (z[left] + np.clip(t, 0.0, 1.0) * (z[right] - z[left])).reshape(hb, wb).astype(np.float32)


def bev_points(
    points: np.ndarray,
    x_range: tuple[float, float] = (6.0, 46.0),
    y_range: tuple[float, float] = (-10.0, 10.0),
    cell: float = 0.5,
    max_points: int = 16384,
) -> np.ndarray:
    """The points inside the BEV grid as (max_points, 3) float32 x, y, z (velodyne), NaN rows after the last, for
    sparse transforms through the points themselves (SHPL). More points than ``max_points``: an evenly strided
    subset."""
    _, keep = bev_cells(points, x_range, y_range, cell)
    inside = np.asarray(points, np.float32)[keep, :3]
    if len(inside) > max_points:
        inside = inside[np.linspace(0, len(inside) - 1, max_points).astype(np.int64)]
    out = np.full((max_points, 3), np.nan, np.float32)
    out[: len(inside)] = inside
    return out
