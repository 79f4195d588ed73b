"""Torch dataset over a KITTI-layout folder: network-ready modalities, targets, conditions and an on-disk cache
of the derived LiDAR modalities (keyed by folder, frame, parameters and the size and modification time of the
files they come from, so the second epoch does no LiDAR work and a file replaced since is read again)."""

from __future__ import annotations

import hashlib
import json
import os
import uuid
import zlib
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from torch.utils.data import Dataset

from ablate.data import DataError, kitti, lidar, masks
from ablate.data.augment import Augment, View, flip_box, flip_calibration, mirror_points, warp
from ablate.data.conditions import apply_condition, apply_corruption
from ablate.data.lidar_weather import LIDAR_WEATHER, apply_lidar_weather

MODALITIES = {"rgb": 3, "intensity": 1, "sparse_depth": 1, "dense_depth": 1, "ddm_jet": 3, "dhi": 3, "bev": 6}
#: Per-frame geometry for the space transforms (ablate.fusion.geometry), asked for like targets: calibration
#: [4,3,4], dense LiDAR heights per pixel [1,H,W] and per BEV cell [1,Hb,Wb] (BiFNet DST), points in the BEV grid.
GEOMETRY = ("calib", "height_image", "height_bev", "lidar_points")
TARGETS = (
    "free_space",
    "road_objects",
    "semantic",
    "instances",
    "boxes2d",
    "road_bev",
    "road_valid",
    "road_bev_valid",
    *GEOMETRY,
)
CLASSES = ("Car", "Pedestrian", "Cyclist")  # label ids 0, 1, 2
#: ``boxes2d`` label ids: the classes, then the KITTI types its evaluation ignores (ablate.metrics.kitti.LABEL_NAMES):
#: Van (neighbour of Car), Person_sitting (of Pedestrian) and DontCare regions.
BOX_LABELS = (*CLASSES, "Van", "Person_sitting", "DontCare")
LIDAR_DERIVED = {"sparse_depth", "dense_depth", "ddm_jet", "dhi", "bev"}
NO_MASKS = "no instance masks: no instance_2/ folder, nor velodyne/ and label_2/ to derive them from"


def spread(frames: list[str], names: list[str], seed: int, *salt: int) -> dict[str, str]:
    """Each frame's condition: ``names`` in turn over a seeded permutation of the frames (equal shares)."""
    order = np.random.default_rng([seed, len(frames), *salt]).permutation(len(frames))
    return {f: names[i % len(names)] for f, i in zip(frames, np.argsort(order))}


def _key(obj: object) -> str:
    return hashlib.sha1(json.dumps(obj, sort_keys=True).encode()).hexdigest()[:10]


def _sources(*paths: Path) -> list[list[int] | None]:
    """[size, mtime_ns] of each file (None where there is none): part of a cache key, so that an entry derived from a
    file is never served for another one written in its place (a damaged scan repaired, a frame replaced)."""
    out: list[list[int] | None] = []
    for path in paths:
        try:
            st = path.stat()
        except FileNotFoundError:
            out.append(None)
            continue
        out.append([st.st_size, st.st_mtime_ns])
    return out


