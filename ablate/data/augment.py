"""Geometric training augmentation that keeps the camera, the LiDAR and the calibration consistent.

BiFNet (Li et al., ../shared/seeds/004 §V-B) trains with "flip, translation and scaling" augmentation and gives
no ranges or probabilities. Its fusion indexes image and BEV features through the calibration (DST), so moving
pixels alone would break the correspondence; each augmentation here is a change of the *scene or the camera*
that every derived modality follows:

- **Flip** (probability ``flip``, default 0.5): the world is mirrored in the rectified camera frame,
  ``M = diag(-1, 1, 1)`` on X. The image is flipped left-right (``u' = W - 1 - u``), the LiDAR points are mirrored
  (``p_velo' = T^-1 M T p_velo`` with ``T = R0_rect Tr_velo_to_cam``), ``P2' = F P2 M`` with
  ``F = [[-1, 0, W-1], [0, 1, 0], [0, 0, 1]]`` (so a mirrored point lands on the flipped pixel of the original one)
  and ``Tr_cam_to_road' = Tr_cam_to_road M``. Every LiDAR raster (depth, DHI, BEV, heights) is recomputed from the
  mirrored points, so the BEV is the mirrored scene, not an approximate column flip.
- **Scaling and translation** (a zoom ``s`` drawn uniformly in ``scale``, default [1.0, 1.2], and a shift drawn
  uniformly over the margin the zoom leaves): a change of the camera's intrinsics,
  ``A = [[s, 0, tx], [0, s, ty], [0, 0, 1]]``, ``P2' = A P2``. Every camera-space tensor is warped by ``A``
  (bilinear for the camera image, nearest for LiDAR rasters and labels), boxes are mapped and clipped; the points,
  the BEV and its ground truth do not move. The reading chosen: zoom in only, with the shift inside the margin, so
  the warped image always covers the frame and no pixel is left without data or label.

- **Photometric distortion** (probability ``photometric`` for each of its four steps, default 0: off), the camera's
  only: SSD's (Liu et al. 2016, §2.2 and its released augmentation), which SMoE trains with ("the data augmentations
  used in SSD ... modulating brightness and contrast", ../shared/seeds/000 §4.3). Brightness ``+ b``, ``b`` uniform
  in +-32/255; contrast ``x c``, ``c`` in [0.5, 1.5], applied first or last with equal odds; saturation ``x s``, ``s``
  in [0.5, 1.5]; hue ``+ h``, ``h`` in +-18 degrees; the image clipped to [0, 1]. Readings chosen: it acts on the camera
  image after its condition (night, rain, glare are part of Complex KITTI's images, which SSD's distortion would
  see); SSD's channel swap is left out (it makes a red tail light blue); no LiDAR raster changes (the jet DDM's
  colours are depths, not light).

Augmentation is for the training split only; the draws come from torch's generator (seeded per worker by
Lightning), so a frame's augmentation changes from epoch to epoch. The frozen experts' feature cache
(``ablate.jobs.experts.FeatureCache``), which assumes each frame's input is a constant, is off when it is on.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from ablate.data import kitti

#: Camera-space tensors resampled bilinearly; every other camera-space tensor (LiDAR rasters, labels) takes the
#: nearest value, so sparse depths and class ids stay what they were.
SMOOTH = ("rgb", "intensity", "ddm_jet")
#: Sample keys that are not in camera space: BEV rasters and targets, points in the BEV grid.
NOT_CAMERA = ("bev", "road_bev", "road_bev_valid", "height_bev", "lidar_points")
MIRROR = np.diag([-1.0, 1.0, 1.0, 1.0])


@dataclass(frozen=True)
class View:
    """One draw: ``flip`` the world, then look through intrinsics changed by ``affine`` (3x3, None: unchanged)."""

    flip: bool = False
    affine: np.ndarray | None = None
    photometric: Photometric | None = None


@dataclass(frozen=True)
class Photometric:
    """One draw of SSD's photometric distortion (the module docstring); the neutral value of a step not drawn."""

    brightness: float = 0.0
    contrast: float = 1.0
    saturation: float = 1.0
    hue: float = 0.0
    contrast_first: bool = True

    @classmethod
    def draw(cls, p: float, generator: torch.Generator | None = None) -> Photometric:
        u = torch.rand(9, generator=generator, dtype=torch.float64).tolist()
        return cls(
            brightness=(2 * u[1] - 1) * 32 / 255 if u[0] < p else 0.0,
            contrast=0.5 + u[3] if u[2] < p else 1.0,
            saturation=0.5 + u[5] if u[4] < p else 1.0,
            hue=(2 * u[7] - 1) * 18.0 if u[6] < p else 0.0,
            contrast_first=u[8] < 0.5,
        )

    def apply(self, rgb: np.ndarray) -> np.ndarray:
        """The (H, W, 3) float32 image in [0, 1], distorted."""
        img: np.ndarray = rgb + np.float32(self.brightness)
        if self.contrast_first:
            img = img * np.float32(self.contrast)
        if self.saturation != 1.0 or self.hue != 0.0:
            hsv = cv2.cvtColor(np.clip(img, 0, 1).astype(np.float32), cv2.COLOR_RGB2HSV)  # H in degrees
            hsv[..., 1] = np.clip(hsv[..., 1] * self.saturation, 0, 1)
            hsv[..., 0] = np.mod(hsv[..., 0] + self.hue, 360.0)
            img = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)
        if not self.contrast_first:
            img = img * np.float32(self.contrast)
        return np.clip(img, 0, 1).astype(np.float32)


