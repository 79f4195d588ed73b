"""Per-sample geometry of a batch for the space transforms (:mod:`ablate.fusion.space`): calibration, the BEV grid,
the dense LiDAR heights of BiFNet's DST (§IV-A1, §IV-A2) and the LiDAR points, with the pinhole projection and
its inverse in torch (float64).

Batch keys (the data module gives them when they are listed in ``targets``; see ``ablate.data.dataset``):
``calib`` [B,4,3,4] (P2, R0_rect in [:3,:3], Tr_velo_to_cam, Tr_cam_to_road; ``ablate.data.dataset.calib_array``),
``height_image`` [B,1,H,W] and ``height_bev`` [B,1,Hb,Wb] (m, velodyne z), ``lidar_points`` [B,N,3] (velodyne
x, y, z; NaN rows are padding).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, cast

import numpy as np
import torch
from torch import Tensor

if TYPE_CHECKING:
    from ablate.data.kitti import Calibration

GEOMETRY_KEYS = ("calib", "height_image", "height_bev", "lidar_points")
#: Keys of ``data.bev`` that set the dense heights and points (``ablate.data.dataset``), not the grid.
HEIGHT_OPTIONS = ("window", "azimuth_res", "max_points")


@dataclass(frozen=True)
class BevGrid:
    """The BEV raster of :func:`ablate.data.lidar.bev_image`: rows along x (row 0 at ``x_range[1]``), columns along
    y (column 0 at ``y_range[1]``), square cells of ``cell`` metres."""

    x_range: tuple[float, float] = (6.0, 46.0)
    y_range: tuple[float, float] = (-10.0, 10.0)
    cell: float = 0.5

    @classmethod
    def from_config(cls, grid: Mapping | None) -> BevGrid:
        grid = {k: v for k, v in dict(grid or {}).items() if k not in HEIGHT_OPTIONS}
        unknown = sorted(set(grid) - {"x_range", "y_range", "cell"})
        if unknown:
            raise ValueError(f"BEV grid: unknown key(s) {unknown}; valid: x_range, y_range, cell")
        values: dict[str, Any] = {k: tuple(float(x) for x in v) if k != "cell" else float(v) for k, v in grid.items()}
        out = cls(**values)
        if out.cell <= 0 or out.x_range[1] <= out.x_range[0] or out.y_range[1] <= out.y_range[0]:
            raise ValueError(f"BEV grid: need cell > 0 and increasing ranges, got {out}")
        return out

    @property
    def shape(self) -> tuple[int, int]:
        return (
            int(round((self.x_range[1] - self.x_range[0]) / self.cell)),
            int(round((self.y_range[1] - self.y_range[0]) / self.cell)),
        )


@dataclass
class Geometry:
    """One batch's calibration, BEV grid, dense heights and points (any of the last three may be None when the
    space transform in use does not need it)."""

    calib: Tensor
    grid: BevGrid
    image_size: tuple[int, int]
    height_image: Tensor | None = None
    height_bev: Tensor | None = None
    points: Tensor | None = None

    @classmethod
    def from_batch(cls, batch: Mapping, grid: BevGrid, image_size: tuple[int, int]) -> Geometry:
        if "calib" not in batch:
            raise KeyError(
                f"space transform needs batch['calib'] (list `calib` in the task's targets); got {sorted(batch)}"
            )
        return cls(
            batch["calib"].double(),
            grid,
            cast("tuple[int, int]", tuple(image_size)),
            batch.get("height_image"),
            batch.get("height_bev"),
            batch.get("lidar_points"),
        )

    @classmethod
    def from_frame(
        cls,
        points: np.ndarray,
        calib: Calibration,
        image_size: tuple[int, int],
        grid: BevGrid = BevGrid(),
        **heights: Any,
    ) -> Geometry:
        """The geometry of one frame (B = 1) from its velodyne scan and :class:`~ablate.data.kitti.Calibration`,
        built as the data module builds it; ``heights``: options of the height functions (``window``,
        ``azimuth_res``)."""
        from ablate.data import lidar
        from ablate.data.dataset import calib_array

        box: dict[str, Any] = {"x_range": grid.x_range, "y_range": grid.y_range, "cell": grid.cell}
        window = {k: heights[k] for k in ("window",) if k in heights}
        azimuth = {k: heights[k] for k in ("azimuth_res",) if k in heights}
        t = lambda a: torch.from_numpy(np.ascontiguousarray(a))[None]  # noqa: E731
        return cls(
            t(calib_array(calib)).double(),
            grid,
            cast("tuple[int, int]", tuple(image_size)),
            t(lidar.perspective_height(points, calib, image_size, **window))[:, None],
            t(lidar.bev_height(points, **box, **azimuth))[:, None],
            t(lidar.bev_points(points, **box)),
        )

    def need(self, *names: str, by: str = "space transform") -> None:
        missing = [n for n in names if getattr(self, n) is None]
        if missing:
            keys = {"height_image": "height_image", "height_bev": "height_bev", "points": "lidar_points"}
            raise KeyError(f"{by} needs batch keys {[keys[n] for n in missing]} (list them in the task's targets)")


def velo_to_rect(calib: Tensor) -> Tensor:
    """[B,4,4]: velodyne -> rectified camera, R0_rect . Tr_velo_to_cam."""
    b = calib.shape[0]
    r0, tr = calib[:, 1, :, :3], calib[:, 2]
    out = torch.zeros(b, 4, 4, dtype=calib.dtype, device=calib.device)
    out[:, :3] = r0 @ tr
    out[:, 3, 3] = 1.0
    return out


def project(geometry: Geometry, xyz: Tensor) -> tuple[Tensor, Tensor]:
    """Velodyne points [B,M,3] -> (image_2 pixels [B,M,2] (u, v), depth [B,M] = rectified camera z)."""
    m = velo_to_rect(geometry.calib)
    rect = xyz.double() @ m[:, :3, :3].transpose(1, 2) + m[:, None, :3, 3]
    p2 = geometry.calib[:, 0]
    hom = rect @ p2[:, :, :3].transpose(1, 2) + p2[:, None, :, 3]
    return hom[..., :2] / hom[..., 2:].clamp(min=1e-9), rect[..., 2]


def backproject(geometry: Geometry, uv: Tensor, height: Tensor, min_depth: float = 0.1) -> tuple[Tensor, Tensor]:
    """BiFNet eq. 5-7: the point on each pixel's ray whose velodyne z is ``height``.

    With P2 = [M | p], the ray of pixel (u, v) in the rectified camera frame is X(s) = s M^-1 (u, v, 1) - M^-1 p
    (eq. 5 at s = 1 is the "pseudo spatial position"); in the velodyne frame its z is linear in s, so the scale
    (eq. 6) that puts the point at ``height`` is solved for, and X(s) is the 3D position (eq. 7).
    Returns (xyz [B,M,3] velodyne, ok [B,M]: the point lies ``min_depth`` m or more in front of the camera)."""
    p2 = geometry.calib[:, 0]
    inv = torch.linalg.inv(p2[:, :, :3])
    hom = torch.cat([uv.double(), torch.ones_like(uv[..., :1], dtype=torch.float64)], -1)
    direction = hom @ inv.transpose(1, 2)  # [B,M,3], rectified
    offset = -(inv @ p2[:, :, 3:])[:, None, :, 0]  # [B,1,3]
    to_velo = torch.linalg.inv(velo_to_rect(geometry.calib))
    rot, shift = to_velo[:, :3, :3], to_velo[:, None, :3, 3]
    d_velo = direction @ rot.transpose(1, 2)
    o_velo = offset @ rot.transpose(1, 2) + shift
    dz = d_velo[..., 2]
    steep = dz.abs() > 1e-9
    s = (height.double() - o_velo[..., 2]) / torch.where(steep, dz, torch.ones_like(dz))
    xyz = o_velo + s[..., None] * d_velo
    depth = (offset + s[..., None] * direction)[..., 2]
    return xyz, steep & (depth >= min_depth)
