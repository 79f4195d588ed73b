"""Instance masks for real KITTI from its LiDAR scan and 3D boxes.

SMoE §3.1 annotates KITTI's 7481 object frames semi-automatically: Mask R-CNN (trained on Cityscapes and the 200
KITTI instance frames) proposes masks that people refine with polygons, over 8 iterations. Without those masks,
:func:`from_lidar` derives masks with no human step from what KITTI ships (the labelled 3D boxes and the scan), in
the spirit of the annotation from 3D boxes and point clouds of Chen et al. that SMoE §2 cites as [24]. The
dataset (``ablate.data.dataset``) uses them for a KITTI folder with no instance_2/.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, cast

import cv2
import numpy as np
from scipy import ndimage

from ablate.data.kitti import Calibration, Object3D
from ablate.data.lidar import dense_depth, project_points, sparse_depth

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

MARGIN = 0.2
"""Metres each 3D box is enlarged by on every side except its bottom (label noise, the LiDAR's range noise)."""
GROUND = 0.1
"""Metres above the box's bottom face below which nothing counts: the road under and beside a car."""
Window = tuple[int, int, int, int]
"""An object's 2D box as a pixel window (x0, y0, x1, y1), x1 and y1 excluded, clipped to the image."""


def _back_project(calib: Calibration, u: np.ndarray, v: np.ndarray, z: np.ndarray) -> np.ndarray:
    """(N,3) rectified-camera points of pixels (u, v) at depth z (rectified z, as in sparse_depth)."""
    inv = np.linalg.inv(calib.P2[:, :3])
    ray = np.stack([u, v, np.ones_like(u)], 1) @ inv.T  # P2[:, :3]^-1 (u, v, 1), one per pixel
    off = inv @ calib.P2[:, 3]
    scale = (z + off[2]) / ray[:, 2]  # the homogeneous scale that puts the point at depth z
    return ray * scale[:, None] - off


def _hull(calib: Calibration, corners: np.ndarray, origin: tuple[int, int], shape: tuple[int, int]) -> np.ndarray:
    """(H,W) bool crop at ``origin`` (x, y) of the projected 3D box; all True when a corner is behind the camera."""
    if corners[:, 2].min() <= 0.1:
        return np.ones(shape, bool)
    uv = calib.rect_to_image(corners).astype(np.float32)
    poly = np.rint(uv[cv2.convexHull(uv, returnPoints=False).ravel()] - origin).astype(np.int32)
    return cv2.fillConvexPoly(np.zeros(shape, np.uint8), poly, 1).view(bool)


def from_lidar(
    points: np.ndarray,
    calib: Calibration,
    objects: list[Object3D],
    shape: tuple[int, int],
    dense: np.ndarray | None = None,
) -> np.ndarray:
    """(N,H,W) bool instance masks, one per object of ``objects`` (as ``ablate.data.kitti.read_labels`` returns
    them), in that order; stands in for SMoE §3.1's semi-automatic annotation (see the module docstring).

    Readings (each step is limited to the object's labelled 2D box):

    1. Seeds: the LiDAR pixels (nearest point per pixel, ``project_points``) whose point lies inside the
       object's 3D box, enlarged by MARGIN = 0.2 m on every side but its bottom, which is raised by GROUND = 0.1 m
       so that the road the box stands on is no seed.
    2. Growth: a pixel is a candidate when its dense depth (``dense_depth`` of the frame's sparse depth,
       SMoE §3.2) back-projects inside that same box. This reads "the pixels whose depth lies within the box's
       depth range" with the whole box, not only its depth extent, so the road and walls beside the object at the
       same depth stay out. The confirmed mask is the candidates 8-connected to a seed.
    3. Completion: the LiDAR misses dark paint and glass and, far away, the roof above its top scan line; so each
       column of the mask grows upward from its top pixel, inside the projected 3D box, while nothing nearer than
       the box occludes the pixel; then enclosed holes are filled.
    4. Overlaps: masks never overlap. A confirmed pixel (step 2) beats another object's completed one (step 3);
       otherwise the nearest object (box centre nearest the camera) wins.

    Objects with no 3D box (DontCare, or any label with a non-positive dimension) and objects with no seed in
    their 2D box get an all-False mask. ``dense``: the frame's dense depth when at hand (computed otherwise).
    """
    h, w = shape
    masks = np.zeros((len(objects), h, w), bool)
    cores = np.zeros_like(masks)  # the LiDAR-confirmed part of each mask (steps 1-2)
    boxed = [k for k, o in enumerate(objects) if o.type != "DontCare" and min(o.dimensions) > 0]
    if not boxed:
        return masks
    lin, idx = project_points(points, calib, shape)
    seed_rect = calib.velo_to_rect(points[idx, :3])
    if dense is None:
        dense = dense_depth(sparse_depth(points, calib, shape))
    distance: dict[int, float] = {}
    for k in boxed:
        o = objects[k]
        found = _seeds(o, lin[o.contains(seed_rect, MARGIN, GROUND)], shape)
        if found is None:
            continue
        window, sv, su = found
        x0, y0, x1, y1 = window
        mask = _grow(o, calib, dense, window, sv, su)
        cores[k, y0:y1, x0:x1] = mask
        masks[k, y0:y1, x0:x1], distance[k] = _complete(o, calib, dense, window, mask)
    _resolve_overlaps(masks, cores, distance)
    return masks


def _seeds(o: Object3D, seeds: np.ndarray, shape: tuple[int, int]) -> tuple[Window, np.ndarray, np.ndarray] | None:
    """Step 1 of :func:`from_lidar`: the window of ``o``'s 2D box and the rows and columns of the seeds (flat
    indices ``seeds``) inside it; None when the window is empty or holds no seed."""
    h, w = shape
    x0, y0 = max(int(np.floor(o.bbox[0])), 0), max(int(np.floor(o.bbox[1])), 0)
    x1, y1 = min(int(np.ceil(o.bbox[2])) + 1, w), min(int(np.ceil(o.bbox[3])) + 1, h)
    sv, su = np.divmod(seeds, w)
    inside = (su >= x0) & (su < x1) & (sv >= y0) & (sv < y1)
    if not inside.any() or x1 <= x0 or y1 <= y0:
        return None
    return (x0, y0, x1, y1), sv[inside], su[inside]


def _grow(
    o: Object3D, calib: Calibration, dense: np.ndarray, window: Window, sv: np.ndarray, su: np.ndarray
) -> np.ndarray:
    """Step 2 of :func:`from_lidar`: the window's pixels whose dense depth back-projects inside ``o``'s enlarged
    box, 8-connected to a seed (rows ``sv``, columns ``su``): the LiDAR-confirmed mask, cropped to the window."""
    x0, y0, x1, y1 = window
    v, u = np.mgrid[y0:y1, x0:x1]
    rect = _back_project(calib, u.ravel().astype(float), v.ravel().astype(float), dense[y0:y1, x0:x1].ravel())
    cand = o.contains(rect, MARGIN, GROUND).reshape(v.shape)
    cand[sv - y0, su - x0] = True
    _, comp = cv2.connectedComponents(cand.view(np.uint8), connectivity=8)
    keep = np.zeros(comp.max() + 1, bool)
    keep[comp[sv - y0, su - x0]] = True
    keep[0] = False
    return keep[comp]


def _complete(
    o: Object3D, calib: Calibration, dense: np.ndarray, window: Window, core: np.ndarray
) -> tuple[np.ndarray, float]:
    """Step 3 of :func:`from_lidar`: ``core`` grown up each column from its top pixel, inside the projected box,
    while nothing nearer occludes the pixel, with its holes filled; and the distance of the box centre."""
    x0, y0, x1, y1 = window
    corners = o.corners()
    ok = _hull(calib, corners, (x0, y0), core.shape) & (dense[y0:y1, x0:x1] >= corners[:, 2].min() - MARGIN)
    above = np.arange(len(core))[:, None] < np.where(core.any(0), core.argmax(0), 0)
    mask = core | np.logical_and.accumulate((ok | ~above)[::-1], 0)[::-1] & above
    return ndimage.binary_fill_holes(mask), float(np.linalg.norm(corners.mean(0)))


def _resolve_overlaps(masks: np.ndarray, cores: np.ndarray, distance: dict[int, float]) -> None:
    """Step 4 of :func:`from_lidar`, in place: each pixel to one object, a confirmed pixel beating another
    object's completed one, the nearest object winning otherwise."""
    h, w = masks.shape[1:]
    owner = np.full((h, w), -1)
    for stack in (masks, cores):  # far to near, the filled parts first: the nearest paints last and wins, and a
        for k in sorted(distance, key=distance.__getitem__, reverse=True):  # confirmed pixel beats another's filled one
            owner[stack[k]] = k
    for k in distance:
        masks[k] &= owner == k


def instance_map(masks: np.ndarray) -> np.ndarray:
    """(H,W) uint16 instance map in instance_2's encoding: label line number from 1 of each mask, 0 none."""
    ids = np.arange(1, len(masks) + 1, dtype=np.uint16)[:, None, None]
    return (masks * ids).max(0, initial=0).astype(np.uint16) if len(masks) else np.zeros(masks.shape[1:], np.uint16)


def figure(split_dir: str | Path, frame: str, out: str | Path) -> None:
    """Save ``frame`` with its :func:`from_lidar` masks in colour and the labelled 2D boxes (DontCare dashed):
    the whole image above, the objects' region enlarged below; 80 dpi, 128 colours (a few hundred KB)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ablate.data import kitti

    paths = kitti.frame_paths(Path(split_dir), frame)
    image = kitti.read_image(paths["image"])
    objects = kitti.read_labels(paths["label"])
    masks = from_lidar(
        kitti.read_velodyne(paths["velodyne"]), kitti.Calibration.from_file(paths["calib"]), objects, image.shape[:2]
    )
    colours = plt.get_cmap("tab10")(np.arange(len(objects)) % 10)[:, :3]
    shown = image / 255.0
    for mask, colour in zip(masks, colours):
        shown[mask] = 0.4 * shown[mask] + 0.6 * colour
    h, w = image.shape[:2]
    x0, y0, x1, y1 = _objects_region(objects, w, h)
    zoom_w = min(2 * (x1 - x0), w)
    fig = plt.figure(figsize=(w / 100, (h + zoom_w * (y1 - y0) / (x1 - x0)) / 100 + 0.3), dpi=80)
    top, bottom = fig.subplots(2, 1, height_ratios=[h, zoom_w * (y1 - y0) / (x1 - x0)])
    for ax, (left, right, up, down) in ((top, (0, w, 0, h)), (bottom, (x0, x1, y0, y1))):
        ax.imshow(shown)
        ax.set_xlim(left, right)
        ax.set_ylim(down, up)
        ax.set_axis_off()
        _draw_boxes(ax, objects, masks, colours, counts=ax is bottom)
    top.set_title(
        f"KITTI object {frame}: instance masks from LiDAR + 3D boxes (ablate.data.masks.from_lidar), "
        "label_2 2D boxes (DontCare dashed); below, the objects enlarged",
        fontsize=9,
    )
    _save_png(fig, out)


def _objects_region(objects: list[Object3D], w: int, h: int) -> tuple[float, float, float, float]:
    """(x0, y0, x1, y1) around all the labelled 2D boxes with a 20-pixel margin, inside the image (all of it
    without a box)."""
    boxes = np.array([o.bbox for o in objects]).reshape(-1, 4)
    x0, y0 = np.maximum(boxes[:, :2].min(0, initial=np.inf) - 20, 0) if len(boxes) else (0, 0)
    x1, y1 = np.minimum(boxes[:, 2:].max(0, initial=-np.inf) + 20, (w, h)) if len(boxes) else (w, h)
    return x0, y0, x1, y1


def _draw_boxes(ax: Axes, objects: list[Object3D], masks: np.ndarray, colours: np.ndarray, counts: bool) -> None:
    """Each object's 2D box in its mask's colour (DontCare dashed, white); ``counts``: with its type and mask
    pixels."""
    import matplotlib.pyplot as plt

    for o, mask, colour in zip(objects, masks, colours):
        bx0, by0, bx1, by1 = o.bbox
        dontcare = o.type == "DontCare"
        ax.add_patch(
            plt.Rectangle(
                (bx0, by0),
                bx1 - bx0,
                by1 - by0,
                fill=False,
                lw=1,
                ls="--" if dontcare else "-",
                ec="white" if dontcare else colour,
            )
        )
        if counts and not dontcare:
            ax.text(bx0, by0 - 1, f"{o.type} {int(mask.sum())} px", color=colour, fontsize=8)


def _save_png(fig: Figure, out: str | Path) -> None:
    """Save ``fig`` as a 128-colour PNG at ``out`` (its folder made) and close it."""
    import matplotlib.pyplot as plt
    from PIL import Image

    fig.tight_layout(pad=0.2)
    fig.canvas.draw()
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.asarray(cast("FigureCanvasAgg", fig.canvas).buffer_rgba())[..., :3]).quantize(128).save(
        out, optimize=True
    )
    plt.close(fig)
