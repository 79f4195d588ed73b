"""KITTI readers: velodyne scans, calibration, images, object labels and road ground truth.

Object layout (KITTI object benchmark)::

    ROOT/image_2/000000.png    RGB image (sizes from 1224x370 to 1242x375)
    ROOT/velodyne/000000.bin   float32 (x, y, z, reflectance) per point
    ROOT/calib/000000.txt      P0-P3, R0_rect, Tr_velo_to_cam, Tr_imu_to_velo
    ROOT/label_2/000000.txt    15 fields per object, DontCare included

Road layout (KITTI road benchmark)::

    ROOT/image_2/um_000000.png, ROOT/calib/um_000000.txt (with Tr_cam_to_road),
    ROOT/gt_image_2/um_road_000000.png   magenta (255,0,255) road, red (255,0,0) not road, black void

``ROOT`` may be the benchmark folder itself or its parent holding ``training/``.

:func:`check_frame` is the cheap check of one frame's files that ``ablate.data.datamodule`` runs when it indexes its
splits (what it checks, and what only fails when a file is read, is said there).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path
from typing import cast

import cv2
import numpy as np

from ablate.data import DataError

_ALIASES = {"R0_rect": ("R0_rect", "R_rect"), "Tr_velo_to_cam": ("Tr_velo_to_cam", "Tr_velo_cam")}
_SHAPES = {"R0_rect": (3, 3)}


def _read_key_values(path: Path) -> dict[str, np.ndarray]:
    """Parse ``KEY: v0 v1 ...`` lines; blank lines (KITTI files end with one) are skipped."""
    try:
        text = Path(path).read_text()
    except OSError as err:
        raise DataError(f"{path}: cannot read calibration ({err.strerror})") from err
    out: dict[str, np.ndarray] = {}
    for num, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        key, sep, rest = line.partition(":")
        if not sep:
            raise DataError(f"{path}:{num}: expected 'KEY: values', got {line[:40]!r}")
        try:
            out[key.strip()] = np.array(rest.split(), dtype=np.float64)
        except ValueError as err:
            raise DataError(f"{path}:{num}: non-numeric value for {key.strip()}") from err
    return out


def _matrix(values: dict[str, np.ndarray], name: str, shape: tuple[int, int], path: Path) -> np.ndarray:
    for key in _ALIASES.get(name, (name,)):
        if key in values:
            if values[key].size != shape[0] * shape[1]:
                raise DataError(f"{path}: {key} has {values[key].size} values, expected {shape[0] * shape[1]}")
            return values[key].reshape(shape)
    raise DataError(f"{path}: calibration key {name} is missing (found: {', '.join(values) or 'none'})")


@dataclass(frozen=True)
class Calibration:
    """Projection velodyne -> rectified camera -> image_2: ``x = P2 . R0_rect . Tr_velo_to_cam . X``.

    This is SMoE eq. (1) ``z (u v 1)^T = M_i M_e (X Y Z)^T`` with ``M_i = P2`` and ``M_e = R0_rect Tr_velo_to_cam``.
    """

    P2: np.ndarray
    R0_rect: np.ndarray
    Tr_velo_to_cam: np.ndarray
    Tr_cam_to_road: np.ndarray | None = None
    path: str = ""

    @classmethod
    def from_file(cls, path: str | Path) -> Calibration:
        path = Path(path)
        values = _read_key_values(path)
        road = _matrix(values, "Tr_cam_to_road", (3, 4), path) if "Tr_cam_to_road" in values else None
        return cls(
            P2=_matrix(values, "P2", (3, 4), path),
            R0_rect=_matrix(values, "R0_rect", (3, 3), path),
            Tr_velo_to_cam=_matrix(values, "Tr_velo_to_cam", (3, 4), path),
            Tr_cam_to_road=road,
            path=str(path),
        )

    @property
    def velo_to_rect_matrix(self) -> np.ndarray:
        """(4,4) homogeneous velodyne -> rectified camera transform, ``R0_rect . Tr_velo_to_cam``."""
        out = np.eye(4)
        out[:3, :3] = self.R0_rect @ self.Tr_velo_to_cam[:, :3]
        out[:3, 3] = self.R0_rect @ self.Tr_velo_to_cam[:, 3]
        return out

    def velo_to_rect(self, xyz: np.ndarray) -> np.ndarray:
        """(N,3) velodyne points -> (N,3) points in the rectified camera frame."""
        xyz = np.asarray(xyz, dtype=np.float64)[:, :3]
        cam = xyz @ self.Tr_velo_to_cam[:, :3].T + self.Tr_velo_to_cam[:, 3]
        return cam @ self.R0_rect.T

    def rect_to_image(self, rect: np.ndarray) -> np.ndarray:
        """(N,3) rectified camera points -> (N,2) unrounded image_2 pixel coordinates."""
        hom = rect @ self.P2[:, :3].T + self.P2[:, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            return hom[:, :2] / hom[:, 2:3]

    def velo_to_image(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N,3) velodyne points -> (uv (N,2) unrounded pixels, depth (N,) = z in the rectified camera frame)."""
        rect = self.velo_to_rect(xyz)
        return self.rect_to_image(rect), rect[:, 2]

    def write(self, path: str | Path) -> None:
        """Write in KITTI's object calib format (P0-P3 equal to P2, Tr_imu_to_velo identity)."""
        rows = [f"P{i}: " + _fmt(self.P2) for i in range(4)]
        rows += [
            "R0_rect: " + _fmt(self.R0_rect),
            "Tr_velo_to_cam: " + _fmt(self.Tr_velo_to_cam),
            "Tr_imu_to_velo: " + _fmt(np.eye(3, 4)),
        ]
        if self.Tr_cam_to_road is not None:
            rows.append("Tr_cam_to_road: " + _fmt(self.Tr_cam_to_road))
        Path(path).write_text("\n".join(rows) + "\n\n")


