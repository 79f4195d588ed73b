"""Procedural road scenes for a KITTI-like camera and an HDL-64E-like spinning LiDAR (rendered by ablate.data.generate).

One random generator per frame, seeded by (seed, frame index), so the same seed gives the same bytes whatever
the number of worker processes. Each scene mixes cues that only one sensor carries:

- camera only: road versus a flat border of the same height and reflectance (colour and texture tell them
  apart), lane markings, facade windows; on objects, colour and parts: a car has dark tyres with rims, glass
  windows framed by pillars, tail and head lights and a shadow on the road beneath it; a pedestrian has head,
  torso and legs in skin and clothing colours. Glass windows, dark paint (reflectance 0.02-0.06 at 905 nm) and
  glossy metallic paint give the LiDAR few or no returns (ablate.data.lidar_physics) while the camera sees them.
- LiDAR only: a raised kerb whose sidewalk has the road's colour and texture, objects painted like the road
  or sidewalk behind them (``camouflaged``: height and distance tell them apart), distances.
- Street furniture (``furniture=True``; off in the data of every published table but where its config sets it):
  poles, tree trunks under their crowns, bollards and bins, hedges along the sidewalks. In depth a hedge is a
  car-sized block and a bin or bollard a pedestrian-sized one; the camera tells them apart by colour, texture and
  shape. Real streets have this clutter: on one pixel grid, KITTI's frames have 4x the generated frames' share of
  background pixels at a depth edge without it (``bench/depth_clutter.py``, docs/recipes.md#instance_cpu).

Car colours follow a fleet-like palette (white, silver, grey, black, red, blue, other) with the reflectance of
each paint at 905 nm; a share of non-black cars has glossy metallic paint. Objects: parked and moving cars,
pedestrians on sidewalks and crossing; buildings or walls on either side (brick, plaster or concrete, with
window rows) or open land (then the road is visible beyond 60 m).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from ablate.data.lidar_physics import GLOSS_EXPONENT
from ablate.data.raycast import CAMERA_HEIGHT, road_centre, to_world

KITTI_P2 = (721.5377, 609.5593, 172.854, 1242, 375)  # focal, cx, cy, width, height
LIDAR_ORIGIN = np.array([0.0, -0.08, -0.27])  # velodyne origin in the camera frame (1.73 m above the road)
BEAMS = np.linspace(2.0, -24.8, 64)  # HDL-64E elevation angles (degrees), top to bottom
CAR, PEDESTRIAN, BUILDING = 0, 1, 2
CLASS_NAMES = {CAR: "Car", PEDESTRIAN: "Pedestrian"}
# Box parts: how the camera shades them and whether their faces are glass.
FACADE, BODY, CABIN, WHEEL, HEAD, TORSO, LEGS, FURNITURE = range(8)
#: Car paints: (share, RGB, reflectance range at 905 nm).
PAINTS = [
    (0.22, (0.88, 0.88, 0.86), (0.6, 0.8)),
    (0.18, (0.66, 0.67, 0.69), (0.4, 0.6)),
    (0.15, (0.38, 0.38, 0.40), (0.2, 0.4)),
    (0.20, (0.045, 0.045, 0.05), (0.02, 0.06)),
    (0.09, (0.62, 0.07, 0.06), (0.3, 0.5)),
    (0.08, (0.09, 0.17, 0.45), (0.1, 0.25)),
    (0.08, None, (0.2, 0.5)),
]
GLOSSY_SHARE = 0.3  # of non-black cars: metallic / clear-coat paint (cos^8 angular response)
FACADES = [
    (0.55, 0.30, 0.22),
    (0.78, 0.70, 0.55),
    (0.60, 0.60, 0.60),
    (0.86, 0.85, 0.80),
    (0.35, 0.35, 0.37),
    (0.80, 0.68, 0.40),
]
SKIN = [(0.87, 0.72, 0.60), (0.62, 0.46, 0.34), (0.38, 0.26, 0.19), (0.95, 0.80, 0.70)]
TROUSERS = [(0.14, 0.19, 0.33), (0.07, 0.07, 0.08), (0.55, 0.50, 0.38), (0.40, 0.40, 0.42)]


def camera_matrix(height: int, width: int) -> np.ndarray:
    """KITTI's P2 scaled to the chosen resolution (square pixels, scaled by width; cy scaled by height)."""
    f, cx, cy, w0, h0 = KITTI_P2
    s = width / w0
    return np.array([[f * s, 0, cx * s, 0], [0, f * s, cy * height / h0, 0], [0, 0, 1, 0]], np.float64)


