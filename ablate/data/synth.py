"""Procedural road scenes rendered by ray casting, with a KITTI-like camera and a 64-beam spinning LiDAR.

One random generator per frame, seeded by (seed, frame index), so the same seed gives the same bytes
whatever the number of worker processes. Each scene mixes cues that only one sensor carries:

- camera only: road versus a flat border of the same height and reflectance (colour and texture tell them
  apart), lane markings, facade texture;
- LiDAR only: a raised kerb whose sidewalk has the road's colour and texture, cars and pedestrians painted
  like the road behind them (height and distance tell them apart), distances.

Objects: parked and moving cars (a body and a cabin box), pedestrians on sidewalks and crossing; buildings or
walls on either side or open land (then the road is visible beyond 60 m).
"""
from __future__ import annotations

import numpy as np

from ablate.data.raycast import BORDER, BOX, CAMERA_HEIGHT, ROAD, SKY, road_centre

KITTI_P2 = (721.5377, 609.5593, 172.854, 1242, 375)  # focal, cx, cy, width, height
LIDAR_ORIGIN = np.array([0.0, -0.08, -0.27])  # velodyne origin in the camera frame (1.73 m above the road)
BEAMS = np.linspace(2.0, -24.8, 64)  # HDL-64E elevation angles (degrees), top to bottom
CAR, PEDESTRIAN, BUILDING = 0, 1, 2
CLASS_NAMES = {CAR: "Car", PEDESTRIAN: "Pedestrian"}


def camera_matrix(height: int, width: int) -> np.ndarray:
    """KITTI's P2 scaled to the chosen resolution (square pixels, scaled by width; cy scaled by height)."""
    f, cx, cy, w0, h0 = KITTI_P2
    s = width / w0
    return np.array([[f * s, 0, cx * s, 0], [0, f * s, cy * height / h0, 0], [0, 0, 1, 0]], np.float64)