def _fmt(m: np.ndarray) -> str:
    return " ".join(f"{v:.12e}" for v in np.asarray(m).ravel())


def read_velodyne(path: str | Path) -> np.ndarray:
    """Read a KITTI scan: (N,4) float32 x, y, z (metres, velodyne frame: forward, left, up), reflectance."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as err:
        raise DataError(f"{path}: cannot read velodyne scan ({err.strerror})") from err
    _check_scan_size(path, len(raw))
    return np.frombuffer(raw, dtype=np.float32).reshape(-1, 4).copy()


def _check_scan_size(path: Path, size: int) -> None:
    if size == 0 or size % 16:
        raise DataError(
            f"{path}: truncated velodyne scan, {size} bytes is not a positive multiple of 16 (4 float32 per point)"
        )


def read_image(path: str | Path) -> np.ndarray:
    """Read an image as (H,W,3) uint8 RGB."""
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise DataError(f"{path}: missing or unreadable image")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


@dataclass(frozen=True)
class Object3D:
    """One label_2 line. bbox is xyxy pixels, dimensions are (h, w, l) metres, location (x, y, z) in the
    rectified camera frame (bottom centre of the box), rotation_y around the camera Y axis."""

    type: str
    truncated: float
    occluded: int
    alpha: float
    bbox: tuple[float, float, float, float]
    dimensions: tuple[float, float, float]
    location: tuple[float, float, float]
    rotation_y: float

    @property
    def difficulty(self) -> int:
        """KITTI difficulty: 0 easy, 1 moderate, 2 hard, -1 none (min height 40/25/25 px,
        max occlusion 0/1/2, max truncation 0.15/0.30/0.50)."""
        return self.difficulty_at(1.0)

    def difficulty_at(self, scale: float) -> int:
        """KITTI difficulty with the minimum heights scaled by ``scale`` (image height / 375)."""
        if self.type == "DontCare":
            return -1
        height = self.bbox[3] - self.bbox[1]
        for level, (min_h, max_occ, max_trunc) in enumerate(((40, 0, 0.15), (25, 1, 0.30), (25, 2, 0.50))):
            if height >= min_h * scale and self.occluded <= max_occ and self.truncated <= max_trunc:
                return level
        return -1

    def corners(self) -> np.ndarray:
        """(8,3) box corners in the rectified camera frame."""
        h, w, l = self.dimensions
        x = np.array([1, 1, -1, -1, 1, 1, -1, -1]) * l / 2
        y = np.array([0, 0, 0, 0, -1, -1, -1, -1]) * h
        z = np.array([1, -1, -1, 1, 1, -1, -1, 1]) * w / 2
        c, s = np.cos(self.rotation_y), np.sin(self.rotation_y)
        return np.stack([c * x + s * z, y, -s * x + c * z], 1) + np.asarray(self.location)

    def contains(self, rect: np.ndarray, margin: float = 0.0, ground: float = 0.0) -> np.ndarray:
        """(N,) bool: which rectified-camera points ((N,>=3)) lie in the 3D box, enlarged by ``margin`` metres on
        its four sides and at its top, with its bottom raised by ``ground`` metres (so the road under it is out)."""
        h, w, l = self.dimensions
        c, s = np.cos(self.rotation_y), np.sin(self.rotation_y)
        d = np.asarray(rect, np.float64)[:, :3] - np.asarray(self.location)
        x, z = c * d[:, 0] - s * d[:, 2], s * d[:, 0] + c * d[:, 2]  # along the box's length and width
        return (
            (np.abs(x) <= l / 2 + margin)
            & (np.abs(z) <= w / 2 + margin)
            & (d[:, 1] <= -ground)
            & (d[:, 1] >= -h - margin)
        )

    def to_line(self) -> str:
        vals = [
            self.truncated,
            self.occluded,
            self.alpha,
            *self.bbox,
            *self.dimensions,
            *self.location,
            self.rotation_y,
        ]
        return self.type + " " + " ".join(f"{v:.2f}" if not isinstance(v, int) else str(v) for v in vals)


def read_labels(path: str | Path) -> list[Object3D]:
    """Read a label_2 file: 15 fields per line (a 16th, the score, is allowed in result files)."""
    path = Path(path)
    try:
        lines = path.read_text().splitlines()
    except OSError as err:
        raise DataError(f"{path}: cannot read labels ({err.strerror})") from err
    objects = []
    for num, line in enumerate(lines, 1):
        f = line.split()
        if not f:
            continue
        if len(f) not in (15, 16):
            raise DataError(f"{path}:{num}: label line has {len(f)} fields, expected 15")
        try:
            v = [float(x) for x in f[1:15]]
        except ValueError as err:
            raise DataError(f"{path}:{num}: non-numeric label field") from err
        objects.append(
            Object3D(
                f[0],
                v[0],
                int(v[1]),
                v[2],
                cast("tuple[float, float, float, float]", tuple(v[3:7])),
                cast("tuple[float, float, float]", tuple(v[7:10])),
                cast("tuple[float, float, float]", tuple(v[10:13])),
                v[13],
            )
        )
    return objects


def read_road_gt(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a gt_image_2 file in KITTI road colours -> (road (H,W) bool, valid (H,W) bool).

    Magenta (R=255, B=255) is road; red (R=255, B=0) is not road; black is outside the evaluated area."""
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise DataError(f"{path}: missing or unreadable road ground truth")
    road = (img[..., 0] > 127) & (img[..., 2] > 127)
    return road, img[..., 2] > 127


