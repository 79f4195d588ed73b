"""BiFNet's road task: focal loss and eq. 13 against hand-computed values, the warps into the devkit's metric BEV
against RoadMaxF's own, the network in its three modes with two-stage training, and one evaluation."""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
import torch

from ablate.data.dataset import calib_array, calibration
from ablate.data.generate import calibration as rig
from ablate.fusion import build
from ablate.metrics.road import RoadMaxF
from ablate.tasks.road_bev import MetricBev, RoadLoss, RoadNet, RoadTask, focal_loss

H, W = 64, 208
BACKBONE = {"depth": 18, "width": 0.125}


def batch(b: int = 2, modalities=("rgb", "bev")) -> dict:
    torch.manual_seed(0)
    road = torch.zeros(b, 1, H, W)
    road[:, :, 40:, 60:150] = 1.0
    out = {
        "free_space": road,
        "road_valid": torch.ones(b, 1, H, W),
        "road_bev": torch.zeros(b, 1, 80, 40),
        "road_bev_valid": torch.ones(b, 1, 80, 40),
        "frame": [f"{i:06d}" for i in range(b)],
        "calib": torch.from_numpy(calib_array(rig(H, W)))[None].repeat(b, 1, 1, 1),
        "height_image": torch.full((b, 1, H, W), -1.73),
        "height_bev": torch.full((b, 1, 80, 40), -1.73),
        "lidar_points": torch.tensor([[10.0, 0.0, -1.73], [20.0, 2.0, -1.73]]).repeat(b, 1, 1),
    }
    out["road_bev"][:, :, 30:78, 14:26] = 1.0
    channels = {"rgb": 3, "bev": 6, "dhi": 3}
    for m in modalities:
        out[m] = torch.rand(b, channels[m], *((80, 40) if m == "bev" else (H, W)))
    return out


def net(stage="backbone", modalities=("rgb", "bev"), op="cbf", **kw) -> RoadNet:
    channels = {"rgb": 3, "bev": 6, "dhi": 3}
    return RoadNet(
        stage,
        {m: channels[m] for m in modalities},
        functools.partial(build, name=op) if op else None,
        backbone=BACKBONE,
        fpn_channels=8,
        **kw,
    )


def test_focal_loss_hand_computed():
    logits = torch.zeros(1, 1, 1, 2)  # p = 0.5: (1 - p_t)^2 = 1/4, -log p_t = log 2
    target = torch.tensor([[[[1.0, 0.0]]]])
    per_pixel = [0.25 * 0.25 * math.log(2), 0.75 * 0.25 * math.log(2)]
    assert focal_loss(logits, target).item() == pytest.approx(sum(per_pixel) / 2)
    assert focal_loss(logits, target, torch.tensor([[[[1.0, 0.0]]]])).item() == pytest.approx(per_pixel[0])
    assert focal_loss(logits, target, gamma=0, alpha=0.5).item() == pytest.approx(0.5 * math.log(2))
    # a confident right answer costs far less than under cross-entropy
    easy = focal_loss(torch.tensor([[[[4.0]]]]), torch.ones(1, 1, 1, 1), gamma=2, alpha=0.5)
    assert easy.item() < 1e-3 * (0.5 * math.log(1 + math.exp(-4)))


def test_multi_task_loss_is_camera_plus_lambda_bev():
    b = batch()
    out = {"road_cam": torch.randn(2, 1, 16, 52), "road_bev": torch.randn(2, 1, 20, 10)}
    one, three = RoadLoss(lam=1.0)(out, b), RoadLoss(lam=3.0)(out, b)
    assert three["loss"].item() == pytest.approx(one["loss_cam"].item() + 3 * one["loss_bev"].item(), rel=1e-6)
    only_bev = RoadLoss()({"road_bev": out["road_bev"]}, b)
    assert only_bev["loss_cam"].item() == 0 and only_bev["loss"].item() == pytest.approx(one["loss_bev"].item())
    with pytest.raises(KeyError, match="road_bev needs batch\\['road_bev'\\]"):
        RoadLoss()(out, {k: v for k, v in b.items() if k != "road_bev"})
    with pytest.raises(ValueError, match="task.loss: need 0 <= alpha <= 1"):
        RoadLoss(alpha=2)


def test_camera_warp_scores_as_roadmaxf_with_the_calibration():
    b = batch()
    prob = torch.rand(2, H, W)
    warp = MetricBev()
    target, inside = warp.camera(b["free_space"], b["calib"])
    mine = RoadMaxF()
    mine.update(warp.camera(prob, b["calib"])[0], target > 0.5, inside)
    theirs = RoadMaxF()
    theirs.update(prob, b["free_space"][:, 0] > 0.5, calib=[calibration(c) for c in b["calib"]])
    for name in ("tp", "fp", "fn"):
        assert torch.equal(getattr(mine, name), getattr(theirs, name)), name
    assert theirs.tp[0] > 0


