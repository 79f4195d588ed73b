"""Road predictions of both spaces warped into the KITTI road devkit's metric BEV, to be scored by
:class:`ablate.metrics.road.RoadMaxF` ("All metrics are calculated in BEV space", BiFNet §V-A).

* Camera space: each metric cell's nearest image pixel through the road homography (``road_homography`` and
  ``bev_lookup`` of :mod:`ablate.metrics.road`): what ``RoadMaxF.update(..., calib=...)`` does.
* LiDAR BEV (the 0.5 m raster of ``ablate.data.lidar.bev_image`` in the velodyne frame, not the devkit's 0.05 m
  grid on the road plane): each metric cell's centre on the road plane (``Tr_cam_to_road``) is carried into the
  velodyne frame and takes the value of the raster cell that contains it (0 outside the raster).
* Ground truth and don't-care: the image road mask and its void mask warped as in the camera case, for both spaces,
  so the two branches of one model are scored on the same cells against the same ground truth; cells whose centre
  falls outside the image are don't-care, as in the devkit.

Lookups depend on the calibration only and are cached per calibration and image size.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from ablate.data import DataError
from ablate.data.dataset import calibration
from ablate.data.kitti import Calibration
from ablate.fusion.geometry import BevGrid
from ablate.metrics.road import BEV_RES, BEV_X, BEV_Z, bev_centres, bev_lookup, bev_shape, road_homography


class MetricBev:
    """Warps [B,H,W] camera maps and [B,Hb,Wb] LiDAR-BEV maps to the devkit grid [B,rows,cols]."""

    def __init__(
        self,
        grid: BevGrid = BevGrid(),
        res: float = BEV_RES,
        x_range: Sequence[float] = BEV_X,
        z_range: Sequence[float] = BEV_Z,
        cache_size: int = 256,
    ) -> None:
        self.grid, self.res, self.x_range, self.z_range = grid, res, tuple(x_range), tuple(z_range)
        self.shape = bev_shape(res, self.x_range, self.z_range)
        self.cache_size = cache_size
        self._cache: dict[tuple, tuple[Tensor, Tensor]] = {}

    def _lookup(self, kind: str, calib: Tensor, size: tuple[int, int]) -> tuple[Tensor, Tensor]:
        a = np.asarray(calib.detach().cpu(), np.float64)
        key = (kind, a.tobytes(), tuple(size))
        if key not in self._cache:
            if len(self._cache) >= self.cache_size:
                self._cache.clear()
            cal = calibration(a)
            if cal.Tr_cam_to_road is None:
                raise DataError(
                    "road metrics in BEV need Tr_cam_to_road in each frame's calibration (KITTI road "
                    "layout, or the generated data)"
                )
            index, inside = (
                bev_lookup(road_homography(cal), size, self.res, self.x_range, self.z_range)
                if kind == "camera"
                else self._lidar(cal)
            )
            self._cache[key] = torch.from_numpy(index), torch.from_numpy(inside)
        return self._cache[key]

    def _lidar(self, cal: Calibration) -> tuple[np.ndarray, np.ndarray]:
        """Per metric cell: the flat index of the LiDAR raster cell holding its centre, and whether there is one."""
        assert cal.Tr_cam_to_road is not None  # _lookup raised otherwise
        x, z = bev_centres(self.res, self.x_range, self.z_range)
        road = np.stack([x.ravel(), np.zeros(x.size), z.ravel(), np.ones(x.size)])
        to_road = np.vstack([cal.Tr_cam_to_road, [0, 0, 0, 1]])
        rect = np.eye(4)
        rect[:3, :3] = cal.R0_rect
        velo = np.linalg.inv(cal.velo_to_rect_matrix) @ rect @ np.linalg.inv(to_road) @ road
        g = self.grid
        row = np.floor((g.x_range[1] - velo[0]) / g.cell).astype(np.int64)
        col = np.floor((g.y_range[1] - velo[1]) / g.cell).astype(np.int64)
        hb, wb = g.shape
        inside = (row >= 0) & (row < hb) & (col >= 0) & (col < wb)
        return np.where(inside, row * wb + col, 0), inside

    def _warp(self, kind: str, maps: Tensor, calibs: Tensor, fill: float = 0.0) -> tuple[Tensor, Tensor]:
        out, mask = [], []
        for m, c in zip(maps, calibs):
            index, inside = (t.to(m.device) for t in self._lookup(kind, c, tuple(m.shape[-2:])))
            v = m.reshape(-1)[index]
            out.append(torch.where(inside, v, torch.full_like(v, fill)).view(self.shape))
            mask.append(inside.view(self.shape))
        return torch.stack(out), torch.stack(mask)

    def camera(self, maps: Tensor, calibs: Tensor) -> tuple[Tensor, Tensor]:
        """[B,H,W] (or [B,1,H,W]) image-space maps -> (metric-BEV maps, cells inside the image)."""
        return self._warp("camera", maps.flatten(0, -3) if maps.ndim == 4 else maps, calibs)

    def lidar(self, maps: Tensor, calibs: Tensor) -> Tensor:
        """[B,Hb,Wb] (or [B,1,Hb,Wb]) LiDAR-raster maps -> metric-BEV maps (0 outside the raster)."""
        return self._warp("lidar", maps.flatten(0, -3) if maps.ndim == 4 else maps, calibs)[0]