def write_road_gt(path: str | Path, road: np.ndarray, valid: np.ndarray | None = None) -> None:
    """Write a road mask in KITTI road colours (inverse of :func:`read_road_gt`)."""
    valid = np.ones_like(road, bool) if valid is None else valid
    img = np.zeros(road.shape + (3,), np.uint8)
    img[valid, 2] = 255
    img[road & valid, 0] = 255
    cv2.imwrite(str(path), img)


def find_split_dir(root: str | Path, benchmark: str) -> Path:
    """Locate the folder holding image_2/ for ``benchmark`` ('object' or 'road') under ``root``."""
    root = Path(root)
    for cand in (root, root / "training", root / benchmark / "training", root / f"data_{benchmark}" / "training"):
        if (cand / "image_2").is_dir() and (cand / "calib").is_dir():
            return cand
    raise DataError(
        f"{root}: no KITTI {benchmark} layout found (expected image_2/ and calib/ under it, "
        f"under training/ or under {benchmark}/training/)"
    )


def frame_paths(split_dir: Path, frame: str) -> dict[str, Path]:
    """File paths of one frame; the calib must exist (an image with no calib is an error)."""
    paths = {
        "image": split_dir / "image_2" / f"{frame}.png",
        "calib": split_dir / "calib" / f"{frame}.txt",
        "velodyne": split_dir / "velodyne" / f"{frame}.bin",
        "label": split_dir / "label_2" / f"{frame}.txt",
    }
    paths["instance"] = split_dir / "instance_2" / f"{frame}.png"
    if "_" in frame:  # KITTI road naming: um_000000 -> um_road_000000
        cat, idx = frame.split("_", 1)
        paths["road_gt"] = split_dir / "gt_image_2" / f"{cat}_road_{idx}.png"
    else:  # generated object-layout frames
        paths["road_gt"] = split_dir / "gt_image_2" / f"road_{frame}.png"
    if not paths["calib"].is_file():
        raise DataError(f"{paths['image']}: image has no calibration file {paths['calib']}")
    return paths