def sample_scene(rng: np.random.Generator) -> dict:
    """Road layout, border mode, palette, buildings, cars and pedestrians of one frame."""
    road_grey = rng.uniform(0.25, 0.45)
    mode = rng.choice(["kerb_distinct", "kerb_camouflaged", "flat_distinct"])
    s = {"offset": rng.uniform(-1.5, 1.5), "curvature": rng.uniform(-1, 1) / 250.0,
         "road_half_width": rng.uniform(3.0, 7.0), "sidewalk": rng.uniform(1.5, 3.5),
         "curb": 0.0 if mode == "flat_distinct" else rng.uniform(0.12, 0.2), "mode": mode,
         "road_rgb": road_grey * rng.uniform(0.92, 1.08, 3), "road_refl": rng.uniform(0.15, 0.35),
         "exposure": rng.uniform(0.75, 1.2), "sun": _unit(rng.uniform([-0.6, -1.0, -0.6], [0.6, -0.4, 0.6])),
         "tex_seed": int(rng.integers(1 << 30)), "lane_dash": rng.uniform(2.0, 4.0)}
    if mode == "kerb_camouflaged":
        s["border_rgb"], s["border_refl"] = s["road_rgb"] * rng.uniform(0.97, 1.03), s["road_refl"]
    else:
        palette = [(0.25, 0.45, 0.15), (0.5, 0.42, 0.3), (0.6, 0.6, 0.58), (0.35, 0.3, 0.25)]
        s["border_rgb"] = np.array(palette[rng.integers(len(palette))]) * rng.uniform(0.8, 1.2)
        s["border_refl"] = s["road_refl"] if mode == "flat_distinct" else rng.uniform(0.05, 0.6)
    boxes, owner, cls, rgb, refl = [], [], [], [], []

    def add(box, own, c, colour, r):
        boxes.append(box), owner.append(own), cls.append(c), rgb.append(colour), refl.append(r)

    half, side = s["road_half_width"], s["sidewalk"]
    for sign in (-1, 1):  # buildings / walls or open land on each side
        if rng.random() < 0.25:
            continue
        z = rng.uniform(-5, 5)
        while z < 90:
            length = rng.uniform(6, 25)
            zc = z + length / 2
            lateral = sign * (half + side + rng.uniform(0.3, 4.0))
            height = rng.uniform(2.5, 14.0) if rng.random() < 0.8 else rng.uniform(1.0, 2.5)
            depth = rng.uniform(4, 12)
            xc = road_centre(s, zc) + lateral + sign * depth / 2
            yaw = np.pi / 2 + np.arctan(s["curvature"] * zc)
            add((xc, CAMERA_HEIGHT - s["curb"], zc, length / 2, height / 2, depth / 2, yaw), -1, BUILDING,
                rng.uniform(0.2, 0.85, 3), rng.uniform(0.1, 0.6))
            z += length + rng.uniform(0, 8)
    placed: list[tuple[float, float, float]] = []
    objects: list[tuple] = []  # (class, x, bottom y, z, l, h, w, yaw) in the camera frame
    n_obj = 0
    for _ in range(int(rng.integers(2, 12))):
        is_car = rng.random() < 0.7
        zc = 4 + 60 * rng.random() ** 1.5 if rng.random() < 0.85 else rng.uniform(60, 100)
        if is_car:
            where = rng.choice(["parked", "lane"])
            lat = np.sign(rng.uniform(-1, 1)) * (half - 1.2 if where == "parked" else rng.uniform(0.2, 0.6) * half)
            dims = (rng.uniform(3.5, 4.8), rng.uniform(1.4, 1.65), rng.uniform(1.6, 1.9))  # l h w
            base = CAMERA_HEIGHT
        else:
            on_road = rng.random() < 0.3
            lat = rng.uniform(-half, half) if on_road else np.sign(rng.uniform(-1, 1)) * (half + rng.uniform(0.4, side))
            dims = (rng.uniform(0.35, 0.6), rng.uniform(1.5, 1.9), rng.uniform(0.45, 0.7))
            base = CAMERA_HEIGHT if on_road else CAMERA_HEIGHT - s["curb"]
        xc = road_centre(s, zc) + lat
        radius = max(dims[0], dims[2]) / 2 + 0.3
        if any(np.hypot(xc - px, zc - pz) < radius + pr for px, pz, pr in placed) or abs(xc) < 0.9 and zc < 6:
            continue
        placed.append((xc, zc, radius))
        yaw = np.arctan(s["curvature"] * zc) + rng.normal(0, 0.08) - np.pi / 2
        if rng.random() < 0.5:
            yaw += np.pi
        camo = rng.random() < 0.25
        colour = (s["border_rgb"] if base < CAMERA_HEIGHT else s["road_rgb"]) if camo else rng.uniform(0.05, 0.95, 3)
        l, h, w = dims
        if is_car:
            add((xc, base - 0.15, zc, l / 2, h * 0.3, w / 2, yaw), n_obj, CAR, colour, rng.uniform(0.3, 0.7))
            add((xc, base - 0.15 - h * 0.6, zc, l * 0.28, (h * 0.4 - 0.15) / 2, w * 0.45, yaw),
                n_obj, CAR, colour * 0.85, rng.uniform(0.1, 0.3))
        else:
            add((xc, base, zc, l / 2, h / 2, w / 2, yaw), n_obj, PEDESTRIAN, colour, rng.uniform(0.2, 0.5))
        objects.append((CAR if is_car else PEDESTRIAN, xc, base, zc, l, h, w, yaw))
        n_obj += 1
    s["boxes"] = np.array(boxes, np.float32).reshape(-1, 7)
    s["owner"], s["cls"] = np.array(owner, np.int64), np.array(cls, np.int64)
    s["box_rgb"], s["box_refl"] = np.array(rgb, np.float32).reshape(-1, 3), np.array(refl, np.float32)
    s["objects"] = objects
    return s


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _noise(a: np.ndarray, b: np.ndarray, seed: int, scale: float) -> np.ndarray:
    """Value noise in [0, 1) on a grid of ``scale`` metres, hashed from world coordinates (deterministic)."""
    ia = np.floor(a / scale).astype(np.int64)
    ib = np.floor(b / scale).astype(np.int64)
    h = (ia * 73856093) ^ (ib * 19349663) ^ seed
    h = (h ^ (h >> 13)) * 1274126177
    return ((h ^ (h >> 16)) & 0xFFFF).astype(np.float32) / 65536.0


