"""Adverse conditions on camera images (Complex KITTI, SMoE §3.3) and sensor corruptions (DGFN §IV-A).

Every function takes a ``numpy.random.Generator`` seeded per sample, so a sample always gets the same
drops, wiper, glare spot or box. ``severity`` scales strength (1.0 = the defaults below, 0 = no change for
the Complex-KITTI conditions).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import cast

import cv2
import numpy as np
from numpy.typing import NDArray

Image = np.ndarray  # (H,W,3) float32 RGB in [0, 1]


def clear(img: Image, rng: np.random.Generator, severity: float = 1.0) -> Image:
    """The unmodified KITTI image."""
    return img


def night(img: Image, rng: np.random.Generator, severity: float = 1.0) -> Image:
    """SMoE §3.3 night: reduced brightness (gamma and gain), Gaussian sensor noise and motion blur."""
    dark = np.power(img, 1.0 + 1.2 * severity) * (1.0 - 0.6 * min(severity, 1.0))
    length = 1 + 2 * int(round(rng.uniform(2, 5) * severity))
    kernel: np.ndarray = np.zeros((length, length), np.float32)
    kernel[length // 2] = 1.0 / length
    rot = cv2.getRotationMatrix2D((length / 2 - 0.5, length / 2 - 0.5), rng.uniform(-30, 30), 1.0)
    kernel = cast("NDArray[np.float32]", cv2.warpAffine(kernel, rot, (length, length)))  # float32 in, float32 out
    kernel /= max(kernel.sum(), 1e-6)
    blurred = cv2.filter2D(dark.astype(np.float32), -1, kernel, borderType=cv2.BORDER_REFLECT)
    noise = rng.normal(0, 0.025 * severity, img.shape).astype(np.float32)
    return np.clip(blurred + noise, 0, 1)


def rain_day(img: Image, rng: np.random.Generator, severity: float = 1.0) -> Image:
    """SMoE §3.3 light rain: randomly placed Gaussian-blurred drop circles on the lens and a dark windscreen
    wiper polygon sweeping up from a bottom corner."""
    h, w = img.shape[:2]
    sigma = max(2.0, 0.02 * w)
    blurred = cv2.GaussianBlur(img, (0, 0), sigma)
    mask: np.ndarray = np.zeros((h, w), np.float32)
    for _ in range(int(round(rng.uniform(8, 20) * severity))):
        centre = (int(rng.uniform(0, w)), int(rng.uniform(0, h)))
        cv2.circle(mask, centre, max(2, int(rng.uniform(0.03, 0.09) * h)), 1.0, -1, lineType=cv2.LINE_AA)
    mask = cv2.GaussianBlur(mask, (0, 0), max(1.0, 0.01 * w))[..., None]
    out = img * (1 - mask) + blurred * 1.05 * mask
    if severity > 0:
        left = rng.random() < 0.5
        x0 = 0 if left else w - 1
        angle = np.deg2rad(rng.uniform(25, 70))
        reach = rng.uniform(0.8, 1.3) * w
        thick = rng.uniform(0.05, 0.1) * w * min(severity, 1.5)
        dx = reach * np.cos(angle) * (1 if left else -1)
        tip = np.array([x0 + dx, h - reach * np.sin(angle)])
        base = np.array([x0, h], float)
        normal = np.array([np.sin(angle) * (1 if left else -1), np.cos(angle)]) * thick / 2
        poly = np.array([base - normal, tip - normal * 0.5, tip + normal * 0.5, base + normal], np.int32)
        wiper = np.zeros((h, w), np.float32)
        cv2.fillPoly(wiper, [poly], 1.0, lineType=cv2.LINE_AA)
        out = out * (1 - 0.9 * wiper[..., None]) + 0.03 * wiper[..., None]
    return np.clip(out, 0, 1).astype(np.float32)


def rain_night(img: Image, rng: np.random.Generator, severity: float = 1.0) -> Image:
    """SMoE §3.3 light rain at night: night, then rain drops and wiper."""
    return rain_day(night(img, rng, severity), rng, severity)


def glare(img: Image, rng: np.random.Generator, severity: float = 1.0) -> Image:
    """SMoE §3.3 sun glare: a randomly placed bright white area with a soft falloff."""
    h, w = img.shape[:2]
    cx, cy = rng.uniform(0.1, 0.9) * w, rng.uniform(0.0, 0.6) * h
    radius = rng.uniform(0.15, 0.3) * w * max(severity, 1e-3)
    yy, xx = np.mgrid[:h, :w].astype(np.float32)
    d2 = ((xx - cx) ** 2 + (yy - cy) ** 2) / radius**2
    alpha = np.clip(1.6 * np.exp(-d2), 0, 1)[..., None] * min(severity, 1.0)
    return np.clip(img + (1 - img) * alpha, 0, 1).astype(np.float32)


CONDITIONS: dict[str, Callable[..., Image]] = {
    "clear": clear,
    "night": night,
    "rain_day": rain_day,
    "rain_night": rain_night,
    "glare": glare,
}


def apply_condition(name: str, img: Image, rng: np.random.Generator, severity: float = 1.0) -> Image:
    """Apply a Complex-KITTI condition to an (H,W,3) float32 RGB image in [0, 1]."""
    if name not in CONDITIONS:
        raise KeyError(f"unknown condition {name!r}; valid: {', '.join(CONDITIONS)}")
    return CONDITIONS[name](np.asarray(img, np.float32), rng, severity).astype(np.float32)


# DGFN §IV-A corruptions, on network-ready (C,H,W) float32 arrays.
def blank(x: np.ndarray, rng: np.random.Generator, severity: float = 1.0) -> np.ndarray:
    """All-zero input in place of either modality."""
    return np.zeros_like(x)


def occlusion(x: np.ndarray, rng: np.random.Generator, severity: float = 1.0) -> np.ndarray:
    """A black (zero) box whose size (10-40 % of each side, times severity) and location are random."""
    _, h, w = x.shape
    bh = max(1, int(h * min(rng.uniform(0.1, 0.4) * severity, 1.0)))
    bw = max(1, int(w * min(rng.uniform(0.1, 0.4) * severity, 1.0)))
    y0, x0 = int(rng.integers(0, h - bh + 1)), int(rng.integers(0, w - bw + 1))
    out = x.copy()
    out[:, y0 : y0 + bh, x0 : x0 + bw] = 0
    return out


def noise(x: np.ndarray, rng: np.random.Generator, severity: float = 1.0) -> np.ndarray:
    """Additive Gaussian noise, camera only; the standard deviation is drawn in [0.02, 0.1] x severity."""
    sigma = rng.uniform(0.02, 0.1) * severity
    return np.clip(x + rng.normal(0, sigma, x.shape).astype(np.float32), 0, 1)


def illumination(x: np.ndarray, rng: np.random.Generator, severity: float = 1.0) -> np.ndarray:
    """Abrupt illumination change, camera only: a local disc brightened by a random amount, with random centre
    and radius."""
    _, h, w = x.shape
    cy, cx = rng.uniform(0, h), rng.uniform(0, w)
    radius = rng.uniform(0.1, 0.3) * max(h, w)
    gain = rng.uniform(0.3, 0.7) * severity
    yy, xx = np.mgrid[:h, :w]
    disc = ((yy - cy) ** 2 + (xx - cx) ** 2 <= radius**2).astype(np.float32)
    return np.clip(x + gain * disc[None], 0, 1)


CORRUPTIONS: dict[str, Callable[..., np.ndarray]] = {
    "blank": blank,
    "occlusion": occlusion,
    "noise": noise,
    "illumination": illumination,
}
CAMERA_ONLY = {"noise", "illumination"}
CAMERA_MODALITIES = {"rgb", "intensity"}


def apply_corruption(
    name: str, x: np.ndarray, rng: np.random.Generator, modality: str, severity: float = 1.0
) -> np.ndarray:
    """Apply a DGFN corruption to one (C,H,W) modality; noise and illumination are camera-only."""
    if name not in CORRUPTIONS:
        raise KeyError(f"unknown corruption {name!r}; valid: {', '.join(CORRUPTIONS)}")
    if name in CAMERA_ONLY and modality not in CAMERA_MODALITIES:
        raise ValueError(
            f"corruption {name!r} applies to the camera only ({', '.join(sorted(CAMERA_MODALITIES))}),"
            f" not to {modality!r}"
        )
    return CORRUPTIONS[name](np.asarray(x, np.float32), rng, severity).astype(np.float32)
