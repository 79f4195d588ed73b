"""InstanceTask: loss and gradients through a tiny fusion model, mask AP on rigged outputs, per-condition AP,
anchors taken from the head, figures."""

from __future__ import annotations

import functools

import lightning as L
import matplotlib.pyplot as plt
import pytest
import torch
import torch.nn.functional as F
from torch.utils.data import DataLoader

from ablate.fusion import FusionModel, build
from ablate.tasks.instance import Anchors, InstanceTask, YolactHead
from ablate.tasks.yolact.anchors import box_iou, cxcywh_to_xyxy, encode

SIZE = (64, 64)
LEVELS = [(8, 8), (4, 4), (2, 2), (1, 1), (1, 1)]  # P3..P7 of a 64 x 64 input
K = 2  # prototypes of the rigged outputs: one per ground-truth instance
SGD = functools.partial(torch.optim.SGD, lr=0.01, momentum=0.9)


def tiny_model(stage: str = "fpn", op: str = "smoe", **head) -> FusionModel:
    return FusionModel(
        stage=stage,
        modalities={"rgb": 3, "ddm_jet": 3},
        single="rgb",
        head=functools.partial(YolactHead, num_classes=2, num_prototypes=4, **head),
        fusion=functools.partial(build, name=op),
        backbone={"depth": 18, "width": 0.125},
        fpn_channels=16,
    )


def box_mask(box: list[int]) -> torch.Tensor:
    mask = torch.zeros(SIZE, dtype=torch.bool)
    mask[box[1] : box[3], box[0] : box[2]] = True
    return mask


def make_batch(conditions: list[str]) -> dict:
    """One car and one pedestrian per frame, on a 4-pixel grid so prototype-resolution masks are exact."""
    boxes = [[4, 24, 36, 48], [44, 8, 56, 40]]
    g = torch.Generator().manual_seed(0)
    n = len(conditions)
    instance = {
        "masks": torch.stack([box_mask(b) for b in boxes]),
        "labels": torch.tensor([0, 1]),
        "boxes": torch.tensor(boxes, dtype=torch.float32),
    }
    return {
        "rgb": torch.rand(n, 3, *SIZE, generator=g),
        "ddm_jet": torch.rand(n, 3, *SIZE, generator=g),
        "instances": [dict(instance) for _ in range(n)],
        "ignore": torch.zeros(n, *SIZE, dtype=torch.bool),
        "condition": list(conditions),
    }