class KittiDataset(Dataset):
    """One split of a KITTI-layout folder. Returns the sample dict described in ``ablate.data.datamodule``."""

    def __init__(
        self,
        split_dir: Path,
        frames: list[str],
        modalities: list[str],
        targets: list[str],
        conditions: list[str],
        severity: float = 1.0,
        corruption: dict[str, Any] | None = None,
        seed: int = 0,
        max_depth: float = 80.0,
        cache_dir: str | Path | None = None,
        bev: dict[str, Any] | None = None,
        image_size: Sequence[int] | None = None,
        lidar_weather: list[str] | None = None,
        augment: dict[str, Any] | None = None,
    ) -> None:
        for m in modalities:
            if m not in MODALITIES:
                raise KeyError(f"unknown modality {m!r}; valid: {', '.join(MODALITIES)}")
        for t in targets:
            if t not in TARGETS:
                raise KeyError(f"unknown target {t!r}; valid: {', '.join(TARGETS)}")
        self.split_dir, self.frames = Path(split_dir), list(frames)
        self.modalities, self.targets = list(modalities), list(targets)
        self.severity, self.corruption, self.seed, self.max_depth = severity, corruption, seed, max_depth
        bev = {k: v if isinstance(v, (int, float, str)) else tuple(v) for k, v in dict(bev or {}).items()}  # plain
        self.bev: dict[str, Any] = {"x_range": (6.0, 46.0), "y_range": (-10.0, 10.0), "cell": 0.5, **bev}
        # options of the dense heights and points (GEOMETRY), kept apart from the raster's own
        self.heights: dict[str, Any] = {
            k: self.bev.pop(k) for k in ("window", "azimuth_res", "max_points") if k in self.bev
        }
        self.cache_dir = Path(cache_dir) / _key(str(self.split_dir.resolve())) if cache_dir else None
        self.cache_hits = self.cache_misses = 0
        self.image_size = tuple(image_size) if image_size else None  # bottom-centre crop (KITTI sizes vary)
        self._check_available()
        self.condition = spread(self.frames, conditions, seed)
        # Optional LiDAR weather (ablate.data.lidar_weather), spread over the frames by its own permutation.
        for w in lidar_weather or ():
            if w not in LIDAR_WEATHER:
                raise KeyError(f"unknown LiDAR weather {w!r}; valid: {', '.join(LIDAR_WEATHER)}")
        self.lidar_condition = spread(self.frames, lidar_weather, seed, 1) if lidar_weather else {}
        self.augment = Augment.from_config(dict(augment)) if augment else None  # ablate.data.augment

    def _check_available(self) -> None:
        d = self.split_dir
        has = {
            "velodyne": (d / "velodyne").is_dir(),
            "labels": (d / "label_2").is_dir(),
            "instances": (d / "instance_2").is_dir() or (d / "velodyne").is_dir() and (d / "label_2").is_dir(),
            "road": (d / "gt_image_2").is_dir(),
        }  # instance masks: instance_2/, else derived from LiDAR + boxes
        need = {
            "free_space": "road",
            "semantic": "road",
            "road_bev": "road",
            "road_objects": "instances",
            "instances": "instances",
            "boxes2d": "labels",
            "road_valid": "road",
            "road_bev_valid": "road",
            "calib": None,
            **{g: "velodyne" for g in GEOMETRY[1:]},
        }
        for name in [m for m in self.modalities if m in LIDAR_DERIVED] + self.targets:
            src = "velodyne" if name in LIDAR_DERIVED else need[name]
            if src and not has[src]:
                raise DataError(
                    f"{d}: cannot provide {name!r}: this data has no {src} "
                    f"({NO_MASKS if src == 'instances' else src + ' folder missing'})"
                )
        if "semantic" in self.targets and not has["instances"]:
            raise DataError(f"{d}: cannot provide 'semantic': this data has {NO_MASKS}")

    def __len__(self) -> int:
        return len(self.frames)

    def _cached(
        self,
        frame: str,
        name: str,
        params: dict[str, Any],
        compute: Callable[[], np.ndarray],
        sources: list[list[int] | None] | None = None,
    ) -> np.ndarray:
        """``compute()``'s value for ``frame``, from the cache when there; ``sources`` (:func:`_sources` of the files
        it reads) is in the entry's name, so an entry is only ever served for the files it was derived from."""
        if self.cache_dir is None:
            self.cache_misses += 1
            return compute()
        stem = frame if sources is None else f"{frame}-{_key(sources)}"
        path = self.cache_dir / f"{name}-{_key(params)}" / f"{stem}.npy"
        if path.is_file():
            self.cache_hits += 1
            return np.load(path)
        self.cache_misses += 1
        value = compute()
        path.parent.mkdir(parents=True, exist_ok=True)
        # a name of this process's own: parallel jobs seeded alike draw the same numbers from numpy's global rng
        tmp = path.with_name(f"{path.stem}.{os.getpid()}.{uuid.uuid4().hex}.tmp.npy")
        np.save(tmp, value)
        tmp.replace(path)
        return value

    def lidar(self, frame: str, name: str, shape: tuple[int, int], flip: bool = False) -> np.ndarray:
        """A derived LiDAR modality in its raw units (metres, uint8 DHI, BEV), from the cache when present;
        ``flip``: of the world mirrored in the camera frame (ablate.data.augment), cached apart."""
        paths = kitti.frame_paths(self.split_dir, frame)
        weather = self.lidar_condition.get(frame, "clear")
        key = {"weather": weather, "severity": self.severity} if weather != "clear" else {}
        key.update({"flip": True} if flip else {})
        sources = _sources(paths["velodyne"], paths["calib"])

        def calib() -> kitti.Calibration:
            c = kitti.Calibration.from_file(paths["calib"])
            return flip_calibration(c, shape[1]) if flip else c

        def points() -> np.ndarray:
            pts = kitti.read_velodyne(paths["velodyne"])
            if weather != "clear":
                rng = np.random.default_rng([self.seed, zlib.crc32(frame.encode()), 1])
                pts = apply_lidar_weather(weather, pts, rng, self.severity)
            return mirror_points(pts, kitti.Calibration.from_file(paths["calib"])) if flip else pts

        if name == "sparse_depth":
            return self._cached(
                frame, name, {"shape": shape, **key}, lambda: lidar.sparse_depth(points(), calib(), shape), sources
            )
        if name == "dense_depth":
            return self._cached(
                frame,
                name,
                {"shape": shape, **key},
                lambda: lidar.dense_depth(self.lidar(frame, "sparse_depth", shape, flip)),
                sources,
            )
        if name == "dhi":
            return self._cached(
                frame, name, {"shape": shape, **key}, lambda: lidar.dhi_image(points(), calib(), shape), sources
            )
        grid = {k: self.bev[k] for k in ("x_range", "y_range", "cell")}
        if name == "height_image":
            opts: dict[str, Any] = {k: v for k, v in self.heights.items() if k == "window"}
            return self._cached(
                frame,
                name,
                {"shape": shape, **opts, **key},
                lambda: lidar.perspective_height(points(), calib(), shape, **opts),
                sources,
            )
        if name == "height_bev":
            opts = {k: v for k, v in self.heights.items() if k == "azimuth_res"}
            return self._cached(
                frame, name, {**grid, **opts, **key}, lambda: lidar.bev_height(points(), **grid, **opts), sources
            )
        if name == "lidar_points":
            opts = {k: v for k, v in self.heights.items() if k == "max_points"}
            return self._cached(
                frame, name, {**grid, **opts, **key}, lambda: lidar.bev_points(points(), **grid, **opts), sources
            )
        return self._cached(frame, name, {**self.bev, **key}, lambda: lidar.bev_image(points(), **self.bev), sources)

    def lidar_instances(self, frame: str, labels: list[kitti.Object3D], shape: tuple[int, int]) -> np.ndarray:
        """(H,W) uint16 instance map in instance_2's encoding from ``ablate.data.masks.from_lidar`` of the clean
        scan (never the LiDAR weather of the frame), cached."""
        paths = kitti.frame_paths(self.split_dir, frame)
        return self._cached(
            frame,
            "instances",
            {"shape": shape, "margin": masks.MARGIN, "ground": masks.GROUND},
            lambda: masks.instance_map(
                masks.from_lidar(
                    kitti.read_velodyne(paths["velodyne"]), kitti.Calibration.from_file(paths["calib"]), labels, shape
                )
            ),
            _sources(paths["velodyne"], paths["calib"], paths["label"]),
        )

    def __getitem__(self, i: int) -> dict[str, Any]:
        frame = self.frames[i]
        paths = kitti.frame_paths(self.split_dir, frame)
        condition = self.condition[frame]
        rng = np.random.default_rng([self.seed, zlib.crc32(frame.encode())])
        rgb = kitti.read_image(paths["image"]).astype(np.float32) / 255.0
        shape = rgb.shape[:2]
        view = self.augment.draw(shape) if self.augment else View()
        if view.flip:
            rgb = np.ascontiguousarray(rgb[:, ::-1])
        rgb = apply_condition(condition, rgb, rng, self.severity)
        corr = self.corruption or {}
        if corr.get("modality") == "rgb" and rng.random() < corr.get("p", 1.0):
            rgb = apply_corruption(corr["name"], rgb.transpose(2, 0, 1), rng, "rgb", self.severity).transpose(1, 2, 0)
        sample: dict[str, Any] = {"frame": frame, "condition": condition}
        if self.lidar_condition:
            sample["lidar_condition"] = self.lidar_condition[frame]
        for m in self.modalities:
            if m == "rgb":
                x: np.ndarray = rgb.transpose(2, 0, 1)
            elif m == "intensity":
                x = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)[None]
            elif m in ("sparse_depth", "dense_depth"):
                x = self.lidar(frame, m, shape, view.flip)[None] / self.max_depth
            elif m == "ddm_jet":
                x = lidar.jet(self.lidar(frame, "dense_depth", shape, view.flip), self.max_depth)
                x = x.transpose(2, 0, 1) / 255.0
            elif m == "dhi":
                x = self.lidar(frame, "dhi", shape, view.flip).transpose(2, 0, 1) / 255.0
            else:
                x = self.lidar(frame, "bev", shape, view.flip)
            if corr.get("modality") == m and m != "rgb" and rng.random() < corr.get("p", 1.0):
                x = apply_corruption(corr["name"], x, rng, m, self.severity)
            sample[m] = torch.from_numpy(np.ascontiguousarray(x, np.float32))
        sample.update(self._targets(paths, shape, view.flip))
        if view.affine is not None:
            sample = warp(sample, view.affine, shape)
        return self._crop(sample, shape) if self.image_size and self.image_size != shape else sample

    def _crop(self, sample: dict[str, Any], shape: tuple[int, int]) -> dict[str, Any]:
        """Crop every image-space tensor to ``image_size``, keeping the bottom rows and the centre columns."""
        assert self.image_size is not None  # called only with an image_size
        (h, w), (ch, cw) = shape, self.image_size
        if ch > h or cw > w:
            raise DataError(f"{self.split_dir}: image {w}x{h} is smaller than image_size {cw}x{ch}")
        top, left = h - ch, (w - cw) // 2
        shift = torch.tensor([left, top, left, top], dtype=torch.float32)
        for k, v in sample.items():
            if k == "calib":  # the principal point moves with the crop: P2 <- [[1,0,-left],[0,1,-top],[0,0,1]] P2
                v = v.clone()
                v[0, :2] -= torch.tensor([[left], [top]], dtype=v.dtype) * v[0, 2:3]
                sample[k] = v
            elif isinstance(v, torch.Tensor) and k not in (
                "bev",
                "road_bev",
                "road_bev_valid",
                "height_bev",
                "lidar_points",
            ):
                sample[k] = v[..., top : top + ch, left : left + cw]
            elif k in ("instances", "boxes2d"):
                v = dict(v, boxes=v["boxes"] - shift)
                if "masks" in v:
                    v["masks"] = v["masks"][..., top : top + ch, left : left + cw]
                sample[k] = v
        return sample

    def _targets(self, paths: dict[str, Path], shape: tuple[int, int], flip: bool = False) -> dict[str, Any]:
        out: dict[str, Any] = {}
        if not self.targets:
            return out
        h, w = shape
        labels = kitti.read_labels(paths["label"]) if paths["label"].is_file() else []
        road_gt: tuple[np.ndarray, ...] | None = (
            kitti.read_road_gt(paths["road_gt"]) if "road_gt" in paths and paths["road_gt"].is_file() else None
        )
        inst = cv2.imread(str(paths["instance"]), cv2.IMREAD_UNCHANGED) if paths["instance"].is_file() else None
        if (
            inst is None
            and not paths["instance"].parent.is_dir()
            and paths["label"].is_file()
            and any(t in self.targets for t in ("road_objects", "semantic", "instances"))
        ):
            inst = self.lidar_instances(paths["image"].stem, labels, shape)
        if flip:  # the image-space labels of the flipped image (ablate.data.augment)
            labels = [replace(o, bbox=flip_box(o.bbox, w)) for o in labels]
            road_gt = tuple(np.ascontiguousarray(a[:, ::-1]) for a in road_gt) if road_gt is not None else None
            inst = np.ascontiguousarray(inst[:, ::-1]) if inst is not None else None
        road = road_gt[0] if road_gt is not None else None
        if (
            any(t in self.targets for t in ("free_space", "semantic", "road_bev", "road_valid", "road_bev_valid"))
            and road is None
        ):
            raise DataError(f"{paths['image']}: road ground truth {paths.get('road_gt')} is missing")
        if any(t in self.targets for t in ("road_objects", "semantic", "instances")) and inst is None:
            raise DataError(f"{paths['image']}: instance masks {paths['instance']} are missing")
        if "free_space" in self.targets:
            assert road is not None  # checked above
            out["free_space"] = torch.from_numpy(road[None].astype(np.float32))
        if "road_objects" in self.targets:
            assert inst is not None  # checked above
            out["road_objects"] = torch.from_numpy((inst > 0)[None].astype(np.float32))
        if "semantic" in self.targets:
            assert inst is not None and road is not None  # checked above
            out["semantic"] = torch.from_numpy(np.where(inst > 0, 2, road.astype(np.int64)).astype(np.int64))
        if "instances" in self.targets:
            assert inst is not None  # checked above
            present = set(np.unique(inst).tolist())  # a labelled object with no mask pixel is left out
            ids = [k + 1 for k, o in enumerate(labels) if o.type in CLASSES[:2] and k + 1 in present]
            out["instances"] = {
                "masks": torch.from_numpy(np.stack([inst == k for k in ids]) if ids else np.zeros((0, h, w), bool)),
                "labels": torch.tensor([CLASSES.index(labels[k - 1].type) for k in ids], dtype=torch.int64),
                "boxes": torch.tensor([labels[k - 1].bbox for k in ids], dtype=torch.float32).reshape(-1, 4),
            }
        if "boxes2d" in self.targets:
            objs = [o for o in labels if o.type in BOX_LABELS]
            scale = h / 375.0  # KITTI's difficulty heights are for 375-row images
            out["boxes2d"] = {
                "boxes": torch.tensor([o.bbox for o in objs], dtype=torch.float32).reshape(-1, 4),
                "labels": torch.tensor([BOX_LABELS.index(o.type) for o in objs], dtype=torch.int64),
                "difficulty": torch.tensor([o.difficulty_at(scale) for o in objs], dtype=torch.int64),
            }
        if "instances" in self.targets or "boxes2d" in self.targets:
            ignore = np.zeros((h, w), bool)
            for o in labels:
                if o.type == "DontCare":
                    x0, y0, x1, y1 = (int(round(v)) for v in o.bbox)
                    ignore[max(y0, 0) : y1 + 1, max(x0, 0) : x1 + 1] = True
            out["ignore"] = torch.from_numpy(ignore)
        out.update(self._road(paths, shape, road_gt, flip))
        return out

    def _road(
        self, paths: dict[str, Path], shape: tuple[int, int], road_gt: tuple[np.ndarray, ...] | None, flip: bool = False
    ) -> dict[str, Any]:
        """The road targets beyond ``free_space`` (the image road mask) and the frame's geometry (GEOMETRY)."""
        out: dict[str, Any] = {}
        grid = {k: self.bev[k] for k in ("x_range", "y_range", "cell")}
        calib = (
            kitti.Calibration.from_file(paths["calib"])
            if any(t in self.targets for t in ("road_bev", "road_bev_valid", "calib"))
            else None
        )
        calib = flip_calibration(calib, shape[1]) if flip and calib is not None else calib
        if "road_valid" in self.targets:
            assert road_gt is not None  # _targets raised otherwise
            out["road_valid"] = torch.from_numpy(road_gt[1][None].astype(np.float32))
        if "road_bev" in self.targets:
            assert road_gt is not None and calib is not None  # _targets raised otherwise; read above
            out["road_bev"] = torch.from_numpy(road_bev(road_gt[0], calib, **grid)[None])
        if "road_bev_valid" in self.targets:  # cells whose centre on the road plane sees a non-void gt pixel
            assert road_gt is not None and calib is not None  # _targets raised otherwise; read above
            out["road_bev_valid"] = torch.from_numpy(road_bev(road_gt[1], calib, **grid)[None])
        if "calib" in self.targets:
            assert calib is not None  # read above
            out["calib"] = torch.from_numpy(calib_array(calib))
        for name in [g for g in GEOMETRY[1:] if g in self.targets]:  # heights get their channel axis
            value = self.lidar(paths["image"].stem, name, shape, flip)
            out[name] = torch.from_numpy(np.ascontiguousarray(value if name == "lidar_points" else value[None]))
        return out


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
