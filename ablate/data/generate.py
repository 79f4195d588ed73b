"""Render generated frames and write them in the KITTI object layout (plus masks for the other tasks).

Per frame ``NNNNNN``: image_2/NNNNNN.png, velodyne/NNNNNN.bin, calib/NNNNNN.txt (with Tr_cam_to_road),
label_2/NNNNNN.txt (true 2D/3D boxes, truncation, occlusion; DontCare for objects under 25 px at KITTI's
375-row scale, or with under 20 visible pixels), instance_2/NNNNNN.png (uint16: label line number from 1, 0 none), gt_image_2/road_NNNNNN.png (visible
road in KITTI road colours). ImageSets/{train,val,test}.txt hold a seeded 60/20/20 split; synth.json the
parameters.
"""

from __future__ import annotations

import json
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from tqdm import tqdm

from ablate.data import GENERATOR_VERSION
from ablate.data import lidar_physics as physics
from ablate.data.kitti import Calibration, Object3D, write_road_gt
from ablate.data.raycast import BORDER, BOX, CAMERA_HEIGHT, ROAD, cast
from ablate.data.shade import glass_mask, shade
from ablate.data.synth import (
    BUILDING,
    CLASS_NAMES,
    LIDAR_ORIGIN,
    beam_directions,
    camera_matrix,
    camera_rays,
    lidar_angles,
    sample_scene,
)

TR_VELO_TO_CAM = np.array([[0, -1, 0, 0], [0, 0, -1, LIDAR_ORIGIN[1]], [1, 0, 0, LIDAR_ORIGIN[2]]], np.float64)


def calibration(height: int, width: int) -> Calibration:
    """Calibration of the generated rig: scaled KITTI P2, identity R0_rect, velodyne 1.73 m above the road."""
    road = np.hstack([np.eye(3), [[0.0], [-CAMERA_HEIGHT], [0.0]]])
    return Calibration(camera_matrix(height, width), np.eye(3), TR_VELO_TO_CAM, road)


def frame_rng(seed: int, index: int) -> np.random.Generator:
    return np.random.default_rng([seed, index])


def render_frame(
    seed: int, index: int, height: int = 128, width: int = 416, lidar_fov: float = 45.0, furniture: bool = False
) -> dict:
    """Render one frame: rgb (H,W,3) uint8, depth (H,W) float32 (0 = sky), points (N,4) float32, labels
    (list of Object3D), instance (H,W) uint16, road (H,W) bool, calib. ``furniture``: street furniture in the
    scene (:func:`ablate.data.synth.sample_scene`)."""
    rng, scene, calib, rays, hit = camera_cast(seed, index, height, width, furniture)
    rgb = shade(scene, hit, rays) + rng.normal(0, 0.01, (len(rays), 3)).astype(np.float32)
    image = np.round(np.clip(rgb, 0, 1) * 255).astype(np.uint8).reshape(height, width, 3)
    depth = np.where(np.isfinite(hit["t"]), hit["t"], 0).astype(np.float32).reshape(height, width)
    owner = np.where(hit["box"] >= 0, scene["owner"][np.maximum(hit["box"], 0)], -1)
    labels, instance = _labels(scene, hit, owner, calib, height, width)
    return {
        "rgb": image,
        "depth": depth,
        "points": scan(scene, rng, height, width, lidar_fov),
        "labels": labels,
        "calib": calib,
        "instance": instance,
        "road": (hit["kind"] == ROAD).reshape(height, width),
    }


def camera_cast(
    seed: int, index: int, height: int, width: int, furniture: bool = False
) -> tuple[np.random.Generator, dict, Calibration, np.ndarray, dict]:
    """Frame ``index``'s scene cast from the camera: (its generator, after the scene drew from it; the scene; the
    calibration; one ray per pixel; what each ray hits, :func:`ablate.data.raycast.cast`)."""
    rng = frame_rng(seed, index)
    scene = sample_scene(rng, furniture)
    calib = calibration(height, width)
    rays = camera_rays(calib.P2, height, width)
    return rng, scene, calib, rays, cast(scene, np.zeros(3, np.float32), rays)