def test_lidar_raster_lands_where_the_road_frame_says():
    # the generated rig: road x = -velodyne y (lateral), road z = velodyne x - 0.27 (forward)
    b = batch()
    raster = torch.zeros(2, 80, 40)
    raster[:, :, :20] = 1.0  # velodyne y > 0: the left half
    out = MetricBev().lidar(raster, b["calib"])
    x = -10 + (np.arange(400) + 0.5) * 0.05
    z = 46 - (np.arange(800) + 0.5) * 0.05
    left, right = x < -0.05, x > 0.05
    rows = z < 45.5  # beyond 46 - 0.27 m the cell centre leaves the raster: 0
    assert (out[0][np.ix_(rows, left)] == 1).all() and (out[0][np.ix_(rows, right)] == 0).all()
    assert (out[0][z > 45.8] == 0).all()


@pytest.mark.parametrize(
    "stage,modalities,keys",
    [
        ("single", ("rgb",), {"road_cam"}),
        ("single", ("bev",), {"road_bev"}),
        ("backbone", ("rgb", "bev"), {"road_cam", "road_bev"}),
        ("backbone", ("rgb", "dhi"), {"road_cam"}),
    ],
)
def test_the_network_in_each_mode(stage, modalities, keys):
    model = net(stage, modalities, op="cbf" if stage == "backbone" else None, single=modalities[0])
    out = model(batch(modalities=modalities))
    assert set(out) == keys
    if "road_cam" in out:
        assert out["road_cam"].shape == (2, 1, 16, 52)
    if "road_bev" in out:
        assert out["road_bev"].shape == (2, 1, 20, 10)
    assert len(model.fusion_modules()) == {"single": 0, "backbone": 8 if "bev" in modalities else 4}[stage]


@pytest.mark.parametrize("space", ["dst", "shpl"])
def test_experts_load_frozen_and_their_features_can_be_cached(space):
    b = batch()
    experts = {m: net("single", ("rgb", "bev"), op=None, single=m) for m in ("rgb", "bev")}
    model = net(space=space, context=False)
    assert not model.cacheable
    for m, expert in experts.items():
        model.load_expert(m, expert, freeze=True)
        assert torch.equal(model.branches[m].encoder.conv1.weight, expert.branches[m].encoder.conv1.weight)
        assert torch.equal(model.branches[m].head[2].weight, expert.branches[m].head[2].weight)
    assert model.cacheable and not any(p.requires_grad for p in model.branches["rgb"].encoder.parameters())
    model.train()
    assert not model.branches["bev"].encoder.training and model.branches["bev"].decoder.training
    model.eval()
    with torch.no_grad():
        direct = model(b)
        cached = model(b, features=model.frozen_features({m: b[m] for m in ("rgb", "bev")}))
    for key in direct:
        assert torch.allclose(direct[key], cached[key])
    with pytest.raises(ValueError, match="stage 'single' road model of that modality"):
        model.load_expert("rgb", experts["bev"])


def test_bad_options_are_one_clear_error():
    with pytest.raises(ValueError, match="unknown stage 'fpn'; valid: single, backbone"):
        net("fpn")
    with pytest.raises(ValueError, match="needs a fusion operator"):
        net(op=None)
    with pytest.raises(ValueError, match="fuses a camera-space modality with `bev`"):
        RoadNet("backbone", {"bev": 6}, functools.partial(build, name="sum"))
    with pytest.raises(ValueError, match="unknown space transform 'sparse'"):
        net(space="sparse")
    with pytest.raises(ValueError, match="levels must be indices 0..3"):
        net(levels=(4,))
    with pytest.raises(KeyError, match="calib"):
        net()({k: v for k, v in batch().items() if k != "calib"})
    with pytest.raises(ValueError, match=r"task.loss: unknown option\(s\) \['beta'\]; valid: alpha, gamma, lam"):
        RoadTask(net("single", ("rgb",), op=None, single="rgb"), optimizer=torch.optim.Adam, loss={"beta": 1})


def test_an_evaluation_logs_both_branches_and_the_camera_branch_as_the_prediction():
    model = net()
    task = RoadTask(model, optimizer=functools.partial(torch.optim.Adam, lr=1e-3))
    logged = {}
    task.log = lambda name, value, *a, **k: logged.__setitem__(name, float(value))
    model.eval()
    with torch.no_grad():
        task._eval_step(batch(), "val")
        task._eval_end("val")
    for branch in ("cam", "bev"):
        for k in ("max_f", "ap", "pre", "rec"):
            assert 0 <= logged[f"val/{branch}_{k}"] <= 100, (branch, k)
    assert logged["val/max_f"] == logged["val/cam_max_f"] and "val/loss" in logged
    assert task.val_road["cam"].update_count == 0  # reset for the next epoch
    fig = task.figure(batch())
    assert fig is not None and len(fig.axes) == 2 * 5
    assert task.gate_figure(batch()) is not None  # CBF keeps its gains
