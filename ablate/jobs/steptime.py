"""A job's steps measured outside a trainer, in the calling process: what a sweep's plan estimates its wall time from
(:mod:`ablate.sweep.plan`), and what the paper check measures at the paper's scale (:mod:`ablate.capacity.measure`).

:func:`build` makes a job's data, model and task as :mod:`ablate.jobs.train` does (the frozen experts of a
two-stage row, SMoE §4.3, loaded from freshly built ones: what is frozen is what a job freezes) and the feature cache
a job would use on the CPU. :func:`step_times` times, on one training batch of the job's batch size: a training step
with the experts run (every step of a job without a feature cache, the first epoch of one with it), a training step
with the experts' features read from the cache (the later epochs), and a validation step. Each is the fastest of
``repeats`` after one untimed step, with the job's ``trainer.threads`` and its precision (bf16 autocast where its
resolved ``trainer.precision`` is bf16, as Lightning's ``bf16-mixed`` runs it), on the device the job trains on: the
CPU, or the first CUDA device for ``trainer=gpu`` where there is one (:func:`ablate.hardware.gpu`), each step waited
for on the device. On a GPU the experts' feature cache is left out (a job sizes its own against the GPU's free
memory, :mod:`ablate.jobs.experts`): its later epochs are timed as its first, an upper bound.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import lightning as L
import torch
from hydra.utils import instantiate
from lightning.fabric.utilities.apply_func import move_data_to_device
from omegaconf import DictConfig

from ablate import hardware
from ablate.data.datamodule import collate
from ablate.jobs.experts import expert_config, feature_cache, needed


def build(cfg: DictConfig, small: DictConfig, batch_size: int = 1) -> dict[str, Any]:
    """The data (a training batch of ``batch_size`` frames, the training split's first ones, repeated where it has
    fewer, and a test batch of one frame), model and task of job config ``cfg`` on the frames of ``small``, with the
    experts of a two-stage row loaded (frozen where ``experts.freeze``) and the frozen experts' feature cache a job
    would use on the CPU (:func:`ablate.jobs.experts.feature_cache`); ``splits``: the frames of each split."""
    L.seed_everything(int(small.seed), workers=True, verbose=False)
    datamodule = instantiate(small.data)
    datamodule.setup("fit")
    train = datamodule.datasets["train"]
    test = datamodule.datasets["test"] if len(datamodule.datasets["test"]) else train
    start = time.perf_counter()
    batch, test_batch = collate([train[i % len(train)] for i in range(batch_size)]), collate([test[0]])
    data_s = time.perf_counter() - start
    model = instantiate(small.model)
    task = instantiate(small.task, model=model)
    freeze = bool((cfg.get("experts") or {}).get("freeze", True))
    two_stage = cfg.get("experts") and cfg.stage.name != "single"
    for modality in needed(cfg) if two_stage else []:  # stage 2 starts from the experts, as experts.attach loads them
        model.load_expert(modality, instantiate(expert_config(cfg, modality).model), freeze=freeze)
    task.feature_cache = feature_cache(small, model)
    task.train()
    step_batch = task.train_corruptions.apply(batch, 0) if task.train_corruptions is not None else batch
    return {
        "task": task,
        "model": model,
        "batch": step_batch,
        "test_batch": test_batch,
        "data_s": data_s,
        "distinct_frames": min(batch_size, len(train)),
        "splits": {split: len(frames) for split, frames in datamodule.datasets.items()},
    }


@dataclass(frozen=True)
class StepTimes:
    """Seconds of a job's steps and its batches an epoch (:func:`step_times`)."""

    train_s: float  # a training step, the experts run
    cached_s: float  # a training step, the experts' features from the cache (train_s where the job has no cache)
    eval_s: float  # a validation step
    train_batches: int  # training batches an epoch
    eval_batches: int  # validation batches an epoch
    test_batches: int  # test batches

    def fit_seconds(self, epochs: int, max_steps: int | None = None, cached: bool = False) -> float:
        """A fit of ``epochs`` epochs (Lightning's ``max_epochs``; -1: unbounded) stopped at ``max_steps`` steps
        where set: its training steps, the first epoch's at :attr:`train_s` and the rest's at :attr:`cached_s` where
        the job caches the experts' features (``cached``), and a validation epoch after each epoch."""
        steps = epochs * self.train_batches if epochs > 0 else 0
        if max_steps and max_steps > 0:
            steps = min(steps, max_steps) if epochs > 0 else max_steps
        first = min(steps, self.train_batches) if cached else steps
        epochs_run = math.ceil(steps / max(self.train_batches, 1))
        return first * self.train_s + (steps - first) * self.cached_s + epochs_run * self.eval_batches * self.eval_s

    @classmethod
    def mean(cls, times: list[StepTimes]) -> StepTimes:
        """The mean step times of several measured rows of one kind, at the batches an epoch of the first (the rows
        of one sweep read one data module)."""
        n = len(times)
        first = times[0]
        return cls(
            sum(t.train_s for t in times) / n,
            sum(t.cached_s for t in times) / n,
            sum(t.eval_s for t in times) / n,
            first.train_batches,
            first.eval_batches,
            first.test_batches,
        )

    def test_seconds(self, conditions: int = 1) -> float:
        """The test: every test batch once per test condition, at a validation step's cost."""
        return self.test_batches * max(conditions, 1) * self.eval_s


