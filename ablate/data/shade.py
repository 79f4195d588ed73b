"""Camera shading of the generated scenes: albedo x texture x (ambient + Lambertian sun), cast shadows, glass.

- Sun: a directional light (``scene["sun"]`` points towards it); faces turned from it get the ambient term only.
- Shadows on the ground: every box's silhouette projected along the sun onto the road plane (a convex
  polygon); under a car the road also loses most of its sky light (contact shadow, x0.35).
- Glass (car cabins' sides, facade windows): a dark interior plus the sky mirrored by Schlick's Fresnel
  approximation, ``F = 0.04 + 0.96 (1 - cos theta)^5``; cabins keep a pillar frame and the roof in the body's paint.
- Cars: tail lights (red) at the back, head lights (white) at the front, rims on the tyres' outer faces.
"""

from __future__ import annotations

import cv2
import numpy as np

from ablate.data.raycast import BORDER, BOX, CAMERA_HEIGHT, ROAD, SKY
from ablate.data.synth import BODY, CABIN, FACADE, WHEEL

AMBIENT, DIRECT = 0.45, 0.75
SKY_HORIZON, SKY_ZENITH = np.array([0.75, 0.82, 0.9]), np.array([0.35, 0.55, 0.85])
INTERIOR = np.array([0.05, 0.06, 0.08])


def noise(a: np.ndarray, b: np.ndarray, seed: int, scale: float) -> np.ndarray:
    """Value noise in [0, 1) on a grid of ``scale`` metres, hashed from world coordinates (deterministic)."""
    ia = np.floor(a / scale).astype(np.int64)
    ib = np.floor(b / scale).astype(np.int64)
    h = (ia * 73856093) ^ (ib * 19349663) ^ seed
    h = (h ^ (h >> 13)) * 1274126177
    return ((h ^ (h >> 16)) & 0xFFFF).astype(np.float32) / 65536.0


def sky_colour(dirs: np.ndarray) -> np.ndarray:
    up = np.clip(-dirs[:, 1] / np.linalg.norm(dirs, axis=1), 0, 1)[:, None]
    return (1 - up) * SKY_HORIZON + up * SKY_ZENITH


def glass_mask(scene: dict, hit: dict, isbox: np.ndarray) -> np.ndarray:
    """Rays (all R) that hit glass: a car cabin's side, front or back within its pillar frame, or a facade
    window (storeys of 3 m, windows 1.4 m wide every 3 m, none on the ground floor)."""
    out = np.zeros(len(isbox), bool)
    b = hit["box"][isbox]
    part, ax, (lx, ly, lz) = scene["part"][b], hit["axis"][isbox], hit["local"][isbox].T
    hl, hh, hw = scene["boxes"][b, 3], scene["boxes"][b, 4], scene["boxes"][b, 5]
    side = ax != 1
    along = np.where(ax == 2, lx, lz)
    half = np.where(ax == 2, hl, hw)
    frame = (half - np.abs(along) > 0.08) & (ly > 0.06) & (2 * hh - ly > 0.08) & ((ax != 2) | (np.abs(lx) > 0.05))
    window = (
        (np.mod(along + half, 3.0) > 0.8)
        & (np.mod(along + half, 3.0) < 2.2)
        & (np.mod(ly, 3.0) > 0.9)
        & (np.mod(ly, 3.0) < 2.2)
        & (ly > 3.0)
        & (2 * hh - ly > 0.5)
    )
    out[isbox] = side & (((part == CABIN) & frame) | ((part == FACADE) & window))
    return out


