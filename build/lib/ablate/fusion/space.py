"""Space transforms between the camera's perspective and the LiDAR's bird's-eye view (BEV), one registry.

A space transform carries feature maps from one space into the other at any feature scale. It holds no weights:
``maps(geometry, cam_size, bev_size, stride)`` builds, from each sample's calibration and LiDAR (a
:class:`Geometry`), the pair ``(to_bev, to_cam)`` of callables ``[B,C,h,w] -> [B,C,h',w']``; positions the
transform does not reach are 0.

* ``dst``: BiFNet's dense space transformation (Li et al., seed 004 §IV-A): dense index maps, one source position
  for every target position whose 3D point the geometry places (:class:`IndexMap`).
* ``shpl``: sparse non-homogeneous pooling (Wang et al. [42], BiFNet §V-E): through the LiDAR points only, each
  target position the mean over the points that fall in it of the features at their other-space positions
  (:class:`PointPooling`); positions with no point stay 0.

Feature position (i, j) at stride s stands for the input position ((i + 0.5) s - 0.5, (j + 0.5) s - 0.5) (pixel
rows and columns; BEV rows along x with row 0 the farthest, columns along y with column 0 the leftmost, the grid of
:func:`ablate.data.lidar.bev_image`), and an input position belongs to the feature position floor(p / s).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, cast

import torch
from torch import Tensor

from ablate.fusion.geometry import Geometry, backproject, project
from ablate.fusion.ops import registry

SPACES: dict[str, type[SpaceTransform]] = {}


#: Class decorator adding a space transform to ``SPACES`` under a name.
register_space = registry(SPACES, "space transform", "space_name")


def build_space(name: str) -> SpaceTransform:
    """The space transform ``name`` of ``SPACES``."""
    if name not in SPACES:
        raise ValueError(f"unknown space transform {name!r}; valid: {', '.join(sorted(SPACES))}")
    return SPACES[name]()


@dataclass
class IndexMap:
    """Dense transform: target position t reads the source position ``index[b, t]`` (-1: none, the output is 0).
    ``index`` is [B, Ht * Wt] (row-major), ``size`` (Ht, Wt)."""

    index: Tensor
    size: tuple[int, int]

    def __call__(self, x: Tensor) -> Tensor:
        b, c = x.shape[:2]
        idx = self.index.clamp(min=0)[:, None, :].expand(b, c, -1)
        out = x.flatten(2).gather(2, idx) * (self.index >= 0)[:, None, :].to(x.dtype)
        return out.view(b, c, *self.size)

    @property
    def coverage(self) -> Tensor:
        """[B, Ht, Wt] bool: where the transform gives a feature."""
        return (self.index >= 0).view(-1, *self.size)


@dataclass
class PointPooling:
    """Sparse transform through points: point n links target position ``target[b, n]`` and source position
    ``source[b, n]`` (-1 in either: the point is not used); a target position is the mean of the source features of
    its points, 0 without any. Both are [B, N] row-major indices; ``size`` the target's (Ht, Wt)."""

    target: Tensor
    source: Tensor
    size: tuple[int, int]

    def __call__(self, x: Tensor) -> Tensor:
        b, c = x.shape[:2]
        valid = (self.target >= 0) & (self.source >= 0)
        vals = x.flatten(2).gather(2, self.source.clamp(min=0)[:, None, :].expand(b, c, -1))
        vals = vals * valid[:, None, :].to(x.dtype)
        tgt = self.target.clamp(min=0)
        out = x.new_zeros(b, c, self.size[0] * self.size[1]).scatter_add_(2, tgt[:, None, :].expand(b, c, -1), vals)
        count = x.new_zeros(b, self.size[0] * self.size[1]).scatter_add_(1, tgt, valid.to(x.dtype))
        return (out / count.clamp(min=1)[:, None, :]).view(b, c, *self.size)

    @property
    def coverage(self) -> Tensor:
        """[B, Ht, Wt] bool: target positions with at least one point."""
        valid = ((self.target >= 0) & (self.source >= 0)).long()
        count = valid.new_zeros(self.target.shape[0], self.size[0] * self.size[1])
        return count.scatter_add_(1, self.target.clamp(min=0), valid).view(-1, *self.size) > 0


