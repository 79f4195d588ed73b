"""What the dense depth map (DDM, SMoE §3.2) tells apart, on real KITTI frames and on the generated ones: the data
side of why SMoE's DDM expert finds twice the camera expert's mask AP here (docs/recipes.md#instance_cpu).

    PYTHONPATH=. python bench/depth_clutter.py [--real ../shared/kitti/object/training] [--synth data/synth-...]
        [--frames 200]

Per frame set, with no model:

- **Depth edges off the objects** (clutter): the share of background pixels (outside every labelled box, dilated by
  2 px; rows from the highest LiDAR return down; depth at most ``NEAR`` m) next to a depth edge: a 4-neighbour whose
  depth differs by more than ``JUMP`` (relative). A DDM whose background is smooth leaves only the objects as
  depth blobs on the road, so a depth detector has few false positives to learn away; a camera has texture there.
- **Camera edges off the objects**: the same share for the L* channel (CIELab) with a step over ``L_STEP``.
- **Top-edge width**: per counted object (Car, Pedestrian, at least 25 px tall at 375 rows), in the column through
  its box centre, the rows between the object's depth (within ``JUMP``) and the background's above its box top
  (the first row beyond 1.2x the object's depth), as a share of its box height: how sharp the DDM draws its outline
  after the Delaunay completion; only objects with such a jump above them count.

The shares are per pixel, so a smaller image of the same scene reads higher (an edge covers more of its pixels):
``--rows`` measures every set on one grid (the generated data's 128 rows: the real frames resized to it, the image
by area and the DDM, made at full size from the full scan, to its nearest pixels). The top-edge width is a share of
the object's height, the same at any size.
"""

from __future__ import annotations

import argparse
import statistics
from pathlib import Path

import cv2
import numpy as np

from ablate.data import kitti
from ablate.data.difficulty import counted
from ablate.data.lidar import dense_depth, sparse_depth

REPO = Path(__file__).resolve().parents[1]
JUMP, L_STEP, NEAR = 0.10, 8.0, 40.0  # relative depth step; L* units; metres


def edges(values: np.ndarray, relative: bool, step: float) -> np.ndarray:
    """Pixels with a 4-neighbour differing by more than ``step`` (relative to the nearer value where ``relative``)."""
    out = np.zeros(values.shape, bool)
    for axis in (0, 1):
        a, b = np.swapaxes(values, 0, axis)[:-1], np.swapaxes(values, 0, axis)[1:]
        diff = np.abs(a - b) / np.minimum(a, b) if relative else np.abs(a - b)
        hit = diff > step
        view = np.swapaxes(out, 0, axis)
        view[:-1] |= hit
        view[1:] |= hit
    return out


def top_width(ddm: np.ndarray, box: tuple[float, float, float, float]) -> float | None:
    """Rows of the depth transition above the box's top, over the box's height (None: no background jump there)."""
    x0, y0, x1, y1 = (int(round(v)) for v in box)
    u = min(max((x0 + x1) // 2, 0), ddm.shape[1] - 1)
    inner = ddm[max(y0, 0) + (y1 - y0) // 4 : y1 - (y1 - y0) // 4, u]
    if inner.size == 0 or y0 <= 0:
        return None
    z = float(np.median(inner))
    column = ddm[: max(y0, 0) + (y1 - y0) // 2, u][::-1]  # from the box's middle upwards
    inside = np.flatnonzero(np.abs(column - z) > JUMP * z)
    beyond = np.flatnonzero(column > 1.2 * z)
    if not len(inside) or not len(beyond):
        return None
    return float(beyond[0] - inside[0] + 1) / max(y1 - y0, 1)


def frame(split: Path, name: str, rows: int | None) -> dict:
    """One frame's counts; ``rows``: first resized to that height (the image by area, the DDM to its nearest
    pixels, the boxes scaled), so that sets of different sizes are measured on one pixel grid."""
    paths = kitti.frame_paths(split, name)
    image = kitti.read_image(paths["image"])
    calib = kitti.Calibration.from_file(paths["calib"])
    sparse = sparse_depth(kitti.read_velodyne(paths["velodyne"]), calib, image.shape[:2])
    top = int(np.flatnonzero(sparse.any(1))[0])  # the highest row with a LiDAR return
    ddm = dense_depth(sparse)
    scale = 1.0 if rows is None else rows / image.shape[0]
    if scale != 1.0:
        size = (round(image.shape[1] * scale), rows)
        image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
        ddm = cv2.resize(ddm, size, interpolation=cv2.INTER_NEAREST)
        top = int(top * scale)
    lab = cv2.cvtColor(image.astype(np.float32) / 255.0, cv2.COLOR_RGB2Lab)[..., 0]
    boxes = [(o.type, tuple(v * scale for v in o.bbox)) for o in kitti.read_labels(paths["label"])]
    background = np.ones(ddm.shape, bool)
    background[:top] = False
    background &= ddm <= NEAR
    for _, box in boxes:
        x0, y0, x1, y1 = (int(round(v)) for v in box)
        background[max(y0 - 2, 0) : y1 + 3, max(x0 - 2, 0) : x1 + 3] = False
    objects = [box for kind, box in boxes if kind in ("Car", "Pedestrian")]
    heights = np.array([b[3] - b[1] for b in objects])
    kept = [b for b, ok in zip(objects, counted(heights, image.shape[0]) if objects else []) if ok]
    widths = [w for w in (top_width(ddm, b) for b in kept) if w is not None]
    return {
        "pixels": int(background.sum()),
        "depth": int((edges(ddm, True, JUMP) & background).sum()),
        "camera": int((edges(lab, False, L_STEP) & background).sum()),
        "widths": widths,
        "shape": image.shape[:2],
    }


def measure(split: Path, limit: int, height: int | None) -> dict:
    names = kitti.list_frames(split)[:limit]
    rows = [frame(split, n, height) for n in names]
    pixels = sum(r["pixels"] for r in rows)
    widths = [w for r in rows for w in r["widths"]]
    return {
        "frames": len(rows),
        "shape": rows[0]["shape"],
        "depth": 100 * sum(r["depth"] for r in rows) / pixels,
        "camera": 100 * sum(r["camera"] for r in rows) / pixels,
        "objects": len(widths),
        "width": statistics.median(widths) if widths else float("nan"),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--real", type=Path, default=REPO.parent / "shared" / "kitti" / "object" / "training")
    parser.add_argument(
        "--synth", type=Path, default=None, help="a generated dataset (default: the newest under data/)"
    )
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--rows", type=int, default=None, help="resize every frame to this height first")
    args = parser.parse_args()
    synth = args.synth or max((REPO / "data").glob("synth-*"), key=lambda p: p.stat().st_mtime, default=None)
    sets = {"real KITTI": args.real, "generated": synth}
    print(f"background: off the labelled boxes, rows from the highest LiDAR return down, depth <= {NEAR:g} m")
    print(
        "| frames | set | size | depth edges % (> 10 % step) | camera edges % (L* step > 8) | top-edge width / height |"
    )
    print("|---|---|---|---|---|---|")
    for label, root in sets.items():
        if root is None or not Path(root).is_dir():
            print(f"| — | {label} | not found: {root} | | | |")
            continue
        m = measure(kitti.find_split_dir(root, "object"), args.frames, args.rows)
        h, w = m["shape"]
        print(
            f"| {m['frames']} | {label} | {w}x{h} | {m['depth']:.1f} | {m['camera']:.1f} "
            f"| {m['width']:.2f} (median of {m['objects']}) |"
        )


if __name__ == "__main__":
    main()