def _loss(out: Any) -> torch.Tensor:
    return out["loss"] if isinstance(out, dict) else out


def step_times(cfg: DictConfig, repeats: int = 2, clock: Callable[[], float] = time.perf_counter) -> StepTimes:
    """The steps of job config ``cfg`` (its own data, batch size and threads) timed on ``clock``; see the module."""
    threads = torch.get_num_threads()
    if cfg.trainer.get("threads"):
        torch.set_num_threads(int(cfg.trainer.threads))
    try:
        with warnings.catch_warnings():  # the task's self.log without a trainer: logged nowhere, as meant
            warnings.filterwarnings("ignore", ".*self.trainer.* reference is not registered.*")
            bf16 = "bf16" in str(cfg.trainer.get("precision", "32"))  # the job's numerics, resolved (ablate.hardware)
            device = torch.device("cuda", 0) if hardware.gpu(cfg.trainer) else torch.device("cpu")
            with torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16):
                built, train_s, cached_s, eval_s = _timed(cfg, repeats, clock, device)
    finally:
        torch.set_num_threads(threads)
    if device.type == "cuda":  # the sweep's own process keeps no model on the GPU its jobs train on
        built = {"splits": built["splits"]}
        torch.cuda.empty_cache()
    splits, batch_size = built["splits"], int(cfg.data.batch_size)
    return StepTimes(
        train_s,
        cached_s,
        eval_s,
        math.ceil(splits.get("train", 0) / batch_size),
        math.ceil(splits.get("val", 0) / batch_size),
        math.ceil(splits.get("test", 0) / batch_size),
    )


def _timed(
    cfg: DictConfig, repeats: int, clock: Callable[[], float], device: torch.device = torch.device("cpu")
) -> tuple[dict[str, Any], float, float, float]:
    """The built job (:func:`build`) and its training step's seconds with the experts run and with them cached, and
    its validation step's, on ``device``."""
    built = build(cfg, cfg, int(cfg.data.batch_size))
    task, batch = built["task"], built["batch"]
    if device.type == "cuda":
        task.to(device)
        task.feature_cache = None  # built on the CPU, for the CPU: see the module
        batch = move_data_to_device(batch, device)
    optimizer, _ = task.optimizers_for(task.trainable(), 1000)

    def train_step() -> None:
        loss = _loss(task.training_step(batch, 0))
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        if device.type == "cuda":  # the kernels queued: the step ends when the device is done
            torch.cuda.synchronize(device)

    cache = task.feature_cache
    task.feature_cache = None
    train_s = _fastest(train_step, repeats, clock)
    task.feature_cache = cache
    cached_s = _fastest(train_step, repeats, clock) if cache is not None else train_s  # the untimed step fills it
    task.feature_cache = None
    task.eval()

    def eval_step() -> None:
        task.validation_step(batch, 0)
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    with torch.no_grad():
        eval_s = _fastest(eval_step, repeats, clock)
    return built, train_s, cached_s, eval_s


def _fastest(step: Callable[[], Any], repeats: int, clock: Callable[[], float]) -> float:
    """The fastest of ``repeats`` timed calls of ``step``, after one untimed call."""
    step()
    times = []
    for _ in range(max(repeats, 1)):
        start = clock()
        step()
        times.append(clock() - start)
    return min(times)