class SpaceMap(Protocol):
    """One direction of a space transform (:class:`IndexMap`, :class:`PointPooling`): ``[B,C,h,w] -> [B,C,h',w']``,
    and the target positions it reaches."""

    def __call__(self, x: Tensor) -> Tensor: ...

    @property
    def coverage(self) -> Tensor: ...


class SpaceTransform:
    """Base class: ``maps(geometry, cam_size, bev_size, stride) -> (to_bev, to_cam)``."""

    space_name = "?"

    def maps(
        self, geometry: Geometry, cam_size: tuple[int, int], bev_size: tuple[int, int], stride: int
    ) -> tuple[SpaceMap, SpaceMap]:
        raise NotImplementedError

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"


def _centres(size: tuple[int, int], stride: int, limit: tuple[int, int], device: torch.device) -> tuple[Tensor, Tensor]:
    """Input positions (rows, cols; float64, each [h*w]) that feature positions of ``size`` at ``stride`` stand for,
    clamped into an input of ``limit`` (rows, cols)."""
    rows = ((torch.arange(size[0], device=device, dtype=torch.float64) + 0.5) * stride - 0.5).clamp(0, limit[0] - 1)
    cols = ((torch.arange(size[1], device=device, dtype=torch.float64) + 0.5) * stride - 0.5).clamp(0, limit[1] - 1)
    r, c = torch.meshgrid(rows, cols, indexing="ij")
    return r.reshape(-1), c.reshape(-1)