def shade(scene: dict, hit: dict, dirs: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
    """RGB in [0, 1] of every camera ray: albedo x texture x Lambertian sun + ambient, sky gradient."""
    p, kind, box = hit["point"], hit["kind"], hit["box"]
    n = len(kind)
    rgb = np.zeros((n, 3), np.float32)
    seed = scene["tex_seed"]
    tex = 0.8 + 0.4 * (0.6 * _noise(p[:, 0], p[:, 2], seed, 0.15) + 0.4 * _noise(p[:, 0], p[:, 2], seed + 1, 0.6))
    ground = (kind == ROAD) | (kind == BORDER)
    rgb[kind == ROAD] = scene["road_rgb"]
    rgb[kind == BORDER] = scene["border_rgb"]
    dx, half = hit["dx"], scene["road_half_width"]
    dash = (np.mod(p[:, 2], 2 * scene["lane_dash"]) < scene["lane_dash"]) & (np.abs(dx) < 0.08)
    edge = np.abs(np.abs(dx) - (half - 0.25)) < 0.08
    rgb[(kind == ROAD) & (dash | edge)] = 0.9
    isbox = kind == BOX
    rgb[isbox] = scene["box_rgb"][box[isbox]]
    building = isbox & (scene["cls"][np.maximum(box, 0)] == BUILDING)
    facade = _noise(p[:, 0] + p[:, 2], p[:, 1], seed + 2, 1.2)
    rgb[building] *= (0.55 + 0.45 * (facade[building] > 0.35))[:, None]
    normal = np.zeros((n, 3), np.float32)
    normal[ground, 1] = -1.0
    if isbox.any():
        yaw = scene["boxes"][box[isbox], 6]
        ax = hit["axis"][isbox]
        local = np.stack([ax == 0, ax == 1, ax == 2], 1).astype(np.float32)
        world = np.stack([np.cos(yaw) * local[:, 0] + np.sin(yaw) * local[:, 2], local[:, 1],
                          -np.sin(yaw) * local[:, 0] + np.cos(yaw) * local[:, 2]], 1)
        world *= -np.sign(np.sum(world * dirs[isbox], 1, keepdims=True) + 1e-9)  # face the viewer
        normal[isbox] = world
    light = 0.45 + 0.75 * np.clip(normal @ -scene["sun"], 0, None)
    rgb = rgb * np.where(ground | isbox, tex, 1.0)[:, None] * light[:, None]
    sky = kind == SKY
    up = np.clip(-dirs[sky, 1] / np.linalg.norm(dirs[sky], axis=1), 0, 1)[:, None]
    rgb[sky] = (1 - up) * np.array([0.75, 0.82, 0.9]) + up * np.array([0.35, 0.55, 0.85])
    return np.clip(rgb * scene["exposure"], 0, 1)


def camera_rays(P2: np.ndarray, height: int, width: int) -> np.ndarray:
    """Ray directions (H*W,3) through every pixel centre, scaled so that their z is 1 (t = depth)."""
    v, u = np.mgrid[:height, :width].astype(np.float32)
    return np.stack([(u - P2[0, 2]) / P2[0, 0], (v - P2[1, 2]) / P2[1, 1], np.ones_like(u)], -1).reshape(-1, 3)


def lidar_rays(width: int, fov: float = 45.0) -> tuple[np.ndarray, np.ndarray]:
    """Unit directions in the camera frame of the 64 beams over azimuths +-fov degrees, with an azimuth step of
    KITTI's 0.09 deg scaled by 1242 / width (so the scan density per pixel matches KITTI's); also the
    (N,3) velodyne-frame directions."""
    step = 0.09 * KITTI_P2[3] / width
    az = np.deg2rad(np.arange(-fov, fov + 1e-9, step))
    el = np.deg2rad(BEAMS)
    el, az = np.meshgrid(el, az, indexing="ij")
    velo = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1).reshape(-1, 3)
    return np.stack([-velo[:, 1], -velo[:, 2], velo[:, 0]], 1), velo