class _Boxes:
    """Accumulates boxes and their per-box attributes."""

    def __init__(self) -> None:
        self.rows: list[tuple] = []

    def add(
        self,
        box: tuple[float, ...],
        owner: int,
        cls: int,
        part: int,
        rgb: ArrayLike,
        refl: float,
        gloss: float = 1.0,
    ) -> None:
        self.rows.append((box, owner, cls, part, np.asarray(rgb, np.float32), refl, gloss))

    def into(self, s: dict[str, Any]) -> None:
        cols = list(zip(*self.rows)) if self.rows else [()] * 7
        s["boxes"] = np.array(cols[0], np.float32).reshape(-1, 7)
        s["owner"], s["cls"], s["part"] = (np.array(c, np.int64) for c in cols[1:4])
        s["box_rgb"] = np.array(cols[4], np.float32).reshape(-1, 3)
        s["box_refl"], s["box_gloss"] = np.array(cols[5], np.float32), np.array(cols[6], np.float32)


def sample_scene(rng: np.random.Generator, furniture: bool = False) -> dict[str, Any]:
    """Road layout, border mode, palette, sun, buildings, cars and pedestrians of one frame; with ``furniture``,
    street furniture too (drawn last, so the rest of the scene is the same as without it)."""
    s = _road_layout(rng)
    _border(rng, s)
    boxes = _Boxes()
    for sign in (-1, 1):  # buildings / walls or open land on each side
        if rng.random() < 0.25:
            continue
        _buildings(rng, s, boxes, sign)
    placed: list[tuple[float, float, float]] = []
    objects = _road_users(rng, s, boxes, placed)
    if furniture:
        for sign in (-1, 1):
            _street_furniture(rng, s, boxes, sign, placed)
    boxes.into(s)
    s["objects"] = objects
    return s


def _road_layout(rng: np.random.Generator) -> dict[str, Any]:
    """The road (offset, curvature, width, sidewalk, kerb), its colour and reflectance, exposure and the sun."""
    road_grey = rng.uniform(0.25, 0.45)
    mode = rng.choice(["kerb_distinct", "kerb_camouflaged", "flat_distinct"])
    elevation, azimuth = np.deg2rad(rng.uniform(25, 65)), rng.uniform(-np.pi, np.pi)
    return {
        "offset": rng.uniform(-1.5, 1.5),
        "curvature": rng.uniform(-1, 1) / 250.0,
        "road_half_width": rng.uniform(3.0, 7.0),
        "sidewalk": rng.uniform(1.5, 3.5),
        "curb": 0.0 if mode == "flat_distinct" else rng.uniform(0.12, 0.2),
        "mode": mode,
        "road_rgb": road_grey * rng.uniform(0.92, 1.08, 3),
        "road_refl": rng.uniform(0.15, 0.35),
        "exposure": rng.uniform(0.75, 1.2),
        "tex_seed": int(rng.integers(1 << 30)),
        "lane_dash": rng.uniform(2.0, 4.0),
        # unit vector towards the sun (y down, so its y is negative)
        "sun": np.array([np.cos(elevation) * np.sin(azimuth), -np.sin(elevation), np.cos(elevation) * np.cos(azimuth)]),
    }


