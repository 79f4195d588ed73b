"""Optional LiDAR weather, off by default: rain and fog on a point cloud, a condition group of its own.

SMoE's Complex-KITTI conditions are camera-only (§3.3), so they stay so; these are for users who want the
LiDAR to suffer too (``data.lidar_weather: [clear, rain, fog]`` spreads them over the frames like the camera
conditions). Each takes (N,4) velodyne points (x, y, z, reflectance), a per-frame generator and ``severity``:

- Extinction: the return loses ``exp(-2 a_w R)`` of its power on the way out and back (Koschmieder:
  ``a_w = 3.912 / V`` for a visibility ``V``). A point survives where its clear-weather power, estimated from
  its reported reflectance and range at normal incidence with ablate.data.lidar_physics's model (an upper
  bound: the incidence is not stored), times that loss still clears the detection threshold.
- Dropouts: drops on the sensor window hide a random share of the beams.
- Near-range clutter: droplets and fog backscatter close to the sensor give false returns of low reflectance
  within a few metres, over the scanned field of view.

Severity 1: rain, visibility 2 km (heavy rain), 5 % dropouts, 100 clutter points within 1-4 m; fog,
visibility 150 m, 2 % dropouts, 800 clutter points within 1-8 m. Severity scales the extinction, the
dropouts and the clutter linearly (0: no change).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ablate.data import lidar_physics as physics


def _weather(
    points: np.ndarray,
    rng: np.random.Generator,
    severity: float,
    visibility: float,
    dropout: float,
    clutter: int,
    clutter_range: tuple[float, float],
) -> np.ndarray:
    pts = np.asarray(points, np.float32)
    if severity <= 0 or not len(pts):
        return pts
    r = np.linalg.norm(pts[:, :3], axis=1)
    alpha = severity * 3.912 / visibility
    power = physics.received_power(pts[:, 3], 1.0, r) * np.exp(-2 * alpha * r)
    keep = (power >= physics.THRESHOLD) & (rng.random(len(pts)) >= dropout * severity)
    n = int(round(clutter * severity))
    az = np.arctan2(pts[:, 1], pts[:, 0])
    el = np.arcsin(np.clip(pts[:, 2] / np.maximum(r, 1e-6), -1, 1))
    a = rng.uniform(az.min(), az.max(), n)
    e = rng.uniform(el.min(), el.max(), n)
    d = rng.uniform(*clutter_range, n)
    fake = np.stack(
        [d * np.cos(e) * np.cos(a), d * np.cos(e) * np.sin(a), d * np.sin(e), rng.uniform(0.0, 0.1, n)], 1
    ).astype(np.float32)
    return np.vstack([pts[keep], fake])


def clear(points: np.ndarray, rng: np.random.Generator, severity: float = 1.0) -> np.ndarray:
    return np.asarray(points, np.float32)


def rain(points: np.ndarray, rng: np.random.Generator, severity: float = 1.0) -> np.ndarray:
    return _weather(points, rng, severity, 2000.0, 0.05, 100, (1.0, 4.0))


def fog(points: np.ndarray, rng: np.random.Generator, severity: float = 1.0) -> np.ndarray:
    return _weather(points, rng, severity, 150.0, 0.02, 800, (1.0, 8.0))


LIDAR_WEATHER: dict[str, Callable[..., np.ndarray]] = {"clear": clear, "rain": rain, "fog": fog}


def apply_lidar_weather(name: str, points: np.ndarray, rng: np.random.Generator, severity: float = 1.0) -> np.ndarray:
    """Apply a LiDAR weather condition to (N,4) velodyne points."""
    if name not in LIDAR_WEATHER:
        raise KeyError(f"unknown LiDAR weather {name!r}; valid: {', '.join(LIDAR_WEATHER)}")
    return LIDAR_WEATHER[name](points, rng, severity)
