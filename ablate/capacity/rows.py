"""The rows of the paper check (:mod:`ablate.capacity.check`) and what each trains at ``scale=paper``.

Every row of every table (``conf/experiment/*.yaml``) has a job config (:func:`ablate.config.compose` of
``experiment=<table> row=<row> scale=paper``) and a config its training runs (:func:`measured_config`: for a
single-modal row of a two-stage table, SMoE §4.3 and BiFNet §V-B, the expert's, which that row is). What it trains
(:func:`measure_key`: model, task, data module, the experts' freezing) names its measurement, so rows of several
tables with one model, task and data share one. :func:`recipe` reads the row's training from its config: batch,
optimiser steps (``trainer.max_steps`` where the recipe sets it, else ``max_epochs`` x the batches of an epoch, as
Lightning bounds them; the experts' with ``experts.max_steps`` / ``max_epochs``), frames and seeds.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable
from typing import Any, cast

from omegaconf import DictConfig, OmegaConf

from ablate.config import compose
from ablate.jobs.experts import expert_config, needed
from ablate.tables.published import experiments
from ablate.tables.raceplan import RacePlan
from ablate.tables.spec import run_rows


def table_rows(experiment: str) -> list[str]:
    """The rows a table runs (its ``table.rows`` but those it only quotes, ``paper_only``)."""
    return run_rows(compose([f"experiment={experiment}", "scale=paper"]).table)


def job_config(experiment: str, row: str, overrides: Iterable[str] = ()) -> DictConfig:
    """The job config of ``row`` of table ``experiment`` at ``scale=paper``."""
    return compose([f"experiment={experiment}", f"row={row}", "scale=paper", *overrides])


def measured_config(experiment: str, row: str, expert: str | None = None, overrides: Iterable[str] = ()) -> DictConfig:
    """The config a row's training runs: its job config; for a single-modal row of a two-stage table, and for an
    ``expert`` of a fused row, the expert's (:func:`ablate.jobs.experts.expert_config`: the job that trains it)."""
    cfg = job_config(experiment, row, overrides)
    if expert is None and cfg.get("experts") and cfg.stage.name == "single":
        expert = str(cfg.stage.modality)
    return expert_config(cfg, expert) if expert is not None else cfg


def needed_experts(cfg: DictConfig) -> list[str]:
    """The modalities whose trained experts a row's fused model starts from (none for a row without two-stage
    training, an early fusion, or a single-modal row, which is itself an expert)."""
    return needed(cfg) if cfg.get("experts") and cfg.stage.name != "single" else []


def first_seeds(cfg: DictConfig) -> int:
    """The seeds every row of the table trains (the first look of its race, ``table.seeds``); 1 without a race."""
    plan = RacePlan.of_table(cfg)
    return plan.first if plan is not None else 1


def measure_key(cfg: DictConfig) -> str:
    """What a measurement depends on: the resolved model, task, modalities, targets, data module (but the frames'
    count, the batch, the loader's workers and memo, and the training frames' order, ``data.order_seed``, which is
    the job's seed) and the experts' freezing; rows of several tables with the same share a measurement."""
    data = cast("dict[str, Any]", OmegaConf.to_container(cfg, resolve=True))
    unmeasured = ("batch_size", "num_workers", "memo_gb", "data_dir", "order_seed")
    datamodule = {k: v for k, v in data["data"].items() if k not in unmeasured}
    datamodule["synth"] = {k: v for k, v in (datamodule.get("synth") or {}).items() if k != "frames"}
    experts = data.get("experts") or {}
    key = {
        "model": data["model"],
        "task": data["task"],
        "data": datamodule,
        "freeze": experts.get("freeze") if needed_experts(cfg) else None,
    }
    return json.dumps(key, sort_keys=True, default=str)