def rigged_outputs(batch: dict, anchors: Anchors, drop: set[tuple[int, int]] = frozenset()) -> dict:
    """Head maps that decode to exactly the ground truth: per instance its best anchor scores its class,
    carries its SSD-encoded box and selects a prototype equal to its mask; ``drop`` (frame, instance) leaves
    that instance undetected."""
    n, a = len(batch["instances"]), anchors.num_per_location
    cls = [torch.zeros(n, a * 3, h, w) for h, w in LEVELS]
    for m in cls:
        m[:, 0::3] = 10.0  # background everywhere
    box = [torch.zeros(n, a * 4, h, w) for h, w in LEVELS]
    coef = [torch.zeros(n, a * K, h, w) for h, w in LEVELS]
    proto = torch.full((n, K, SIZE[0] // 4, SIZE[1] // 4), -10.0)
    table = anchors(SIZE, LEVELS)
    starts = torch.tensor([0] + [h * w * a for h, w in LEVELS]).cumsum(0)
    for b, inst in enumerate(batch["instances"]):
        for j, (gt, label, mask) in enumerate(zip(inst["boxes"], inst["labels"], inst["masks"])):
            proto[b, j] = 20.0 * (F.avg_pool2d(mask[None, None].float(), 4)[0, 0] > 0.5) - 10.0
            if (b, j) in drop:
                continue
            idx = int(box_iou(gt[None], cxcywh_to_xyxy(table))[0].argmax())
            lvl = int((starts[1:] <= idx).sum())
            local = idx - int(starts[lvl])
            w = LEVELS[lvl][1]
            i, col, r = local // (w * a), local // a % w, local % a
            cls[lvl][b, r * 3, i, col] = -10.0
            cls[lvl][b, r * 3 + 1 + int(label), i, col] = 10.0
            box[lvl][b, r * 4 : (r + 1) * 4, i, col] = encode(gt[None], table[idx][None])[0]
            coef[lvl][b, r * K + j, i, col] = 1.0
    return {"proto": proto, "cls": cls, "box": box, "coef": coef}


class Rigged(torch.nn.Module):
    """A 'model' returning fixed head maps, with one parameter so Lightning can place it."""

    def __init__(self, outputs: dict) -> None:
        super().__init__()
        self.outputs, self.w = outputs, torch.nn.Parameter(torch.zeros(()))

    def forward(self, batch: dict) -> dict:
        return {k: [m + self.w for m in v] if isinstance(v, list) else v + self.w for k, v in self.outputs.items()}


def logged(task: InstanceTask) -> dict[str, float]:
    """Route ``task.log`` into a dict (no Trainer needed)."""
    values: dict[str, float] = {}
    task.log = lambda name, value, **kw: values.__setitem__(name, float(torch.as_tensor(value).detach()))
    return values


@pytest.mark.parametrize("stage", ["fpn", "late"])
def test_training_step_gives_a_finite_loss_and_gradients(stage):
    torch.manual_seed(0)
    task = InstanceTask(tiny_model(stage), SGD)
    values = logged(task)
    loss = task.training_step(make_batch(["clear", "night"]), 0)
    assert torch.isfinite(loss) and loss.item() > 0
    assert {"train/loss", "train/loss_cls", "train/loss_box", "train/loss_mask"} <= set(values)
    assert values["train/loss"] == pytest.approx(loss.item())
    loss.backward()
    gate = task.model.fusion_modules()[0].gate.conv.weight.grad
    head = (task.model.head if stage == "fpn" else task.model.heads["ddm_jet"]).cls.weight.grad
    for grad in (gate, head):
        assert grad is not None and torch.isfinite(grad).all() and grad.abs().sum() > 0


def test_anchors_come_from_the_head():
    scales = (0.1, 0.2, 0.3, 0.5, 0.9)
    for stage in ("fpn", "late"):
        model = tiny_model(stage, anchor_scales=scales)
        task = InstanceTask(model, SGD)
        head = model.head if stage == "fpn" else model.heads["rgb"]
        assert task.anchors is head.anchors and task.criterion.anchors is head.anchors
        assert task.anchors.scales == scales


def test_rigged_perfect_outputs_score_100_and_a_missed_class_halves_the_map():
    batch = make_batch(["clear", "clear"])
    task = InstanceTask(Rigged(rigged_outputs(batch, Anchors())), SGD)
    values = logged(task)
    task.validation_step(batch, 0)
    task.on_validation_epoch_end()
    assert values["val/map"] == pytest.approx(100.0) and values["val/map_50"] == pytest.approx(100.0)
    assert values["val/map_75"] == pytest.approx(100.0) and values["val/bbox_map"] == pytest.approx(100.0)
    # pedestrians never detected: car AP 100, pedestrian AP 0, mean 50
    task.model.outputs = rigged_outputs(batch, Anchors(), drop={(0, 1), (1, 1)})
    task.validation_step(batch, 0)
    task.on_validation_epoch_end()
    assert values["val/map"] == pytest.approx(50.0)


def test_test_logs_map_per_condition_group_present():
    batch = make_batch(["clear", "night", "rain_day", "rain_night"])
    # night: nothing detected; rain_night: its pedestrian missed
    outputs = rigged_outputs(batch, Anchors(), drop={(1, 0), (1, 1), (3, 1)})
    trainer = L.Trainer(
        accelerator="cpu",
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
    )
    (res,) = trainer.test(
        InstanceTask(Rigged(outputs), SGD),
        dataloaders=DataLoader([batch], batch_size=None, collate_fn=lambda b: b),
        verbose=False,
    )
    assert res["test/map_clear"] == pytest.approx(100.0)
    assert res["test/map_night"] == pytest.approx(0.0)
    # rain pools rain_day and rain_night: cars 2/2 found (AP 100); pedestrians 1/2 found with the top score, so
    # precision 1 up to recall 0.5: 51 of COCO's 101 recall points (AP 50.5)
    assert res["test/map_rain"] == pytest.approx((100.0 + 100.0 * 51 / 101) / 2, abs=1e-3)
    assert "test/map_glare" not in res
    assert 0 < res["test/map"] < 100


def test_unknown_condition_or_decode_option_is_refused():
    with pytest.raises(ValueError, match="no condition group for \\['fog'\\].*rain_day"):
        InstanceTask(tiny_model(), SGD, conditions=["clear", "fog"])
    with pytest.raises(ValueError, match="task.decode: unknown option.*score_thresh"):
        InstanceTask(tiny_model(), SGD, decode={"threshold": 0.5})
    task = InstanceTask(tiny_model(), SGD, conditions=["clear", "rain_night"])
    assert task.groups == ["clear", "rain"]


def test_figure_draws_ground_truth_and_predictions_per_frame():
    task = InstanceTask(tiny_model(), SGD, figure_frames=3)
    fig = task.figure(make_batch(["clear", "night", "glare", "rain_day"]))
    assert len(fig.axes) == 3 * 2
    assert fig.axes[2].get_title() == "ground truth (night)"
    assert len(fig.axes[0].patches) == 2  # the two ground-truth boxes
    assert task.model.training  # figures leave the training mode as it was
    plt.close(fig)


def test_gate_figure_shows_night_and_glare_gates_of_the_first_gated_op():
    torch.manual_seed(0)
    task = InstanceTask(tiny_model("fpn", "smoe"), SGD)
    fig = task.gate_figure(make_batch(["clear", "glare", "rain_day", "night"]))
    titles = [ax.get_title() for ax in fig.axes]
    assert titles[0] == "rgb (night)" and titles[4] == "rgb (glare)" and titles[2] == "ddm_jet (night)"
    # per modality: its input, then its gate upsampled to the input size; SMoE eq. 3 gates are W and 1 - W
    rgb_gate, ddm_gate = fig.axes[1].images[-1].get_array(), fig.axes[3].images[-1].get_array()
    assert rgb_gate.shape == SIZE and 0 <= rgb_gate.min() and rgb_gate.max() <= 1
    assert abs((rgb_gate + ddm_gate) - 1).max() < 1e-5
    plt.close(fig)


@pytest.mark.parametrize("stage,op", [("fpn", "sum"), ("fpn", "sharpen"), ("single", "sum"), ("early", "smoe")])
def test_gate_figure_is_none_without_a_gated_op(stage, op):
    assert InstanceTask(tiny_model(stage, op), SGD).gate_figure(make_batch(["night", "glare"])) is None
