"""Space transforms (DST, SHPL) on the real KITTI road frame um_000000 with its calibration.

The road sample has no velodyne scan (../shared/kitti/SOURCES.md: no repository ships one), so the scan is that of
object frame 000001, taken by the same rig: its calib's P2, R0_rect and Tr_velo_to_cam equal um_000000's, which the
fixture checks, so the scan and um_000000's calibration belong together geometrically.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from ablate.data import DataError, lidar
from ablate.data.kitti import Calibration, read_velodyne
from ablate.fusion.geometry import BevGrid, Geometry, backproject, project
from ablate.fusion.space import SPACES, IndexMap, PointPooling, build_space

STRIDES = (4, 8, 16, 32)


@pytest.fixture(scope="module")
def frame(kitti_root):
    calib = Calibration.from_file(kitti_root / "road" / "training" / "calib" / "um_000000.txt")
    same_rig = Calibration.from_file(kitti_root / "object" / "training" / "calib" / "000001.txt")
    for key in ("P2", "R0_rect", "Tr_velo_to_cam"):
        np.testing.assert_array_equal(getattr(calib, key), getattr(same_rig, key))
    points = read_velodyne(kitti_root / "object" / "training" / "velodyne" / "000001.bin")
    shape = (375, 1242)  # um_000000.png
    return calib, points, shape, Geometry.from_frame(points, calib, shape)


def feature_size(size: tuple[int, int], stride: int) -> tuple[int, int]:
    return -(-size[0] // stride), -(-size[1] // stride)  # ResNet's conv1 and max-pool round up


def ground_returns(calib, points, shape):
    """Pixels (u, v) holding a LiDAR return on the ground ahead (velodyne z < -1.4 m, 8-40 m), and the points."""
    lin, idx = lidar.project_points(points, calib, shape)
    v, u = np.divmod(lin, shape[1])
    p = points[idx]
    ground = (p[:, 2] < -1.4) & (p[:, 0] > 8) & (p[:, 0] < 40) & (np.abs(p[:, 1]) < 9)
    return u[ground], v[ground], p[ground]


def test_back_projection_inverts_projection_at_the_same_height(frame):
    calib, points, shape, g = frame
    u, v, p = ground_returns(calib, points, shape)
    uv = torch.tensor(np.stack([u, v], 1), dtype=torch.float64)[None]
    xyz, ok = backproject(g, uv, torch.tensor(p[:, 2], dtype=torch.float64)[None])  # eq. 5-7 at the point's height
    assert ok.all()
    assert np.abs(project(g, xyz)[0] - uv).max() < 1e-6
    # the pixel of a return, scaled to the return's height, is the return itself (up to the pixel's width)
    assert np.median(np.linalg.norm(xyz[0].numpy() - p[:, :3], axis=1)) < 0.05


def test_dst_round_trip_pixel_bev_pixel_lands_within_a_pixel_where_the_height_is_known(frame):
    # pixel -> 3D at its dense perspective height (eq. 2, 5-7) -> BEV cell -> cell's dense BEV height (eq. 3-4)
    # -> pixel (eq. 8), on the ground returns, where both dense heights rest on measured points
    calib, points, shape, g = frame
    u, v, _ = ground_returns(calib, points, shape)
    assert len(u) > 3000
    uv = torch.tensor(np.stack([u, v], 1), dtype=torch.float64)[None]
    height = g.height_image[0, 0].double()[torch.from_numpy(v), torch.from_numpy(u)][None]
    xyz, ok = backproject(g, uv, height)
    row = ((g.grid.x_range[1] - xyz[..., 0]) / g.grid.cell).floor().long()
    col = ((g.grid.y_range[1] - xyz[..., 1]) / g.grid.cell).floor().long()
    assert ok.all() and (row >= 0).all() and (row < 80).all() and (col >= 0).all() and (col < 40).all()
    back, depth = project(g, torch.stack([xyz[..., 0], xyz[..., 1], g.height_bev[0, 0].double()[row, col]], -1))
    error = (back - uv).norm(dim=-1)[0]
    assert (depth > 0).all()
    assert error.median() < 0.5 and (error < 1).float().mean() > 0.7


def test_dense_index_maps_at_every_scale(frame):
    _, _, shape, g = frame
    dst = build_space("dst")
    for stride in STRIDES:
        cam, bev = feature_size(shape, stride), feature_size((80, 40), stride)
        to_bev, to_cam = dst.maps(g, cam, bev, stride)
        assert isinstance(to_bev, IndexMap) and isinstance(to_cam, IndexMap)
        assert to_bev.index.shape == (1, bev[0] * bev[1]) and to_cam.index.shape == (1, cam[0] * cam[1])
        assert to_bev.coverage.shape == (1, *bev) and to_cam.coverage.shape == (1, *cam)
        assert int(to_bev.index.max()) < cam[0] * cam[1] and int(to_cam.index.max()) < bev[0] * bev[1]
        x = torch.randn(1, 5, *cam)
        assert to_bev(x).shape == (1, 5, *bev) and to_cam(torch.randn(1, 5, *bev)).shape == (1, 5, *cam)
        if stride <= 16:  # dense: nearly every BEV cell (in the camera's view) and the image below the far edge
            assert to_bev.coverage.float().mean() > 0.9 and to_cam.coverage.float().mean() > 0.6
    # at full resolution every pixel of the road ahead reads a cell, and every cell in view a pixel
    to_bev, to_cam = dst.maps(g, shape, (80, 40), 1)
    assert to_cam.coverage[0, -100:, 400:850].all() and to_bev.coverage[0, :-2, 12:28].all()


def test_dst_maps_agree_both_ways(frame):
    # a BEV cell -> its pixel -> that pixel's cell is the cell or a neighbour for most cells (occluded cells are not:
    # their pixel shows what stands in front of them)
    _, _, shape, g = frame
    stride = 4
    bev = feature_size((80, 40), stride)
    to_bev, to_cam = build_space("dst").maps(g, feature_size(shape, stride), bev, stride)
    cells = torch.nonzero(to_bev.index[0] >= 0)[:, 0]
    back = to_cam.index[0, to_bev.index[0, cells]]
    near = (back >= 0) & ((back // bev[1] - cells // bev[1]).abs() <= 1) & ((back % bev[1] - cells % bev[1]).abs() <= 1)
    assert near.float().mean() > 0.75


def test_shpl_covers_only_where_points_are(frame):
    calib, points, shape, g = frame
    shpl, dst = build_space("shpl"), build_space("dst")
    # the cells and pixels of the frame's points (those inside the grid) that project into the image
    pts = g.points[0].double().numpy()  # float64, as the transform computes
    pts = pts[np.isfinite(pts).all(1)]
    assert len(pts) > 10000
    lin, keep = lidar.bev_cells(pts)
    uv, depth = calib.velo_to_image(pts[keep, :3])
    u, v = np.floor(uv[:, 0] + 0.5), np.floor(uv[:, 1] + 0.5)
    seen = (depth > 0) & (u >= 0) & (u < shape[1]) & (v >= 0) & (v < shape[0])
    for stride in STRIDES:
        cam, bev = feature_size(shape, stride), feature_size((80, 40), stride)
        to_bev, to_cam = shpl.maps(g, cam, bev, stride)
        assert isinstance(to_bev, PointPooling)
        want_bev = np.zeros(bev, bool)
        r, c = np.divmod(lin[seen], 40)
        want_bev[r // stride, c // stride] = True
        want_cam = np.zeros(cam, bool)
        want_cam[(v[seen] // stride).astype(int), (u[seen] // stride).astype(int)] = True
        np.testing.assert_array_equal(to_bev.coverage[0].numpy(), want_bev)
        np.testing.assert_array_equal(to_cam.coverage[0].numpy(), want_cam)
        out = to_bev(torch.ones(1, 3, *cam))  # a mean of ones where points are, 0 elsewhere
        assert torch.equal(out[0, 0] > 0, to_bev.coverage[0])
        assert torch.allclose(out[0][:, to_bev.coverage[0]], torch.ones(1))
        # sparse: at the finest scale SHPL reaches fewer camera positions than DST
        if stride == 4:
            assert to_cam.coverage.float().mean() < 0.5 * dst.maps(g, cam, bev, stride)[1].coverage.float().mean()


def test_shpl_pools_the_mean_of_its_points():
    # two points in one BEV cell seeing pixels with features 2 and 4 give the cell 3
    calib = Calibration(
        P2=np.array([[100.0, 0, 50, 0], [0, 100, 50, 0], [0, 0, 1, 0]]),
        R0_rect=np.eye(3),
        Tr_velo_to_cam=np.array([[0.0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0]]),
    )
    from ablate.data.dataset import calib_array

    pts = torch.tensor([[[10.1, 0.1, -1.0], [10.3, 0.3, -1.0], [float("nan")] * 3]])
    g = Geometry(torch.from_numpy(calib_array(calib))[None], BevGrid(), (100, 100), points=pts)
    to_bev, to_cam = build_space("shpl").maps(g, (100, 100), (80, 40), 1)
    uv, _ = project(g, pts[:, :2].double())
    x = torch.zeros(1, 1, 100, 100)
    for value, (u, v) in zip((2.0, 4.0), torch.floor(uv[0] + 0.5).long().tolist()):
        x[0, 0, v, u] = value
    out = to_bev(x)[0, 0]
    assert out.sum() == pytest.approx(3.0) and out[71, 19] == pytest.approx(3.0)  # both in cell (71, 19)
    assert to_cam.coverage.sum() == 2


def test_bad_input_is_one_clear_error(frame, tmp_path):
    _, _, _, g = frame
    with pytest.raises(ValueError, match="unknown space transform 'dense'; valid: dst, shpl"):
        build_space("dense")
    assert sorted(SPACES) == ["dst", "shpl"]
    sparse = Geometry(g.calib, g.grid, g.image_size, points=g.points)
    with pytest.raises(KeyError, match=r"'dst' needs batch keys \['height_image', 'height_bev'\]"):
        build_space("dst").maps(sparse, (10, 10), (20, 10), 4)
    with pytest.raises(KeyError, match="batch\\['calib'\\]"):
        Geometry.from_batch({"height_image": g.height_image}, BevGrid(), (375, 1242))
    with pytest.raises(ValueError, match="BEV grid: unknown key"):
        BevGrid.from_config({"cell": 0.5, "range": 3})
    bad = tmp_path / "um_000000.txt"
    bad.write_text("P2: " + " ".join(["1"] * 12) + "\nR0_rect: " + " ".join(["1"] * 9) + "\n")
    with pytest.raises(DataError, match=r"um_000000.txt: calibration key Tr_velo_to_cam is missing"):
        Calibration.from_file(bad)
