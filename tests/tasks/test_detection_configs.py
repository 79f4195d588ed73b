"""The DGFN configs: recipes per scale, the rows of Tables I and II, and Table II reusing Table I's DGFN runs."""

from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

from ablate.store import config_hash

CONF = Path(__file__).resolve().parents[2] / "conf"


def cfg(*overrides: str):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("config", overrides=list(overrides))


def test_paper_scale_is_dgfns_sgd_and_cpu_scale_a_documented_adam():
    paper = cfg("experiment=dgfn_table1", "row=dgfn", "scale=paper")
    opt = paper.task.optimizer
    assert (opt._target_, opt.lr, opt.momentum, opt.weight_decay) == ("torch.optim.SGD", 0.0003, 0.9, 0.0005)
    assert paper.data.batch_size == 2 and paper.trainer.max_steps == 240000 and paper.task.scheduler is None
    assert paper.model.width == 1.0 and list(paper.model.input_size) == [300, 300]
    cpu = cfg("experiment=dgfn_table1", "row=dgfn")
    assert cpu.task.optimizer._target_ == "torch.optim.Adam" and cpu.trainer.max_epochs == 6  # 678 updates
    assert cfg("experiment=dgfn_table1", "row=dgfn", "scale=smoke").trainer.max_epochs == 1


def test_table1_rows_differ_only_in_the_gates_and_train_with_the_five_corruptions():
    gfu, base = cfg("experiment=dgfn_table1", "row=dgfn"), cfg("experiment=dgfn_table1", "row=dgfn_baseline")
    assert gfu.model._target_ == "ablate.tasks.detection.DGFN" and gfu.fusion.name == base.fusion.name == "gfu"
    assert (gfu.fusion.gated, base.fusion.gated) == (True, False)
    assert gfu.model.l2norm_scale == base.model.l2norm_scale == 1.0  # before a GFU (ablate.tasks.ssd.model.DGFN)
    assert gfu.task.train_corruptions == base.task.train_corruptions and len(gfu.task.train_corruptions.choices) == 5
    assert list(gfu.task.eval_conditions) == [
        "normal",
        "camera_blank",
        "lidar_blank",
        "camera_occlusion",
        "lidar_occlusion",
        "camera_noise",
        "camera_illumination",
    ]
    assert gfu.task.eval_pooled == "full" and [c.condition for c in gfu.table.conditions][0] == "full"


def test_table2_reuses_table1s_dgfn_and_trains_plain_single_sensor_ssds():
    one, two = cfg("experiment=dgfn_table1", "row=dgfn", "seed=1"), cfg("experiment=dgfn_table2", "row=dgfn", "seed=1")
    assert config_hash(one) == config_hash(two)
    rgb = cfg("experiment=dgfn_table2", "row=ssd_rgb")
    assert (rgb.model.single, list(rgb.modalities), rgb.task.train_corruptions) == ("rgb", ["rgb"], None)
    assert cfg("experiment=dgfn_table2", "row=ssd_dhi").model.single == "dhi" and rgb.model.l2norm_scale == 20.0
    table = cfg("experiment=dgfn_table2").table
    assert table.layout == "rows" and table.primary_condition == "normal" and table.conditions is None
    assert [r.row for r in table.rows if r.get("paper_only")] == ["3dop", "mono3d", "deep_manta", "mv3d"]
    assert dict(table.metrics) == {"car_easy": "Easy", "car_moderate": "Moderate", "car_hard": "Hard"}


@pytest.mark.parametrize(
    "overrides", [["experiment=dgfn_table1", "row=dgfn"], ["task=detection", "model=fusion", "stage=late"]]
)
def test_the_detection_task_builds_on_dgfn_and_on_a_fusion_model(overrides):
    c = cfg(*overrides, "scale=smoke")
    task = instantiate(c.task, model=instantiate(c.model))
    assert task.num_classes == 3 and len(task.anchors.num_per_level) == len(task.model.out_channels["cls"])