def _flat(row: Tensor, col: Tensor, full: tuple[int, int], size: tuple[int, int], stride: int) -> Tensor:
    """Index of the feature position (``size``, ``stride``) holding input position (row, col) of an input of
    ``full``; -1 outside the input (or outside the feature map)."""
    r, c = torch.floor(row), torch.floor(col)
    inside = (r >= 0) & (r < full[0]) & (c >= 0) & (c < full[1])
    r, c = (r.clamp(0, full[0] - 1) // stride).long(), (c.clamp(0, full[1] - 1) // stride).long()
    inside &= (r < size[0]) & (c < size[1])
    return torch.where(inside, r * size[1] + c, torch.full_like(r, -1))


@register_space("dst")
class DST(SpaceTransform):
    """Dense space transformation, BiFNet §IV-A (eq. 2-8).

    Reading chosen: each direction is a gather defined on the *target* space, so that every target position gets a
    feature ("the transformation relationship of each pixel of feature maps in different spaces", §V-E), and the
    dense heights serve the direction §IV-A1 and §IV-A2 name: "to achieve dense mapping from BEV space to camera
    space, the height of each pixel in camera image is needed" and "from camera space to BEV space, it is required to
    know the spatial position of each pixel in BEV".

    * ``to_cam`` (features BEV -> camera): a pixel's ray is back-projected (eq. 5) and scaled (eq. 6-7) so that
      its point's LiDAR height equals the pixel's dense height (:func:`ablate.data.lidar.perspective_height`); the
      point indexes a BEV cell. Reading of eq. 6: the scale runs along the pixel's ray from the camera centre (the
      text's ratio of heights is this scale when the LiDAR height is measured from the camera).
    * ``to_bev`` (features camera -> BEV): a cell's centre at its dense height
      (:func:`ablate.data.lidar.bev_height`) is projected into the image (eq. 8) and indexes a pixel.

    A feature position's height is the dense height of the input position it stands for (nearest pixel or cell).
    """

    def maps(
        self, geometry: Geometry, cam_size: tuple[int, int], bev_size: tuple[int, int], stride: int
    ) -> tuple[IndexMap, IndexMap]:
        g = geometry
        g.need("height_image", "height_bev", by="space transform 'dst'")
        assert g.height_image is not None and g.height_bev is not None  # need raised otherwise
        dev = g.height_image.device
        image, bev = g.image_size, g.grid.shape
        # camera -> BEV features: every BEV feature position projected into the image (eq. 8)
        r, c = _centres(bev_size, stride, bev, dev)
        heights = g.height_bev[:, 0].double().flatten(1)[:, (r.round().long() * bev[1] + c.round().long())]
        x, y = g.grid.x_range[1] - (r + 0.5) * g.grid.cell, g.grid.y_range[1] - (c + 0.5) * g.grid.cell
        xyz = torch.stack([x.expand_as(heights), y.expand_as(heights), heights], -1)
        uv, depth = project(g, xyz)
        to_bev = _flat(uv[..., 1] + 0.5, uv[..., 0] + 0.5, image, cam_size, stride)
        to_bev = torch.where(depth > 0, to_bev, torch.full_like(to_bev, -1))
        # BEV -> camera features: every camera feature position back-projected at its dense height (eq. 5-7)
        r, c = _centres(cam_size, stride, image, dev)
        heights = g.height_image[:, 0].double().flatten(1)[:, (r.round().long() * image[1] + c.round().long())]
        uv = torch.stack([c, r], -1).expand(heights.shape[0], -1, -1)
        xyz, ok = backproject(g, uv, heights)
        to_cam = _flat(
            (g.grid.x_range[1] - xyz[..., 0]) / g.grid.cell,
            (g.grid.y_range[1] - xyz[..., 1]) / g.grid.cell,
            bev,
            bev_size,
            stride,
        )
        to_cam = torch.where(ok, to_cam, torch.full_like(to_cam, -1))
        return (
            IndexMap(to_bev, cast("tuple[int, int]", tuple(bev_size))),
            IndexMap(to_cam, cast("tuple[int, int]", tuple(cam_size))),
        )


@register_space("shpl")
class SHPL(SpaceTransform):
    """Sparse non-homogeneous pooling (Wang et al. [42]), BiFNet's baseline in §V-E: "based on the points of the
    point cloud to establish the relationship between image and BEV"; "only a small proportion of pixels in feature
    maps have corresponding feature vectors".

    Every LiDAR point inside the BEV grid that projects into the image (:attr:`Geometry.points`) links its BEV cell
    and its pixel at each scale; a BEV feature position is the mean of the camera features at the pixels of its
    points, and a camera feature position the mean of the BEV features at the cells of its points (the pooling's
    non-homogeneous weights: 1 / the number of points). No point, no feature: 0.
    """

    def maps(
        self, geometry: Geometry, cam_size: tuple[int, int], bev_size: tuple[int, int], stride: int
    ) -> tuple[PointPooling, PointPooling]:
        g = geometry
        g.need("points", by="space transform 'shpl'")
        assert g.points is not None  # need raised otherwise
        present = torch.isfinite(g.points).all(-1)
        count = int(present.sum(1).max()) if present.numel() else 0  # the padding (NaN rows) comes last
        pts, present = g.points[:, :count].double(), present[:, :count]
        uv, depth = project(g, torch.nan_to_num(pts))
        pixel = _flat(torch.floor(uv[..., 1] + 0.5), torch.floor(uv[..., 0] + 0.5), g.image_size, cam_size, stride)
        cell = _flat(
            (g.grid.x_range[1] - pts[..., 0]) / g.grid.cell,
            (g.grid.y_range[1] - pts[..., 1]) / g.grid.cell,
            g.grid.shape,
            bev_size,
            stride,
        )
        used = present & (depth > 0) & (pixel >= 0) & (cell >= 0)
        pixel, cell = (torch.where(used, t, torch.full_like(t, -1)) for t in (pixel, cell))
        return (
            PointPooling(cell, pixel, cast("tuple[int, int]", tuple(bev_size))),
            PointPooling(pixel, cell, cast("tuple[int, int]", tuple(cam_size))),
        )
