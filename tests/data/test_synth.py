"""Generated dataset: camera/LiDAR consistency, labels, determinism, file layout, CLI."""

import hashlib

import numpy as np
import pytest

from ablate.data.__main__ import main
from ablate.data.generate import render_frame
from ablate.data.kitti import Calibration, list_frames, read_labels, read_velodyne
from ablate.data.lidar import sparse_depth


@pytest.fixture(scope="module")
def frames():
    return [render_frame(3, i, 64, 208) for i in range(4)]


def test_lidar_agrees_with_rendered_depth(frames):
    for f in frames:
        sp = sparse_depth(f["points"], f["calib"], f["depth"].shape)
        both = (sp > 0) & (f["depth"] > 0)
        assert both.sum() > 500  # 11 beams at 64 rows (ablate.data.synth.lidar_angles)
        rel = np.abs(sp[both] - f["depth"][both]) / f["depth"][both]
        # A 64x208 pixel spans 8 mrad, so a point and its pixel's centre differ by up to 1-2 % on the ground;
        # misses beyond that only at silhouette edges (mixed pixels, pixel quantisation).
        assert np.median(rel) < 0.015 and (rel < 0.03).mean() > 0.85
        # Every scan point lies on a surface: none is under the road (velodyne z > -1.73 - noise).
        assert f["points"][:, 2].min() > -1.8


def test_labels_match_instances_and_boxes(frames):
    for f in frames:
        ids = np.unique(f["instance"])
        assert list(ids[ids > 0]) == [k + 1 for k, o in enumerate(f["labels"]) if o.type != "DontCare"]
        for k, o in enumerate(f["labels"]):
            if o.type == "DontCare":
                continue
            ys, xs = np.nonzero(f["instance"] == k + 1)
            x0, y0, x1, y1 = o.bbox  # the 2D box encloses the visible mask
            assert xs.min() >= x0 - 1 and xs.max() <= x1 + 1 and ys.min() >= y0 - 1 and ys.max() <= y1 + 1
            assert o.type in ("Car", "Pedestrian") and 0 <= o.occluded <= 2 and 0 <= o.truncated <= 1
        assert not (f["road"] & (f["instance"] > 0)).any()
    assert sum(len([o for o in f["labels"] if o.type != "DontCare"]) for f in frames) > 0


def _digest(folder):
    h = hashlib.sha256()
    for p in sorted(folder.rglob("*")):
        if p.is_file() and p.name != "synth.json":
            h.update(p.relative_to(folder).as_posix().encode() + p.read_bytes())
    return h.hexdigest()


def _synth_cli(out, seed: int, workers: int) -> None:
    """`python -m ablate.data synth`: 5 frames at 64 x 208."""
    size = ["--frames", "5", "--height", "64", "--width", "208"]
    main(["synth", "--out", str(out), "--seed", str(seed), "--workers", str(workers), *size])


def test_cli_same_seed_same_bytes(tmp_path):
    _synth_cli(tmp_path / "a", seed=7, workers=1)
    _synth_cli(tmp_path / "b", seed=7, workers=2)
    _synth_cli(tmp_path / "c", seed=8, workers=1)
    assert _digest(tmp_path / "a") == _digest(tmp_path / "b") != _digest(tmp_path / "c")
    root = tmp_path / "a"
    assert list_frames(root) == [f"{i:06d}" for i in range(5)]
    calib = Calibration.from_file(root / "calib" / "000000.txt")
    assert calib.P2[0, 0] == pytest.approx(721.5377 * 208 / 1242) and calib.Tr_cam_to_road is not None
    assert read_velodyne(root / "velodyne" / "000000.bin").shape[1] == 4
    read_labels(root / "label_2" / "000000.txt")
    sets = {s: (root / "ImageSets" / f"{s}.txt").read_text().split() for s in ("train", "val", "test")}
    assert sorted(sum(sets.values(), [])) == [f"{i:06d}" for i in range(5)] and len(sets["train"]) == 3


def test_street_furniture_adds_unlabelled_depth_clutter_and_leaves_the_rest_of_the_scene():
    from ablate.data.datamodule import synth_dir
    from ablate.data.synth import BUILDING, FURNITURE, sample_scene

    plain, furnished = (sample_scene(np.random.default_rng([0, 5]), furniture=f) for f in (False, True))
    extra = len(furnished["boxes"]) - len(plain["boxes"])
    assert extra > 0 and (furnished["part"][-extra:] == FURNITURE).all()  # drawn after everything else
    assert (furnished["owner"][-extra:] == -1).all() and (furnished["cls"][-extra:] == BUILDING).all()
    np.testing.assert_array_equal(furnished["boxes"][:-extra], plain["boxes"])
    assert furnished["objects"] == plain["objects"]  # the same road users: the same labels to find
    for f in (render_frame(0, 5, 64, 208, furniture=True),):
        ids = np.unique(f["instance"])  # furniture is background: no instance, no label of its own
        assert list(ids[ids > 0]) == [k + 1 for k, o in enumerate(f["labels"]) if o.type != "DontCare"]
    params = {"frames": 5, "seed": 0, "height": 64, "width": 208, "version": 2}
    assert (
        synth_dir("d", {**params, "furniture": False})
        == synth_dir("d", params)
        != synth_dir("d", {**params, "furniture": True})
    )
