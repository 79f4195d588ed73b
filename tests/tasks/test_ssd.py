"""SSD matching, hard negative mining, loss and decoding on hand-made default boxes and rigged predictions."""

import functools
import math

import pytest
import torch

from ablate.fusion import FusionModel, build
from ablate.tasks.boxes import Anchors, encode
from ablate.tasks.detection import DGFN, SSDHead, SSDLoss, decode

K = 3  # Car, Pedestrian, Cyclist; labels 3 Van, 4 Person_sitting, 5 DontCare are ignore regions
IMAGE = (20, 20)


def grid(cells: int) -> Anchors:
    """One level of cells x cells square default boxes tiling a 20 x 20 image (ratio 1, no extra box)."""
    return Anchors((1.0 / cells,), (1.0,), relative_to="image")


def outputs(
    cells: int,
    logits: dict[int, list[float]] | None = None,
    loc: dict[int, list[float]] | None = None,
    batch: int = 1,
    background: float = 0.0,
) -> dict:
    """Head maps on a cells x cells grid: every anchor's logits [background, 0, 0, 0] unless given; offsets 0."""
    cls = torch.zeros(batch, cells * cells, K + 1)
    cls[..., 0] = background
    box = torch.zeros(batch, cells * cells, 4)
    for a, v in (logits or {}).items():
        cls[:, a] = torch.tensor(v)
    for a, v in (loc or {}).items():
        box[:, a] = torch.tensor(v)
    maps = lambda t: t.reshape(batch, cells, cells, -1).permute(0, 3, 1, 2).requires_grad_()  # noqa: E731
    return {"cls": [maps(cls)], "box": [maps(box)]}


def target(*objects) -> dict:
    return {
        "boxes": torch.tensor([o[1] for o in objects], dtype=torch.float32).reshape(-1, 4),
        "labels": torch.tensor([o[0] for o in objects], dtype=torch.long),
    }


def test_matching_leaves_van_and_dontcare_out_of_positives_and_negatives():
    # 2 x 2 anchors of 10 px: [0,0,10,10], [10,0,20,10], [0,10,10,20], [10,10,20,20]
    anchors = grid(2)(IMAGE, [(2, 2)])
    loss = SSDLoss(grid(2), K)
    t = target((0, [0, 0, 10, 10]), (5, [10, 0, 20, 20]), (3, [0, 10, 10, 20]))
    conf, state, idx, real = loss.assign(t["boxes"], t["labels"], anchors)
    assert state.tolist() == [1, -1, -1, -1] and conf.tolist() == [1, 0, 0, 0] and real.tolist() == [True, False, False]
    # a Pedestrian over anchor 3 at IoU 0.64, a Car with its best anchor at IoU 0.25 (forced positive), rest negative
    t = target((1, [11, 11, 19, 19]), (0, [0, 0, 5, 5]))
    conf, state, _, _ = loss.assign(t["boxes"], t["labels"], anchors)
    assert state.tolist() == [1, 0, 0, 1] and conf.tolist() == [1, 0, 0, 2]


def test_hard_negative_mining_takes_three_per_positive_by_background_loss():
    # 4 x 4 anchors of 5 px, one Car exactly on anchor 5: one positive, 15 negatives, 3 of them mined
    loss = SSDLoss(grid(4), K)
    t = [target((0, [5, 5, 10, 10]))]
    flat = loss(outputs(4), t, IMAGE)
    assert flat["cls"].item() == pytest.approx(4 * math.log(4))  # (1 positive + 3 negatives) x log 4, / 1
    assert flat["box"].item() == 0.0 and flat["total"].item() == pytest.approx(4 * math.log(4))
    # two negatives fire on Car (logit 5): they are mined first; the others are sure background (logit 10)
    rigged = outputs(4, {5: [0, 0, 0, 0], 0: [0, 5, 0, 0], 15: [0, 5, 0, 0]}, background=10.0)
    easy = math.log(math.exp(10) + 3) - 10
    expected = math.log(4) + 2 * math.log(3 + math.exp(5)) + easy
    assert loss(rigged, t, IMAGE)["cls"].item() == pytest.approx(expected, rel=1e-5)
    assert SSDLoss(grid(4), K, neg_pos_ratio=1)(rigged, t, IMAGE)["cls"].item() == pytest.approx(
        math.log(4) + math.log(3 + math.exp(5)), rel=1e-5
    )


def test_an_image_without_objects_adds_nothing_and_no_objects_at_all_is_zero_loss():
    loss = SSDLoss(grid(4), K)
    one = loss(outputs(4), [target((0, [5, 5, 10, 10]))], IMAGE)["total"]
    two = loss(outputs(4, batch=2), [target((0, [5, 5, 10, 10])), target()], IMAGE)["total"]
    assert two.item() == pytest.approx(one.item())
    out = outputs(4, batch=2)
    none = loss(out, [target(), target((5, [0, 0, 20, 20]))], IMAGE)["total"]
    assert none.item() == 0.0
    none.backward()  # SSD eq. 1: L = 0 when N = 0, still a graph
    assert out["cls"][0].grad is not None


def test_box_loss_is_smooth_l1_of_the_encoded_offsets_over_positives():
    loss = SSDLoss(grid(4), K)
    gt = [5.0, 5.0, 10.0, 11.0]  # on anchor 5, one px taller
    anchor = grid(4)(IMAGE, [(4, 4)])[5]
    enc = encode(torch.tensor(gt), anchor)
    off = enc.clone()
    off[0] += 0.5  # centre x off by 0.5 (encoded units): smooth L1 0.5 * 0.5^2
    out = outputs(4, loc={5: off.tolist()})
    assert loss(out, [target((0, gt))], IMAGE)["box"].item() == pytest.approx(0.125, abs=1e-6)
    assert SSDLoss(grid(4), K, alpha=2.0)(out, [target((0, gt))], IMAGE)["total"].item() == pytest.approx(
        loss(out, [target((0, gt))], IMAGE)["cls"].item() + 0.25, abs=1e-5
    )


