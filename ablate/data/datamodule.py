"""Lightning DataModule over real KITTI or the generated default dataset.

Sample dict (a batch after :func:`collate` holds the same keys):

- modalities, float32 [C,H,W]: ``rgb`` [3] 0-1 (condition applied), ``intensity`` [1] grayscale of that rgb,
  ``sparse_depth`` / ``dense_depth`` [1] metres / max_depth, ``ddm_jet`` [3] 0-1, ``dhi`` [3] 0-1, ``bev`` [6,Hb,Wb];
- targets: ``free_space`` / ``road_objects`` [1,H,W] {0,1}; ``semantic`` [H,W] int64 (0 background, 1 free space,
  2 road object); ``instances`` dict(masks [N,H,W] bool, labels [N] 0 car 1 pedestrian, boxes [N,4] xyxy);
  ``boxes2d`` dict(boxes, labels 0 car 1 pedestrian 2 cyclist, difficulty 0/1/2/-1); ``ignore`` [H,W] bool
  (DontCare boxes); ``road_bev`` [1,Hb,Wb] {0,1};
- ``frame`` (id) and ``condition`` (name), ``lidar_condition`` (name, only with ``lidar_weather``); lists in a
  batch, as are ``instances`` and ``boxes2d``.

``augment`` (``{flip: p, scale: [lo, hi]}``, ablate.data.augment) gives each training frame a random flip, zoom and
shift of the scene or camera, followed by every modality, target and the calibration; validation and test frames
are never augmented.

What a job's seed changes (docs/verdicts.md#what-a-seed-randomises): the shuffled order of the training frames
(``order_seed``, the config's ``${seed}``), besides the initialisation and the augmentation's draws (torch's global
generator, which the job seeds). The data module's own ``seed`` stays fixed: each frame's condition and corruption,
so every row and seed is tested on one test set, and the generated dataset (``synth.seed``) and the split with it.

Splits (fixed, independent of ``seed``): a folder's ``ImageSets/{train,val,test}.txt`` when present (the
generated dataset writes a seeded 60/20/20 split there); otherwise a permutation of the sorted frames with seed 0
cut 4489/1496/1496 when all 7481 KITTI object frames are present (SMoE §3.3), else 60/20/20.

Bad frames (``on_bad_frame``, ``data.on_bad_frame`` in the config: ``error``, the default, or ``skip``). ``setup``
indexes each split by checking every frame it will use with :func:`ablate.data.kitti.check_frame`: a frame listed
in ``ImageSets`` whose image is missing, an image that is not a PNG or is cut short (its header and its end are read,
never its pixels), a calibration file that does not parse or lacks P2, R0_rect or Tr_velo_to_cam, a velodyne scan
missing or whose size is not a positive multiple of 16 bytes, a label line without 15 numeric fields, and a road
ground truth or instance map that is not a PNG. That costs about 0.3 ms a frame (KITTI's 7481 frames in some 2 s on
a 2-core machine, file cache warm). With ``error`` the first bad frame is one DataError naming its file and frame,
raised at setup, before the first batch; with ``skip`` the frame is left out of its split, a warning names its file
and the reason, and the count is :attr:`KittiDataModule.skipped_frames` (per split and with the reasons:
:attr:`KittiDataModule.bad_frames`). ``limit_frames`` counts the frames kept, so a cap still gives that many.

Why at setup rather than in ``__getitem__``: skipping while indexing fixes a split's frames before the loader
exists, so its length, its seeded shuffle and each frame's condition (spread over the frame list) are the same in
every epoch, every loader worker and every rerun. Replacing a bad frame by another in ``__getitem__`` would repeat
a frame in an epoch, or make the batches depend on which worker met the file first. Whether a frame is kept depends
on its files alone, never on the row's modalities or targets (a camera-only row checks the scan too), so every row
of a table trains and is tested on the same frames. What the check cannot see (compressed pixels corrupt between an
intact PNG header and end, a scan cut at a multiple of 16 bytes) fails when read, as one DataError naming the file,
whichever the mode. The cache of derived LiDAR modalities never holds a bad frame: a skipped frame is never read,
an entry is written only once its value has been computed (a read that raises writes none), and its key holds the
size and modification time of the scan, calibration and labels it was derived from, so a file repaired or replaced
later is read again, never served from the entry of the old one.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import logging
from collections.abc import Sequence
from pathlib import Path

import lightning as L
import torch
from omegaconf.errors import ValidationError
from torch.utils.data import DataLoader
from tqdm import tqdm

from ablate.data import DEFAULT_SYNTH, GENERATOR_VERSION, DataError, kitti
from ablate.data.dataset import LIDAR_DERIVED, MODALITIES, KittiDataset
from ablate.data.generate import generate, split_frames
from ablate.data.order import ResumableLoader, trained_batches
from ablate.hardware import cores

LIST_KEYS = ("frame", "condition", "lidar_condition", "instances", "boxes2d")
#: What ``data.on_bad_frame`` takes: a bad frame is one DataError (``error``) or is left out and logged (``skip``).
ON_BAD_FRAME = ("error", "skip")

log = logging.getLogger(__name__)


def collate(samples: list[dict]) -> dict:
    """Stack tensors; keep the ``LIST_KEYS`` as lists."""
    return {k: [s[k] for s in samples] if k in LIST_KEYS else torch.stack([s[k] for s in samples]) for k in samples[0]}


def synth_dir(data_dir: str | Path, params: dict) -> Path:
    """data_dir/synth-<hash of the generator parameters>; ``furniture`` counts only where on (the datasets made
    before it keep their names)."""
    params = {k: v for k, v in params.items() if k != "furniture" or v}
    key = hashlib.sha1(json.dumps(params, sort_keys=True).encode()).hexdigest()[:8]
    return Path(data_dir) / f"synth-{key}"


def ensure_synth(data_dir: str | Path, params: dict | None) -> Path:
    """The generated dataset for ``params``, generated on first use."""
    params = {**DEFAULT_SYNTH, **(params or {})}
    if params["version"] != GENERATOR_VERSION:
        raise DataError(
            f"data.synth.version={params['version']}: this ablate generates version {GENERATOR_VERSION} "
            "only (check out an older ablate for older generated data)"
        )
    out = synth_dir(data_dir, params)
    if not (out / "synth.json").is_file():  # written last, so its presence means a complete dataset
        out.parent.mkdir(parents=True, exist_ok=True)
        # the jobs of a parallel sweep start together on a fresh machine: one generates, the others wait for it
        # (two writers of one frame's files would let a reader see a file half rewritten)
        with open(out.parent / f"{out.name}.lock", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            if not (out / "synth.json").is_file():
                log.info("Generating the default dataset: %d frames in %s", params["frames"], out)
                generate(
                    out,
                    params["frames"],
                    params["seed"],
                    params["height"],
                    params["width"],
                    workers=cores(),  # the other jobs wait for it: every core; the frames are the same at any count
                    furniture=bool(params.get("furniture", False)),
                )
    return out


def resolve_split_dir(root: str | Path) -> Path:
    for bench in ("object", "road"):
        try:
            return kitti.find_split_dir(root, bench)
        except DataError:
            continue
    raise DataError(f"{root}: no KITTI object or road layout (image_2/ and calib/) found")


def splits(split_dir: Path) -> dict[str, list[str]]:
    sets = split_dir / "ImageSets"
    if all((sets / f"{s}.txt").is_file() for s in ("train", "val", "test")):
        return {s: (sets / f"{s}.txt").read_text().split() for s in ("train", "val", "test")}
    frames = kitti.list_frames(split_dir, check=False)  # each frame's files are checked by index_frames
    if len(frames) == 7481:
        return split_frames(frames, 0, (4489 / 7481, 1496 / 7481, 1496 / 7481))
    return split_frames(frames, 0)


def check_on_bad_frame(value: str) -> str:
    """``value`` if ``data.on_bad_frame`` takes it, else a ValidationError naming the option and what it takes."""
    if value not in ON_BAD_FRAME:
        raise ValidationError(
            f"data.on_bad_frame={value!r}: expected error (a bad frame stops the job with a "
            "DataError naming its file) or skip (a bad frame is left out and logged)"
        )
    return value


def index_frames(
    split_dir: Path, frames: list[str], on_bad_frame: str = "error", cap: int | None = None, where: str = ""
) -> tuple[list[str], dict[str, str]]:
    """The frames of ``frames`` that pass :func:`ablate.data.kitti.check_frame`, in order, at most ``cap`` of them,
    and the bad ones met on the way (frame -> reason). With ``on_bad_frame="error"`` the first bad frame is one
    DataError naming its file, the frame and ``where`` it is listed."""
    kept: list[str] = []
    bad: dict[str, str] = {}
    for frame in frames:
        if cap is not None and len(kept) >= cap:
            break
        try:
            kitti.check_frame(split_dir, frame)
        except DataError as err:
            if on_bad_frame == "error":
                raise DataError(
                    f"{err} (frame {frame}{where}; data.on_bad_frame=skip leaves such frames out)"
                ) from None
            log.warning("Skipping frame %s%s: %s", frame, where, err)
            bad[frame] = str(err)
            continue
        kept.append(frame)
    return kept, bad


class KittiDataModule(L.LightningDataModule):
    """Camera + LiDAR data for every task; every argument is a plain value so Hydra can build it.

    After :meth:`setup` (which the loaders call), :attr:`skipped_frames` is the number of bad frames left out with
    ``on_bad_frame="skip"`` (0 with ``error``, where a bad frame raises) and :attr:`bad_frames` holds them per
    split, each frame with the reason (the module's docstring says what is checked).
    """

    def __init__(
        self,
        root: str | None = None,
        synth: dict | None = None,
        data_dir: str = "data",
        modalities: Sequence[str] = ("rgb", "dense_depth"),
        targets: Sequence[str] = (),
        conditions: Sequence[str] = ("clear",),
        severity: float = 1.0,
        corruption: dict | None = None,
        batch_size: int = 4,
        num_workers: int = 0,
        seed: int = 0,
        order_seed: int | None = None,
        max_depth: float = 80.0,
        limit_frames: dict | None = None,
        bev: dict | None = None,
        cache: bool = True,
        image_size: list[int] | None = None,
        lidar_weather: list[str] | None = None,
        augment: dict | None = None,
        on_bad_frame: str = "error",
        memo_gb: float = 0,
    ) -> None:
        super().__init__()
        self.on_bad_frame = check_on_bad_frame(on_bad_frame)
        for m in modalities:
            if m not in MODALITIES:
                raise KeyError(f"unknown modality {m!r}; valid: {', '.join(MODALITIES)}")
        self.root, self.synth, self.data_dir = root, synth, data_dir
        self.modalities, self.targets, self.conditions = list(modalities), list(targets), list(conditions)
        self.severity, self.corruption, self.batch_size = severity, corruption, batch_size
        self.num_workers, self.seed, self.max_depth = num_workers, seed, max_depth
        # the training data's order: the training seed's (data.order_seed: ${seed}), the data's seed without one
        self.order_seed = seed if order_seed is None else int(order_seed)
        self.limit_frames, self.bev, self.cache = dict(limit_frames or {}), bev, cache
        self.lidar_weather = list(lidar_weather) if lidar_weather else None
        # flip / scale / translation of the training split (ablate.data.augment): {flip: p, scale: [lo, hi]}
        self.augment = dict(augment) if augment else None
        # GiB of decoded training and validation frames kept in memory between epochs (ablate.data.memo), per split
        self.memo_gb = float(memo_gb)
        # Real KITTI images range from 1224x370 to 1242x375: crop to the smallest unless told otherwise.
        self.image_size = image_size if image_size or root is None else [370, 1224]
        self.datasets: dict[str, KittiDataset] = {}
        #: split -> {frame: reason} of the bad frames left out at setup (``on_bad_frame="skip"``)
        self.bad_frames: dict[str, dict[str, str]] = {}

    @property
    def skipped_frames(self) -> int:
        """How many bad frames ``setup`` left out, all splits together (runs ``setup`` if it has not run)."""
        self.setup()
        return sum(len(bad) for bad in self.bad_frames.values())

    @property
    def channels(self) -> dict[str, int]:
        return {m: MODALITIES[m] for m in self.modalities}

    def split_dir(self) -> Path:
        if self.root is not None:
            if not Path(self.root).exists():
                raise DataError(f"data root {self.root} does not exist")
            return resolve_split_dir(self.root)
        return ensure_synth(self.data_dir, self.synth)

    def prepare_data(self) -> None:
        self.split_dir()

    def setup(self, stage: str | None = None) -> None:
        if self.datasets:
            return
        split_dir = self.split_dir()
        datasets, bad_frames = {}, {}
        for name, frames in splits(split_dir).items():
            listed = split_dir / "ImageSets" / f"{name}.txt"
            where = f", listed in {listed}" if listed.is_file() else f" of the {name} split"
            kept, bad_frames[name] = index_frames(
                split_dir, frames, self.on_bad_frame, self.limit_frames.get(name), where
            )
            datasets[name] = KittiDataset(
                split_dir,
                kept,
                self.modalities,
                self.targets,
                self.conditions,
                self.severity,
                self.corruption,
                self.seed,
                self.max_depth,
                Path(self.data_dir) / "cache" if self.cache else None,
                self.bev,
                self.image_size,
                self.lidar_weather,
                self.augment if name == "train" else None,
                # the test split is read once (per condition): nothing to keep
                self.memo_gb * 2**30 if name in ("train", "val") else 0,
            )
        self.datasets, self.bad_frames = datasets, bad_frames
        if skipped := sum(len(bad) for bad in bad_frames.values()):
            log.warning(
                "data.on_bad_frame=skip: left out %d bad frame(s) of %s (%s)",
                skipped,
                split_dir,
                ", ".join(f"{name} {len(bad)}" for name, bad in bad_frames.items()),
            )

    def teardown(self, stage: str) -> None:
        """Lightning's hook at the end of a fit or test: once a fit ends, the frames its splits kept between epochs
        (ablate.data.memo) are let go, so that a process that fits again holds one fit's frames at a time."""
        if stage == "fit":
            for dataset in self.datasets.values():
                if dataset.memo is not None:
                    dataset.memo.clear()

    def _loader(self, split: str, shuffle: bool) -> DataLoader:
        self.setup()
        if not self.datasets[split].frames:
            d, n = self.datasets[split].split_dir, sum(len(ds.frames) for ds in self.datasets.values())
            cap = f", data.limit_frames.{split}={self.limit_frames[split]}" if split in self.limit_frames else ""
            raise DataError(
                f"{d}: the {split} split has no frames ({n} in all{cap}); list them in "
                f"{d / 'ImageSets' / (split + '.txt')} or give more frames"
            )
        gen = torch.Generator().manual_seed(self.order_seed if shuffle else self.seed)
        # pinned (page-locked) host memory where a CUDA device will read the batches: faster, asynchronous copies
        common = dict(
            num_workers=self.num_workers,
            collate_fn=collate,
            persistent_workers=self.num_workers > 0,
            pin_memory=torch.cuda.is_available(),
        )
        if shuffle and self._world_size() == 1:  # the same order as shuffle=True, resumable (ablate.data.order)
            return ResumableLoader(self.datasets[split], self.batch_size, gen, self._trained_batches, **common)
        # several processes: Lightning's DistributedSampler shuffles, by its seed and the epoch
        return DataLoader(self.datasets[split], self.batch_size, shuffle=shuffle, generator=gen, **common)

    def _world_size(self) -> int:
        """The trainer's processes (1 without a trainer)."""
        trainer = getattr(self, "trainer", None)
        return int(getattr(trainer, "world_size", 1) or 1) if trainer is not None else 1

    def _trained_batches(self) -> tuple[int, float] | None:
        return trained_batches(getattr(self, "trainer", None))

    def train_dataloader(self) -> DataLoader:
        return self._loader("train", True)

    def val_dataloader(self) -> DataLoader:
        return self._loader("val", False)

    def test_dataloader(self) -> DataLoader:
        return self._loader("test", False)


def prepare(
    root: str | None,
    data_dir: str = "data",
    modalities: Sequence[str] = ("sparse_depth", "dense_depth"),
    max_depth: float = 80.0,
) -> int:
    """Precompute the cache of derived LiDAR modalities for every frame of ``root`` (tqdm progress bar)."""
    split_dir = resolve_split_dir(root) if root else ensure_synth(data_dir, None)
    derived = [m for m in modalities if m in LIDAR_DERIVED and m != "ddm_jet"]
    ds = KittiDataset(
        split_dir,
        kitti.list_frames(split_dir),
        derived,
        [],
        ["clear"],
        max_depth=max_depth,
        cache_dir=Path(data_dir) / "cache",
    )
    for frame in tqdm(ds.frames, desc=f"caching {', '.join(derived)}", unit="frame", disable=None):  # a terminal's
        shape = kitti.read_image(kitti.frame_paths(split_dir, frame)["image"]).shape[:2]
        for m in derived:
            ds.lidar(frame, m, shape)
    return len(ds.frames)
