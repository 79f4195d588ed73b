"""ablate.diagnose: which objects each expert finds, their union, and the room fusion has over the better one."""

import numpy as np
import pandas as pd
import pytest
import torch

from ablate.tasks.yolact.diagnose import found_objects
from ablate.tasks.yolact.diagnosis_report import checks, recall_table


def _mask(h, w, y0, y1, x0, x1):
    m = torch.zeros(h, w, dtype=torch.bool)
    m[y0:y1, x0:x1] = True
    return m


def test_an_object_is_found_by_a_same_class_detection_with_mask_iou_at_least_half():
    h, w = 375, 100
    target = {
        "masks": torch.stack([_mask(h, w, 0, 40, 0, 20), _mask(h, w, 100, 120, 0, 20), _mask(h, w, 200, 240, 50, 70)]),
        "labels": torch.tensor([0, 0, 1]),
        "boxes": torch.tensor([[0, 0, 20, 40], [0, 100, 20, 120], [50, 200, 70, 240]], dtype=torch.float),
    }
    pred = {
        "masks": torch.stack(
            [
                _mask(h, w, 0, 30, 0, 20),  # IoU 0.75 with object 0, same class
                _mask(h, w, 100, 120, 0, 20),  # exact on object 1, but it is only 20 px tall
                _mask(h, w, 200, 240, 50, 70),
            ]
        ),  # exact on object 2, wrong class
        "labels": torch.tensor([0, 0, 0]),
        "scores": torch.tensor([0.9, 0.8, 0.7]),
    }
    counted, found = found_objects(pred, target, height=h)
    assert counted.tolist() == [True, False, True]
    assert found.tolist() == [True, True, False]
    # the height threshold scales with the image: at 187 px, 25 px becomes 12.5 px, so object 1 counts
    counted, _ = found_objects(pred, target, height=187)
    assert counted.tolist() == [True, True, True]


def test_an_iou_just_below_half_is_a_miss():
    h, w = 100, 100
    target = {"masks": _mask(h, w, 0, 40, 0, 10)[None], "labels": torch.tensor([1])}
    pred = {
        "masks": _mask(h, w, 0, 40, 0, 5)[None] | _mask(h, w, 0, 1, 90, 91)[None],
        "labels": torch.tensor([1]),
        "scores": torch.tensor([0.9]),
    }
    # intersection 200, union 401: IoU 0.4988
    assert found_objects(pred, target, height=h)[1].tolist() == [False]


def test_recall_table_has_experts_union_and_rgb_only_per_condition():
    rows = []
    # seed 0, night: 3 objects; RGB finds object 0, DDM finds 1 and 2 -> union 100 %, RGB only 33.3 %
    for obj, (rgb, ddm, fused) in enumerate([(True, False, True), (False, True, True), (False, True, False)]):
        for row, modality, found in (("smoe_rgb", "rgb", rgb), ("smoe_ddm", "ddm_jet", ddm), ("smoe_fpn", None, fused)):
            rows.append(
                {
                    "seed": 0,
                    "group": "night",
                    "image": 0,
                    "object": obj,
                    "found": found,
                    "row": row,
                    "name": row,
                    "modality_row": modality,
                }
            )
    # seed 0, clear: 1 object found by DDM only
    for row, modality, found in (("smoe_rgb", "rgb", False), ("smoe_ddm", "ddm_jet", True), ("smoe_fpn", None, True)):
        rows.append(
            {
                "seed": 0,
                "group": "clear",
                "image": 1,
                "object": 0,
                "found": found,
                "row": row,
                "name": row,
                "modality_row": modality,
            }
        )
    table = recall_table(pd.DataFrame(rows))
    assert list(table.index) == ["clear", "night", "all"]
    night = table.loc["night"]
    assert night[("smoe_rgb", "mean")] == pytest.approx(100 / 3)
    assert night[("smoe_ddm", "mean")] == pytest.approx(200 / 3)
    assert night[("RGB ∪ DDM", "mean")] == pytest.approx(100)
    assert night[("RGB only", "mean")] == pytest.approx(100 / 3)
    assert night[("objects", "mean")] == 3
    assert table.loc["all", ("smoe_fpn", "mean")] == pytest.approx(75)
    assert table.loc["all", ("RGB ∪ DDM", "mean")] == pytest.approx(100)
    assert np.isnan(table.loc["all", ("smoe_fpn", "std")])  # one seed: no spread
    assert night[("DDM only", "mean")] == pytest.approx(200 / 3)  # objects 1 and 2


def test_data_checks_on_hand_made_experts():
    objects = []
    # 10 objects, one seed: RGB finds 0-5, DDM finds 4-9 -> RGB only 40 %, DDM only 40 %, union 100 vs 60
    for obj in range(10):
        for row, modality, found in (("smoe_rgb", "rgb", obj < 6), ("smoe_ddm", "ddm_jet", obj >= 4)):
            objects.append(
                {
                    "seed": 0,
                    "group": "clear",
                    "image": obj,
                    "object": 0,
                    "found": found,
                    "row": row,
                    "name": row,
                    "modality_row": modality,
                }
            )
    ap = {"rgb": {"clear": 18.0, "night": 9.0, "glare": 16.0}, "ddm_jet": {"clear": 30.0, "night": 30.0, "glare": 30.0}}
    conditions = pd.DataFrame(
        [{"seed": 0, "modality": m, "condition": c, "map": v} for m, per in ap.items() for c, v in per.items()]
    )
    got = checks({"objects": pd.DataFrame(objects), "conditions": conditions}).set_index("check")
    assert got.loc["RGB AP in clear weather / DDM AP in clear weather", "value"] == pytest.approx(0.6)
    assert got.loc["found by RGB only (%)", "value"] == pytest.approx(40)
    assert got.loc["found by DDM only (%)", "value"] == pytest.approx(40)
    assert got.loc["union minus the better expert (recall points)", "value"] == pytest.approx(40)
    assert got.loc["RGB AP drop at night (%)", "value"] == pytest.approx(50)
    glare = got.loc["RGB AP drop in glare (%)"]
    assert glare["value"] == pytest.approx(100 / 9) and not glare["passes"]  # 11 % < 20 %: not a clear drop
    assert got.loc["DDM AP change at night or in glare (%, at most)", "passes"]
    assert got["passes"].sum() == 6
