"""BiFNet Tables IV-VI: each table's rows, paper numbers and recipe, every row's network, and Table IV end to end at
smoke scale (a sweep regenerating results/bifnet_table4.md in a temporary directory)."""

from __future__ import annotations

import pytest
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import OmegaConf
from test_cli import FIGURES, REPO, SERIAL, TINY, ablate, runs

from ablate.fusion.bidirectional import WithContext  # (importing ablate registers ${channels:...})
from ablate.tables.spec import sweep_params

TABLES = {
    "bifnet_table4": ["bifnet_image", "bifnet_bev", "bifnet_dst_sum", "bifnet_dst_cbf"],
    "bifnet_table5": ["bifnet_dst_sum", "bifnet_shpl_sum"],
    "bifnet_table6": ["bifnet_lidcamnet", "bifnet_lidcamnet_cbf", "bifnet_plard", "bifnet_plard_cbf"],
}


def config(*overrides: str, hydra: bool = False):
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        return compose("config", overrides=list(overrides), return_hydra_config=hydra)


@pytest.mark.parametrize("table", sorted(TABLES))
def test_each_table_sweeps_its_rows_with_the_papers_numbers(table):
    cfg = config(f"experiment={table}", hydra=True)
    assert [r["row"] for r in cfg.table.rows] == TABLES[table]
    assert sweep_params({}, [], cfg.table)["row"] == ",".join(TABLES[table])  # the sweep, from the rows
    assert all(r["paper"] for r in cfg.table.rows) and cfg.table.primary in cfg.table.metrics
    assert cfg.task._target_ == "ablate.tasks.road_bev.RoadTask" and cfg.model._target_.endswith("RoadNet")


def test_paper_numbers_are_the_papers():
    t4, t5, t6 = (config(f"experiment={t}").table.rows for t in sorted(TABLES))
    assert [r["paper"]["max_f"] for r in t4] == [93.01, 94.30, 95.57, 96.21]
    assert dict(t5[1]["paper"]) == {
        "cam_max_f": 92.87,
        "cam_ap": 93.53,
        "cam_pre": 91.85,
        "cam_rec": 93.75,
        "bev_max_f": 95.11,
        "bev_ap": 94.99,
        "bev_pre": 95.14,
        "bev_rec": 95.08,
    }
    assert [r["paper"]["ap"] for r in t6] == [93.29, 93.97, 94.52, 94.33]


@pytest.mark.parametrize("table,row", [(t, r) for t, rows in sorted(TABLES.items()) for r in rows])
def test_every_row_builds_its_network(table, row):
    cfg = config(f"experiment={table}", f"row={row}", "scale=smoke")
    model = instantiate(cfg.model)
    single = cfg.stage.name == "single"
    assert model.mode == ("single" if single else "perspective" if "dhi" in cfg.modalities else "bidirectional")
    if not single:
        assert model.space_name == (None if model.mode == "perspective" else "shpl" if "shpl" in row else "dst")
        ops = model.fusion_modules()
        plus_cbf = model.mode == "perspective" and row.endswith("_cbf")  # "+CBF": CBF's gains before the operator
        assert all(isinstance(op, WithContext) == plus_cbf for op in ops)
        assert {(op.op if plus_cbf else op).op_name for op in ops} == {cfg.fusion.name}


def test_experts_are_shared_by_dst_and_shpl_rows():
    from ablate.jobs.experts import expert_config
    from ablate.store import config_hash

    dst, shpl = (config("experiment=bifnet_table5", f"row={r}") for r in TABLES["bifnet_table5"])
    for m in ("rgb", "bev"):
        assert config_hash(expert_config(dst, m)) == config_hash(expert_config(shpl, m))


@pytest.mark.parametrize(
    "scale,lr,epochs,expert_epochs,freeze",
    [("smoke", 0.001, 1, None, True), ("cpu", 0.001, 3, 6, True), ("paper", 0.01, -1, None, False)],
)
def test_recipes(scale, lr, epochs, expert_epochs, freeze):
    cfg = config("experiment=bifnet_table4", f"scale={scale}")
    opt = cfg.task.optimizer
    assert (opt._target_, opt.lr, opt.weight_decay) == ("torch.optim.Adam", lr, 0.0001)
    assert cfg.task.scheduler.power == 1.0 and cfg.trainer.max_epochs == epochs  # linear decay (§V-B)
    assert cfg.experts.get("max_epochs") == expert_epochs and cfg.experts.freeze is freeze
    if scale == "paper":
        assert cfg.trainer.max_steps == 30000
    # §V-B's flip / translation / scaling at paper scale; below it the frozen experts' features are cached per frame
    augment = {"flip": 0.5, "scale": [1.0, 1.2]} if scale == "paper" else None
    assert OmegaConf.to_container(cfg.data).get("augment") == augment


