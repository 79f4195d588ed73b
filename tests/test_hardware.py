"""Numerics resolved per machine (ablate.hardware): precision, memory format and threads, in the config hash."""

import warnings
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

from ablate.hardware import Cpu, cpu, parallel_jobs, resolve, tags
from ablate.store import config_hash
from ablate.tasks.base import to_float32

CONF = Path(__file__).resolve().parents[1] / "conf"
XEON = Cpu("Intel(R) Xeon(R) Platinum 8488C", frozenset({"avx2", "avx512f", "avx512_bf16", "amx_tile", "amx_bf16"}))
EPYC = Cpu("AMD EPYC", frozenset({"avx2", "fma"}))


def job(*overrides: str):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("config", overrides=["experiment=chinet_table2", "row=chinet", *overrides])


def test_the_cpu_is_read_from_this_machine():
    here = cpu()
    assert here.model and isinstance(here.flags, frozenset)
    assert here.has_bf16 == bool({"amx_bf16", "avx512_bf16"} & here.flags)


def test_auto_is_fp32_nchw_on_a_cpu_without_bf16():
    cfg = job("recipe.bf16=true")
    why = resolve(cfg, EPYC)
    assert (cfg.trainer.precision, cfg.trainer.channels_last) == ("32-true", False)
    assert "no bf16 in hardware" in why and "avx2" in why


def test_auto_is_bf16_channels_last_on_a_cpu_with_bf16_where_the_familys_parity_is_measured():
    cfg = job("recipe.bf16=true")
    why = resolve(cfg, XEON)
    assert (cfg.trainer.precision, cfg.trainer.channels_last) == ("bf16-mixed", True)
    assert "amx_bf16" in why


def test_auto_stays_fp32_for_a_family_whose_recipe_keeps_it():
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("config", overrides=["experiment=bifnet_table4", "row=bifnet_dst_cbf"])
    assert cfg.recipe.bf16 is False  # conf/recipe/road_cpu.yaml: not measured
    why = resolve(cfg, XEON)
    assert cfg.trainer.precision == "32-true" and "recipe keeps fp32" in why


@pytest.mark.parametrize("machine, bf16, budget", [(XEON, "true", 60.0), (XEON, "false", 120.0), (EPYC, "true", 120.0)])
def test_a_tables_race_gets_half_the_wall_time_where_its_jobs_train_in_bf16(monkeypatch, machine, bf16, budget):
    monkeypatch.setattr("ablate.hardware.cpu", lambda: machine)
    cfg = job(f"recipe.bf16={bf16}")
    assert cfg.table.seeds.budget_min == budget
    assert job(f"recipe.bf16={bf16}", "trainer.precision=bf16-mixed").table.seeds.budget_min == 60.0


def test_the_gpu_trainers_use_bf16():
    for trainer in ("gpu", "ddp_gpu"):
        cfg = job(f"trainer={trainer}")
        assert cfg.trainer.precision == "bf16-mixed"
        resolve(cfg, EPYC)  # the CPU does not matter there, and no warning is due
        assert cfg.trainer.precision == "bf16-mixed" and cfg.trainer.channels_last is True


def test_an_explicit_bf16_on_a_cpu_without_it_warns_that_it_is_far_slower():
    cfg = job("trainer.precision=bf16-mixed")
    with pytest.warns(UserWarning, match="far slower"):
        resolve(cfg, EPYC)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        resolve(job("trainer.precision=bf16-mixed"), XEON)


def test_the_resolved_precision_and_the_threads_are_in_the_config_hash():
    fp32, bf16 = job("recipe.bf16=true"), job("recipe.bf16=true")
    resolve(fp32, EPYC), resolve(bf16, XEON)
    assert config_hash(fp32) != config_hash(bf16)
    explicit = job("recipe.bf16=true", "trainer.precision=32-true", "trainer.channels_last=false")
    resolve(explicit, XEON)
    assert config_hash(explicit) == config_hash(fp32)  # auto is hashed as what it resolved to
    one, two = job("trainer.threads=1"), job("trainer.threads=2")
    resolve(one, EPYC), resolve(two, EPYC)
    assert config_hash(one) != config_hash(two)
    assert "auto" not in (fp32.trainer.precision, fp32.trainer.channels_last)


def test_the_runs_tags_name_the_numerics_and_the_cpu():
    cfg = job("trainer.threads=2")
    resolve(cfg, EPYC)
    found = tags(cfg)
    assert found["precision"] in ("32-true", "bf16-mixed") and found["threads"] == "2"
    assert found["cpu"] == cpu().model and found["cpu_isa"]


def test_a_sweep_runs_one_job_per_core_with_one_thread_per_job(monkeypatch):
    monkeypatch.setattr("ablate.hardware.cores", lambda: 8)
    assert (parallel_jobs(1), parallel_jobs(2), parallel_jobs(3), parallel_jobs(None), parallel_jobs(16)) == (
        8,
        4,
        2,
        1,
        1,
    )
    assert (parallel_jobs(1, 2), parallel_jobs(1, -1), parallel_jobs(1, "auto"), parallel_jobs(1, 1, "gpu")) == (
        4,
        1,
        1,
        1,
    )
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        hydra = compose("config", overrides=["trainer.threads=4"], return_hydra_config=True).hydra
    assert hydra.launcher._target_.endswith("JoblibLauncher") and hydra.launcher.n_jobs == 2


def test_model_outputs_reach_losses_and_metrics_in_fp32():
    out = to_float32(
        {
            "a": torch.ones(2, dtype=torch.bfloat16),
            "b": [torch.ones(1, dtype=torch.float16)],
            "c": torch.ones(1, dtype=torch.long),
            "d": (torch.zeros(1, dtype=torch.bfloat16),),
        }
    )
    assert out["a"].dtype == out["b"][0].dtype == out["d"][0].dtype == torch.float32
    assert out["c"].dtype == torch.long


def test_a_config_hashes_as_its_numerics_resolve_on_this_machine():
    """A config composed afresh (diagnose, latency, the report) finds the runs its jobs made: ``auto`` hashes as
    what a job resolves it to here."""
    fresh, job_cfg = job(), job()
    resolve(job_cfg)
    assert fresh.trainer.precision == "auto" and config_hash(fresh) == config_hash(job_cfg)
    assert fresh.trainer.precision == "auto"  # hashing leaves the config as it was


@pytest.mark.parametrize(
    "override, named",
    [
        ("trainer.threads=0", "trainer.threads=0"),
        ("trainer.threads=two", "trainer.threads='two'"),
        ("trainer.channels_last=maybe", "trainer.channels_last='maybe'"),
    ],
)
def test_a_bad_numerics_option_is_one_error_naming_it(override, named):
    from omegaconf.errors import ValidationError

    with pytest.raises(ValidationError, match=named.replace(".", r"\.")):
        resolve(job(override), EPYC)


def test_loader_workers_are_the_cores_up_to_a_bound(monkeypatch):
    from ablate import hardware

    monkeypatch.setattr(hardware, "cores", lambda: 2)
    assert (hardware.loader_workers(8), hardware.loader_workers(1)) == (2, 1)
    monkeypatch.setattr(hardware, "cores", lambda: 64)
    assert hardware.loader_workers(8) == 8
