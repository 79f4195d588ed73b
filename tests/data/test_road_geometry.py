"""BiFNet DST's dense heights (ablate.data.lidar) on hand-made scans, and the road targets and per-frame geometry
of the data module (ablate.data.dataset)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from ablate.data import DataError, lidar
from ablate.data.datamodule import KittiDataModule
from ablate.data.dataset import calib_array, calibration
from ablate.data.kitti import Calibration

F, CX, CY = 100.0, 50.0, 50.0
#: velodyne (x forward, y left, z up) -> camera (x right, y down, z forward); identity rectification
CALIB = Calibration(
    P2=np.array([[F, 0, CX, 0], [0, F, CY, 0], [0, 0, 1, 0]]),
    R0_rect=np.eye(3),
    Tr_velo_to_cam=np.array([[0.0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0]]),
)
GEOMETRY = ["calib", "height_image", "height_bev", "lidar_points"]
SMALL = {"frames": 5, "seed": 3, "height": 64, "width": 208}


def point_at(u: float, v: float, z: float) -> list[float]:
    """The velodyne point of height z that CALIB projects to pixel (u, v) (v above the principal row)."""
    x = F * z / (CY - v) if v != CY else 10.0
    return [x, -(u - CX) * x / F, z, 0.5]


def test_perspective_height_weights_neighbours_by_distance_and_fills_the_rest():
    pts = np.array([point_at(10, 10, 1.0), point_at(12, 10, 3.0)], np.float32)
    h = lidar.perspective_height(pts, CALIB, (100, 100), window=4)
    assert h.shape == (100, 100) and h.dtype == np.float32
    assert h[10, 11] == pytest.approx(2.0)  # both at distance 1: the mean
    assert h[10, 10] == pytest.approx((1.0 + 3.0 / 3.0) / (1.0 + 1.0 / 3.0))  # weights 1 and 1 / (1 + 2)
    assert h[90, 10] == pytest.approx(1.0) and h[90, 14] == pytest.approx(3.0)  # outside any window: nearest point
    with pytest.raises(DataError, match="no LiDAR point projects"):
        lidar.perspective_height(np.array([[-5.0, 0, 0, 0]], np.float32), CALIB, (100, 100))


def test_bev_height_interpolates_along_the_column_in_horizontal_distance():
    # one azimuth column straight ahead: z = -1 at 10 m, +1 at 20 m
    pts = np.array([[10.0, 0.0, -1.0, 0.5], [20.0, 0.0, 1.0, 0.5]], np.float32)
    h = lidar.bev_height(pts)
    assert h.shape == (80, 40) and h.dtype == np.float32
    row = lambda x: int((46.0 - x) / 0.5)  # noqa: E731  the row whose centre is x + 0.25 ... x - 0.25
    d = np.hypot(46.0 - (row(15.2) + 0.5) * 0.5, 0.25)  # the centre of column 19 (y = 0.25 m)
    assert h[row(15.2), 19] == pytest.approx(-1.0 + 2.0 * (d - 10.0) / 10.0, abs=1e-5)
    assert h[row(8.0), 19] == pytest.approx(-1.0) and h[row(30.0), 19] == pytest.approx(1.0)  # beyond: clamped
    # two columns: each cell takes the nearest non-empty one
    pts = np.array(
        [[15.0, 15.0 * np.tan(np.radians(20)), 2.0, 0.5], [15.0, -15.0 * np.tan(np.radians(20)), -2.0, 0.5]], np.float32
    )
    h = lidar.bev_height(pts)
    assert (h[:, :19] == 2.0).all() and (h[:, 21:] == -2.0).all()  # left (y > 0) and right
    with pytest.raises(DataError, match="azimuth_res must be > 0"):
        lidar.bev_height(pts, azimuth_res=0)


def test_bev_points_pads_with_nan_and_thins_evenly():
    pts = np.array([[10.0, 0, -1, 0.1], [50.0, 0, -1, 0.1], [20.0, 3, -1, 0.1]], np.float32)
    out = lidar.bev_points(pts, max_points=4)
    assert out.shape == (4, 3) and np.isnan(out[2:]).all()
    np.testing.assert_array_equal(out[:2], pts[[0, 2], :3])  # the point at 50 m is outside the grid
    many = np.column_stack([np.linspace(7, 45, 100), np.zeros(100), -np.ones(100), np.zeros(100)]).astype(np.float32)
    thin = lidar.bev_points(many, max_points=10)
    assert np.isfinite(thin).all() and thin[0, 0] == pytest.approx(7) and thin[-1, 0] == pytest.approx(45)


def test_calibration_round_trips_through_its_array():
    road = np.hstack([np.eye(3), [[0.0], [-1.65], [0.0]]])
    cal = Calibration(CALIB.P2, CALIB.R0_rect, CALIB.Tr_velo_to_cam, road)
    back = calibration(torch.from_numpy(calib_array(cal)))
    for key in ("P2", "R0_rect", "Tr_velo_to_cam", "Tr_cam_to_road"):
        np.testing.assert_array_equal(getattr(back, key), getattr(cal, key))
    assert calibration(calib_array(CALIB)).Tr_cam_to_road is None


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    return str(tmp_path_factory.mktemp("data"))


def test_the_data_module_gives_road_targets_and_geometry(data_dir):
    dm = KittiDataModule(
        synth=SMALL,
        data_dir=data_dir,
        modalities=["rgb", "bev"],
        batch_size=2,
        targets=["free_space", "road_valid", "road_bev", "road_bev_valid", *GEOMETRY],
        bev={"x_range": [6.0, 46.0], "y_range": [-10.0, 10.0], "cell": 0.5, "max_points": 4096},
    )
    b = next(iter(dm.train_dataloader()))
    h, w = SMALL["height"], SMALL["width"]
    assert b["road_valid"].shape == (2, 1, h, w) and b["road_valid"].all()  # the generated ground truth has no void
    assert b["road_bev_valid"].shape == b["road_bev"].shape == (2, 1, 80, 40)
    assert (b["road_bev"] <= b["road_bev_valid"]).all() and 0 < b["road_bev_valid"].mean() < 1  # road only in view
    assert b["calib"].shape == (2, 4, 3, 4) and b["calib"].dtype == torch.float64
    assert b["height_image"].shape == (2, 1, h, w) and b["height_bev"].shape == (2, 1, 80, 40)
    assert b["lidar_points"].shape == (2, 4096, 3)
    # the generated rig's ground is 1.73 m below the velodyne: the dense heights of the road are near it
    road = b["free_space"][:, 0] > 0
    assert abs(float(b["height_image"][:, 0][road].median()) + 1.73) < 0.1
    assert abs(float(b["height_bev"][b["road_bev"] > 0].median()) + 1.73) < 0.1


def test_a_crop_moves_the_principal_point_with_the_image(data_dir):
    kw = dict(synth=SMALL, data_dir=data_dir, modalities=["rgb"], targets=["calib", "height_image"], batch_size=1)
    full = next(iter(KittiDataModule(**kw).test_dataloader()))
    crop = next(iter(KittiDataModule(**kw, image_size=[60, 200]).test_dataloader()))
    top, left = 4, 4
    assert torch.equal(crop["height_image"], full["height_image"][..., top:, left : left + 200])
    xyz = np.array([[12.0, 1.5, -1.7], [30.0, -4.0, 0.5]])
    uv_full, _ = calibration(full["calib"][0]).velo_to_image(xyz)
    uv_crop, _ = calibration(crop["calib"][0]).velo_to_image(xyz)
    np.testing.assert_allclose(uv_crop, uv_full - [left, top], atol=1e-9)


def test_geometry_needs_a_velodyne_folder(kitti_root, tmp_path):
    dm = KittiDataModule(
        root=str(kitti_root / "road"), data_dir=str(tmp_path), modalities=["rgb"], targets=["free_space", "height_bev"]
    )
    with pytest.raises(DataError, match="cannot provide 'height_bev': this data has no velodyne"):
        dm.setup()
