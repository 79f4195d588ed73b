"""YOLACT head pieces: anchors, matching, box encoding, head maps, Fast NMS, mask assembly, decode."""

from __future__ import annotations

import math

import pytest
import torch

from ablate.metrics.coco import MaskAP
from ablate.tasks.instance import Anchors, YolactHead, assemble_masks, decode, fast_nms, match
from ablate.tasks.yolact.anchors import box_iou, cxcywh_to_xyxy, decode_boxes, encode

LEVELS = [(8, 16), (4, 8), (2, 4), (1, 2), (1, 1)]


def xyxy_to_cxcywh(b: torch.Tensor) -> torch.Tensor:
    return torch.cat([(b[:, :2] + b[:, 2:]) / 2, b[:, 2:] - b[:, :2]], 1)


def test_anchor_count_centres_and_sizes():
    anchors = Anchors(scales=(0.8, 1.6, 3.2, 3.2, 1.0))(image_size=(64, 128), level_sizes=LEVELS)
    assert anchors.shape == ((128 + 32 + 8 + 2 + 1) * 3, 4)
    # first cell of P3 (stride 8): centre (4, 4); ratios 1, 1/2, 2 of a 0.8 strides = 6.4 px anchor
    r = math.sqrt(2)
    expected = torch.tensor([[4, 4, 6.4, 6.4], [4, 4, 6.4 / r, 6.4 * r], [4, 4, 6.4 * r, 6.4 / r]])
    torch.testing.assert_close(anchors[:3], expected)
    # second column, same row, next; last anchor: the single P7 cell at the image centre, 64 px
    torch.testing.assert_close(anchors[3, :2], torch.tensor([12.0, 4.0]))
    torch.testing.assert_close(anchors[-3], torch.tensor([64.0, 32.0, 64.0, 64.0]))
    # sizes scale with the input
    big = Anchors(scales=(0.8, 1.6, 3.2, 3.2, 1.0))((128, 256), LEVELS)
    torch.testing.assert_close(big, anchors * 2)


def test_matching_on_hand_made_boxes():
    anchors = xyxy_to_cxcywh(
        torch.tensor(
            [
                [0, 0, 10, 10],  # IoU 1 with gt 0            -> positive
                [5, 0, 15, 10],  # IoU 50/150 = 0.33           -> negative
                [3, 0, 13, 10],  # IoU 70/130 = 0.54           -> positive
                [4, 0, 14, 10],  # IoU 60/140 = 0.43           -> neutral
                [95, 95, 115, 115],  # IoU 16/400 = 0.04 with gt 1, its best anchor -> forced positive
            ],
            dtype=torch.float32,
        )
    )
    gt = torch.tensor([[0, 0, 10, 10], [100, 100, 104, 104]], dtype=torch.float32)
    idx, state = match(gt, anchors)
    assert state.tolist() == [1, 0, 1, -1, 1]
    assert idx[state == 1].tolist() == [0, 0, 1]
    idx, state = match(gt[:0], anchors)
    assert state.tolist() == [0] * 5


def test_encode_decode_round_trip_and_hand_values():
    anchors = torch.tensor([[50.0, 40.0, 20.0, 10.0]])
    same = cxcywh_to_xyxy(anchors)
    torch.testing.assert_close(encode(same, anchors), torch.zeros(1, 4))
    wider = torch.tensor([[32.0, 35.0, 72.0, 45.0]])  # centre (52, 40), twice the width
    torch.testing.assert_close(encode(wider, anchors), torch.tensor([[2 / (0.1 * 20), 0, math.log(2) / 0.2, 0]]))
    g = torch.Generator().manual_seed(0)
    boxes = torch.rand(50, 2, generator=g) * 100
    boxes = torch.cat([boxes, boxes + 1 + torch.rand(50, 2, generator=g) * 50], 1)
    anchors = xyxy_to_cxcywh(boxes + torch.randn(50, 4, generator=g))
    torch.testing.assert_close(decode_boxes(encode(boxes, anchors), anchors), boxes, rtol=1e-5, atol=1e-4)


def test_head_maps_match_out_channels():
    head = YolactHead(in_channels=8, num_classes=2, num_prototypes=4)
    feats = [torch.randn(2, 8, h, w) for h, w in LEVELS]
    out = head(feats)
    assert out["proto"].shape == (2, 4, 16, 32) and out["proto"].min() >= 0
    for key in ("cls", "box", "coef"):
        assert [m.shape for m in out[key]] == [(2, c, h, w) for c, (h, w) in zip(head.out_channels[key], LEVELS)]
    assert head.out_channels["cls"][0] == 3 * 3 and head.out_channels["coef"][0] == 3 * 4
    assert max(m.abs().max() for m in out["coef"]) <= 1
    with pytest.raises(ValueError, match="FPN levels"):
        head(feats[:4])


