"""Vectorised ray casting of procedural road scenes: ground planes and yaw-rotated boxes.

Everything is in KITTI's rectified camera frame: x right, y down, z forward (metres); the road plane is
``y = CAMERA_HEIGHT``. A scene is a dict of numpy arrays (see :func:`ablate.data.synth.sample_scene`)."""
from __future__ import annotations

import numpy as np

CAMERA_HEIGHT = 1.65  # KITTI's camera height above the road (m)
SKY, ROAD, BORDER, BOX = 0, 1, 2, 3  # surface kinds


def road_centre(scene: dict, z: np.ndarray) -> np.ndarray:
    """Lateral position of the road centre line at depth z (a parabola: offset + curvature z^2 / 2)."""
    return scene["offset"] + 0.5 * scene["curvature"] * z * z


def intersect_boxes(origin: np.ndarray, dirs: np.ndarray, boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Slab test of R rays against B yaw-rotated boxes.

    boxes: (B,7) = centre x, bottom y, centre z, half length (local x), half height, half width (local z), yaw.
    Returns per ray: nearest hit distance t (inf where none), index of the box hit (-1), hit face axis (0/1/2),
    and (B,R) bool: whether each box lies on each ray at all (ignoring the others)."""
    r = len(dirs)
    any_hit = np.zeros((len(boxes), r), bool)
    best_t = np.full(r, np.inf, np.float32)
    best_b = np.full(r, -1, np.int64)
    best_axis = np.zeros(r, np.int8)
    for b, (cx, by, cz, hl, hh, hw, yaw) in enumerate(boxes):
        c, s = np.cos(yaw), np.sin(yaw)
        # World -> box frame: rotate by -yaw around y (KITTI's rotation_y convention).
        ox, oy, oz = origin[0] - cx, origin[1] - (by - hh), origin[2] - cz
        lox, loz = c * ox - s * oz, s * ox + c * oz
        ldx, ldz = c * dirs[:, 0] - s * dirs[:, 2], s * dirs[:, 0] + c * dirs[:, 2]
        t_near = np.full(r, -np.inf, np.float32)
        t_far = np.full(r, np.inf, np.float32)
        axis = np.zeros(r, np.int8)
        with np.errstate(divide="ignore", invalid="ignore"):
            for k, (o, d, half) in enumerate(((lox, ldx, hl), (oy, dirs[:, 1], hh), (loz, ldz, hw))):
                inv = 1.0 / d
                t1, t2 = (-half - o) * inv, (half - o) * inv
                lo, hi = np.minimum(t1, t2), np.maximum(t1, t2)
                lo = np.where(np.isnan(lo), -np.inf, lo)
                hi = np.where(np.isnan(hi), np.inf, hi)
                axis = np.where(lo > t_near, k, axis).astype(np.int8)
                t_near = np.maximum(t_near, lo)
                t_far = np.minimum(t_far, hi)
        any_hit[b] = (t_near <= t_far) & (t_near > 1e-3)
        hit = any_hit[b] & (t_near < best_t)
        best_t = np.where(hit, t_near, best_t)
        best_b = np.where(hit, b, best_b)
        best_axis = np.where(hit, axis, best_axis)
    return best_t, best_b, best_axis, any_hit


def cast(scene: dict, origin: np.ndarray, dirs: np.ndarray, max_t: float = 1000.0) -> dict[str, np.ndarray]:
    """Cast rays (origin (3,), dirs (R,3)) into the scene.

    Returns t (distance along dirs, inf for sky), kind (SKY/ROAD/BORDER/BOX), box (index or -1), point (R,3),
    lateral offset from the road centre ``dx`` and the box face axis."""
    dirs = dirs.astype(np.float32)
    t_box, box, axis, any_hit = intersect_boxes(origin, dirs, scene["boxes"])
    with np.errstate(divide="ignore", invalid="ignore"):
        # Raised border plane first: a hit there counts if it lies off the road.
        t_up = (CAMERA_HEIGHT - scene["curb"] - origin[1]) / dirs[:, 1]
        t_road = (CAMERA_HEIGHT - origin[1]) / dirs[:, 1]
    t_up = np.where(t_up > 0, t_up, np.inf)
    t_road = np.where(t_road > 0, t_road, np.inf)
    half = scene["road_half_width"]

    def lateral(t):
        p = origin + np.where(np.isfinite(t), t, 0)[:, None] * dirs
        return p[:, 0] - road_centre(scene, p[:, 2])

    dx_up = lateral(t_up)
    t_ground = np.where(np.isfinite(t_up) & (np.abs(dx_up) >= half), t_up, t_road)
    dx = lateral(t_ground)
    kind = np.where(np.isfinite(t_ground), np.where(np.abs(dx) < half, ROAD, BORDER), SKY)
    t_ground = np.where(t_ground < max_t, t_ground, np.inf)
    kind = np.where(np.isfinite(t_ground), kind, SKY)
    use_box = t_box < t_ground
    t = np.where(use_box, t_box, t_ground).astype(np.float32)
    kind = np.where(use_box, BOX, kind)
    box = np.where(use_box, box, -1)
    point = origin + np.where(np.isfinite(t), t, 0)[:, None] * dirs
    return {"t": t, "kind": kind, "box": box, "point": point, "dx": np.where(use_box, 0, dx), "axis": axis,
            "any_hit": any_hit}