class Augment:
    """The draws of one training split (see the module docstring for what each does)."""

    def __init__(self, flip: float = 0.5, scale: tuple[float, float] = (1.0, 1.2), photometric: float = 0.0) -> None:
        lo, hi = (float(v) for v in scale)
        for name, p in (("flip", flip), ("photometric", photometric)):
            if not 0.0 <= float(p) <= 1.0:
                raise ValueError(f"data.augment.{name} must be a probability in [0, 1], got {p}")
        if not 1.0 <= lo <= hi:
            raise ValueError(f"data.augment.scale must be [lo, hi] with 1 <= lo <= hi (zoom in only), got {scale}")
        self.flip, self.scale, self.photometric = float(flip), (lo, hi), float(photometric)

    @classmethod
    def from_config(cls, options: dict) -> Augment:
        """From ``data.augment``; an unknown option is one error that names it."""
        valid = ("flip", "scale", "photometric")
        for key in options:
            if key not in valid:
                raise KeyError(f"unknown option data.augment.{key}; valid: {', '.join(valid)}")
        return cls(**options)

    def draw(self, shape: tuple[int, int], generator: torch.Generator | None = None) -> View:
        """A random :class:`View` of an image of ``shape`` (H, W). Without photometric distortion it draws no more
        numbers than before it existed, so a config without it keeps its stream."""
        u = torch.rand(4, generator=generator, dtype=torch.float64).tolist()
        flip = u[0] < self.flip
        photometric = Photometric.draw(self.photometric, generator) if self.photometric > 0 else None
        s = self.scale[0] + (self.scale[1] - self.scale[0]) * u[1]
        if s == 1.0:
            return View(flip, photometric=photometric)
        h, w = shape
        # the output pixel grid 0..W-1 must map inside the zoomed image: tx in [-(s-1)(W-1), 0]
        tx, ty = -(s - 1.0) * (w - 1) * u[2], -(s - 1.0) * (h - 1) * u[3]
        return View(flip, np.array([[s, 0.0, tx], [0.0, s, ty], [0.0, 0.0, 1.0]]), photometric)


