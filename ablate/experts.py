"""Two-stage training, SMoE §4.3: single-modal experts first, then the fusion network on top of them, frozen.

Stage 1 trains one expert per modality: the job's own config with stage ``single`` on that modality, no fusion
operator and no ``experts`` key. That config's hash names the expert, so it is trained once per (modality, seed,
scale, data, backbone, head, trainer) and tracked as a run of the MLflow experiment ``experts`` (tag
``kind=expert``); its best checkpoint lives in ``checkpoints/experts/<hash>/``. Every stage-2 job that needs it
reuses it; a file lock keeps two parallel jobs from training the same expert twice.

Stage 2 copies the experts into the fusion model (``FusionModel.load_expert``: encoders, plus FPNs at stage fpn,
plus heads at stage late), freezes them (``experts.freeze``) and trains the rest: gates, fusion operators, and the
parts after the fusion point. Stage ``early`` has no per-modality part and trains end to end. A single-modal job
is itself an expert: it is tested from the expert's checkpoint and not trained again.
"""
from __future__ import annotations

import fcntl
import logging
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf, open_dict

from ablate.tracking import Tracker, config_hash

log = logging.getLogger(__name__)
EXPERTS_TABLE = "experts"
KIND_EXPERT = "expert"


def expert_config(cfg: DictConfig, modality: str) -> DictConfig:
    """The stage-1 config of ``modality``'s expert, derived from a job's config."""
    if modality not in cfg.modalities:
        raise KeyError(f"no modality {modality!r} to train an expert on; modalities are {list(cfg.modalities)}")
    ecfg = OmegaConf.create(OmegaConf.to_container(cfg, resolve=False))
    with open_dict(ecfg):
        ecfg.stage = {"name": "single", "modality": modality}
        ecfg.fusion = None
        ecfg.experts = None
        ecfg.force = False
        ecfg.table = {"name": EXPERTS_TABLE, "title": "Single-modal experts", "primary": None, "metrics": None,
                      "rows": []}
    return ecfg


@contextmanager
def _locked(path: Path) -> Iterator[None]:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def ensure_expert(cfg: DictConfig, modality: str) -> tuple[Path, str]:
    """The best checkpoint and MLflow run id of ``modality``'s expert, training it first if there is none."""
    from ablate.train import run

    ecfg = expert_config(cfg, modality)
    chash = config_hash(ecfg)
    with _locked(Path("checkpoints") / EXPERTS_TABLE / f"{chash}.lock"):
        outcome = run(ecfg, kind=KIND_EXPERT, row=f"expert {modality}")
        best = outcome.ckpt_dir / "best.ckpt"
        if not best.exists():  # tracked as FINISHED but the checkpoint is gone: train it again
            log.warning("Expert %s (%s) has no checkpoint at %s; training it again", modality, chash, best)
            with open_dict(ecfg):
                ecfg.force = True
            outcome = run(ecfg, kind=KIND_EXPERT, row=f"expert {modality}")
    return best, outcome.run_id


def load_model(cfg: DictConfig, checkpoint: Path) -> torch.nn.Module:
    """The model of ``cfg`` with the weights of a task checkpoint (keys ``model.*``)."""
    model = instantiate(cfg.model)
    state = torch.load(checkpoint, map_location="cpu", weights_only=True)["state_dict"]
    model.load_state_dict({k[len("model."):]: v for k, v in state.items() if k.startswith("model.")})
    return model


def needed(cfg: DictConfig) -> list[str]:
    """The modalities whose experts a job needs: none at stage early, its own at single, all otherwise."""
    stage = cfg.stage.name
    if stage == "early":
        return []
    return [cfg.stage.modality] if stage == "single" else list(cfg.modalities)


def prepare(cfg: DictConfig) -> dict[str, tuple[Path, str]]:
    """Stage 1: every expert the job needs, trained now if missing -> {modality: (checkpoint, run id)}."""
    return {m: ensure_expert(cfg, m) for m in needed(cfg)}


def attach(cfg: DictConfig, model: torch.nn.Module, experts: dict[str, tuple[Path, str]], tracker: Tracker,
           run_id: str) -> str | None:
    """Stage 2: load the experts into ``model``. Returns the checkpoint to test from when the job is itself an
    expert (stage single), else None (the caller trains the fusion network)."""
    tracker.set_tags(run_id, {f"expert_{m}": expert_run for m, (_, expert_run) in experts.items()})
    if cfg.stage.name == "single":
        return str(experts[cfg.stage.modality][0])
    freeze = bool(cfg.experts.get("freeze", True))
    for modality, (best, _) in experts.items():
        model.load_expert(modality, load_model(expert_config(cfg, modality), best), freeze=freeze)
        log.info("Loaded expert %s from %s%s", modality, best, " (frozen)" if freeze else "")
    return None