def recipe(cfg: DictConfig, train_frames: int | None = None) -> dict[str, Any]:
    """The row's training at the paper's sizes: batch, optimiser steps, frames trained on and seeds, for its own
    training and (two-stage rows) each expert's. ``train_frames``: the training split (60 % of ``data.synth``'s
    frames, as the generated dataset's split; 4489 on KITTI's 7481). ``fit_frames``: the training and the validation
    split (20 % of the frames; 5985 of KITTI's 7481), the frames whose frozen features a feature cache would hold;
    ``cache_max_bytes``: its cap (``experts.cache_max_gb``); ``frozen``: whether the row trains on frozen experts."""
    synth = cfg.data.get("synth") or {}
    total = int(synth.get("frames", 7481))
    frames = train_frames or int(round(0.6 * total))
    batch = int(cfg.data.batch_size)

    def steps(max_steps: Any, epochs: Any) -> int:
        """The optimiser steps a trainer takes, as Lightning bounds them (``Trainer.estimated_stepping_batches``):
        the fewer of ``max_steps`` and ``max_epochs`` x the batches of an epoch, -1 bounding nothing."""
        bounds = [int(max_steps)] if max_steps is not None and int(max_steps) >= 0 else []
        if epochs is not None and int(epochs) >= 0:
            bounds.append(int(epochs) * math.ceil(frames / batch))
        if not bounds:
            raise ValueError(f"neither max_steps ({max_steps}) nor max_epochs ({epochs}) bounds the training")
        return min(bounds)

    trainer, experts = cfg.trainer, cfg.get("experts") or {}
    own = steps(trainer.get("max_steps"), trainer.get("max_epochs"))
    # the experts' trainer as ablate.jobs.experts.expert_config makes it: the job's, with experts.max_epochs and
    # experts.max_steps where the recipe or the row sets them (SMoE at scale=paper: 80k steps each stage, §4.3)
    expert_steps = steps(
        _set_or(experts.get("max_steps"), trainer.get("max_steps")),
        _set_or(experts.get("max_epochs"), trainer.get("max_epochs")),
    )
    single = cfg.get("experts") and cfg.stage.name == "single"
    cache_gb = experts.get("cache_max_gb")
    return {
        "batch": batch,
        "train_frames": frames,
        "fit_frames": frames + int(round(0.2 * total)),
        "frozen": bool(needed_experts(cfg)) and bool(experts.get("freeze", True)),
        "cache_max_bytes": None if cache_gb is None else float(cache_gb) * 2**30,
        "steps": expert_steps if single else own,
        "expert_steps": expert_steps,
        "seeds": first_seeds(cfg),
        "optimizer": str(cfg.task.optimizer._target_).rsplit(".", 1)[-1],
    }


def _set_or(value: Any, default: Any) -> Any:
    return default if value is None else value


def family(cfg: DictConfig) -> str:
    """The task family of a job config (instance: SMoE, detection: DGFN, semantic: ChiNet, road: BiFNet)."""
    return str(cfg.task._target_).rsplit(".", 1)[-1].replace("Task", "").lower()


def plan(chosen_experiments: list[str] | None = None, chosen_rows: list[str] | None = None) -> list[tuple[str, str]]:
    """(table, row) of every row of the chosen tables (all by default), limited to ``chosen_rows``."""
    out = []
    for experiment in chosen_experiments or experiments():
        for row in table_rows(experiment):
            if not chosen_rows or row in chosen_rows:
                out.append((experiment, row))
    return out


def describe(pairs: Iterable[tuple[str, str]], overrides: Iterable[str] = ()) -> list[dict[str, Any]]:
    """Per (table, row): its family, recipe (:func:`recipe`), the key of what it trains (:func:`measure_key` of
    :func:`measured_config`) and the keys of the experts it starts from, with how to measure each (``specs``:
    key -> (table, row, expert modality or None))."""
    entries = []
    for experiment, row in pairs:
        cfg = job_config(experiment, row, overrides)
        trains = measured_config(experiment, row, overrides=overrides)
        experts = {m: measure_key(expert_config(cfg, m)) for m in needed_experts(cfg)}
        entries.append(
            {
                "table": experiment,
                "row": row,
                "family": family(cfg),
                "key": measure_key(trains),
                "spec": [experiment, row, None],
                "experts": experts,
                "expert_specs": {m: [experiment, row, m] for m in experts},
                **recipe(trains),
                # the row's race, also where what it trains is an expert's config (which races nothing itself)
                "seeds": first_seeds(cfg),
                "expert_steps": recipe(cfg)["expert_steps"],
            }
        )
    return entries


def order(entries: list[dict[str, Any]]) -> list[tuple[str, list]]:
    """Every distinct measurement of ``entries`` (rows and the experts they start from) once, as (key, spec): the
    first row of each task family first, then the others in table order, each row's experts before it."""
    firsts: list[tuple[str, Any]] = []
    rest: list[tuple[str, Any]] = []
    seen: set[str] = set()
    families: set[str] = set()
    for e in entries:
        items = [(k, e["expert_specs"][m]) for m, k in e["experts"].items()] + [(e["key"], e["spec"])]
        target = firsts if e["family"] not in families else rest
        families.add(e["family"])
        for key, spec in items:
            if key not in seen:
                seen.add(key)
                target.append((key, spec))
    return firsts + rest