def test_fast_nms_matches_hand_computation():
    boxes = torch.tensor(
        [
            [0, 0, 10, 10],  # A .9 kept
            [3, 0, 13, 10],  # B .8 IoU(A, B) = 0.54 -> suppressed
            [6, 0, 16, 10],  # C .7 IoU(A, C) = 0.25 but IoU(B, C) = 0.54 -> suppressed too
            [30, 30, 40, 40],
        ],  # D .6 disjoint -> kept
        dtype=torch.float32,
    )
    scores = torch.tensor([[0.9, 0.01], [0.8, 0.01], [0.7, 0.01], [0.6, 0.3]])
    idx, labels, s = fast_nms(boxes, scores, iou_threshold=0.5, score_threshold=0.05)
    assert idx.tolist() == [0, 3, 3]
    assert labels.tolist() == [0, 0, 1]
    torch.testing.assert_close(s, torch.tensor([0.9, 0.6, 0.3]))
    assert box_iou(boxes[1:2], boxes[2:3]).item() > 0.5  # the hand computation above
    idx, _, _ = fast_nms(boxes, scores, iou_threshold=0.6)
    assert idx.tolist() == [0, 1, 2, 3, 3]


def test_mask_assembly_crops_outside_the_box():
    proto = torch.ones(1, 8, 8)
    masks = assemble_masks(proto, torch.tensor([[10.0], [-10.0]]), torch.tensor([[4.0, 2.0, 12.0, 9.0]] * 2), (16, 16))
    expected = torch.zeros(16, 16, dtype=torch.bool)
    expected[2:9, 4:12] = True
    assert torch.equal(masks[0], expected)
    assert not masks[1].any()  # sigmoid(-10) < 0.5 inside the box as well


def test_decode_returns_the_confident_anchor_as_an_instance():
    image, levels, k = (32, 32), [(4, 4), (2, 2), (1, 1), (1, 1), (1, 1)], 2
    cls = [torch.zeros(1, 9, h, w) for h, w in levels]
    for m in cls:
        m[:, 0::3] = 10.0  # background everywhere ...
    cls[1][0, 3 + 2, 1, 0] = 20.0  # ... except anchor (row 1, col 0, ratio 1/2) of P4: pedestrian
    outputs = {
        "proto": torch.ones(1, k, 8, 8),
        "cls": cls,
        "box": [torch.zeros(1, 12, h, w) for h, w in levels],
        "coef": [torch.ones(1, 3 * k, h, w) for h, w in levels],
    }
    anchors = Anchors(scales=(0.1, 0.25, 0.5, 0.75, 1.0))
    (res,) = decode(outputs, image, score_thresh=0.5, anchors=anchors)
    assert res["labels"].tolist() == [1] and res["scores"].item() > 0.99
    a = anchors(image, levels)[4 * 4 * 3 + (1 * 2 + 0) * 3 + 1]
    torch.testing.assert_close(res["boxes"][0], cxcywh_to_xyxy(a))
    assert res["masks"].shape == (1, 32, 32) and res["masks"][0].sum() > 0
    assert not res["masks"][0][:16].any()  # the box lies in the lower half
    # the output is MaskAP's input format: scored against its own masks it is perfect
    metric = MaskAP(min_height=0)
    metric.update([res], [{"masks": res["masks"], "labels": res["labels"]}])
    assert metric.compute()["map"].item() == 1.0
    (none,) = decode(outputs, image, score_thresh=0.9999999, anchors=anchors)
    assert none["masks"].shape == (0, 32, 32) and none["boxes"].shape == (0, 4) and none["labels"].numel() == 0


def test_default_anchors_keep_yolacts_layout_at_any_input_size():
    # YOLACT at 550 px: 24 px anchors on P3's 8 px grid; a small KITTI-shaped input keeps 3 strides per anchor
    for image, p3 in (((550, 550), (69, 69)), ((128, 416), (16, 52))):
        levels = [(math.ceil(p3[0] / 2**i), math.ceil(p3[1] / 2**i)) for i in range(5)]
        anchors = Anchors()(image, levels)
        stride = image[0] / p3[0]
        torch.testing.assert_close(anchors[0, 2:], torch.full((2,), 3.0 * stride))
    # every 24 px box on the 128x416 grid has an anchor with IoU >= 0.5 somewhere
    anchors = Anchors()((128, 416), [(16, 52), (8, 26), (4, 13), (2, 7), (1, 4)])
    for x in range(0, 390, 5):
        box = torch.tensor([[x, 50.0, x + 24, 74.0]])
        a = torch.cat([anchors[:, :2] - anchors[:, 2:] / 2, anchors[:, :2] + anchors[:, 2:] / 2], 1)
        lt, rb = torch.max(a[:, :2], box[:, :2]), torch.min(a[:, 2:], box[:, 2:])
        inter = (rb - lt).clamp(min=0).prod(1)
        iou = inter / ((a[:, 2:] - a[:, :2]).prod(1) + 24 * 24 - inter)
        assert iou.max() >= 0.5, x
