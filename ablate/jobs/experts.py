"""Two-stage training, SMoE §4.3: single-modal experts first, then the fusion network on top of them, frozen.

Stage 1 trains one expert per modality: the job's own config with stage ``single`` on that modality, no fusion
operator and no ``experts`` key. That config's hash names the expert, so it is trained once per (modality, seed,
scale, data, backbone, head, trainer) and tracked as a run of the MLflow experiment ``experts`` (tag
``kind=expert``); its best checkpoint lives in ``checkpoints/experts/<hash>/``. Every stage-2 job that needs it
reuses it; a file lock keeps two parallel jobs from training the same expert twice. An expert that one of its
table's tuning trials already trained (the trial chosen, at the trials' seed, which stage 2's trials train on) is
copied from that trial's run and checkpoint instead (:func:`ablate.jobs.reuse.reuse`).

Stage 2 copies the experts into the fusion model (``FusionModel.load_expert``: encoders, plus FPNs at stage fpn,
plus heads at stage late), freezes them (``experts.freeze``) and trains the rest: gates, fusion operators, and the
parts after the fusion point. Stage ``early`` has no per-modality part and trains end to end. A single-modal job
is itself an expert: it is tested from the expert's checkpoint and not trained again. With frozen experts, stage 2
computes each frame's expert features once and reuses them (:class:`FeatureCache`, ``experts.cache_features``).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any, cast

import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf, open_dict

from ablate.data.trees import tree_map, tree_tensors
from ablate.jobs.spec import apply_draws, checkpoint_dir
from ablate.store import KIND_EXPERT, Tracker, config_hash, file_lock

log = logging.getLogger(__name__)
EXPERTS_TABLE = "experts"


def expert_config(cfg: DictConfig, modality: str) -> DictConfig:
    """The stage-1 config of ``modality``'s expert, derived from a job's config: its trainer with the experts' own
    ``experts.max_epochs`` and ``experts.max_steps`` where the job sets them (SMoE §4.3 at scale=paper: 80k steps
    for each stage, conf/recipe/instance_paper.yaml), and the values its table's tuning chose for this expert
    (``experts.draws.<modality>``, :mod:`ablate.sweep.tuning`), applied and kept under ``draws``."""
    if modality not in cfg.modalities:
        raise KeyError(f"no modality {modality!r} to train an expert on; modalities are {list(cfg.modalities)}")
    ecfg = OmegaConf.create(OmegaConf.to_container(cfg, resolve=False))
    experts = cfg.get("experts") or {}
    epochs, steps = experts.get("max_epochs"), experts.get("max_steps")  # resolved here, where `table` is the row's
    tuned = (experts.get("draws") or {}).get(modality)
    with open_dict(ecfg):
        if epochs is not None:  # the experts' own epochs (stage 1), where the recipe sets them
            ecfg.trainer.max_epochs = int(epochs)
        if steps is not None:  # the experts' own optimiser steps (stage 1), where the recipe sets them
            ecfg.trainer.max_steps = int(steps)
        ecfg.stage = {"name": "single", "modality": modality}
        ecfg.fusion = None
        ecfg.experts = None
        ecfg.force = False
        ecfg.trial = ecfg.tuned = None  # a tuning trial's row shares its experts with every trial
        cast(DictConfig, ecfg).pop(
            "rung", None
        )  # at every rung of successive halving (ablate.sweep.halving): trained in full
        ecfg.draws = OmegaConf.to_container(tuned, resolve=True) if tuned else None  # the expert's own, if tuned
        ecfg.table = {
            "name": EXPERTS_TABLE,
            "title": "Single-modal experts",
            "primary": None,
            "metrics": None,
            "rows": [],
        }
    apply_draws(cast(DictConfig, ecfg))
    return cast(DictConfig, ecfg)


def job_config(cfg: DictConfig) -> tuple[DictConfig, str | None]:
    """The config a job runs and its row name where the config says better than the overrides: an expert's tuning
    trial where ``experts.tune`` is set (:func:`trial_config`), else ``cfg`` itself and None."""
    return trial_config(cfg) if (cfg.get("experts") or {}).get("tune") else (cfg, None)


def trial_config(cfg: DictConfig) -> tuple[DictConfig, str]:
    """A tuning trial of an expert's own recipe (``experts.tune=<modality>``, set by the racing sweeper,
    :mod:`ablate.sweep.tuning`): the expert's config (:func:`expert_config`) with the trial's number and draws (not
    yet applied) and the job's table, so that it is a trial of that table, under its sweep; and its row name,
    ``expert <modality>``."""
    modality = str(cfg.experts.tune)
    ecfg = expert_config(cfg, modality)
    with open_dict(ecfg):
        ecfg.trial, ecfg.table = cfg.trial, OmegaConf.to_container(cfg.table, resolve=False)
        ecfg.draws = OmegaConf.to_container(cfg.draws, resolve=True) if cfg.get("draws") else None
        if cfg.get("rung") is not None:  # the trial's rung of successive halving (ablate.sweep.halving)
            ecfg.rung = cfg.rung
    return ecfg, f"expert {modality}"


#: How stage 1 runs an expert's job: ``run(cfg, kind=..., row=...) -> Outcome`` with ``ckpt_dir`` and ``run_id``
#: (:func:`ablate.jobs.job.run`, which passes itself in: this module never imports the job back).
RunJob = Callable[..., Any]


def ensure_expert(cfg: DictConfig, modality: str, run: RunJob, wait: bool = True) -> tuple[Path, str] | None:
    """The best checkpoint and MLflow run id of ``modality``'s expert, training it first (with ``run``) if there is
    none; under the expert's lock, so that no two jobs train it. ``wait=False``: None at once where another job holds
    the lock (is training it)."""
    ecfg = expert_config(cfg, modality)
    chash = config_hash(ecfg)
    with file_lock(checkpoint_dir(EXPERTS_TABLE, chash).with_suffix(".lock"), wait=wait) as held:
        if not held:
            return None
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
    model.load_state_dict({k[len("model.") :]: v for k, v in state.items() if k.startswith("model.")})
    return model


def needed(cfg: DictConfig) -> list[str]:
    """The modalities whose experts a job needs: none at stage early, its own at single, all otherwise."""
    stage = cfg.stage.name
    if stage == "early":
        return []
    return [cfg.stage.modality] if stage == "single" else list(cfg.modalities)


def prepare(cfg: DictConfig, run: RunJob) -> dict[str, tuple[Path, str]]:
    """Stage 1: every expert the job needs, trained now with ``run`` if missing -> {modality: (checkpoint, run
    id)}, in the order of :func:`needed`. The job takes whichever expert no other job is training: two jobs of a
    sweep that need the same two experts train them side by side, one each, instead of one training while the
    other waits for its lock; a job waits only where every expert it still needs is being trained by another."""
    order = needed(cfg)
    done: dict[str, tuple[Path, str]] = {}
    while len(done) < len(order):
        left = [m for m in order if m not in done]
        for modality in left:
            got = ensure_expert(cfg, modality, run, wait=False)
            if got is not None:
                done[modality] = got
                break
        else:  # each is being trained by another job: wait for the first
            got = ensure_expert(cfg, left[0], run)
            assert got is not None  # a waiting lock is always held
            done[left[0]] = got
    return {m: done[m] for m in order}


def attach(
    cfg: DictConfig, model: torch.nn.Module, experts: dict[str, tuple[Path, str]], tracker: Tracker, run_id: str
) -> str | None:
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


class FeatureCache:
    """The frozen experts' features per frame, in memory for one stage-2 fit, keyed by frame id.

    Valid because SMoE §4.3 fine-tunes the fusion network "with fixed weights of each expert network": the experts'
    weights are frozen and their BatchNorm stays in eval mode
    (:meth:`~ablate.fusion.stages.FusionModel.load_expert`), and the data module gives each frame a fixed input (one
    condition per frame, a per-frame seeded rng for conditions and corruptions, no random augmentation), so an
    expert's output for a frame (:meth:`~ablate.fusion.stages.FusionModel.frozen_features`) is a constant. It is
    computed on the frame's first batch (the first epoch; validation frames in the sanity check) and read back
    afterwards, so the experts no longer run. Frame ids are unique across the splits of one data module; the cache
    holds one model's experts and one data module's frames, so each job builds its own (:func:`feature_cache`).

    Features are stored per frame on the CPU in ``dtype`` (float32: the result is that of running the experts) and
    handed to the model as float32 on its device. ``max_bytes`` caps the memory: frames beyond it are not stored,
    and each step runs the experts on its frames that are not in the cache only (eval-mode BatchNorm treats each
    frame on its own, so a frame's features do not depend on its batch).

    On a GPU (the model's device is CUDA) with ``fit_frames`` given, the features are kept on the GPU, where they are
    read, when those frames' features (one frame's size, known at the first batch, x ``fit_frames``) fit in
    ``GPU_CACHE_SHARE`` of the GPU's free memory then (the rest is the training step's); where they would not, the
    cache turns itself off (:attr:`off`, one log line saying why) and the experts run every step.
    """

    def __init__(
        self, max_bytes: float = float("inf"), dtype: torch.dtype = torch.float32, fit_frames: int | None = None
    ) -> None:
        self.max_bytes, self.dtype, self.fit_frames = max_bytes, dtype, fit_frames
        self.frames: dict[str, Any] = {}
        self.nbytes = 0  # bytes held by the cached features
        self.hits = self.misses = 0
        self.device: torch.device | None = None  # where the features are kept; chosen at the first batch
        self.off = False  # turned off at the first batch: the features would not fit the GPU

    def __call__(self, model: torch.nn.Module, batch: dict) -> dict:
        """``model.frozen_features(batch)``, its frames in the cache read from it, the others computed (and stored
        while the cache has room)."""
        if self.off:
            return model.frozen_features(batch)
        if "frame" not in batch:
            raise KeyError(f"FeatureCache needs batch['frame'] (frame ids) to key the features; got {sorted(batch)}")
        frames = list(batch["frame"])
        missing = [i for i, f in enumerate(frames) if f not in self.frames]
        self.hits, self.misses = self.hits + len(frames) - len(missing), self.misses + len(missing)
        fresh = None
        if missing:
            sub = batch if len(missing) == len(frames) else {m: batch[m][missing] for m in model.modalities}
            fresh = model.frozen_features(sub)
            size = sum(t[0].numel() for t in tree_tensors(fresh)) * self.dtype.itemsize  # one frame's features
            if self.device is None:
                self.device = self._place(next(model.parameters()).device, size)
            if self.off:
                return fresh
            for j, i in enumerate(missing):
                if self.nbytes + size <= self.max_bytes:
                    self.frames[frames[i]] = tree_map(
                        lambda t: t[j].to(device=self.device, dtype=self.dtype, copy=True), fresh
                    )
                    self.nbytes += size
            if len(missing) == len(frames):
                return fresh
        per_frame = {i: self.frames[f] for i, f in enumerate(frames) if i not in missing}
        per_frame.update({i: tree_map(lambda t: t[j], fresh) for j, i in enumerate(missing)})
        return _stack([per_frame[i] for i in range(len(frames))], next(model.parameters()).device)

    def _place(self, device: torch.device, size: int) -> torch.device:
        """Where to keep features of ``size`` bytes a frame for a model on ``device``: the CPU, or on a GPU the GPU
        when ``fit_frames`` of them fit in ``GPU_CACHE_SHARE`` of its free memory; else :attr:`off` is set."""
        if device.type != "cuda" or self.fit_frames is None:
            return torch.device("cpu")
        need, free = size * self.fit_frames, torch.cuda.mem_get_info(device)[0]
        if need <= GPU_CACHE_SHARE * free:
            log.info(
                "Expert feature cache on %s: %d frames x %.1f MiB = %.2f GiB",
                device,
                self.fit_frames,
                size / 2**20,
                need / 2**30,
            )
            return device
        self.off = True
        log.info(
            "experts.cache_features is off: the frozen experts' features of %d frames (%.1f MiB a frame, %.1f GiB) "
            "exceed %.0f %% of the %.1f GiB free on %s; the experts run every step",
            self.fit_frames,
            size / 2**20,
            need / 2**30,
            100 * GPU_CACHE_SHARE,
            free / 2**30,
            device,
        )
        return device


#: The share of a GPU's free memory (at the first training batch) that the frozen experts' features may take there.
GPU_CACHE_SHARE = 0.5


def _stack(trees: list[Any], device: torch.device) -> Any:
    """Per-frame trees of one structure -> one tree of float32 batches on ``device``."""
    first = trees[0]
    if torch.is_tensor(first):
        return torch.stack([t.to(device=device, dtype=torch.float32) for t in trees])
    if isinstance(first, dict):
        return {k: _stack([t[k] for t in trees], device) for k in first}
    return [_stack([t[i] for t in trees], device) for i in range(len(first))]


def feature_cache(cfg: DictConfig, model: torch.nn.Module) -> FeatureCache | None:
    """A :class:`FeatureCache` of at most ``experts.cache_max_gb`` GiB (default unbounded) for stage 2 when
    ``experts.cache_features`` is on and every per-modality part of ``model`` is a frozen expert (stages backbone,
    fpn, late with ``experts.freeze``), else None: fine-tuned experts (``freeze: false``) change every step, and
    stages early and single have no frozen part; nor with ``data.augment``, where a frame's input changes per epoch."""
    experts = cfg.get("experts") or {}
    if not experts.get("cache_features", False) or not getattr(model, "cacheable", False):
        return None
    if (cfg.get("data") or {}).get("augment"):
        log.info("experts.cache_features is off: data.augment gives each frame a new view every epoch")
        return None
    max_gb = experts.get("cache_max_gb")
    return FeatureCache(float("inf") if max_gb is None else float(max_gb) * 2**30, fit_frames=fit_frames(cfg))


def fit_frames(cfg: DictConfig) -> int | None:
    """The training and validation frames of a job whose fit runs on a GPU (their features are what a feature
    cache holds), from its data module; None where no GPU is used."""
    accelerator = str(OmegaConf.select(cfg, "trainer.accelerator", default="auto"))
    if not torch.cuda.is_available() or accelerator not in ("gpu", "cuda", "auto"):
        return None
    datamodule = instantiate(cfg.data)
    datamodule.setup("fit")
    return sum(len(datamodule.datasets[split]) for split in ("train", "val"))