def list_frames(split_dir: Path, check: bool = True) -> list[str]:
    """Sorted frame ids of ``split_dir``/image_2; with ``check``, every image must have its calib."""
    frames = sorted(p.stem for p in (split_dir / "image_2").glob("*.png"))
    if not frames:
        raise DataError(f"{split_dir / 'image_2'}: no .png images")
    for f in frames if check else ():
        frame_paths(split_dir, f)
    return frames


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def check_png(path: Path, what: str = "image") -> tuple[int, int]:
    """(height, width) of a PNG from its header, after checking that it starts as a PNG (signature, IHDR chunk)
    and ends as one (the IEND chunk): a DataError naming ``path`` if not. Reads 36 bytes, never the pixels."""
    try:
        with open(path, "rb") as f:
            head = f.read(24)
            size = f.seek(0, 2)
            f.seek(max(size - 12, 0))
            tail = f.read(12)
    except FileNotFoundError:
        raise DataError(f"{path}: {what} is missing") from None
    except OSError as err:
        raise DataError(f"{path}: cannot read {what} ({err.strerror})") from None
    if head[:8] != _PNG_SIGNATURE or head[12:16] != b"IHDR":
        raise DataError(f"{path}: {what} is not a PNG (it starts with {head[:8]!r})")
    width, height = struct.unpack(">II", head[16:24])
    if not width or not height:
        raise DataError(f"{path}: {what} is {width}x{height} pixels")
    if tail[4:8] != b"IEND":
        raise DataError(f"{path}: {what} is a PNG cut short ({size} bytes, no IEND chunk at its end)")
    return height, width


def check_frame(split_dir: Path, frame: str) -> None:
    """The cheap check of one frame's files, at most a few hundred bytes of binary read from each: a DataError
    naming the file and what is wrong with it.

    - the image exists and has a PNG's header and end (:func:`check_png`), as has the road ground truth and the
      instance map where the frame has one;
    - the calibration exists and parses, with P2, R0_rect and Tr_velo_to_cam of the right sizes;
    - the velodyne scan exists (where the data has ``velodyne/``) and its size is a positive multiple of 16 bytes;
    - the labels, where the frame has a label file, parse: 15 fields per line, numeric.

    Not checked (they fail when the file is read, each as one DataError naming it): a PNG whose compressed pixels
    are corrupt between an intact header and end, and a scan cut at a multiple of 16 bytes (its points read fine).
    """
    image = split_dir / "image_2" / f"{frame}.png"
    if not image.is_file():
        calib = "" if (split_dir / "calib" / f"{frame}.txt").is_file() else "; so is its calibration"
        raise DataError(f"{image}: the frame's image is missing{calib}")
    paths = frame_paths(split_dir, frame)
    check_png(image)
    Calibration.from_file(paths["calib"])
    if paths["velodyne"].parent.is_dir():
        try:
            size = paths["velodyne"].stat().st_size
        except FileNotFoundError:
            raise DataError(f"{paths['velodyne']}: velodyne scan is missing") from None
        _check_scan_size(paths["velodyne"], size)
    if paths["label"].is_file():
        read_labels(paths["label"])
    for key, what in (("road_gt", "road ground truth"), ("instance", "instance map")):
        if paths[key].is_file():
            check_png(paths[key], what)