def _border(rng: np.random.Generator, s: dict[str, Any]) -> None:
    """The border's colour and reflectance: the road's where camouflaged (the LiDAR-only cue), else a palette's."""
    if s["mode"] == "kerb_camouflaged":
        s["border_rgb"], s["border_refl"] = s["road_rgb"] * rng.uniform(0.97, 1.03), s["road_refl"]
    else:
        palette = [(0.25, 0.45, 0.15), (0.5, 0.42, 0.3), (0.6, 0.6, 0.58), (0.35, 0.3, 0.25)]
        s["border_rgb"] = np.array(palette[rng.integers(len(palette))]) * rng.uniform(0.8, 1.2)
        s["border_refl"] = s["road_refl"] if s["mode"] == "flat_distinct" else rng.uniform(0.05, 0.6)


def _buildings(rng: np.random.Generator, s: dict[str, Any], boxes: _Boxes, sign: int) -> None:
    """A row of buildings or walls along one side of the road (``sign``: -1 left, 1 right), up to 90 m."""
    half, side = s["road_half_width"], s["sidewalk"]
    z = rng.uniform(-5, 5)
    while z < 90:
        length = rng.uniform(6, 25)
        zc = z + length / 2
        lateral = sign * (half + side + rng.uniform(0.3, 4.0))
        height = rng.uniform(2.5, 14.0) if rng.random() < 0.8 else rng.uniform(1.0, 2.5)
        depth = rng.uniform(4, 12)
        xc = road_centre(s, zc) + lateral + sign * depth / 2
        yaw = np.pi / 2 + np.arctan(s["curvature"] * zc)
        colour = np.array(FACADES[rng.integers(len(FACADES))]) * rng.uniform(0.85, 1.15, 3)
        boxes.add(
            (xc, CAMERA_HEIGHT - s["curb"], zc, length / 2, height / 2, depth / 2, yaw),
            -1,
            BUILDING,
            FACADE,
            colour,
            rng.uniform(0.1, 0.6),
        )
        z += length + rng.uniform(0, 8)


def _road_users(
    rng: np.random.Generator, s: dict[str, Any], boxes: _Boxes, placed: list[tuple[float, float, float]]
) -> list[tuple]:
    """Parked and moving cars and pedestrians on sidewalks and crossing, none overlapping another; returns their
    (class, x, bottom y, z, l, h, w, yaw) in the camera frame and adds their footprints (x, z, radius) to
    ``placed``."""
    half, side = s["road_half_width"], s["sidewalk"]
    objects: list[tuple] = []  # (class, x, bottom y, z, l, h, w, yaw) in the camera frame
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
        camo = (s["border_rgb"] if base < CAMERA_HEIGHT else s["road_rgb"]) if rng.random() < 0.25 else None
        (_car if is_car else _pedestrian)(boxes, len(objects), rng, xc, base, zc, dims, yaw, camo)
        objects.append((CAR if is_car else PEDESTRIAN, xc, base, zc, *dims, yaw))
    return objects


#: Street furniture: (share, kind). Sizes in metres, reflectances at 905 nm (foliage about 0.8, the HDL-64E
#: datasheet's figure; painted metal and plastic as car paint).
FURNITURE_KINDS = ((0.3, "pole"), (0.25, "tree"), (0.3, "bollard"), (0.15, "hedge"))
FOLIAGE = ((0.16, 0.32, 0.10), (0.22, 0.38, 0.14), (0.12, 0.24, 0.08))
STREET_GREYS = ((0.45, 0.46, 0.48), (0.25, 0.27, 0.25), (0.12, 0.30, 0.16), (0.55, 0.50, 0.40))


