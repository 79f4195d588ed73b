"""Readers and LiDAR representations on the real KITTI sample frames, and every bad-input case."""

import numpy as np
import pytest

from ablate.data import DataError
from ablate.data.kitti import (
    Calibration,
    find_split_dir,
    frame_paths,
    list_frames,
    read_image,
    read_labels,
    read_road_gt,
    read_velodyne,
)
from ablate.data.lidar import bev_image, dense_depth, dhi_image, jet, sparse_depth


@pytest.fixture(scope="module")
def obj(kitti_root):
    return kitti_root / "object" / "training"


def load(obj, frame):
    return (
        Calibration.from_file(obj / "calib" / f"{frame}.txt"),
        read_velodyne(obj / "velodyne" / f"{frame}.bin"),
        read_image(obj / "image_2" / f"{frame}.png"),
    )


@pytest.mark.parametrize("frame", ["000000", "000006"])
def test_points_in_image_and_boxes_hold_points(obj, frame):
    calib, pts, img = load(obj, frame)
    assert pts.dtype == np.float32 and pts.shape[1] == 4 and len(pts) > 100_000
    uv, depth = calib.velo_to_image(pts[:, :3])
    h, w = img.shape[:2]
    inside = (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    assert 17_000 <= inside.sum() <= 20_500
    rect = calib.velo_to_rect(pts[:, :3])
    homogeneous = np.c_[pts[:, :3].astype(np.float64), np.ones(len(pts))] @ calib.velo_to_rect_matrix.T
    np.testing.assert_allclose(homogeneous[:, :3], rect, atol=1e-9)  # the 4x4 form is the same transform
    assert (homogeneous[:, 3] == 1).all()
    for o in read_labels(obj / "label_2" / f"{frame}.txt"):
        if o.type == "DontCare":
            continue
        c, s = np.cos(o.rotation_y), np.sin(o.rotation_y)
        d = rect - np.asarray(o.location)
        lx, lz = c * d[:, 0] - s * d[:, 2], s * d[:, 0] + c * d[:, 2]
        h_, w_, l_ = o.dimensions
        n = ((np.abs(lx) < l_ / 2) & (np.abs(lz) < w_ / 2) & (d[:, 1] < 0) & (d[:, 1] > -h_)).sum()
        assert n >= 3, (o.type, n)


def test_labels_keep_dontcare_and_difficulty(obj):
    labels = read_labels(obj / "label_2" / "000001.txt")
    assert [o.type for o in labels].count("DontCare") == 4
    truck = labels[0]
    assert truck.type == "Truck" and truck.bbox == (599.41, 156.40, 629.75, 189.25)
    assert truck.dimensions == (2.85, 2.63, 12.34) and truck.location == (0.47, 1.49, 69.44)
    assert labels[2].occluded == 3 and labels[2].difficulty == -1  # Cyclist, occlusion unknown
    assert labels[1].difficulty == -1  # Car 21.6 px high: under the 25 px of moderate and hard
    assert truck.difficulty == 1  # 32.9 px high, fully visible: under easy's 40 px
    assert read_labels(obj / "label_2" / "000000.txt")[0].difficulty == 0


def test_sparse_dense_depth(obj):
    calib, pts, img = load(obj, "000000")  # the 1224x370 frame
    shape = img.shape[:2]
    assert shape == (370, 1224)
    sp = sparse_depth(pts, calib, shape)
    assert sp.dtype == np.float32 and sp.shape == shape and 17_000 < (sp > 0).sum() < 20_500
    uv, depth = calib.velo_to_image(pts[:, :3])
    ok = (depth > 0) & (np.rint(uv[:, 0]) == 600) & (np.rint(uv[:, 1]) == 300)
    if ok.any():  # the nearest point wins its pixel
        assert sp[300, 600] == pytest.approx(depth[ok].min(), rel=1e-5)
    dd = dense_depth(sp)
    assert dd.dtype == np.float32 and np.isfinite(dd).all() and (dd > 0).all()
    np.testing.assert_array_equal(dd[sp > 0], sp[sp > 0])
    assert dd.max() <= sp.max() + 1e-4 and dd.min() >= sp[sp > 0].min() - 1e-4
    colour = jet(dd, 80.0)
    assert colour.shape == shape + (3,) and colour.dtype == np.uint8
    assert colour[dd < 5].mean(0)[0] > colour[dd < 5].mean(0)[2]  # near is red


def test_dense_depth_interpolates_linearly():
    sp = np.zeros((20, 20), np.float32)
    sp[2, 2], sp[2, 17], sp[17, 2], sp[17, 17] = 10, 10, 40, 40  # depth linear in the row
    dd = dense_depth(sp)
    assert dd[12, 9] == pytest.approx(30.0, abs=1e-4) and dd[0, 0] == 10 and dd[19, 19] == 40
    with pytest.raises(DataError, match="no LiDAR return"):
        dense_depth(np.zeros((4, 4), np.float32))


def test_dhi_and_bev_ranges(obj):
    calib, pts, img = load(obj, "000001")
    dhi = dhi_image(pts, calib, img.shape[:2])
    assert dhi.shape == img.shape[:2] + (3,) and dhi.dtype == np.uint8
    hit = dhi.any(-1)
    assert 17_000 < hit.sum() < 20_500
    # eq. (2): depth channel 255 (1 - x / 80): near points bright, far points dark.
    assert dhi[hit, 0].max() > 230 and dhi[hit, 0].min() < 60
    bev = bev_image(pts)
    assert bev.shape == (6, 80, 40) and bev.dtype == np.float32
    occupied = bev[0] != 0
    assert occupied.mean() > 0.2
    assert (bev[0] >= bev[2] - 1e-5).all() and (bev[2] >= bev[1] - 1e-5).all()  # max >= mean >= min
    assert (bev[3:] >= 0).all() and (bev[3:] <= 1).all() and np.abs(bev[1][occupied]).min() < 0.5
    assert (bev[:, ~occupied] == 0).all()


def test_road_layout(kitti_root):
    split = find_split_dir(kitti_root / "road", "road")
    assert list_frames(split) == ["um_000000"]
    paths = frame_paths(split, "um_000000")
    road, valid = read_road_gt(paths["road_gt"])
    assert road.shape == (375, 1242) and 0.05 < road.mean() < 0.5 and valid.mean() > 0.9
    calib = Calibration.from_file(paths["calib"])
    assert calib.Tr_cam_to_road.shape == (3, 4) and calib.P2.shape == (3, 4) and calib.R0_rect.shape == (3, 3)


# Bad input: one DataError naming the file.
def test_truncated_velodyne(tmp_path, obj):
    raw = (obj / "velodyne" / "000000.bin").read_bytes()
    bad = tmp_path / "000000.bin"
    bad.write_bytes(raw[: 1000 * 16 + 7])
    with pytest.raises(DataError, match=r"000000\.bin.*multiple of 16"):
        read_velodyne(bad)
    bad.write_bytes(b"")
    with pytest.raises(DataError, match="000000.bin"):
        read_velodyne(bad)


def test_calib_missing_key(tmp_path, obj):
    lines = (obj / "calib" / "000000.txt").read_text().splitlines()
    bad = tmp_path / "calib.txt"
    bad.write_text("\n".join(ln for ln in lines if not ln.startswith("Tr_velo_to_cam")))
    with pytest.raises(DataError, match=r"calib\.txt.*Tr_velo_to_cam is missing"):
        Calibration.from_file(bad)


def test_image_without_calib(tmp_path, obj):
    for sub in ("image_2", "calib"):
        (tmp_path / sub).mkdir()
    (tmp_path / "image_2" / "000000.png").write_bytes((obj / "image_2" / "000000.png").read_bytes())
    with pytest.raises(DataError, match=r"000000\.png.*no calibration"):
        list_frames(tmp_path)


def test_label_wrong_field_count(tmp_path, obj):
    lines = (obj / "label_2" / "000001.txt").read_text().splitlines()
    lines[2] = " ".join(lines[2].split()[:14])
    bad = tmp_path / "label.txt"
    bad.write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match=r"label\.txt:3: label line has 14 fields, expected 15"):
        read_labels(bad)
