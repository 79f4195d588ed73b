"""The targets built from a frame's ground truth: the image-space ones (road mask, objects, semantic classes, instance
masks, 2D boxes and the DontCare ``ignore`` mask, as ``ablate.data.dataset`` returns them), the road in the BEV grid,
and the calibration as an array and back."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import numpy as np
import torch

from ablate.data import DataError, kitti, lidar
from ablate.data.augment import flip_box

CLASSES = ("Car", "Pedestrian", "Cyclist")  # label ids 0, 1, 2
#: ``boxes2d`` label ids: the classes, then the KITTI types its evaluation ignores (ablate.metrics.kitti.LABEL_NAMES):
#: Van (neighbour of Car), Person_sitting (of Pedestrian) and DontCare regions.
BOX_LABELS = (*CLASSES, "Van", "Person_sitting", "DontCare")


def mirrored(
    labels: list[kitti.Object3D], road_gt: tuple[np.ndarray, ...] | None, inst: np.ndarray | None, w: int
) -> tuple[list[kitti.Object3D], tuple[np.ndarray, ...] | None, np.ndarray | None]:
    """The image-space labels, road ground truth and instance map of the flipped image (ablate.data.augment)."""
    labels = [replace(o, bbox=flip_box(o.bbox, w)) for o in labels]
    road_gt = tuple(np.ascontiguousarray(a[:, ::-1]) for a in road_gt) if road_gt is not None else None
    inst = np.ascontiguousarray(inst[:, ::-1]) if inst is not None else None
    return labels, road_gt, inst


def image_targets(
    targets: Sequence[str],
    labels: list[kitti.Object3D],
    road: np.ndarray | None,
    inst: np.ndarray | None,
    shape: tuple[int, int],
) -> dict[str, Any]:
    """The image-space targets of ``targets`` from the labels, road mask and instance map (each there when asked
    for), with the ``ignore`` mask of the DontCare regions for ``instances`` and ``boxes2d``."""
    out: dict[str, Any] = {}
    if "free_space" in targets:
        assert road is not None  # checked by the dataset
        out["free_space"] = torch.from_numpy(road[None].astype(np.float32))
    if "road_objects" in targets:
        assert inst is not None  # checked by the dataset
        out["road_objects"] = torch.from_numpy((inst > 0)[None].astype(np.float32))
    if "semantic" in targets:
        assert inst is not None and road is not None  # checked by the dataset
        out["semantic"] = torch.from_numpy(np.where(inst > 0, 2, road.astype(np.int64)).astype(np.int64))
    if "instances" in targets:
        assert inst is not None  # checked by the dataset
        out["instances"] = instance_target(labels, inst, shape)
    if "boxes2d" in targets:
        out["boxes2d"] = boxes2d_target(labels, shape[0])
    if "instances" in targets or "boxes2d" in targets:
        out["ignore"] = torch.from_numpy(dontcare_mask(labels, shape))
    return out


def instance_target(labels: list[kitti.Object3D], inst: np.ndarray, shape: tuple[int, int]) -> dict[str, Any]:
    """Masks, label ids and 2D boxes of the cars and pedestrians with a mask pixel in the instance map ``inst``."""
    h, w = shape
    present = set(np.unique(inst).tolist())  # a labelled object with no mask pixel is left out
    ids = [k + 1 for k, o in enumerate(labels) if o.type in CLASSES[:2] and k + 1 in present]
    return {
        "masks": torch.from_numpy(np.stack([inst == k for k in ids]) if ids else np.zeros((0, h, w), bool)),
        "labels": torch.tensor([CLASSES.index(labels[k - 1].type) for k in ids], dtype=torch.int64),
        "boxes": torch.tensor([labels[k - 1].bbox for k in ids], dtype=torch.float32).reshape(-1, 4),
    }


def boxes2d_target(labels: list[kitti.Object3D], h: int) -> dict[str, torch.Tensor]:
    """2D boxes, :data:`BOX_LABELS` ids and KITTI difficulty of the labels of those types, in an image of ``h`` rows."""
    objs = [o for o in labels if o.type in BOX_LABELS]
    scale = h / 375.0  # KITTI's difficulty heights are for 375-row images
    return {
        "boxes": torch.tensor([o.bbox for o in objs], dtype=torch.float32).reshape(-1, 4),
        "labels": torch.tensor([BOX_LABELS.index(o.type) for o in objs], dtype=torch.int64),
        "difficulty": torch.tensor([o.difficulty_at(scale) for o in objs], dtype=torch.int64),
    }


def dontcare_mask(labels: list[kitti.Object3D], shape: tuple[int, int]) -> np.ndarray:
    """(H,W) bool: the pixels of the DontCare regions' 2D boxes."""
    ignore = np.zeros(shape, bool)
    for o in labels:
        if o.type == "DontCare":
            x0, y0, x1, y1 = (int(round(v)) for v in o.bbox)
            ignore[max(y0, 0) : y1 + 1, max(x0, 0) : x1 + 1] = True
    return ignore