def ground_shadow(scene: dict, point: np.ndarray, ground: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per ray: in a cast shadow (the sun blocked by a box), and under a car's footprint (contact shadow)."""
    shadow, contact = np.zeros(len(point), bool), np.zeros(len(point), bool)
    idx = np.flatnonzero(ground)
    if not len(idx) or not len(scene["boxes"]):
        return shadow, contact
    p = point[idx][:, [0, 2]]
    sun = scene["sun"]
    for b, (cx, by, cz, hl, hh, hw, yaw) in enumerate(scene["boxes"]):
        c, s = np.cos(yaw), np.sin(yaw)
        lx, ly, lz = np.meshgrid([-hl, hl], [0, 2 * hh], [-hw, hw], indexing="ij")
        x, z = cx + c * lx + s * lz, cz - s * lx + c * lz
        y = by - ly
        lam = (y - CAMERA_HEIGHT) / sun[1]  # along -sun down to the road plane
        poly = np.stack([x - lam * sun[0], z - lam * sun[2]], -1).reshape(-1, 2).astype(np.float32)
        hull = cv2.convexHull(poly)[:, 0]
        lo, hi = hull.min(0), hull.max(0)
        near = np.flatnonzero((p[:, 0] >= lo[0]) & (p[:, 0] <= hi[0]) & (p[:, 1] >= lo[1]) & (p[:, 1] <= hi[1]))
        if not len(near):
            continue
        q = p[near]
        inside = np.ones(len(q), bool)
        sign = np.sign(_cross(hull[1] - hull[0], hull[2] - hull[1]))
        for k in range(len(hull)):
            inside &= sign * _cross(hull[(k + 1) % len(hull)] - hull[k], q - hull[k]) >= 0
        shadow[idx[near[inside]]] = True
        if scene["part"][b] == BODY:
            dx, dz = q[:, 0] - cx, q[:, 1] - cz
            under = (np.abs(c * dx - s * dz) < hl + 0.1) & (np.abs(s * dx + c * dz) < hw + 0.1)
            contact[idx[near[under]]] = True
    return shadow, contact


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def lane_marking(scene: dict, hit: dict) -> np.ndarray:
    """Per ray: on a painted road marking (the dashed centre line, a solid line 0.25 m inside each road edge)."""
    dx, half, z = hit["dx"], scene["road_half_width"], hit["point"][:, 2]
    dash = (np.mod(z, 2 * scene["lane_dash"]) < scene["lane_dash"]) & (np.abs(dx) < 0.08)
    edge = np.abs(np.abs(dx) - (half - 0.25)) < 0.08
    return (hit["kind"] == ROAD) & (dash | edge)


def shade(scene: dict, hit: dict, dirs: np.ndarray) -> np.ndarray:
    """RGB in [0, 1] of every camera ray."""
    p, kind, box = hit["point"], hit["kind"], hit["box"]
    n = len(kind)
    seed = scene["tex_seed"]
    tex = 0.8 + 0.4 * (0.6 * noise(p[:, 0], p[:, 2], seed, 0.15) + 0.4 * noise(p[:, 0], p[:, 2], seed + 1, 0.6))
    ground = (kind == ROAD) | (kind == BORDER)
    isbox = kind == BOX
    rgb = np.zeros((n, 3), np.float32)
    rgb[kind == ROAD] = scene["road_rgb"]
    rgb[kind == BORDER] = scene["border_rgb"]
    rgb[lane_marking(scene, hit)] = 0.9
    rgb[isbox] = scene["box_rgb"][box[isbox]]
    part = np.where(isbox, scene["part"][np.maximum(box, 0)], -1)
    lx, ly, lz = hit["local"].T
    hl, hh, hw = (scene["boxes"][np.maximum(box, 0), k] for k in (3, 4, 5))
    # Lights on the body's front and back faces, rims on the tyres' outer faces.
    light_row = (part == BODY) & (hit["axis"] == 0) & (np.abs(lz) > hw - 0.32) & (ly > 1.1 * hh) & (ly < 1.6 * hh)
    rgb[light_row & (lx < 0)] = (0.85, 0.08, 0.05)
    rgb[light_row & (lx > 0)] = (0.97, 0.95, 0.85)
    rgb[(part == WHEEL) & (hit["axis"] == 2) & (np.hypot(lx, ly - hh) < 0.17)] = 0.55
    facade = noise(p[:, 0] + p[:, 2], p[:, 1], seed + 2, 1.2)
    building = part == FACADE
    rgb[building] *= (0.85 + 0.15 * facade[building])[:, None]
    light = AMBIENT + DIRECT * np.clip(hit["normal"] @ scene["sun"], 0, None)
    shadow, contact = ground_shadow(scene, p, ground)
    light = np.where(shadow, AMBIENT, light) * np.where(contact, 0.35, 1.0)
    rgb = rgb * np.where(ground | isbox, tex, 1.0)[:, None] * light[:, None]
    glass = glass_mask(scene, hit, isbox)
    if glass.any():
        cos = np.abs(np.sum(hit["normal"][glass] * dirs[glass], 1)) / np.linalg.norm(dirs[glass], axis=1)
        fresnel = (0.04 + 0.96 * (1 - cos) ** 5)[:, None]
        d, nrm = dirs[glass], hit["normal"][glass]
        mirrored = d - 2 * np.sum(d * nrm, 1, keepdims=True) * nrm
        seen = np.where(mirrored[:, 1:2] < 0, sky_colour(mirrored), 0.25)  # sky above, ground below
        rgb[glass] = (1 - fresnel) * INTERIOR + fresnel * seen + 0.06
    sky = kind == SKY
    rgb[sky] = sky_colour(dirs[sky])
    return np.clip(rgb * scene["exposure"], 0, 1)