def flip_calibration(calib: kitti.Calibration, width: int) -> kitti.Calibration:
    """The calibration of the mirrored world seen in the flipped image: ``P2' = F P2 M``, ``Tr_cam_to_road' =
    Tr_cam_to_road M`` (R0_rect and Tr_velo_to_cam unchanged: the points are mirrored instead)."""
    f = np.array([[-1.0, 0.0, width - 1.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    road = None if calib.Tr_cam_to_road is None else calib.Tr_cam_to_road @ MIRROR
    return kitti.Calibration(
        P2=f @ calib.P2 @ MIRROR,
        R0_rect=calib.R0_rect,
        Tr_velo_to_cam=calib.Tr_velo_to_cam,
        Tr_cam_to_road=road,
        path=calib.path,
    )


def mirror_points(points: np.ndarray, calib: kitti.Calibration) -> np.ndarray:
    """(N,4) velodyne points (x, y, z, reflectance) of the world mirrored in the rectified camera frame."""
    t = calib.velo_to_rect_matrix
    xyz1 = np.hstack([points[:, :3].astype(np.float64), np.ones((len(points), 1))])
    out = points.copy()
    out[:, :3] = (xyz1 @ (np.linalg.inv(t) @ MIRROR @ t).T)[:, :3]
    return out


def flip_box(bbox: tuple[float, float, float, float], width: int) -> tuple[float, float, float, float]:
    """An xyxy box in the flipped image (``u' = W - 1 - u``)."""
    x0, y0, x1, y1 = bbox
    return (width - 1.0 - x1, y0, width - 1.0 - x0, y1)


def warp(sample: dict, affine: np.ndarray, shape: tuple[int, int]) -> dict:
    """The sample of an image of ``shape`` (H, W) seen through intrinsics changed by ``affine``: camera-space tensors
    warped, ``calib``'s P2 premultiplied, boxes mapped and clipped (a box left with less than a pixel of width or
    height is dropped, with its mask and fields). The output keeps each tensor's size."""
    a = affine[:2].astype(np.float64)
    out = dict(sample)
    for k, v in sample.items():
        if k == "calib":
            v = v.clone()
            v[0] = torch.from_numpy(affine).to(v.dtype) @ v[0]
            out[k] = v
        elif isinstance(v, torch.Tensor) and k not in NOT_CAMERA and v.dim() >= 2:
            out[k] = _warp_tensor(v, a, cv2.INTER_LINEAR if k in SMOOTH else cv2.INTER_NEAREST)
        elif k in ("instances", "boxes2d"):
            out[k] = _warp_boxes(v, affine, a, shape)
    return out


def _warp_tensor(v: torch.Tensor, a: np.ndarray, interpolation: int) -> torch.Tensor:
    """Warp the last two axes of ``v`` by the 2x3 ``a`` (output pixel = a @ input pixel), size kept."""
    h, w = v.shape[-2:]
    if v.numel() == 0:  # no planes (a frame without instances): nothing to warp
        return v
    flat = v.reshape(-1, h, w).numpy()
    dtype = flat.dtype
    work = flat if dtype in (np.uint8, np.uint16, np.float32, np.float64) else flat.astype(np.float32)  # cv2's
    planes = [
        cv2.warpAffine(np.ascontiguousarray(p), a, (w, h), flags=interpolation, borderMode=cv2.BORDER_REPLICATE)
        for p in work
    ]
    return torch.from_numpy(np.stack(planes).astype(dtype).reshape(v.shape))


def _warp_boxes(target: dict, affine: np.ndarray, a: np.ndarray, shape: tuple[int, int]) -> dict:
    s, tx, ty = affine[0, 0], affine[0, 2], affine[1, 2]
    h, w = shape
    mapped = target["boxes"].double() * s + torch.tensor([tx, ty, tx, ty], dtype=torch.float64)
    mapped[:, 0::2] = mapped[:, 0::2].clamp(0, w - 1)
    mapped[:, 1::2] = mapped[:, 1::2].clamp(0, h - 1)
    keep = ((mapped[:, 2] - mapped[:, 0]) >= 1) & ((mapped[:, 3] - mapped[:, 1]) >= 1)
    out = {key: val[keep] for key, val in target.items()}
    out["boxes"] = mapped[keep].to(target["boxes"].dtype)
    if "masks" in out:
        out["masks"] = _warp_tensor(out["masks"], a, cv2.INTER_NEAREST)
    return out