def scan(scene: dict, rng: np.random.Generator, height: int, width: int, lidar_fov: float = 45.0) -> np.ndarray:
    """The LiDAR scan of a scene, (N,4) velodyne x, y, z, reflectance: each beam traced as sub-rays over its
    footprint, kept where the received power clears the threshold (ablate.data.lidar_physics)."""
    el, az = lidar_angles(height, width, lidar_fov)
    origin = LIDAR_ORIGIN.astype(np.float32)
    sub = physics.footprint_rays(el, az)
    power, dist, refl = (np.zeros((len(sub), len(el))) for _ in range(3))
    for k, (e, a) in enumerate(sub):
        dirs, _ = beam_directions(e, a)
        h = cast(scene, origin, dirs, max_t=150.0)
        isbox = h["kind"] == BOX
        b = np.maximum(h["box"], 0)
        rho = np.select(
            [h["kind"] == ROAD, h["kind"] == BORDER, isbox],
            [scene["road_refl"], scene["border_refl"], scene["box_refl"][b]],
            0.0,
        )
        gloss = np.where(isbox, scene["box_gloss"][b], 0.0)  # ground: angle-independent (see lidar_physics)
        cos = np.abs(np.sum(h["normal"] * dirs, 1))
        rho = np.where(glass_mask(scene, h, isbox), 0.0, rho)
        power[k], dist[k], refl[k] = physics.received_power(rho, cos, h["t"], gloss), h["t"], rho
    ok, distance, reflectance = physics.combine(power, dist, refl)
    distance = distance[ok] + rng.normal(0, physics.RANGE_SIGMA, ok.sum())
    reflectance = np.clip(reflectance[ok] + rng.normal(0, 0.03, ok.sum()), 0, 1)
    _, velo = beam_directions(el[ok], az[ok])
    return np.hstack([velo * distance[:, None], reflectance[:, None]]).astype(np.float32)


def _labels(
    scene: dict[str, Any], hit: dict[str, np.ndarray], owner: np.ndarray, calib: Calibration, height: int, width: int
) -> tuple[list[Object3D], np.ndarray]:
    """label_2 objects (true 3D boxes, projected 2D boxes, truncation, occlusion) and the instance map."""
    instance = np.zeros(height * width, np.uint16)
    labels: list[Object3D] = []
    for i, (cls, x, y, z, l, h, w, yaw) in enumerate(scene["objects"]):
        if cls == BUILDING:
            continue
        ry = float(np.arctan2(np.sin(yaw), np.cos(yaw)))
        obj = Object3D(CLASS_NAMES[cls], 0.0, 0, 0.0, (0, 0, 0, 0), (h, w, l), (x, y, z), ry)
        uv = calib.rect_to_image(obj.corners())
        x0, y0, x1, y1 = uv[:, 0].min(), uv[:, 1].min(), uv[:, 0].max(), uv[:, 1].max()
        cx0, cy0, cx1, cy1 = max(x0, 0), max(y0, 0), min(x1, width - 1), min(y1, height - 1)
        if cx1 <= cx0 or cy1 <= cy0:
            continue
        truncated = 1.0 - (cx1 - cx0) * (cy1 - cy0) / ((x1 - x0) * (y1 - y0))
        visible = owner == i
        n_vis = int(visible.sum())
        n_any = int(hit["any_hit"][scene["owner"] == i].any(0).sum())
        if n_vis == 0:
            continue
        occ = 1.0 - n_vis / max(n_any, 1)
        alpha = float(np.arctan2(np.sin(ry - np.arctan2(x, z)), np.cos(ry - np.arctan2(x, z))))
        box = (float(cx0), float(cy0), float(cx1), float(cy1))
        if cy1 - cy0 < 25 * height / 375 or n_vis < 20:  # KITTI's smallest evaluated height, scaled
            labels.append(Object3D("DontCare", -1.0, -1, -10.0, box, (-1.0, -1.0, -1.0), (-1000.0,) * 3, -10.0))
            continue
        labels.append(
            Object3D(
                obj.type,
                round(truncated, 2),
                0 if occ < 0.1 else 1 if occ < 0.5 else 2,
                alpha,
                box,
                obj.dimensions,
                obj.location,
                ry,
            )
        )
        instance[visible] = len(labels)
    return labels, instance.reshape(height, width)


