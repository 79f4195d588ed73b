"""Vectorised ray casting of procedural road scenes: ground planes and yaw-rotated boxes.

Everything is in KITTI's rectified camera frame: x right, y down, z forward (metres); the road plane is
``y = CAMERA_HEIGHT``. A scene is a dict of numpy arrays (see :func:`ablate.data.synth.sample_scene`)."""

from __future__ import annotations

from typing import TypeVar

import numpy as np

CAMERA_HEIGHT = 1.65  # KITTI's camera height above the road (m)
SKY, ROAD, BORDER, BOX = 0, 1, 2, 3  # surface kinds
#: What the elementwise geometry below takes and gives: one value or an array of them.
Num = TypeVar("Num", float, np.ndarray)


def road_centre(scene: dict, z: Num) -> Num:
    """Lateral position of the road centre line at depth z (a parabola: offset + curvature z^2 / 2)."""
    return scene["offset"] + 0.5 * scene["curvature"] * z * z


def to_world(yaw: Num, lx: Num, lz: Num) -> tuple[Num, Num]:
    """A box-frame horizontal offset (local x along the length, local z along the width) in the camera frame."""
    c, s = np.cos(yaw), np.sin(yaw)
    return c * lx + s * lz, -s * lx + c * lz


def intersect_boxes(origin: np.ndarray, dirs: np.ndarray, boxes: np.ndarray) -> dict[str, np.ndarray]:
    """Slab test of R rays against B yaw-rotated boxes.

    boxes: (B,7) = centre x, bottom y, centre z, half length (local x), half height, half width (local z), yaw.
    Returns per ray: ``t`` nearest hit distance (inf where none), ``box`` index of the box hit (-1), ``axis`` hit
    face axis (0/1/2), ``local`` (R,3) the hit in the box frame (x along the length, height above the box bottom,
    z along the width); and ``any_hit`` (B,R) bool: whether each box lies on each ray at all (ignoring the others).
    Rays are tested only against boxes whose bounding sphere they pass through."""
    r = len(dirs)
    any_hit = np.zeros((len(boxes), r), bool)
    best_t = np.full(r, np.inf, np.float32)
    best_b = np.full(r, -1, np.int64)
    best_axis = np.zeros(r, np.int8)
    local = np.zeros((r, 3), np.float32)
    unit = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    for b, (cx, by, cz, hl, hh, hw, yaw) in enumerate(boxes):
        v = np.array([cx, by - hh, cz]) - origin
        along = unit @ v
        radius2 = hl * hl + hh * hh + hw * hw
        idx = np.flatnonzero((v @ v - along * along <= radius2) & (along > -np.sqrt(radius2)))
        if not len(idx):
            continue
        d = dirs[idx]
        c, s = np.cos(yaw), np.sin(yaw)
        # World -> box frame: rotate by -yaw around y (KITTI's rotation_y convention).
        ox, oy, oz = origin[0] - cx, origin[1] - (by - hh), origin[2] - cz
        lox, loz = c * ox - s * oz, s * ox + c * oz
        ldx, ldz = c * d[:, 0] - s * d[:, 2], s * d[:, 0] + c * d[:, 2]
        n = len(idx)
        t_near = np.full(n, -np.inf, np.float32)
        t_far = np.full(n, np.inf, np.float32)
        axis = np.zeros(n, np.int8)
        with np.errstate(divide="ignore", invalid="ignore"):
            for k, (o, dd, half) in enumerate(((lox, ldx, hl), (oy, d[:, 1], hh), (loz, ldz, hw))):
                inv = 1.0 / dd
                t1, t2 = (-half - o) * inv, (half - o) * inv
                lo, hi = np.minimum(t1, t2), np.maximum(t1, t2)
                lo = np.where(np.isnan(lo), -np.inf, lo)
                hi = np.where(np.isnan(hi), np.inf, hi)
                axis = np.where(lo > t_near, k, axis).astype(np.int8)
                t_near = np.maximum(t_near, lo)
                t_far = np.minimum(t_far, hi)
        on = (t_near <= t_far) & (t_near > 1e-3)
        any_hit[b, idx] = on
        hit = on & (t_near < best_t[idx])
        j = idx[hit]
        th = t_near[hit]
        best_t[j], best_b[j], best_axis[j] = th, b, axis[hit]
        local[j] = np.stack([lox + th * ldx[hit], hh - (oy + th * d[hit, 1]), loz + th * ldz[hit]], 1)
    return {"t": best_t, "box": best_b, "axis": best_axis, "local": local, "any_hit": any_hit}


def box_normals(scene: dict, hit: dict, dirs: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """World normals (M,3) of the box faces hit by the rays ``mask``, turned towards the viewer."""
    yaw = scene["boxes"][hit["box"][mask], 6]
    ax = hit["axis"][mask]
    lx, ly, lz = (ax == 0).astype(np.float32), (ax == 1).astype(np.float32), (ax == 2).astype(np.float32)
    wx, wz = to_world(yaw, lx, lz)
    world = np.stack([wx, ly, wz], 1)
    return world * -np.sign(np.sum(world * dirs[mask], 1, keepdims=True) + 1e-9)


def cast(scene: dict, origin: np.ndarray, dirs: np.ndarray, max_t: float = 1000.0) -> dict[str, np.ndarray]:
    """Cast rays (origin (3,), dirs (R,3)) into the scene.

    Returns t (distance along dirs, inf for sky), kind (SKY/ROAD/BORDER/BOX), box (index or -1), point (R,3),
    lateral offset from the road centre ``dx``, the box face ``axis``, the hit in the box frame ``local`` and
    ``normal`` (R,3): the surface normal facing the ray's origin (ground: up; sky: 0)."""
    dirs = dirs.astype(np.float32)
    boxes = intersect_boxes(origin, dirs, scene["boxes"])
    t_box, box = boxes["t"], boxes["box"]
    with np.errstate(divide="ignore", invalid="ignore"):
        # Raised border plane first: a hit there counts if it lies off the road.
        t_up = (CAMERA_HEIGHT - scene["curb"] - origin[1]) / dirs[:, 1]
        t_road = (CAMERA_HEIGHT - origin[1]) / dirs[:, 1]
    t_up = np.where(t_up > 0, t_up, np.inf)
    t_road = np.where(t_road > 0, t_road, np.inf)
    half = scene["road_half_width"]

    def lateral(t: np.ndarray) -> np.ndarray:
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
    out = {
        "t": t,
        "kind": kind,
        "box": box,
        "point": point,
        "dx": np.where(use_box, 0, dx),
        "axis": boxes["axis"],
        "local": boxes["local"],
        "any_hit": boxes["any_hit"],
    }
    normal = np.zeros((len(t), 3), np.float32)
    normal[(kind == ROAD) | (kind == BORDER), 1] = -1.0
    isbox = kind == BOX
    if isbox.any():
        normal[isbox] = box_normals(scene, out, dirs, isbox)
    out["normal"] = normal
    return out