def calib_array(calib: kitti.Calibration) -> np.ndarray:
    """(4,3,4) float64: P2, R0_rect (in [:3,:3]), Tr_velo_to_cam, Tr_cam_to_road (NaN when the file has none)."""
    out = np.full((4, 3, 4), np.nan)
    out[0], out[2] = calib.P2, calib.Tr_velo_to_cam
    out[1] = 0.0
    out[1, :, :3] = calib.R0_rect
    if calib.Tr_cam_to_road is not None:
        out[3] = calib.Tr_cam_to_road
    return out


def calibration(array: np.ndarray | torch.Tensor) -> kitti.Calibration:
    """The :class:`~ablate.data.kitti.Calibration` of a :func:`calib_array` (numpy or a CPU/GPU tensor)."""
    a = np.asarray(array.detach().cpu() if isinstance(array, torch.Tensor) else array, np.float64)
    road = None if np.isnan(a[3]).any() else a[3]
    return kitti.Calibration(P2=a[0], R0_rect=a[1, :, :3], Tr_velo_to_cam=a[2], Tr_cam_to_road=road)


def road_bev(
    road: np.ndarray,
    calib: kitti.Calibration,
    x_range: tuple[float, float] = (6.0, 46.0),
    y_range: tuple[float, float] = (-10.0, 10.0),
    cell: float = 0.5,
) -> np.ndarray:
    """Road mask in the BEV grid of :func:`ablate.data.lidar.bev_image`: each cell centre is dropped onto the road
    plane (Tr_cam_to_road) and looked up in the image road mask; cells outside the image are 0."""
    if calib.Tr_cam_to_road is None:
        raise DataError(f"{calib.path}: road_bev needs Tr_cam_to_road in the calibration")
    hb, wb = lidar.bev_grid(x_range, y_range, cell)
    xs = x_range[1] - (np.arange(hb) + 0.5) * cell
    ys = y_range[1] - (np.arange(wb) + 0.5) * cell
    x, y = np.meshgrid(xs, ys, indexing="ij")
    # velodyne -> road frame is affine; solve for the z that puts the point on the road plane (road Y = 0).
    a = calib.Tr_cam_to_road[1] @ calib.velo_to_rect_matrix  # road Y as a function of (x, y, z, 1)
    z = -(a[0] * x + a[1] * y + a[3]) / a[2]
    uv, depth = calib.velo_to_image(np.stack([x.ravel(), y.ravel(), z.ravel()], 1))
    u, v = np.rint(uv[:, 0]), np.rint(uv[:, 1])
    h, w = road.shape
    ok = (depth > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    out = np.zeros(hb * wb, np.float32)
    out[ok] = road[v[ok].astype(np.int64), u[ok].astype(np.int64)]
    return out.reshape(hb, wb)
