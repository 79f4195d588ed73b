"""The ChiNet task: losses, the Det. Rate definition, the class-map precedence and the NaN guard."""

import functools

import pytest
import torch

from ablate.tasks.base import NonFiniteLossError, poly_lr
from ablate.tasks.semantic import SegmentationHead, SemanticTask, class_map, median_frequency


class Fixed(torch.nn.Module):
    """A 'model' returning fixed outputs, with one parameter so an optimiser can be built."""

    def __init__(self, outputs):
        super().__init__()
        self.outputs = outputs
        self.w = torch.nn.Parameter(torch.zeros(()))

    def forward(self, batch):
        return {k: v + self.w for k, v in self.outputs.items()}


def _task(outputs):
    return SemanticTask(Fixed(outputs), functools.partial(torch.optim.SGD, lr=0.1))


def _onehot_logits(labels):
    return 10.0 * torch.nn.functional.one_hot(labels, 3).permute(0, 3, 1, 2).float() - 5.0


def test_det_rate_is_accuracy_over_free_space_and_object_pixels():
    target = torch.tensor([[[0, 0, 1, 1, 1, 2, 2, 2]]])  # 3 free-space, 3 object, 2 background pixels
    pred = torch.tensor([[[1, 2, 1, 1, 0, 2, 1, 2]]])  # background mistakes must not count
    task = _task({"semantic": _onehot_logits(pred)})
    task._eval_step({"semantic": target}, "test")
    rate = 100.0 * task.test_rate.compute()
    assert rate.item() == pytest.approx(100.0 * 4 / 6)
    iou = task.test_iou.compute()
    assert iou[1].item() == pytest.approx(2 / 5)  # free space: tp 2, fp 2, fn 1
    assert iou[2].item() == pytest.approx(2 / 4)  # objects: tp 2, fp 1, fn 1


def test_multilabel_class_map_object_wins_over_free_space():
    free = torch.tensor([[[[5.0, 5.0, -5.0, -5.0]]]])
    obj = torch.tensor([[[[5.0, -5.0, 5.0, -5.0]]]])
    labels = class_map({"free_space": free, "road_objects": obj}, (1, 4))
    assert labels.tolist() == [[[2, 1, 2, 0]]]


def test_low_resolution_outputs_are_upsampled_to_the_labels():
    labels = class_map({"semantic": _onehot_logits(torch.ones(1, 2, 3, dtype=torch.long))}, (8, 12))
    assert labels.shape == (1, 8, 12) and (labels == 1).all()


def test_multilabel_loss_is_bce_per_branch():
    free, obj = torch.zeros(1, 1, 2, 2), torch.zeros(1, 1, 2, 2)
    batch = {
        "semantic": torch.zeros(1, 2, 2, dtype=torch.long),
        "free_space": torch.ones(1, 1, 2, 2),
        "road_objects": torch.zeros(1, 1, 2, 2),
    }
    loss = _task({"free_space": free, "road_objects": obj}).loss({"free_space": free, "road_objects": obj}, batch)
    assert loss.item() == pytest.approx(2 * torch.log(torch.tensor(2.0)).item())


def test_median_frequency_weights_are_the_median_share_over_each_class_share():
    # pixel shares 6/10 background, 3/10 free space, 1/10 objects: median 3/10 -> weights 0.5, 1, 3
    labels = torch.tensor([[0, 0, 0, 0, 0, 0, 1, 1, 1, 2]])
    batches = [{"semantic": labels[:, :5]}, {"semantic": labels[:, 5:]}]
    assert median_frequency(batches).tolist() == pytest.approx([0.5, 1.0, 3.0])
    # a class no label holds weighs nothing, and the median is over the classes present
    assert median_frequency([{"semantic": torch.tensor([0, 0, 0, 1])}]).tolist() == pytest.approx([1 / 3, 1.0, 0.0])


def test_weighted_multiclass_loss_is_torchs_weighted_cross_entropy():
    logits = torch.randn(2, 3, 4, 5)
    target = torch.randint(0, 3, (2, 4, 5))
    task = SemanticTask(
        Fixed({"semantic": logits}), functools.partial(torch.optim.SGD, lr=0.1), class_weights=[0.5, 1.0, 3.0]
    )
    loss = task.loss({"semantic": logits}, {"semantic": target})
    w = torch.tensor([0.5, 1.0, 3.0])[target]  # sum of w_i * nll_i over sum of w_i
    nll = -logits.log_softmax(1).gather(1, target[:, None])[:, 0]
    assert loss.item() == pytest.approx(((w * nll).sum() / w.sum()).item(), rel=1e-5)
    assert "class_weight" in task.state_dict()  # kept in the checkpoint


@pytest.mark.parametrize("bad", ["inverse", [1.0, 2.0]])
def test_unknown_class_weights_name_the_option(bad):
    with pytest.raises(ValueError, match="task.class_weights"):
        SemanticTask(Fixed({}), functools.partial(torch.optim.SGD, lr=0.1), class_weights=bad)


def test_nan_loss_stops_the_job_with_a_clear_message():
    task = _task({"semantic": torch.full((1, 3, 2, 2), float("nan"))})
    batch = {"semantic": torch.zeros(1, 2, 2, dtype=torch.long)}
    with pytest.raises(NonFiniteLossError, match="loss is nan at epoch 0"):
        task.training_step(batch, 0)


def test_segmentation_head_sums_levels_at_p3():
    head = SegmentationHead(in_channels=4, num_levels=5, levels=3)
    feats = [torch.rand(2, 4, 16 // 2**i, 32 // 2**i) for i in range(5)]
    out = head(feats)
    assert set(out) == {"free_space", "road_objects"} and out["free_space"].shape == (2, 1, 16, 32)
    assert head.out_channels == {"free_space": 1, "road_objects": 1}
    with pytest.raises(ValueError, match="head.levels"):
        SegmentationHead(in_channels=4, num_levels=5, levels=6)


def test_poly_lr_follows_smoe_eq6():
    opt = torch.optim.SGD([torch.nn.Parameter(torch.zeros(()))], lr=1.0)
    sched = poly_lr(opt, total_steps=10, power=0.9)
    for _ in range(5):
        opt.step()
        sched.step()
    assert opt.param_groups[0]["lr"] == pytest.approx((1 - 5 / 10) ** 0.9)


def test_poly_lr_warms_up_linearly_from_a_third():
    opt = torch.optim.SGD([torch.nn.Parameter(torch.zeros(()))], lr=1.0)
    sched = poly_lr(opt, total_steps=100, power=1.0, warmup_steps=10)
    assert opt.param_groups[0]["lr"] == pytest.approx(1 / 3)
    for _ in range(5):
        opt.step()
        sched.step()
    assert opt.param_groups[0]["lr"] == pytest.approx((1 / 3 + 2 / 3 * 0.5) * 0.95)
