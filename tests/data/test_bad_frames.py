"""Bad frames in real data, each kind under ``data.on_bad_frame=error`` (one DataError naming the file and the
frame, at setup) and ``skip`` (left out of its split, logged, counted), on a copy of real KITTI frames."""

from __future__ import annotations

import logging
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from omegaconf.errors import ValidationError

from ablate.data import DataError
from ablate.data.datamodule import KittiDataModule
from ablate.data.dataset import KittiDataset
from ablate.data.kitti import check_frame

REPO = Path(__file__).resolve().parents[2]
FRAMES = ("000000", "000001", "000002", "000003", "000004")
SPLITS = {"train": FRAMES[:3], "val": FRAMES[3:4], "test": FRAMES[4:]}
BAD = "000001"  # of the train split


def layout(src: Path, dst: Path) -> Path:
    """A KITTI object layout in ``dst`` of real frames: links to the shared files, ImageSets with SPLITS."""
    out = dst / "object" / "training"
    for sub, ext in (("image_2", "png"), ("calib", "txt"), ("velodyne", "bin"), ("label_2", "txt")):
        (out / sub).mkdir(parents=True)
        for frame in FRAMES:
            (out / sub / f"{frame}.{ext}").symlink_to(src / sub / f"{frame}.{ext}")
    (out / "ImageSets").mkdir()
    for name, frames in SPLITS.items():
        (out / "ImageSets" / f"{name}.txt").write_text("\n".join(frames) + "\n")
    return out


def replace(path: Path, data: bytes | str) -> None:
    """Write ``data`` as ``path``, a file of its own (never through the link to the shared frame)."""
    path.unlink()
    path.write_bytes(data) if isinstance(data, bytes) else path.write_text(data)


def truncated_scan(d: Path) -> tuple[Path, str]:
    path = d / "velodyne" / f"{BAD}.bin"
    replace(path, path.read_bytes()[: 1000 * 16 + 7])
    return path, "truncated velodyne scan, 16007 bytes is not a positive multiple of 16"


def calib_without_p2(d: Path) -> tuple[Path, str]:
    path = d / "calib" / f"{BAD}.txt"
    replace(path, "\n".join(ln for ln in path.read_text().splitlines() if not ln.startswith("P2:")) + "\n")
    return path, "calibration key P2 is missing"


def label_with_14_fields(d: Path) -> tuple[Path, str]:
    path = d / "label_2" / f"{BAD}.txt"
    lines = path.read_text().splitlines()
    lines[1] = " ".join(lines[1].split()[:14])
    replace(path, "\n".join(lines) + "\n")
    return path, ":2: label line has 14 fields, expected 15"


def image_not_an_image(d: Path) -> tuple[Path, str]:
    path = d / "image_2" / f"{BAD}.png"
    replace(path, "this is not an image\n" * 50)
    return path, "image is not a PNG (it starts with b'this is ')"


