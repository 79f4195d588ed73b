"""A job's identity, owned in one place: its table, row, seed, config hash, checkpoint directory and outbox, and the
sweep it belongs to (:class:`JobSpec`, built once per job from the composed config and the
:class:`~ablate.store.SweepContext` read at the job's start).

The job (:mod:`ablate.jobs.job`), the experts (:mod:`ablate.jobs.experts`), latency, the diagnosis and the
reproduction check take paths and names from here; the racing sweeper names rows with the same function
(:func:`ablate.store.row_name`) as the job.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf, open_dict

from ablate import hardware
from ablate.jobs.rungs import checkpoint_config
from ablate.store import KIND_JOB, KIND_TRIAL, Outbox, SweepContext, config_hash, row_name
from ablate.store.outbox import FILE as OUTBOX_FILE

#: Where jobs keep their checkpoints, relative to the launch directory (a job runs there).
CHECKPOINTS = Path("checkpoints")


def apply_draws(cfg: DictConfig) -> None:
    """Apply a tuning trial's draws (``draws``: the config's own keys, nested, set by the racing sweeper,
    :mod:`ablate.sweep.tuning`) over ``cfg``, in place; ``draws`` stays, so that the config hash tells trials apart.
    A key the config lacks (a weight decay the recipe's optimiser does not set) is added."""
    draws = cfg.get("draws")
    if not draws:
        return
    with open_dict(cfg):
        for key, value in flatten_leaves(OmegaConf.to_container(draws, resolve=True)):
            OmegaConf.update(cfg, key, value, force_add=True)


def flatten_leaves(tree: Any, prefix: str = "") -> list[tuple[str, Any]]:
    """(dotted key, value) of every leaf of nested dicts."""
    if not isinstance(tree, dict):
        return [(prefix, tree)]
    return [leaf for k, v in tree.items() for leaf in flatten_leaves(v, f"{prefix}.{k}" if prefix else str(k))]


def checkpoint_dir(table: str, chash: str) -> Path:
    """The folder of a job's checkpoints and outbox: ``checkpoints/<table>/<config hash>``."""
    return CHECKPOINTS / table / chash


def best_checkpoint(table: str, chash: str) -> Path:
    """A job's best checkpoint (the one it was tested from)."""
    return checkpoint_dir(table, chash) / "best.ckpt"


def job_kind(cfg: DictConfig) -> str:
    """The run kind of job config ``cfg``: a tuning trial where it has a ``trial`` (``table.tune``), else a job."""
    return KIND_TRIAL if cfg.get("trial") is not None else KIND_JOB


def resolved_config(cfg: DictConfig) -> tuple[DictConfig, str, DictConfig | None]:
    """A job's config as it runs and as its config hash holds it: a copy of ``cfg`` with its numerics resolved for
    this machine (:func:`ablate.hardware.resolve`) and a tuning trial's draws applied (:func:`apply_draws`); the
    sentence saying why those numerics; and the config before the draws (None without any). The job
    (:meth:`JobSpec.of`) and the sweep's plan (:mod:`ablate.sweep.plan`, which finds the jobs already done by
    their hashes) both take it from here."""
    resolved = copy.deepcopy(cfg)
    numerics = hardware.resolve(resolved)
    base = copy.deepcopy(resolved) if resolved.get("draws") else None
    apply_draws(resolved)
    return resolved, numerics, base


@dataclass(frozen=True)
class JobSpec:
    """One job: ``cfg`` is its config with the numerics resolved for this machine (a copy: ``trainer.precision`` and
    ``channels_last`` are ``auto`` no longer, :func:`ablate.hardware.resolve`), which is what its config hash holds;
    ``numerics`` says why, in one sentence; ``kind`` is ``job`` or ``expert``; ``context`` is where it runs;
    ``outbox`` keeps the metrics and the ends of its runs while the server does not answer, beside its checkpoints."""

    cfg: DictConfig
    numerics: str
    kind: str
    row: str
    config_hash: str
    context: SweepContext
    outbox: Outbox = field(compare=False)  # one instance per job: it keeps what it has read of its file
    base: DictConfig | None = field(default=None, compare=False)  # the config before its draws (table.tune)

    @classmethod
    def of(cls, cfg: DictConfig, context: SweepContext, kind: str | None = None, row: str | None = None) -> JobSpec:
        """The spec of job config ``cfg`` in ``context``; ``row`` names it where the caller knows better than the
        overrides (an expert)."""
        kind = kind or job_kind(cfg)
        resolved, numerics, base = resolved_config(cfg)
        name = row or row_name(context.overrides, context.swept, context.row_choice)
        chash = config_hash(resolved)
        outbox = Outbox(
            checkpoint_dir(str(resolved.table.name), config_hash(checkpoint_config(resolved))) / OUTBOX_FILE
        )
        return cls(resolved, numerics, kind, name, chash, context, outbox, base)

    @property
    def experts_cfg(self) -> DictConfig:
        """The config the job's experts are derived from (:func:`ablate.jobs.experts.expert_config`): its own,
        without a tuning trial's draws, so that every trial of a row on experts shares them."""
        return self.base if self.base is not None else self.cfg

    @property
    def expert_hash(self) -> str | None:
        """For a tuning trial of a single-modal config (an expert's trial, :func:`ablate.jobs.experts.trial_config`):
        the config hash of the expert it trains, its config without the trial's number. Stage 2's trials (at the
        trials' seed) ask for that expert once the trial is chosen, and take it from the trial
        (:func:`ablate.jobs.reuse.reuse`) instead of training it again. None for any other job."""
        if self.kind != KIND_TRIAL or self.cfg.stage.name != "single":
            return None
        expert = copy.deepcopy(self.cfg)
        with open_dict(expert):
            expert.trial = None
        return config_hash(expert)

    @property
    def table(self) -> str:
        return str(self.cfg.table.name)

    @property
    def seed(self) -> int:
        return int(self.cfg.seed)

    @property
    def ckpt_dir(self) -> Path:
        """``checkpoints/<table>/<config hash>``; a tuning trial's at every rung of successive halving (the hash of
        its config without the rung, :func:`ablate.jobs.rungs.checkpoint_config`), so that a promoted trial resumes."""
        return self.outbox.path.parent

    @property
    def parent_run(self) -> str | None:
        """The sweep's run this job's run is a child of (an expert's run is not: it serves several sweeps)."""
        return self.context.parent_run if self.kind in (KIND_JOB, KIND_TRIAL) else None

    @property
    def note_name(self) -> str:
        """The name of this job's failure note in its sweep directory."""
        return f"{self.context.job_num}_{self.row.replace(' ', '_').replace('/', '-')}"
