"""Tuning the experts' own recipe (ablate.sweep.tuning, ablate.jobs.experts): an expert trial is a validation-only
trial of the expert's config in its table, and a tuned expert's values reach its config, its hash and the raced
jobs' record of what they were tuned to."""

from __future__ import annotations

import json

import pandas as pd
from omegaconf import open_dict

from ablate.analysis.reproduce import tuned_config
from ablate.config import compose
from ablate.jobs.experts import expert_config, job_config
from ablate.jobs.spec import JobSpec
from ablate.jobs.tags import tuned_values
from ablate.store import KIND_TRIAL, SweepContext, config_hash

FUSED = ["experiment=bifnet_table4", "row=bifnet_dst_sum", "scale=cpu", "tune=lr_wd"]  # composed, never trained


def test_a_tuned_experts_values_reach_its_config_and_hash_and_the_other_expert_is_untouched(tmp_path) -> None:
    plain = compose(FUSED)
    tuned = compose([*FUSED, "++experts.draws.bev.task.optimizer.lr=0.0042"])
    assert expert_config(tuned, "bev").task.optimizer.lr == 0.0042
    assert expert_config(plain, "bev").task.optimizer.lr != 0.0042
    assert config_hash(expert_config(tuned, "bev")) != config_hash(expert_config(plain, "bev"))
    assert config_hash(expert_config(tuned, "rgb")) == config_hash(expert_config(plain, "rgb"))
    assert tuned.task.optimizer.lr == plain.task.optimizer.lr  # stage 2 keeps its own recipe
    # the expert's job hashes as what the plan and the diagnosis compute from expert_config (its draws applied once)
    job = JobSpec.of(expert_config(tuned, "bev"), SweepContext(launch_dir=tmp_path), "expert", "expert bev")
    assert job.config_hash == config_hash(expert_config(tuned, "bev")) and job.cfg.task.optimizer.lr == 0.0042
    values = json.loads(tuned_values(tuned))  # what a raced job records it was tuned to
    assert values["experts.bev.task.optimizer.lr"] == 0.0042 and "task.optimizer.lr" in values
    # ... and what the reproduction check reads back from it: the rerun's expert trains on the same value
    rerun = tuned_config(pd.DataFrame({"tuned_config": [tuned_values(tuned)]}), plain)
    assert rerun == ["++experts.draws.bev.task.optimizer.lr=0.0042"]


def test_an_expert_trial_is_a_validation_trial_of_the_experts_config_in_its_table(tmp_path) -> None:
    cfg = compose([*FUSED, "++experts.tune=rgb", "++draws.task.optimizer.lr=0.0031", "seed=1000", "trial=3"])
    trial, row = job_config(cfg)  # what the job runs (ablate.jobs.job.main)
    spec = JobSpec.of(trial, SweepContext(launch_dir=tmp_path), row=row)
    assert (spec.kind, spec.row, spec.table, spec.seed) == (KIND_TRIAL, "expert rgb", "bifnet_table4", 1000)
    assert spec.cfg.stage.name == "single" and spec.cfg.stage.modality == "rgb" and not spec.cfg.get("experts")
    assert spec.cfg.task.optimizer.lr == 0.0031 and spec.cfg.trial == 3
    assert spec.cfg.trainer.max_epochs == compose(FUSED).experts.max_epochs != compose(FUSED).trainer.max_epochs
    other = compose([*FUSED, "++experts.tune=rgb", "++draws.task.optimizer.lr=0.0017", "seed=1000", "trial=4"])
    assert JobSpec.of(job_config(other)[0], SweepContext(launch_dir=tmp_path)).config_hash != spec.config_hash
    with open_dict(cfg):
        cfg.trial = 3
    # the trial and the expert of the same values are different jobs: a trial never tests, an expert does
    expert = JobSpec.of(expert_config(cfg, "rgb"), SweepContext(launch_dir=tmp_path), "expert", "expert rgb")
    assert expert.config_hash != spec.config_hash
    # ... but the trial names the expert it trains: stage 2, once the trial is chosen, copies it instead of training
    chosen = compose([*FUSED, "++experts.draws.rgb.task.optimizer.lr=0.0031", "seed=1000"])
    stage2 = JobSpec.of(expert_config(chosen, "rgb"), SweepContext(launch_dir=tmp_path), "expert", "expert rgb")
    assert spec.expert_hash == stage2.config_hash != expert.config_hash and expert.expert_hash is None


def test_a_tables_n_is_its_familys_and_a_table_that_races_on_the_recipe_says_why() -> None:
    import pandas as pd

    from ablate.sweep.tuning import TuneSpec
    from ablate.tables.tuning import COLUMNS, section

    def spec(*overrides: str) -> TuneSpec | None:
        from omegaconf import OmegaConf

        return TuneSpec.from_config(OmegaConf.to_container(compose(list(overrides)).table.tune, resolve=True))

    assert spec("experiment=chinet_table2", "tune=lr_wd").trials == 6  # type: ignore[union-attr]
    assert spec("experiment=smoe_table1", "tune=lr_wd").trials == 4  # type: ignore[union-attr]
    assert spec("experiment=chinet_table2", "tune=lr_wd", "table.tune.trials=3").trials == 3  # type: ignore[union-attr]
    assert spec("fusion=sum", "tune=lr_wd").trials == 8  # type: ignore[union-attr]
    # halving is tune=lr_wd's default only where it was measured safe (docs/tuning.md): BiFNet IV, not ChiNet
    assert spec("experiment=bifnet_table4", "tune=lr_wd").halving is not None  # type: ignore[union-attr]
    assert spec("experiment=bifnet_table4", "tune=lr_wd", "table.tune.halving=null").halving is None  # type: ignore[union-attr]
    assert spec("experiment=chinet_table4", "tune=lr_wd").halving is None  # type: ignore[union-attr]
    none = pd.DataFrame(columns=COLUMNS)
    lines = section(none, compose(["experiment=dgfn_table2"]).table, {})
    assert lines[-1].startswith("No tuning phase: every row raced on the recipe, because its first look alone")
    assert section(none, compose(["experiment=chinet_table2"]).table, {}) == []
