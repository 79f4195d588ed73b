"""Training augmentation (ablate.data.augment): the mirrored world projects onto the flipped image through the
flipped calibration, a zoom is a change of intrinsics that every camera-space tensor follows, the BEV follows the
mirror, and validation / test frames are never touched."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from ablate.data.augment import Augment, Photometric, View, flip_calibration, mirror_points, warp
from ablate.data.datamodule import KittiDataModule
from ablate.data.dataset import calibration
from ablate.data.kitti import Calibration

SMALL = {"frames": 5, "seed": 3, "height": 64, "width": 208}
TARGETS = ["free_space", "road_valid", "road_bev", "road_bev_valid", "calib", "height_image", "boxes2d"]


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    return str(tmp_path_factory.mktemp("data"))


def first(data_dir: str, augment: dict | None, split: str = "train", modalities=("rgb", "dense_depth", "bev")):
    dm = KittiDataModule(
        synth=SMALL, data_dir=data_dir, modalities=list(modalities), targets=TARGETS, batch_size=1, augment=augment
    )
    dm.setup()
    return dm.datasets[split][0]


def test_the_mirrored_scan_lands_on_the_flipped_pixels_of_a_real_calibration(kitti_root):
    calib = Calibration.from_file(kitti_root / "object" / "training" / "calib" / "000000.txt")
    width = 1242
    rng = np.random.default_rng(0)
    pts = np.column_stack(
        [rng.uniform(5, 60, 200), rng.uniform(-15, 15, 200), rng.uniform(-2, 1, 200), rng.uniform(0, 1, 200)]
    ).astype(np.float32)
    mirrored, flipped = mirror_points(pts, calib), flip_calibration(calib, width)
    uv, depth = calib.velo_to_image(pts)
    uv_m, depth_m = flipped.velo_to_image(mirrored)
    # to float32's precision: the scan, like a KITTI .bin, stays float32
    np.testing.assert_allclose(uv_m[:, 0], width - 1 - uv[:, 0], atol=1e-3)
    np.testing.assert_allclose(uv_m[:, 1], uv[:, 1], atol=1e-3)
    np.testing.assert_allclose(depth_m, depth, atol=1e-5)  # the mirror keeps each point's depth
    np.testing.assert_array_equal(mirrored[:, 3], pts[:, 3])  # and its reflectance
    # a mirror: X of the rectified camera frame changes sign, Y and Z do not
    rect, rect_m = calib.velo_to_rect(pts), calib.velo_to_rect(mirrored)
    np.testing.assert_allclose(rect_m, rect * [-1, 1, 1], atol=1e-5)


def test_the_road_frame_of_the_mirrored_world_gives_each_mirrored_point_its_height():
    road = np.hstack([np.eye(3), [[0.3], [-1.65], [0.1]]])
    road[:, :3] = np.array([[np.cos(0.1), 0, np.sin(0.1)], [0, 1, 0], [-np.sin(0.1), 0, np.cos(0.1)]])
    calib = Calibration(
        P2=np.array([[100.0, 0, 40, 5], [0, 100, 30, 0], [0, 0, 1, 0.01]]),
        R0_rect=np.eye(3),
        Tr_velo_to_cam=np.array([[0.0, -1, 0, 0.1], [0, 0, -1, -0.07], [1, 0, 0, -0.27]]),
        Tr_cam_to_road=road,
    )
    flipped = flip_calibration(calib, 80)
    rect = np.array([[2.0, 1.5, 10.0], [-3.0, 0.2, 25.0]])
    np.testing.assert_allclose(
        (flipped.Tr_cam_to_road @ np.c_[rect * [-1, 1, 1], np.ones(2)].T)[1], (road @ np.c_[rect, np.ones(2)].T)[1]
    )
    np.testing.assert_allclose(flipped.rect_to_image(rect * [-1, 1, 1])[:, 0], 79 - calib.rect_to_image(rect)[:, 0])


def test_a_zoom_maps_the_frame_inside_the_zoomed_image():
    aug = Augment(flip=0.0, scale=(1.1, 1.5))
    gen = torch.Generator().manual_seed(0)
    for _ in range(50):
        view = aug.draw((64, 208), gen)
        assert not view.flip and 1.1 <= view.affine[0, 0] <= 1.5
        back = np.linalg.inv(view.affine) @ np.array([[0, 207, 0, 207], [0, 0, 63, 63], [1, 1, 1, 1]])
        assert (back[0] >= -1e-9).all() and (back[0] <= 207 + 1e-9).all()  # every output pixel sees the image
        assert (back[1] >= -1e-9).all() and (back[1] <= 63 + 1e-9).all()
    assert Augment(flip=1.0, scale=(1.0, 1.0)).draw((64, 208), gen) == View(True, None)


@pytest.mark.parametrize(
    "options, match",
    [
        ({"flip": 0.5, "rotate": 10}, "data.augment.rotate"),
        ({"scale": [0.8, 1.0]}, "data.augment.scale"),
        ({"flip": 2}, "data.augment.flip"),
        ({"photometric": 1.5}, "data.augment.photometric"),
    ],
)
def test_bad_augment_options_are_one_clear_error(options, match):
    with pytest.raises((KeyError, ValueError), match=match):
        Augment.from_config(options)


def test_without_photometric_distortion_the_draws_keep_their_stream():
    """A config that predates the option draws the same views and leaves the generator where it did."""
    a, b = torch.Generator().manual_seed(1), torch.Generator().manual_seed(1)
    for _ in range(5):
        va, vb = (
            Augment(scale=(1.0, 1.3)).draw((64, 208), a),
            Augment(scale=(1.0, 1.3), photometric=0.0).draw((64, 208), b),
        )
        assert va.flip == vb.flip and np.array_equal(va.affine, vb.affine) and vb.photometric is None
    assert torch.equal(a.get_state(), b.get_state())


def test_each_photometric_step_is_the_one_ssd_describes():
    rgb = np.random.default_rng(0).uniform(0.2, 0.6, (8, 12, 3)).astype(np.float32)
    np.testing.assert_array_equal(Photometric().apply(rgb), rgb)  # every step neutral: the image unchanged
    np.testing.assert_allclose(Photometric(brightness=0.1).apply(rgb), rgb + 0.1, atol=1e-6)
    np.testing.assert_allclose(Photometric(contrast=1.4).apply(rgb), np.clip(rgb * 1.4, 0, 1), atol=1e-6)
    grey = Photometric(saturation=0.0).apply(rgb)  # no saturation: every channel the pixel's maximum (HSV's value)
    np.testing.assert_allclose(grey, np.repeat(rgb.max(-1, keepdims=True), 3, -1), atol=1e-5)
    red = np.zeros((1, 1, 3), np.float32) + [0.8, 0.1, 0.1]
    shifted = Photometric(hue=18.0).apply(red.astype(np.float32))[0, 0]
    assert shifted[0] == pytest.approx(0.8, abs=1e-5) and shifted[1] > 0.25 > shifted[2]  # towards orange
    draws = [Photometric.draw(0.5, torch.Generator().manual_seed(s)) for s in range(200)]
    assert all(abs(d.brightness) <= 32 / 255 and 0.5 <= d.contrast <= 1.5 and abs(d.hue) <= 18 for d in draws)
    assert 60 < sum(d.saturation != 1.0 for d in draws) < 140  # each step drawn with its probability
    assert all(d == Photometric(contrast_first=d.contrast_first) for d in [Photometric.draw(0.0)])


def test_photometric_distortion_changes_the_camera_and_no_lidar_raster(data_dir):
    plain = first(data_dir, None, modalities=("rgb", "ddm_jet"))
    torch.manual_seed(3)
    bright = first(data_dir, {"flip": 0.0, "scale": [1.0, 1.0], "photometric": 1.0}, modalities=("rgb", "ddm_jet"))
    assert torch.equal(bright["ddm_jet"], plain["ddm_jet"])
    assert (bright["rgb"] - plain["rgb"]).abs().mean() > 0.01
    assert bright["rgb"].min() >= 0 and bright["rgb"].max() <= 1


def test_a_flipped_frame_is_the_mirrored_scene_in_every_modality(data_dir):
    plain, flip = first(data_dir, None), first(data_dir, {"flip": 1.0, "scale": [1.0, 1.0]})
    for key in ("rgb", "free_space", "road_valid"):
        assert torch.equal(flip[key], plain[key].flip(-1)), key
    # LiDAR rasters are recomputed from the mirrored scan: the camera-space ones match the flipped originals
    for key in ("dense_depth", "height_image"):
        agree = torch.isclose(flip[key], plain[key].flip(-1), atol=0.02).float().mean().item()
        assert agree > 0.97, (key, agree)
    # the BEV of the mirrored scene is, near enough, the original with its y axis reversed (y range -10..10 m)
    # (the BEV is 93 % empty cells: the unflipped original agrees on 95 % of them, the reversed one on all)
    assert (flip["road_bev"] == plain["road_bev"].flip(-1)).float().mean().item() > 0.99
    assert torch.isclose(flip["bev"], plain["bev"].flip(-1), atol=0.05).float().mean().item() > 0.99
    w = SMALL["width"]
    expected = plain["boxes2d"]["boxes"][:, [2, 1, 0, 3]] * torch.tensor([-1, 1, -1, 1]) + torch.tensor(
        [w - 1, 0, w - 1, 0]
    )
    torch.testing.assert_close(flip["boxes2d"]["boxes"], expected)
    assert torch.equal(flip["boxes2d"]["difficulty"], plain["boxes2d"]["difficulty"])
    uv = calibration(plain["calib"]).velo_to_image(np.array([[20.0, 3.0, -1.0]]))[0]
    uv_m = calibration(flip["calib"]).velo_to_image(
        mirror_points(np.array([[20.0, 3.0, -1.0, 0.5]]), calibration(plain["calib"]))
    )[0]
    np.testing.assert_allclose(uv_m, [[w - 1 - uv[0, 0], uv[0, 1]]], atol=1e-6)


def test_a_zoom_is_a_change_of_intrinsics_that_images_labels_and_boxes_follow(data_dir):
    plain = first(data_dir, None)
    a = np.array([[1.25, 0.0, -20.0], [0.0, 1.25, -6.0], [0.0, 0.0, 1.0]])
    zoomed = warp(plain, a, (SMALL["height"], SMALL["width"]))
    xyz = np.array([[15.0, 2.0, -1.5], [30.0, -3.0, 0.0]])
    uv = calibration(plain["calib"]).velo_to_image(xyz)[0]
    np.testing.assert_allclose(calibration(zoomed["calib"]).velo_to_image(xyz)[0], uv * 1.25 + [-20.0, -6.0])
    # a pixel of the output shows the input at A^-1 (u, v): exact for labels (nearest), close for the image
    for u, v in ((40, 30), (100, 50), (150, 10)):
        su, sv = (u + 20.0) / 1.25, (v + 6.0) / 1.25
        assert zoomed["free_space"][0, v, u] == plain["free_space"][0, round(sv), round(su)]
        i0, j0 = int(sv), int(su)
        patch = plain["rgb"][:, i0 : i0 + 2, j0 : j0 + 2]
        assert (patch.amin((1, 2)) - 1e-5 <= zoomed["rgb"][:, v, u]).all()
        assert (zoomed["rgb"][:, v, u] <= patch.amax((1, 2)) + 1e-5).all()
    for key in ("bev", "road_bev", "road_bev_valid"):  # the scan and the BEV do not move
        assert torch.equal(zoomed[key], plain[key]), key
    boxes = plain["boxes2d"]["boxes"].double() * 1.25 - torch.tensor([20.0, 6.0, 20.0, 6.0], dtype=torch.float64)
    boxes[:, 0::2], boxes[:, 1::2] = boxes[:, 0::2].clamp(0, 207), boxes[:, 1::2].clamp(0, 63)
    keep = (boxes[:, 2] - boxes[:, 0] >= 1) & (boxes[:, 3] - boxes[:, 1] >= 1)
    torch.testing.assert_close(zoomed["boxes2d"]["boxes"], boxes[keep].float())
    assert len(zoomed["boxes2d"]["labels"]) == len(zoomed["boxes2d"]["difficulty"]) == int(keep.sum())


def test_only_the_training_split_is_augmented_and_every_epoch_draws_anew(data_dir):
    aug = {"flip": 0.5, "scale": [1.0, 1.3]}
    for split in ("val", "test"):
        assert torch.equal(first(data_dir, aug, split)["rgb"], first(data_dir, None, split)["rgb"])
    dm = KittiDataModule(
        synth=SMALL, data_dir=data_dir, modalities=["rgb"], targets=["calib"], batch_size=1, augment=aug
    )
    dm.setup()
    torch.manual_seed(0)
    views = {tuple(dm.datasets["train"][0]["calib"][0].flatten().tolist()) for _ in range(6)}
    assert len(views) > 1  # the same frame, seen through different cameras


def test_the_feature_cache_is_off_when_frames_are_augmented():
    from omegaconf import OmegaConf

    from ablate.jobs.experts import feature_cache

    model = type("Frozen", (torch.nn.Module,), {"cacheable": True})()
    cfg = OmegaConf.create({"experts": {"cache_features": True}, "data": {}})
    assert feature_cache(cfg, model) is not None
    cfg.data.augment = {"flip": 0.5}
    assert feature_cache(cfg, model) is None


@pytest.mark.parametrize("space", ["dst", "shpl"])
def test_an_augmented_batch_trains_the_bidirectional_network(data_dir, space):
    import functools

    from ablate.fusion import build
    from ablate.tasks.road_bev import RoadLoss, RoadNet

    dm = KittiDataModule(
        synth=SMALL,
        data_dir=data_dir,
        modalities=["rgb", "bev"],
        batch_size=2,
        targets=[
            "free_space",
            "road_valid",
            "road_bev",
            "road_bev_valid",
            "calib",
            "height_image",
            "height_bev",
            "lidar_points",
        ],
        bev={"x_range": [6.0, 46.0], "y_range": [-10.0, 10.0], "cell": 0.5, "max_points": 2048},
        augment={"flip": 0.5, "scale": [1.0, 1.2]},
    )
    torch.manual_seed(1)
    b = next(iter(dm.train_dataloader()))
    model = RoadNet(
        "backbone",
        {"rgb": 3, "bev": 6},
        functools.partial(build, name="cbf"),
        space=space,
        backbone={"depth": 18, "width": 0.125},
        fpn_channels=8,
    )
    loss = RoadLoss()(model(b), b)["loss"]
    loss.backward()
    assert torch.isfinite(loss) and model.branches["rgb"].encoder.conv1.weight.grad.abs().sum() > 0


def test_a_zoom_of_a_frame_without_objects_keeps_its_empty_targets():
    empty = {
        "rgb": torch.rand(3, 8, 10),
        "ignore": torch.zeros(8, 10, dtype=torch.bool),
        "instances": {
            "masks": torch.zeros(0, 8, 10, dtype=torch.bool),
            "labels": torch.zeros(0, dtype=torch.int64),
            "boxes": torch.zeros(0, 4),
        },
        "boxes2d": {
            "boxes": torch.zeros(0, 4),
            "labels": torch.zeros(0, dtype=torch.int64),
            "difficulty": torch.zeros(0, dtype=torch.int64),
        },
    }
    out = warp(empty, np.array([[1.1, 0.0, -0.5], [0.0, 1.1, -0.3], [0.0, 0.0, 1.0]]), (8, 10))
    assert out["instances"]["masks"].shape == (0, 8, 10) and out["instances"]["boxes"].shape == (0, 4)
    assert out["boxes2d"]["difficulty"].shape == (0,) and out["rgb"].shape == (3, 8, 10)
