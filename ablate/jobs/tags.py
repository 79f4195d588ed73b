"""What a job's MLflow run records about it before it trains: its params (the resolved config, less what changes no
number, :func:`params_of`) and the tags its run starts with (what it is, its code, numerics and machine, its race,
tuning and sweep, :func:`run_tags`). The job (:mod:`ablate.jobs.job`) starts its run with them, and a run copied
from another table (:mod:`ablate.jobs.reuse`) is tagged with them as this table's.
"""

from __future__ import annotations

import json

from omegaconf import DictConfig, OmegaConf

from ablate import hardware
from ablate.jobs.spec import JobSpec, flatten_leaves
from ablate.store import UNHASHED, flatten, provenance_tags, tuned_key

#: Config keys that are not a job's params (the run's ``config.yaml`` artifact keeps the whole config): the table it
#: fills (its title, rows and the paper's numbers), the options that change no number (ablate.store.UNHASHED), the
#: metrics' labels, the scale's knobs and the task's modalities and targets (each already in the model's and the data's
#: own params, which they resolve into), the side-by-side timing's options, and a tuning trial's number and rung (tags)
#: and draws (applied over the config: their values are its params).
NOT_PARAMS = (
    *UNHASHED,
    "metrics",
    "primary",
    "modalities",
    "targets",
    "comp_time",
    "recipe",
    "trial",
    "rung",
    "draws",
)
#: Config keys of Hydra's instantiation or of display alone, in any group: not params either.
DISPLAY = ("._partial_", "trainer.enable_model_summary", "task.figure_frames")


def params_of(cfg: DictConfig) -> dict[str, str]:
    """A job's MLflow params: its resolved config, flattened, but :data:`NOT_PARAMS` (``scale.name`` kept) and
    :data:`DISPLAY`."""
    flat = flatten(OmegaConf.to_container(cfg, resolve=True))
    dropped = tuple(f"{k}." for k in NOT_PARAMS) + ("scale.",)
    kept = {k: v for k, v in flat.items() if k == "scale.name" or not (k + ".").startswith(dropped)}
    return {k: v for k, v in kept.items() if not k.endswith(DISPLAY)}


def run_tags(spec: JobSpec) -> dict[str, str]:
    """The tags a job's run starts with: what it is (kind, table, row, seed, config hash, scale), its code, its
    numerics and machine, the race it belongs to, and its sweep's parent run."""
    cfg = spec.cfg
    tags = {
        "kind": spec.kind,
        "table": spec.table,
        "row": spec.row,
        "seed": str(spec.seed),
        "config_hash": spec.config_hash,
        **provenance_tags(spec.context.launch_dir),
        "scale": cfg.scale.name,
        **hardware.tags(cfg),
    }
    if cfg.table.get("seeds"):  # the race this run belongs to: its table replays that race (ablate.tables.racing)
        tags["race_plan"] = json.dumps(OmegaConf.to_container(cfg.table.seeds, resolve=True), sort_keys=True)
    for key in ("trial", "tuned"):  # a tuning trial, or a raced job tuned to one (ablate.sweep.tuning)
        if cfg.get(key) is not None:
            tags |= {key: str(cfg[key]), f"{key}_config": tuned_values(cfg)}
    if cfg.get("trial") is not None:  # the search it is a draw of, for the table's footer (ablate.tables.tuning)
        tune = OmegaConf.to_container(cfg.table.get("tune") or {}, resolve=True)
        assert isinstance(tune, dict)
        tags["tune_search"] = json.dumps({"space": tune.get("space") or {}, "seed": tune.get("seed", 0)})
        if cfg.get("rung") is not None:  # a rung of successive halving short of the full budget (ablate.sweep.halving)
            tags["rung"] = f"{float(cfg.rung):.6g}"
    if spec.expert_hash is not None:  # an expert's trial: the expert it trains, which stage 2 takes from it
        tags["expert_hash"] = spec.expert_hash
    if spec.parent_run:
        tags.update({"mlflow.parentRunId": spec.parent_run, "sweep_id": spec.parent_run})
        tags["job_num"] = str(spec.context.job_num)
    return tags


def tuned_values(cfg: DictConfig) -> str:
    """The values in ``cfg`` of the parameters its table tunes (``table.tune.space``), as JSON: what a trial tried,
    or what a raced job was tuned to, with the values its experts were tuned to (``experts.<modality>.<key>``)."""
    space = (cfg.table.get("tune") or {}).get("space") or {}
    values = {str(k): OmegaConf.select(cfg, str(k)) for k in space}
    for modality, drawn in ((cfg.get("experts") or {}).get("draws") or {}).items():
        values |= {tuned_key(k, modality): v for k, v in flatten_leaves(OmegaConf.to_container(drawn))}
    return json.dumps(values, sort_keys=True, default=str)