def write_frame(out: Path, frame: dict, name: str) -> None:
    cv2.imwrite(
        str(out / "image_2" / f"{name}.png"),
        cv2.cvtColor(frame["rgb"], cv2.COLOR_RGB2BGR),
        [cv2.IMWRITE_PNG_COMPRESSION, 3],
    )
    frame["points"].tofile(out / "velodyne" / f"{name}.bin")
    frame["calib"].write(out / "calib" / f"{name}.txt")
    (out / "label_2" / f"{name}.txt").write_text("".join(o.to_line() + "\n" for o in frame["labels"]))
    cv2.imwrite(str(out / "instance_2" / f"{name}.png"), frame["instance"])
    write_road_gt(out / "gt_image_2" / f"road_{name}.png", frame["road"])


def _job(args: tuple) -> None:
    out, seed, index, height, width, fov, furniture = args
    write_frame(Path(out), render_frame(seed, index, height, width, fov, furniture), f"{index:06d}")


def split_frames(
    frames: list[str], seed: int, fractions: tuple[float, float, float] = (0.6, 0.2, 0.2)
) -> dict[str, list[str]]:
    """Seeded permutation of the sorted frames cut into train/val/test (sorted within each split)."""
    order = np.random.default_rng(seed).permutation(len(frames))
    n_train = int(round(fractions[0] * len(frames)))
    n_val = int(round(fractions[1] * len(frames)))
    cuts = {"train": order[:n_train], "val": order[n_train : n_train + n_val], "test": order[n_train + n_val :]}
    return {k: sorted(frames[i] for i in v) for k, v in cuts.items()}


def generate(
    out: str | Path,
    frames: int,
    seed: int = 0,
    height: int = 128,
    width: int = 416,
    lidar_fov: float = 45.0,
    workers: int = 1,
    progress: bool = True,
    furniture: bool = False,
) -> Path:
    """Write ``frames`` generated frames under ``out`` (KITTI object layout) with a 60/20/20 split; ``furniture``:
    street furniture in every scene (:func:`ablate.data.synth.sample_scene`)."""
    out = Path(out)
    for sub in ("image_2", "velodyne", "calib", "label_2", "instance_2", "gt_image_2", "ImageSets"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    jobs = [(str(out), seed, i, height, width, lidar_fov, furniture) for i in range(frames)]
    # a bar on a terminal only (tqdm's disable=None): in a log file its refreshes would be most of the log
    bar = tqdm(total=frames, desc=f"generating {out}", disable=(not progress) or None, unit="frame")
    if workers > 1 and frames > 1:
        with ProcessPoolExecutor(workers) as pool:
            for _ in pool.map(_job, jobs, chunksize=4):
                bar.update()
    else:
        for job in jobs:
            _job(job)
            bar.update()
    bar.close()
    for name, ids in split_frames([f"{i:06d}" for i in range(frames)], seed).items():
        (out / "ImageSets" / f"{name}.txt").write_text("".join(f + "\n" for f in ids))
    params = {
        "frames": frames,
        "seed": seed,
        "height": height,
        "width": width,
        "lidar_fov": lidar_fov,
        "version": GENERATOR_VERSION,
        **({"furniture": True} if furniture else {}),  # absent where off: the older datasets' parameters
    }
    (out / "synth.json").write_text(json.dumps(params, indent=1) + "\n")
    return out