def image_cut_short(d: Path) -> tuple[Path, str]:
    path = d / "image_2" / f"{BAD}.png"
    raw = path.read_bytes()
    replace(path, raw[: len(raw) // 2])
    return path, "image is a PNG cut short"


def listed_but_missing(d: Path) -> tuple[Path, str]:
    (d / "ImageSets" / "train.txt").write_text("\n".join([*SPLITS["train"][:1], "000009", *SPLITS["train"][1:]]))
    for sub in ("image_2", "calib", "velodyne", "label_2"):  # the listed frame is 000009, and 000001 is fine
        assert not list((d / sub).glob("000009.*"))
    return d / "image_2" / "000009.png", "the frame's image is missing; so is its calibration"


KINDS = [
    truncated_scan,
    calib_without_p2,
    label_with_14_fields,
    image_not_an_image,
    image_cut_short,
    listed_but_missing,
]


@pytest.fixture
def data(kitti_root, tmp_path):
    return layout(kitti_root / "object" / "training", tmp_path / "kitti")


def module(data: Path, tmp_path: Path, **kw) -> KittiDataModule:
    return KittiDataModule(
        root=str(data.parent),
        data_dir=str(tmp_path / "work"),
        modalities=["rgb", "sparse_depth"],
        targets=["boxes2d"],
        batch_size=2,
        **kw,
    )


@pytest.mark.parametrize("kind", KINDS, ids=lambda k: k.__name__)
def test_by_default_a_bad_frame_is_one_data_error_naming_the_file_and_the_frame(data, tmp_path, kind):
    path, reason = kind(data)
    dm = module(data, tmp_path)
    frame = path.stem
    with pytest.raises(DataError) as err:
        dm.setup()
    message = str(err.value)
    assert message.startswith(f"{path}") and reason in message, message
    assert f"(frame {frame}, listed in {data / 'ImageSets' / 'train.txt'};" in message
    assert "data.on_bad_frame=skip" in message  # names the way out
    assert err.value.__cause__ is None and err.value.__suppress_context__  # one error, not a chain
    assert not dm.datasets and not (tmp_path / "work" / "cache").exists()  # nothing indexed, nothing cached


@pytest.mark.parametrize("kind", KINDS, ids=lambda k: k.__name__)
def test_with_skip_a_bad_frame_is_left_out_logged_and_counted(data, tmp_path, kind, caplog):
    path, reason = kind(data)
    frame = path.stem
    kept = [f for f in (data / "ImageSets" / "train.txt").read_text().split() if f != frame]
    dm = module(data, tmp_path, on_bad_frame="skip")
    with caplog.at_level(logging.WARNING, logger="ablate.data.datamodule"):
        dm.setup()
    assert dm.skipped_frames == 1
    assert list(dm.bad_frames) == ["train", "val", "test"] and not dm.bad_frames["val"] and not dm.bad_frames["test"]
    assert list(dm.bad_frames["train"]) == [frame] and reason in dm.bad_frames["train"][frame]
    assert dm.datasets["train"].frames == kept and len(kept) in (2, 3)
    assert dm.datasets["val"].frames == ["000003"] and dm.datasets["test"].frames == ["000004"]
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any(f"Skipping frame {frame}" in w and str(path) in w and reason in w for w in warned), warned
    assert any("left out 1 bad frame(s)" in w and "train 1, val 0, test 0" in w for w in warned), warned
    seen = [f for batch in dm.train_dataloader() for f in batch["frame"]]  # the loader holds the good frames only
    assert sorted(seen) == sorted(kept)
    cached = [p.name for p in (tmp_path / "work" / "cache").rglob("*.npy")]
    assert cached and not [name for name in cached if name.startswith(frame)]  # no entry of the bad frame


def test_limit_frames_counts_the_frames_kept(data, tmp_path):
    calib_without_p2(data)
    dm = module(data, tmp_path, on_bad_frame="skip", limit_frames={"train": 2, "val": 0})
    dm.setup()
    assert dm.datasets["train"].frames == ["000000", "000002"] and dm.skipped_frames == 1
    assert dm.datasets["val"].frames == []
    # with the cap under the bad frame, it is never met
    first = module(data, tmp_path, on_bad_frame="error", limit_frames={"train": 1})
    first.setup()
    assert first.datasets["train"].frames == ["000000"] and first.skipped_frames == 0


def test_without_imagesets_a_frame_whose_calibration_is_missing_is_a_bad_frame(data, tmp_path):
    shutil.rmtree(data / "ImageSets")
    (data / "calib" / f"{BAD}.txt").unlink()
    with pytest.raises(DataError, match=rf"{BAD}\.png: image has no calibration file .*\(frame {BAD} of the "):
        module(data, tmp_path).setup()
    dm = module(data, tmp_path, on_bad_frame="skip")
    assert dm.skipped_frames == 1 and sum(len(d) for d in dm.datasets.values()) == 4


def test_on_bad_frame_takes_error_or_skip_and_the_configs_say_error():
    with pytest.raises(ValidationError, match=r"data\.on_bad_frame='drop': expected error .* or skip "):
        KittiDataModule(on_bad_frame="drop")
    assert OmegaConf.load(REPO / "conf" / "data" / "synth.yaml").on_bad_frame == "error"
    assert OmegaConf.load(REPO / "conf" / "data" / "kitti.yaml").data.on_bad_frame == "error"  # a global package


def test_the_real_frames_pass_the_check(kitti_root):
    for bench, frames in (("object", [f"{i:06d}" for i in range(8)]), ("road", ["um_000000"])):
        for frame in frames:
            check_frame(kitti_root / bench / "training", frame)


def test_what_the_check_cannot_see_fails_when_read_as_one_data_error(data, tmp_path):
    """A PNG corrupt between an intact header and end passes the check, and is a DataError naming it when read."""
    path = data / "image_2" / f"{BAD}.png"
    raw = bytearray(path.read_bytes())
    raw[len(raw) // 2 : len(raw) // 2 + 2000] = bytes(b ^ 0x55 for b in raw[len(raw) // 2 : len(raw) // 2 + 2000])
    replace(path, bytes(raw))
    dm = module(data, tmp_path, on_bad_frame="skip")
    assert dm.skipped_frames == 0
    ds = dm.datasets["train"]
    with pytest.raises(DataError, match=rf"{re.escape(str(path))}: missing or unreadable image"):
        ds[ds.frames.index(BAD)]


def test_a_cache_entry_is_never_served_for_a_file_replaced_since(data, tmp_path):
    """A scan cut at a point's boundary passes every check; once repaired, the frame is read again."""
    path = data / "velodyne" / "000000.bin"
    full = path.read_bytes()
    replace(path, full[: len(full) // 32 * 16])
    ds = KittiDataset(data, ["000000"], ["sparse_depth"], [], ["clear"], cache_dir=tmp_path / "cache")
    half = ds[0]["sparse_depth"]
    path.write_bytes(full)
    misses = ds.cache_misses
    repaired = ds[0]["sparse_depth"]
    assert ds.cache_misses == misses + 1 and (repaired > 0).sum() > (half > 0).sum()
    fresh = KittiDataset(data, ["000000"], ["sparse_depth"], [], ["clear"])[0]["sparse_depth"]
    assert torch.equal(repaired, fresh)
    hits = ds.cache_hits
    assert torch.equal(ds[0]["sparse_depth"], repaired) and ds.cache_hits == hits + 1
    assert np.isfinite(repaired.numpy()).all()