def test_decoding_keeps_the_best_box_per_class_and_clips_to_the_image():
    # anchor 1 moved onto anchor 0 (centre 15 -> 5: -10 in units of 0.1 x 10 px): the same Car, lower score;
    # anchor 2 moved onto it too but a Pedestrian: per-class NMS keeps it; anchor 3 sure background
    out = outputs(
        2,
        {0: [0, 6, 0, 0], 1: [0, 5, 0, 0], 2: [0, 0, 5.5, 0], 3: [10, 0, 0, 0]},
        {1: [-10, 0, 0, 0], 2: [0, -10, 0, 0]},
    )
    (res,) = decode(out, IMAGE, grid(2))
    assert res["labels"].tolist() == [0, 1]
    torch.testing.assert_close(res["boxes"], torch.tensor([[0.0, 0, 10, 10], [0, 0, 10, 10]]))
    torch.testing.assert_close(
        res["scores"], torch.tensor([math.exp(6) / (math.exp(6) + 3), math.exp(5.5) / (math.exp(5.5) + 3)])
    )
    # without NMS overlap limit both Cars stay; a box pushed past the border is clipped
    (res,) = decode(out, IMAGE, grid(2), nms_iou=1.0)
    assert res["labels"].tolist() == [0, 1, 0]
    (res,) = decode(outputs(2, {0: [0, 6, 0, 0]}, {0: [-10, 0, 0, 0]}, background=10.0), IMAGE, grid(2))
    torch.testing.assert_close(res["boxes"], torch.tensor([[0.0, 0, 0, 10]]))


def test_ssd_head_on_dgfn_maps_and_on_a_fusion_models_fpn():
    head = functools.partial(SSDHead, num_classes=K)
    dgfn = DGFN({"rgb": 3, "dhi": 3}, head, functools.partial(build, "gfu"), width=0.0625, input_size=(272, 272))
    x = {"rgb": torch.rand(1, 3, 64, 208), "dhi": torch.rand(1, 3, 64, 208)}
    out = dgfn(x)
    assert [tuple(m.shape[-2:]) for m in out["cls"]] == [(34, 34), (17, 17), (9, 9), (5, 5), (3, 3), (1, 1)]
    assert [m.shape[1] for m in out["cls"]] == [4 * 4, 6 * 4, 6 * 4, 6 * 4, 4 * 4, 4 * 4]
    assert len(dgfn.fusion_modules()) == 6 and dgfn.fusion_modules()[0].last_gates[0].shape == (1, 1, 34, 34)
    fpn = FusionModel(
        "fpn",
        {"rgb": 3, "dhi": 3},
        functools.partial(build, "gfu"),
        head,
        backbone={"depth": 18, "width": 0.125},
        fpn_channels=16,
    )
    out = fpn(x)
    assert len(out["cls"]) == 5 and out["cls"][0].shape == (1, 6 * 4, 8, 26)
    t = [target((0, [20, 20, 60, 50]))]
    assert torch.isfinite(SSDLoss(fpn.head.anchors, K)(out, t, (64, 208))["total"])


def test_a_blanked_trunk_normalises_with_its_running_statistics_and_leaves_them():
    def stats(model, modality):
        norms = [m for m in model.branches[modality].modules() if isinstance(m, torch.nn.BatchNorm2d)]
        return torch.cat([torch.cat([m.running_mean, m.running_var]) for m in norms])

    head = functools.partial(SSDHead, num_classes=K)
    gfu = functools.partial(build, "gfu")
    models = {}
    for flag in (False, True):
        torch.manual_seed(0)
        models[flag] = DGFN(
            {"rgb": 3, "dhi": 3}, head, gfu, width=0.0625, input_size=(272, 272), batch_norm=True,
            blank_running_stats=flag,
        )  # fmt: skip
        models[flag].train()
    blank = {"rgb": torch.zeros(2, 3, 64, 208), "dhi": torch.rand(2, 3, 64, 208)}
    before = {m: stats(models[True], m) for m in ("rgb", "dhi")}
    for model in models.values():
        model(blank)
    torch.testing.assert_close(stats(models[True], "rgb"), before["rgb"])  # the blanked camera's: as they were
    assert not torch.equal(stats(models[True], "dhi"), before["dhi"])  # the LiDAR's batch has statistics
    assert not torch.equal(stats(models[False], "rgb"), before["rgb"])  # without the option: the zeros' statistics
    branch = models[True].branches["rgb"].eval()
    with torch.no_grad():
        expected = branch(models[True]._resize(blank["rgb"]))
    models[True].train()
    with torch.no_grad():
        got = models[True]._trunk("rgb", models[True]._resize(blank["rgb"]))
    for a, b in zip(got, expected):
        torch.testing.assert_close(a, b)  # normalised as at test
    assert all(m.training for m in models[True].modules())  # and back in training mode


def test_bad_model_options_name_the_option():
    head = functools.partial(SSDHead, num_classes=K)
    with pytest.raises(ValueError, match="model.single: 'lidar'"):
        DGFN({"rgb": 3, "dhi": 3}, head, single="lidar")
    with pytest.raises(ValueError, match="fusion=gfu"):
        DGFN({"rgb": 3, "dhi": 3}, head)
    with pytest.raises(ValueError, match="head.aspect_ratios: 2 lists for 6 maps"):
        SSDHead(16, aspect_ratios=[[2], [2]])