def test_table4_end_to_end_at_smoke_scale(tmp_path):
    out = ablate(tmp_path, "-m", "experiment=bifnet_table4", SERIAL, *TINY, FIGURES)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    client, jobs = runs(tmp_path, "bifnet_table4")
    assert sorted(r.data.tags["row"] for r in jobs) == sorted(TABLES["bifnet_table4"])
    assert {r.info.status for r in jobs} == {"FINISHED"}
    _, experts = runs(tmp_path, "experts", kind="expert")
    assert sorted(r.data.tags["row"] for r in experts) == ["expert bev", "expert rgb"]  # trained once each
    by_row = {r.data.tags["row"]: r for r in jobs}
    fused = by_row["bifnet_dst_cbf"]
    for key in ("max_f", "ap", "pre", "rec", "cam_max_f", "bev_max_f", "latency_ms"):
        assert key in fused.data.metrics, key
    assert fused.data.metrics["max_f"] == fused.data.metrics["cam_max_f"]
    bev = by_row["bifnet_bev"].data.metrics
    assert bev["max_f"] == bev["bev_max_f"] and "cam_max_f" not in bev
    artifacts = {a.path for a in client.list_artifacts(fused.info.run_id)}
    assert {"config.yaml", "predictions.png", "gates.png"} <= artifacts
    text = (tmp_path / "results" / "bifnet_table4.md").read_text()
    rows = [line for line in text.split("All metrics:")[0].splitlines() if line.startswith("| ")][1:]
    assert [r.split("|")[1].strip() for r in rows] == [
        "Image",
        "LiDAR BEV",
        "Image + LiDAR BEV + DST (addition)",
        "Image + LiDAR BEV + DST + CBF",
    ]
    assert "MaxF (paper)" in text and "96.21" in text and "AP (paper)" in text and "PRE (ours)" in text
    # each job kept its test frames' level histograms (each branch's); the verdicts resample seeds and frames
    assert "frames/test_counts.csv" in {a.path for a in client.list_artifacts(fused.info.run_id, "frames")}
    assert (tmp_path / "results" / "runs" / "bifnet_table4.frames.csv.gz").is_file()
    assert "The verdicts and Δ read the interval over seeds and test frames" in text


@pytest.mark.parametrize(
    "overrides, option",
    [
        (["row=bifnet_shpl_sum", "+stage.spcae=dst"], "stage.spcae"),  # meant DST; would silently stay SHPL
        (["+stage.space=shpl"], "stage.space"),  # the SMoE fusion model has no space transform
    ],
)
def test_a_stage_option_the_model_does_not_read_is_refused_by_name(overrides, option):
    from omegaconf.errors import ValidationError

    from ablate.jobs.job import check_stage

    with pytest.raises(ValidationError, match=option):
        check_stage(config(*overrides))


@pytest.mark.parametrize("table", sorted(TABLES) + ["smoe_table1", "smoe_table2", "chinet_table2", "dgfn_table1"])
def test_every_row_of_the_tables_passes_the_stage_check(table):
    from ablate.jobs.job import check_stage

    for row in config(f"experiment={table}").table.rows:
        if not row.get("paper_only"):
            check_stage(config(f"experiment={table}", f"row={row.row}"))


def test_the_image_row_runs_on_a_real_kitti_road_frame(kitti_root, tmp_path):
    """The KITTI road layout (image_2, calib with Tr_cam_to_road, gt_image_2 in road colours), read in place: the
    sample has one frame and no scan, so it is each split (ImageSets) and only the image branch can run; a fused
    row fails on the missing scan, naming it, and is recorded FAILED."""
    root = tmp_path / "road" / "training"
    (root / "ImageSets").mkdir(parents=True)
    for sub in ("image_2", "calib", "gt_image_2"):
        (root / sub).symlink_to(kitti_root / "road" / "training" / sub)
    for split in ("train", "val", "test"):
        (root / "ImageSets" / f"{split}.txt").write_text("um_000000\n")
    camera_only = ["modalities=[rgb]", "targets=[free_space,road_valid,road_bev,road_bev_valid,calib]"]
    out = ablate(
        tmp_path,
        "experiment=bifnet_table4",
        "row=bifnet_image",
        "data=kitti",
        f"data.root={root.parent}",
        *camera_only,
        *TINY,
    )
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    _, (job,) = runs(tmp_path, "bifnet_table4")
    assert job.info.status == "FINISHED" and 0 <= job.data.metrics["max_f"] <= 100
    assert job.data.metrics["rec"] > 0  # the real frame's road, warped into the devkit's metric BEV, is scored
    fused = ablate(
        tmp_path, "experiment=bifnet_table4", "row=bifnet_dst_cbf", "data=kitti", f"data.root={root.parent}", *TINY
    )
    assert fused.returncode != 0 and "cannot provide 'bev': this data has no velodyne" in fused.stdout + fused.stderr
    _, jobs = runs(tmp_path, "bifnet_table4")
    assert {r.data.tags["row"]: r.info.status for r in jobs}["bifnet_dst_cbf"] == "FAILED"