def _street_furniture(
    rng: np.random.Generator, s: dict[str, Any], boxes: _Boxes, sign: int, placed: list[tuple[float, float, float]]
) -> None:
    """Poles and bollards at the kerb, trees and hedges at the sidewalk's outer edge, on one side of the road
    (``sign``: -1 left, 1 right), 2-70 m ahead, a gap of 3-12 m after each; background (owner -1, no label) for
    every task. None stands on a road user's footprint (``placed``)."""
    half, side, kerb = s["road_half_width"], s["sidewalk"], CAMERA_HEIGHT - s["curb"]
    z = rng.uniform(2, 8)
    while z < 70:
        kind = FURNITURE_KINDS[rng.choice(len(FURNITURE_KINDS), p=[k[0] for k in FURNITURE_KINDS])][1]
        outer = kind in ("tree", "hedge")
        lateral = sign * (half + (side - rng.uniform(0.4, 0.8) if outer else rng.uniform(0.3, 0.6)))
        xc = road_centre(s, z) + lateral
        along = np.pi / 2 + np.arctan(s["curvature"] * z)  # a box's length along the road
        if kind == "hedge":
            length, width, height = rng.uniform(2, 8), rng.uniform(0.6, 1.0), rng.uniform(0.8, 1.6)
        elif kind == "tree":
            length = width = rng.uniform(0.2, 0.4)
            height = rng.uniform(2.0, 3.0)
        elif kind == "pole":
            length = width = rng.uniform(0.1, 0.25)
            height = rng.uniform(3.0, 8.0)
        else:
            length = width = rng.uniform(0.25, 0.7)
            height = rng.uniform(0.5, 1.2)
        zc, radius = z + (length / 2 if kind == "hedge" else 0.0), max(length, width) / 2
        if not any(np.hypot(xc - px, zc - pz) < radius + pr + 0.2 for px, pz, pr in placed):
            if kind in ("hedge", "tree"):
                colour = np.array(FOLIAGE[rng.integers(len(FOLIAGE))]) * rng.uniform(0.8, 1.2, 3)
                refl = rng.uniform(0.5, 0.8)
            else:
                colour = np.array(STREET_GREYS[rng.integers(len(STREET_GREYS))]) * rng.uniform(0.85, 1.15, 3)
                refl = rng.uniform(0.2, 0.6)
            # a tree's box is its brown trunk, under a crown of foliage
            trunk = kind == "tree"
            base = (
                (np.array((0.30, 0.22, 0.15)) * rng.uniform(0.8, 1.2), rng.uniform(0.3, 0.5))
                if trunk
                else (colour, refl)
            )
            boxes.add((xc, kerb, zc, length / 2, height / 2, width / 2, along), -1, BUILDING, FURNITURE, *base)
            if trunk:
                crown = rng.uniform(2.0, 4.0)
                box = (xc, kerb - height, zc, crown / 2, rng.uniform(1.0, 2.0), crown / 2, along)
                boxes.add(box, -1, BUILDING, FURNITURE, colour, refl)
            placed.append((xc, zc, radius))
        z += (length if kind == "hedge" else 0.0) + rng.uniform(3, 12)


def _car(
    boxes: _Boxes,
    owner: int,
    rng: np.random.Generator,
    xc: float,
    base: float,
    zc: float,
    dims: tuple[float, float, float],
    yaw: float,
    camo: np.ndarray | None,
    paint: int | None = None,
) -> None:
    """Body, glass cabin (roof in the body's paint) and four tyres; heading along local +x (front). ``paint``: an
    index into :data:`PAINTS` (default: drawn by their shares)."""
    l, h, w = dims
    k = rng.choice(len(PAINTS), p=[p[0] for p in PAINTS]) if paint is None else paint
    rgb, (r0, r1) = PAINTS[k][1], PAINTS[k][2]
    colour = np.array(rgb) * rng.uniform(0.9, 1.1, 3) if rgb is not None else rng.uniform(0.1, 0.9, 3)
    refl = rng.uniform(r0, r1)
    if camo is not None:
        colour, refl = camo * rng.uniform(0.95, 1.05, 3), rng.uniform(0.2, 0.4)
    gloss = GLOSS_EXPONENT if r1 > 0.06 and rng.random() < GLOSSY_SHARE else 1.0
    clearance, body_h = 0.2, 0.5 * h
    boxes.add((xc, base - clearance, zc, l / 2, body_h / 2, w / 2, yaw), owner, CAR, BODY, colour, refl, gloss)
    cabin_h = h - clearance - body_h
    ox, oz = to_world(yaw, -0.06 * l, 0.0)  # the cabin sits a little behind the centre
    boxes.add(
        (xc + ox, base - clearance - body_h, zc + oz, 0.28 * l, cabin_h / 2, 0.44 * w, yaw),
        owner,
        CAR,
        CABIN,
        colour,
        refl,
        gloss,
    )
    for sx in (-1, 1):
        for sz in (-1, 1):
            ox, oz = to_world(yaw, sx * (l / 2 - 0.75), sz * (w / 2 - 0.08))
            boxes.add((xc + ox, base, zc + oz, 0.32, 0.32, 0.11, yaw), owner, CAR, WHEEL, (0.05, 0.05, 0.05), 0.05)


