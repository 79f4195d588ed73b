"""The bidirectional fusion module (two groups DST -> DT -> operator) with every operator of the registry, and CBF's
context gains in front of an operator ("+CBF")."""

from __future__ import annotations

import functools

import numpy as np
import pytest
import torch

from ablate.data.dataset import calib_array
from ablate.data.generate import calibration
from ablate.fusion import OPERATORS, BidirectionalFusion, WithContext, build, build_space
from ablate.fusion.geometry import BevGrid, Geometry
from ablate.fusion.ops_bifnet import CBF

H, W = 64, 208  # the smoke scale's image


@pytest.fixture(scope="module")
def geometry():
    """The generated rig's calibration and a flat road 1.73 m below the velodyne, both heights dense."""
    cal = torch.from_numpy(calib_array(calibration(H, W)))[None].repeat(2, 1, 1, 1)
    return Geometry(
        cal,
        BevGrid(),
        (H, W),
        height_image=torch.full((2, 1, H, W), -1.73),
        height_bev=torch.full((2, 1, 80, 40), -1.73),
    )


@pytest.mark.parametrize("name", sorted(OPERATORS))
def test_every_operator_fuses_across_the_spaces(name, geometry):
    torch.manual_seed(0)
    module = BidirectionalFusion(8, 6, build_space("dst"), 8, functools.partial(build, name=name))
    f_cam, f_bev = torch.randn(2, 8, 8, 26), torch.randn(2, 6, 10, 5)
    cam, bev = module(f_cam, f_bev, geometry)
    assert cam.shape == f_cam.shape and bev.shape == f_bev.shape
    (cam.sum() + bev.sum()).backward()
    assert module.dt_bev.weight.grad is not None and module.dt_cam.weight.grad is not None
    assert 0.5 < module.last_coverage["bev"] <= 1 and 0.2 < module.last_coverage["cam"] < 1


def test_the_groups_carry_features_where_the_geometry_says(geometry):
    # with sum and identity DTs, a BEV feature that is 1 in one cell shows up in camera space exactly at the
    # camera positions whose ground point lies in that cell, and a camera feature in the cells that see it
    module = BidirectionalFusion(1, 1, build_space("dst"), 4, functools.partial(build, name="sum"))
    with torch.no_grad():
        for dt in (module.dt_bev, module.dt_cam):
            dt.weight.fill_(1.0)
            dt.bias.zero_()
    to_bev, to_cam = module.space.maps(geometry, (16, 52), (20, 10), 4)
    read = to_cam.index[0][to_cam.index[0] >= 0]
    cell = int(read.mode().values)  # the BEV position most camera positions read
    f_bev = torch.zeros(2, 1, 20, 10)
    f_bev[:, 0, cell // 10, cell % 10] = 1.0
    cam, _ = module(torch.zeros(2, 1, 16, 52), f_bev, geometry)
    assert torch.equal(cam[0, 0] > 0, (to_cam.index[0] == cell).view(16, 52))
    assert (cam[0, 0] > 0).sum() >= 2 and cam.max() == 1.0
    f_cam = torch.zeros(2, 1, 16, 52)
    f_cam[:, 0, 12, 26] = 1.0
    _, bev = module(f_cam, torch.zeros(2, 1, 20, 10), geometry)
    assert torch.equal(bev[0, 0] > 0, (to_bev.index[0] == 12 * 52 + 26).view(20, 10))


def test_context_gains_on_sum_are_cbf():
    torch.manual_seed(1)
    cbf = CBF(channels=16, num_inputs=2, reduction=4)
    wrapped = WithContext(build("sum", channels=16), channels=16, num_inputs=2, reduction=4)
    wrapped.mlp.load_state_dict(cbf.mlps[0].state_dict())
    x = [torch.randn(3, 16, 5, 7), torch.randn(3, 16, 5, 7)]
    assert torch.allclose(wrapped(x), cbf(x), atol=1e-6)
    assert len(wrapped.last_gates) == 2 and wrapped.last_gates[0].shape == (3, 16, 1, 1)


def test_context_gains_keep_the_operators_own_weights():
    # LidCamNet + CBF: f_cam * q_cam + alpha * (f_lidar * q_lidar), with LidCamNet's alpha still learned
    torch.manual_seed(2)
    op = build("lidcamnet", channels=4, init=0.5)
    wrapped = WithContext(op, channels=4)
    x = [torch.randn(2, 4, 3, 3), torch.randn(2, 4, 3, 3)]
    out = wrapped(x)
    q = wrapped.last_gates
    assert torch.allclose(out, q[0] * x[0] + 0.5 * q[1] * x[1], atol=1e-6)
    out.sum().backward()
    assert op.alpha.grad is not None and np.isfinite(op.alpha.grad.numpy()).all()
