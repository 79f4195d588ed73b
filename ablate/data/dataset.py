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
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from torch.utils.data import Dataset, get_worker_info

from ablate.data import DataError, kitti, lidar, masks
from ablate.data.augment import Augment, View, flip_calibration, mirror_points, warp
from ablate.data.conditions import apply_condition, apply_corruption
from ablate.data.lidar_weather import LIDAR_WEATHER, apply_lidar_weather
from ablate.data.memo import FrameMemo
from ablate.data.targets import BOX_LABELS, CLASSES, calib_array, calibration, image_targets, mirrored, road_bev

#: The targets' label ids and the calibration and road helpers (ablate.data.targets) are importable from here too.
__all__ = [
    "BOX_LABELS",
    "CLASSES",
    "GEOMETRY",
    "LIDAR_DERIVED",
    "MODALITIES",
    "NO_MASKS",
    "TARGETS",
    "KittiDataset",
    "calib_array",
    "calibration",
    "road_bev",
    "spread",
]

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
        memo_bytes: float = 0,
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
        # decoded frames kept from one epoch to the next (ablate.data.memo): never with augmentation
        self.memo = FrameMemo(memo_bytes) if memo_bytes > 0 and self.augment is None else None

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
        if self.memo is None or get_worker_info() is not None:  # a loader worker keeps no copy of its own
            return self._read(i)
        sample = self.memo.get(i)
        return sample if sample is not None else self.memo.put(i, self._read(i))

    def _read(self, i: int) -> dict[str, Any]:
        """Frame ``i``'s sample, built from its files (and the cache of derived LiDAR modalities)."""
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
        if view.photometric is not None:  # the camera's own (ablate.data.augment), on the image its condition made
            rgb = view.photometric.apply(rgb)
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
        """The targets asked for, of the frame at ``paths`` (``flip``: of its mirrored image)."""
        if not self.targets:
            return {}
        labels, road_gt, inst = self._ground_truth(paths, shape)
        if flip:  # the image-space labels of the flipped image (ablate.data.augment)
            labels, road_gt, inst = mirrored(labels, road_gt, inst, shape[1])
        road = road_gt[0] if road_gt is not None else None
        if (
            any(t in self.targets for t in ("free_space", "semantic", "road_bev", "road_valid", "road_bev_valid"))
            and road is None
        ):
            raise DataError(f"{paths['image']}: road ground truth {paths.get('road_gt')} is missing")
        if any(t in self.targets for t in ("road_objects", "semantic", "instances")) and inst is None:
            raise DataError(f"{paths['image']}: instance masks {paths['instance']} are missing")
        out = image_targets(self.targets, labels, road, inst, shape)
        out.update(self._road(paths, shape, road_gt, flip))
        return out

    def _ground_truth(
        self, paths: dict[str, Path], shape: tuple[int, int]
    ) -> tuple[list[kitti.Object3D], tuple[np.ndarray, ...] | None, np.ndarray | None]:
        """The frame's labels, road ground truth and instance map (derived from LiDAR where the folder has no
        instance_2/ and an instance target is asked for); None where there is none."""
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
        return labels, road_gt, inst

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