def _pedestrian(
    boxes: _Boxes,
    owner: int,
    rng: np.random.Generator,
    xc: float,
    base: float,
    zc: float,
    dims: tuple[float, float, float],
    yaw: float,
    camo: np.ndarray | None,
) -> None:
    """Legs, torso and head: trousers, a shirt and skin."""
    l, h, w = dims
    shirt = rng.uniform(0.05, 0.9, 3) if camo is None else camo * rng.uniform(0.95, 1.05, 3)
    trousers = np.array(TROUSERS[rng.integers(len(TROUSERS))]) if camo is None else shirt * 0.9
    cloth_refl = lambda c: rng.uniform(0.04, 0.1) if np.mean(c) < 0.15 else rng.uniform(0.2, 0.6)  # noqa: E731
    legs, torso = 0.47 * h, 0.38 * h
    boxes.add(
        (xc, base, zc, l / 2 * 0.8, legs / 2, w / 2 * 0.75, yaw),
        owner,
        PEDESTRIAN,
        LEGS,
        trousers,
        cloth_refl(trousers),
    )
    boxes.add((xc, base - legs, zc, l / 2, torso / 2, w / 2, yaw), owner, PEDESTRIAN, TORSO, shirt, cloth_refl(shirt))
    head = h - legs - torso
    boxes.add(
        (xc, base - legs - torso, zc, 0.1, head / 2, 0.09, yaw),
        owner,
        PEDESTRIAN,
        HEAD,
        np.array(SKIN[rng.integers(len(SKIN))]) * rng.uniform(0.9, 1.1),
        rng.uniform(0.3, 0.5),
    )


def camera_rays(P2: np.ndarray, height: int, width: int) -> np.ndarray:
    """Ray directions (H*W,3) through every pixel centre, scaled so that their z is 1 (t = depth)."""
    v, u = np.mgrid[:height, :width].astype(np.float32)
    return np.stack([(u - P2[0, 2]) / P2[0, 0], (v - P2[1, 2]) / P2[1, 1], np.ones_like(u)], -1).reshape(-1, 3)


def lidar_angles(height: int, width: int, fov: float = 45.0) -> tuple[np.ndarray, np.ndarray]:
    """Elevation and azimuth (radians, (N,) each) of the beams over azimuths +-fov degrees.

    The LiDAR's angular resolution scales with the image, so that its scan density per image pixel matches that of
    KITTI's rig in both directions, and with it the camera's resolution advantage over the LiDAR (a beam every
    ~5.3 image rows, a firing every ~0.4 columns): the azimuth step is KITTI's 0.09 deg x 1242 / width, and of the
    HDL-64E's 64 elevations ``round(64 x height / 375)`` are kept, evenly spread (all 64 at KITTI's 375 rows, 22
    at the cpu scale's 128, 11 at 64). Far and small objects then get as few beams, per pixel of their size, as
    in KITTI."""
    step = 0.09 * KITTI_P2[3] / width
    beams = BEAMS[
        np.round(np.linspace(0, len(BEAMS) - 1, max(2, round(len(BEAMS) * height / KITTI_P2[4])))).astype(int)
    ]
    el, az = np.meshgrid(np.deg2rad(beams), np.deg2rad(np.arange(-fov, fov + 1e-9, step)), indexing="ij")
    return el.ravel(), az.ravel()


def beam_directions(el: np.ndarray, az: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit directions of beams in the camera frame and in the velodyne frame, (N,3) each."""
    velo = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1)
    return np.stack([-velo[:, 1], -velo[:, 2], velo[:, 0]], 1), velo
