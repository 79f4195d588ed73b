"""The box module SSD and YOLACT share: anchor layouts, greedy NMS, box overlap, and YOLACT's layout through it."""

import math

import pytest
import torch

from ablate.tasks import boxes
from ablate.tasks.boxes import Anchors, box_inside, decode_boxes, encode, nms
from ablate.tasks.detection import SSD300_RATIOS, ssd_ratios, ssd_scales
from ablate.tasks.instance import Anchors as YolactAnchors
from ablate.tasks.yolact import anchors as yolact_anchors
from ablate.tasks.yolact import nms as yolact_nms

SSD300_MAPS = [(38, 38), (19, 19), (10, 10), (5, 5), (3, 3), (1, 1)]


def test_ssd_scales_follow_eq_4_with_conv4_3_at_0_1():
    assert ssd_scales(6) == pytest.approx((0.1, 0.2, 0.375, 0.55, 0.725, 0.9))
    assert ssd_scales(5, first=None) == pytest.approx((0.2, 0.375, 0.55, 0.725, 0.9))
    assert ssd_ratios((2, 3)) == pytest.approx((1.0, 2.0, 0.5, 3.0, 1 / 3))


def test_ssd300_layout_has_8732_default_boxes_in_normalised_units():
    anchors = Anchors(ssd_scales(6), [ssd_ratios(r) for r in SSD300_RATIOS], relative_to="image", extra=True)
    assert anchors.num_per_level == [4, 6, 6, 6, 4, 4]
    with pytest.raises(ValueError, match="vary by level"):
        _ = anchors.num_per_location
    a = anchors((300, 600), SSD300_MAPS)
    assert a.shape == (8732, 4)
    # conv4_3 cell (0, 0): centre at half a step; ratio 1 box s W x s H; ratio 2 box sqrt(2) wider, lower
    torch.testing.assert_close(a[0], torch.tensor([600 / 76, 300 / 76, 0.1 * 600, 0.1 * 300]))
    r = math.sqrt(2)
    torch.testing.assert_close(a[1, 2:], torch.tensor([0.1 * 600 * r, 0.1 * 300 / r]))
    # the extra box of conv4_3: ratio 1, scale sqrt(0.1 * 0.2)
    torch.testing.assert_close(a[3, 2:], torch.tensor([600, 300]) * math.sqrt(0.1 * 0.2))
    # the single conv11_2 cell: centre of the image, extra box past the last scale: sqrt(0.9 * 1.075)
    last = math.sqrt(0.9 * 1.075)
    torch.testing.assert_close(a[-1], torch.tensor([300, 150, 600 * last, 300 * last]))


def test_yolact_keeps_its_stride_layout_through_the_shared_anchors():
    assert issubclass(YolactAnchors, Anchors) and YolactAnchors is yolact_anchors.Anchors
    shared = Anchors((3.0,) * 5, (1.0, 0.5, 2.0), relative_to="stride")
    levels = [(16, 52), (8, 26), (4, 13), (2, 7), (1, 4)]
    torch.testing.assert_close(YolactAnchors()((128, 416), levels), shared((128, 416), levels))
    assert yolact_nms.fast_nms is boxes.fast_nms  # one implementation, imported


def test_bad_anchor_options_are_named():
    with pytest.raises(ValueError, match="relative_to"):
        Anchors((1.0,), (1.0,), relative_to="pixels")
    with pytest.raises(ValueError, match="2 aspect-ratio lists for 3 levels"):
        Anchors((1.0, 2.0, 3.0), [(1.0,), (2.0,)])


def test_greedy_nms_keeps_a_box_whose_suppressor_was_suppressed():
    # a > b > c by score; IoU(a, b) = 0.6, IoU(b, c) = 0.6, IoU(a, c) = 0.2: greedy keeps a and c
    # (Fast NMS, where the suppressed b still suppresses c, keeps a only)
    b = torch.tensor([[0.0, 0, 10, 10], [2.5, 0, 12.5, 10], [5.0, 0, 15, 10]])
    assert boxes.box_iou(b, b)[0, 1] == pytest.approx(0.6) and boxes.box_iou(b, b)[0, 2] == pytest.approx(1 / 3)
    keep = nms(b, torch.tensor([0.9, 0.8, 0.7]), 0.45)
    assert keep.tolist() == [0, 2]
    assert nms(b, torch.tensor([0.9, 0.8, 0.7]), 0.7).tolist() == [0, 1, 2]
    assert nms(b[:0], torch.zeros(0), 0.5).tolist() == []


def test_box_inside_is_intersection_over_the_first_box():
    a = torch.tensor([[0.0, 0, 10, 10], [20, 20, 30, 30]])
    region = torch.tensor([[5.0, 0, 100, 10]])
    torch.testing.assert_close(box_inside(a, region), torch.tensor([[0.5], [0.0]]))


def test_ssd_encoding_round_trips():
    anchors = torch.tensor([[50.0, 40, 20, 10], [10, 10, 4, 8]])
    gt = torch.tensor([[35.0, 30, 70, 52], [9, 5, 12, 18]])
    torch.testing.assert_close(decode_boxes(encode(gt, anchors), anchors), gt)
    # SSD eq. 2 with variances: the centre offset in units of 0.1 anchor widths
    assert encode(gt, anchors)[0, 0] == pytest.approx((52.5 - 50) / (0.1 * 20))
