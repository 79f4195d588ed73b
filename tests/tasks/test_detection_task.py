"""DetectionTask end to end on hand-made frames: an oracle model's boxes through decoding and KITTI AP per test
condition, the pooled "Full" result, and a small DGFN's GFU weights and figures."""

import functools

import lightning as L
import pytest
import torch
from torch import nn
from torch.utils.data import DataLoader

from ablate.data.datamodule import collate
from ablate.fusion import build
from ablate.tasks.boxes import box_iou, cxcywh_to_xyxy, encode
from ablate.tasks.detection import DGFN, DetectionTask, SSDHead

H, W = 64, 208
CONDITIONS = {
    "normal": {},
    "camera_blank": {"camera": "blank"},
    "lidar_blank": {"lidar": "blank"},
    "camera_occlusion": {"camera": "occlusion"},
}
SGD = functools.partial(torch.optim.SGD, lr=0.0)


def frame(i: int) -> dict:
    """8 easy Cars in a row (12 px tall: easy from 40 x 64 / 375 = 6.8 px), and a DontCare region."""
    cars = [[4.0 + 25 * k, 20, 24 + 25 * k, 32] for k in range(8)]
    return {
        "frame": f"{i:06d}",
        "rgb": torch.full((3, H, W), 0.5),
        "dhi": torch.full((3, H, W), 0.5),
        "boxes2d": {
            "boxes": torch.tensor(cars + [[0.0, 40, 60, 64]]),
            "labels": torch.tensor([0] * 8 + [5]),
            "difficulty": torch.tensor([0] * 8 + [-1]),
        },
    }


class Oracle(nn.Module):
    """Finds every ground-truth box exactly (its best default box, score 0.99+), unless the camera is blank."""

    modalities = {"rgb": 3, "dhi": 3}

    def __init__(self):
        super().__init__()
        self.head = SSDHead(8, num_levels=2, aspect_ratios=[[2], [2]])
        self.levels = [(8, 26), (4, 13)]
        self.weight = nn.Parameter(torch.zeros(()))

    def forward(self, batch: dict) -> dict:
        anchors = self.head.anchors((H, W), self.levels)
        n, a = anchors.shape[0], self.head.anchors.num_per_level
        cls = torch.zeros(len(batch["boxes2d"]), n, 4)
        cls[..., 0] = 10.0
        loc = torch.zeros(len(batch["boxes2d"]), n, 4)
        for b, t in enumerate(batch["boxes2d"]):
            if not batch["rgb"][b].any():
                continue
            real = t["labels"] < 3
            best = box_iou(t["boxes"][real], cxcywh_to_xyxy(anchors)).argmax(1)
            cls[b, best] = torch.tensor([0.0, 15, 0, 0])
            loc[b, best] = encode(t["boxes"][real], anchors[best])
        cls, loc = cls + self.weight, loc + self.weight

        def split(x, d):
            return [
                m.reshape(x.shape[0], hl, wl, -1).permute(0, 3, 1, 2)
                for m, (hl, wl) in zip(x.split([hl * wl * k for (hl, wl), k in zip(self.levels, a)], 1), self.levels)
            ]

        return {"cls": split(cls, 4), "box": split(loc, 4)}


def loader(n: int = 6) -> DataLoader:
    return DataLoader([frame(i) for i in range(n)], batch_size=3, collate_fn=collate)


def trainer(**kw) -> L.Trainer:
    return L.Trainer(
        logger=False, enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False, **kw
    )


def test_kitti_ap_per_condition_and_pooled_from_an_oracle():
    task = DetectionTask(Oracle(), SGD, eval_conditions=CONDITIONS, eval_pooled="full")
    (res,) = trainer().test(task, loader(), verbose=False)
    for condition in ("normal", "lidar_blank", "camera_occlusion"):  # 48 Cars found: 11-point AP is 100
        assert res[f"test/{condition}/car_easy"] == pytest.approx(100.0)
        assert res[f"test/{condition}/car_moderate_ap40"] == pytest.approx(100.0)
    assert res["test/camera_blank/car_easy"] == 0.0 and res["test/camera_blank/ap11"] == 0.0
    # Full: 192 Cars, 144 found, no false positive: precision 1 up to recall 0.75, then 0
    assert res["test/full/car_hard"] == pytest.approx(100 * 8 / 11, abs=1e-3)
    assert res["test/full/car_hard_ap40"] == pytest.approx(75.0, abs=1e-3)
    assert res["test/normal/pedestrian_easy"] != res["test/normal/pedestrian_easy"]  # no Pedestrian: NaN
    assert not any(k.startswith("test/normal/gate") for k in res)  # no fusion, no gates


def small_dgfn(gated: bool = True) -> DGFN:
    torch.manual_seed(0)
    return DGFN(
        {"rgb": 3, "dhi": 3},
        functools.partial(SSDHead, num_classes=3),
        functools.partial(build, "gfu", gated=gated),
        width=0.0625,
        input_size=(272, 272),
    )


def test_dgfn_trains_tests_under_conditions_and_logs_its_gates():
    task = DetectionTask(
        small_dgfn(),
        functools.partial(torch.optim.Adam, lr=1e-3),
        eval_conditions=CONDITIONS,
        eval_pooled="full",
        train_corruptions={"choices": [{}, {"camera": "noise"}]},
    )
    trainer(max_steps=2, limit_val_batches=1).fit(task, loader(), loader(3))
    (res,) = trainer().test(task, loader(3), verbose=False)
    gates = {c: (res[f"test/{c}/gate_rgb"], res[f"test/{c}/gate_dhi"]) for c in [*CONDITIONS, "full"]}
    assert all(0 < g < 1 for pair in gates.values() for g in pair)
    assert gates["camera_blank"][0] != gates["normal"][0]  # the weights depend on the input
    assert gates["full"][0] == pytest.approx(sum(gates[c][0] for c in CONDITIONS) / 4, rel=1e-4)
    b = next(iter(loader(3)))
    fig = task.gate_figure(b)
    assert fig is not None and len(fig.axes) == 4 * len(CONDITIONS) + 1  # 4 panels per condition + colour bar
    assert [ax.get_title() for ax in fig.axes[0:8:4]] == ["rgb (normal)", "rgb (camera_blank)"]  # a row each
    assert task.figure(b) is not None
    baseline = DetectionTask(small_dgfn(gated=False), SGD, eval_conditions=CONDITIONS)
    (res,) = trainer().test(baseline, loader(3), verbose=False)
    assert res["test/camera_blank/gate_rgb"] == 1.0 and baseline.gate_figure(b) is None  # weights fixed to one


def test_bad_task_options_name_the_option():
    with pytest.raises(ValueError, match=r"task.decode: unknown option\(s\) \['nms'\]"):
        DetectionTask(Oracle(), SGD, decode={"nms": 0.5})
    with pytest.raises(ValueError, match=r"task.classes: \['Truck'\]"):
        DetectionTask(Oracle(), SGD, classes=["Car", "Truck"])
    with pytest.raises(ValueError, match="DetectionTask needs a detection head"):
        DetectionTask(nn.Linear(1, 1), SGD)
