"""SMoE eq. 7 loss of the YOLACT head: hand values, empty images, and a short fit on one synthetic image."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from ablate.tasks.instance import Anchors, YolactHead, YolactLoss, decode, match

IMAGE = (64, 64)
LEVELS = [(8, 8), (4, 4), (2, 2), (1, 1), (1, 1)]


def square_target(x1: int = 16, y1: int = 20, size: int = 24, label: int = 0) -> dict:
    masks = torch.zeros(1, *IMAGE, dtype=torch.bool)
    masks[0, y1 : y1 + size, x1 : x1 + size] = True
    return {
        "boxes": torch.tensor([[x1, y1, x1 + size, y1 + size]], dtype=torch.float32),
        "labels": torch.tensor([label]),
        "masks": masks,
    }


def disc_target(cx: float = 28.0, cy: float = 32.0, r: float = 12.0) -> dict:
    ys, xs = torch.meshgrid(torch.arange(IMAGE[0]) + 0.5, torch.arange(IMAGE[1]) + 0.5, indexing="ij")
    mask = (xs - cx) ** 2 + (ys - cy) ** 2 <= r * r
    return {"boxes": torch.tensor([[cx - r, cy - r, cx + r, cy + r]]), "labels": torch.tensor([1]), "masks": mask[None]}


def empty_target() -> dict:
    return {
        "boxes": torch.zeros(0, 4),
        "labels": torch.zeros(0, dtype=torch.long),
        "masks": torch.zeros(0, *IMAGE, dtype=torch.bool),
    }


def zero_outputs(batch: int = 1, k: int = 2, proto: torch.Tensor | None = None) -> dict:
    """Maps of an untrained head: uniform class logits, zero offsets, zero coefficients."""
    return {
        "proto": (proto if proto is not None else torch.zeros(batch, k, 16, 16)).requires_grad_(),
        "cls": [torch.zeros(batch, 9, h, w, requires_grad=True) for h, w in LEVELS],
        "box": [torch.zeros(batch, 12, h, w, requires_grad=True) for h, w in LEVELS],
        "coef": [torch.zeros(batch, 3 * k, h, w, requires_grad=True) for h, w in LEVELS],
    }


def test_hand_values_with_uniform_logits():
    loss_fn = YolactLoss()
    out = loss_fn(zero_outputs(), [square_target()], IMAGE)
    # CE of uniform logits over K + 1 = 3 classes is log 3 for every selected anchor: (P + 3P) log 3 / P
    assert math.isclose(out["cls"].item(), 4 * math.log(3), rel_tol=1e-5)
    # zero coefficients -> logit 0 -> BCE log 2 at every pixel, whatever the crop
    assert math.isclose(out["mask"].item(), math.log(2), rel_tol=1e-5)
    anchors = Anchors()(IMAGE, LEVELS)
    _, state = match(square_target()["boxes"], anchors)
    assert (state == 1).sum() >= 1
    assert math.isclose(
        out["total"].item(), out["cls"].item() + 1.5 * out["box"].item() + 6.125 * math.log(2), rel_tol=1e-5
    )


def test_image_without_gt_is_finite_and_uses_its_hardest_negatives():
    out = YolactLoss()(zero_outputs(batch=2), [empty_target(), empty_target()], IMAGE)
    assert math.isclose(out["cls"].item(), 2 * 3 * math.log(3), rel_tol=1e-5)
    assert out["box"].item() == 0 and out["mask"].item() == 0
    out["total"].backward()
    assert torch.isfinite(out["total"])
    mixed = YolactLoss()(zero_outputs(batch=2), [square_target(), empty_target()], IMAGE)
    assert all(torch.isfinite(v) for v in mixed.values())


def test_mask_loss_ignores_pixels_outside_the_gt_box():
    target = square_target(x1=16, y1=16, size=32)  # box covers proto pixels 4..11
    gt = F.interpolate(target["masks"][None].float(), (16, 16), mode="bilinear")[0, 0] > 0.5
    inside = torch.zeros(16, 16, dtype=torch.bool)
    inside[4:12, 4:12] = True
    losses = []
    for outside_value in (0.0, 5.0):
        proto = torch.where(gt, 8.0, -8.0)
        proto = torch.where(inside, proto, torch.tensor(outside_value))[None, None].repeat(1, 2, 1, 1)
        outputs = zero_outputs(proto=proto)
        for m in outputs["coef"]:
            m.data.fill_(0.5)  # logit = proto * (0.5 + 0.5)
        losses.append(YolactLoss()(outputs, [target], IMAGE)["mask"].item())
    assert losses[0] == losses[1]
    assert math.isclose(losses[0], F.softplus(torch.tensor(-8.0)).item(), rel_tol=1e-4)


class TinyNet(nn.Module):
    """A conv stem pooled to the five FPN sizes, feeding the head."""

    def __init__(self, c: int = 16) -> None:
        super().__init__()
        self.stem = nn.Sequential(
            nn.Conv2d(3, c, 3, stride=2, padding=1), nn.ReLU(), nn.Conv2d(c, c, 3, stride=2, padding=1), nn.ReLU()
        )
        self.head = YolactHead(in_channels=c, num_prototypes=4)

    def forward(self, x: torch.Tensor) -> dict:
        f = self.stem(x)
        return self.head([F.adaptive_avg_pool2d(f, s) for s in LEVELS])


def test_loss_decreases_on_one_synthetic_image():
    torch.manual_seed(0)
    target = disc_target()  # not a box, so the mask term has a shape to learn
    image = target["masks"].float().expand(3, -1, -1)[None] + 0.1 * torch.randn(1, 3, *IMAGE)
    net, loss_fn = TinyNet(), YolactLoss()
    opt = torch.optim.SGD(net.parameters(), lr=0.01, momentum=0.9)
    history = []
    for _ in range(30):
        out = loss_fn(net(image), [target], IMAGE)
        opt.zero_grad()
        out["total"].backward()
        opt.step()
        history.append({k: v.item() for k, v in out.items()})
    assert all(math.isfinite(h["total"]) for h in history)
    assert history[-1]["total"] < 0.5 * history[0]["total"]
    assert history[-1]["cls"] < history[0]["cls"] and history[-1]["mask"] < history[0]["mask"]
    (res,) = decode(net(image), IMAGE, score_thresh=0.05)
    assert res["masks"].shape[1:] == IMAGE
