"""A job's fingerprint: a few numbers that change when the code changes what the job computes, and only then.

A table asks whether its runs' numbers are still what today's code gives. Files changed since a run's commit say
too much (a rename moves no number), so a job records, at its start, what its resolved config computes on a tiny
fixed input, on the CPU in fp32 with 1 thread (:func:`compute`), in five components (six for a job that trains on
corruptions):

- ``data``: the first two training frames of a small generated dataset (``DATA``: 8 frames at 64 x 208, the job's
  own modalities, targets, conditions and corruptions) as the data pipeline delivers them, generated afresh by each
  process in a temporary folder of its own (no cache across processes: the generator and the derived modalities
  are today's code; the jobs of one process, whose code is one, share it: :func:`scratch`);
- ``model``: the model's outputs on the first of them from its seeded initial weights (eval mode);
- ``loss``: the training loss after two optimiser steps on it (the job's optimiser and training corruptions);
- ``schedule``: the learning rate at steps 0, 1, 10, 100, 500 and 999 of the job's schedule over 1000 steps;
- ``metric``: the task's test metrics on the outputs of the model after those two steps;
- ``corruptions``, for a job that trains on corruptions only: the loss under each of them in turn
  (:func:`corruption_steps`).

Each tensor is summarised by three float64 numbers (its sum, its sum of squares, and its sum weighted by
``sin(index)``, which sees a permutation); they are stored as numbers, not a hash, and compared with a relative
tolerance (:func:`ablate.store.fingerprint.differs`), so that machines whose kernels round differently agree. The report
recomputes the fingerprint of a row only where files its runs build changed since their commit, and flags the row
only where a component differs, naming the first (:mod:`ablate.tables.provenance`).

Readings: the experts of a two-stage job are not loaded (their checkpoints are outputs); the figures are the
job's model and task as configured, so a change in the frozen-expert machinery alone is not seen. A metric whose
value is 0 on an untrained model (an AP) shows a changed rule only where the rule changes these numbers: the
evaluator tag (:data:`ablate.metrics.EVALUATORS`) names such changes outright.
"""

from __future__ import annotations

import atexit
import os
import shutil
import tempfile
import time
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any, cast

import lightning as L
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf, open_dict

from ablate.data.datamodule import collate
from ablate.jobs.preempt import alive
from ablate.store.fingerprint import COMPONENTS, TAG, decode, differs, encode
from ablate.tasks.conditions import corrupt

__all__ = ["COMPONENTS", "TAG", "compute", "decode", "differs", "encode", "timed"]

#: The generated frames every fingerprint reads (``data.synth``), and how many of them it checks (the model runs on
#: the first: DGFN's SSD resizes every input to its own size, so a frame costs the same at any size).
DATA = {"frames": 8, "seed": 0, "height": 64, "width": 208}
FRAMES = 2
SCHEDULE_STEPS, SCHEDULE_TOTAL = (0, 1, 10, 100, 500, 999), 1000


def tiny(cfg: DictConfig, data_dir: str | None = None) -> DictConfig:
    """The job's config on the fingerprint's input: generated frames (``DATA``) under ``data_dir``, batch 1, no
    loader workers, no augmentation."""
    small = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
    with open_dict(small):
        small.data.root = None
        small.data.synth = {**(small.data.get("synth") or {}), **DATA}
        small.data.batch_size = 1
        small.data.num_workers = 0
        if data_dir is not None:
            small.data.data_dir = data_dir
        small.data.limit_frames = None
        if "augment" in small.data:
            small.data.augment = None
    return cast(DictConfig, small)


def summary(tree: Any) -> list[float]:
    """Three float64 numbers per tensor of ``tree`` (dicts, lists, tuples, in their order; dict keys sorted)."""
    out: list[float] = []
    for t in _tensors(tree):
        x = torch.nan_to_num(t.detach().to(torch.float64).reshape(-1).cpu(), nan=0.0)  # NaN: padding (SHPL)
        w = torch.sin(torch.arange(x.numel(), dtype=torch.float64))
        out += [float(x.sum()), float((x * x).sum()), float((x * w).sum())]
    return out


def _tensors(tree: Any) -> Iterator[torch.Tensor]:
    if torch.is_tensor(tree):
        yield tree
    elif isinstance(tree, dict):
        for key in sorted(tree, key=str):
            yield from _tensors(tree[key])
    elif isinstance(tree, (list, tuple)):
        for value in tree:
            yield from _tensors(value)
    elif isinstance(tree, (int, float)) and not isinstance(tree, bool):
        yield torch.tensor(float(tree))


def compute(cfg: DictConfig) -> dict[str, list[float]]:
    """The fingerprint of job config ``cfg`` (see the module docstring): {component: numbers}."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", ".*self.trainer.*reference is not registered.*")
            warnings.filterwarnings("ignore", ".*self.log.*")
            return _compute(tiny(cfg, str(scratch())))
    finally:
        torch.set_num_threads(threads)


_SCRATCH: dict[int, Path] = {}
SCRATCH_PREFIX = "ablate-fingerprint-"


def scratch() -> Path:
    """This process's folder for the fingerprint's generated frames (``ablate-fingerprint-<pid>-*`` in the temporary
    folder), made on first use and removed at its exit; a killed process's, by the next process that makes one. A
    forked process makes its own: its parent may remove the parent's while it runs."""
    pid = os.getpid()
    if pid not in _SCRATCH:
        _remove_orphans()
        _SCRATCH[pid] = Path(tempfile.mkdtemp(prefix=f"{SCRATCH_PREFIX}{pid}-"))
        atexit.register(_remove, pid, _SCRATCH[pid])
    return _SCRATCH[pid]


def _remove_orphans() -> None:
    """Remove the scratch folders of processes that are gone without removing theirs (killed)."""
    for folder in Path(tempfile.gettempdir()).glob(f"{SCRATCH_PREFIX}*-*"):
        owner = folder.name.removeprefix(SCRATCH_PREFIX).split("-", 1)[0]
        if owner.isdigit() and not alive(int(owner)):
            shutil.rmtree(folder, ignore_errors=True)


def _remove(pid: int, folder: Path) -> None:
    if os.getpid() == pid:  # not a forked child's exit: the folder is its parent's
        shutil.rmtree(folder, ignore_errors=True)


def clip(cfg: DictConfig, params: Any) -> None:
    """The job's gradient clipping (``trainer.gradient_clip_val``, by norm or by value as Lightning clips)."""
    value = OmegaConf.select(cfg, "trainer.gradient_clip_val")
    if value is None:
        return
    params = list(params)
    if OmegaConf.select(cfg, "trainer.gradient_clip_algorithm", default="norm") == "value":
        torch.nn.utils.clip_grad_value_(params, float(value))
    else:
        torch.nn.utils.clip_grad_norm_(params, float(value))


def _compute(cfg: DictConfig) -> dict[str, list[float]]:
    L.seed_everything(int(cfg.seed), workers=True, verbose=False)
    datamodule = instantiate(cfg.data)
    datamodule.setup("fit")
    train = datamodule.datasets["train"]
    frames = collate([train[i] for i in range(min(FRAMES, len(train)))])
    out = {"data": summary({k: v for k, v in frames.items() if k not in ("frame", "condition", "lidar_condition")})}
    batch = collate([train[0]])
    L.seed_everything(int(cfg.seed), workers=True, verbose=False)
    model = instantiate(cfg.model)
    task = instantiate(cfg.task, model=model)
    task.eval()
    with torch.no_grad():
        out["model"] = summary(task(batch))
    task.train()
    optimizer = task.optimizer_factory(params=task.trainable())  # the base rate: no schedule for two steps
    for step in range(2):
        step_batch = task.train_corruptions.apply(batch, step) if task.train_corruptions is not None else batch
        optimizer.zero_grad()
        loss = _loss(task.training_step(step_batch, step))
        loss.backward()
        clip(cfg, task.trainable())
        optimizer.step()
    with torch.no_grad():
        out["loss"] = summary(_loss(task.training_step(batch, 2)))
    out["schedule"] = schedule(task)
    task.eval()
    with torch.no_grad():
        task._eval_step(batch, "test")
    out["metric"] = summary([_computed(getattr(task, name)) for name in task._test_metric_names()])
    if task.train_corruptions is not None:
        out["corruptions"] = corruption_steps(task, batch)
    return out


def _loss(out: Any) -> torch.Tensor:
    """The loss of a ``training_step``'s output (a tensor, or a dict holding it as ``loss``)."""
    return out["loss"] if isinstance(out, dict) else out


def corruption_steps(task: Any, batch: dict) -> list[float]:
    """The ``corruptions`` component: the training loss on the first frame under each corruption the job trains
    with (every spec of ``task.train_corruptions.choices`` but no action, in their order), in training mode from
    the weights the other components left, forward only. The two updates of ``loss`` draw their corruptions as the
    job would, and may draw none: a change in how the network meets a blanked or occluded sensor in training
    (DGFN §IV-A; a blanked trunk's BatchNorm, ``model.blank_running_stats``) is seen here. Reading: a change in the
    backward pass alone under a corruption is not (the ``loss`` component's steps see the backward pass)."""
    corruptions = task.train_corruptions
    specs = [spec for options in corruptions.choices for spec in options if spec]
    task.train()
    losses = []
    with torch.no_grad():
        for step, spec in enumerate(specs):
            corrupted = corrupt(batch, spec, (corruptions.seed, step, 0), corruptions.severity)
            losses.append(_loss(task.training_step(corrupted, step)))
    return summary(losses)


def schedule(task: Any) -> list[float]:
    """The learning rate of the task's first parameter group at ``SCHEDULE_STEPS`` of its schedule over
    ``SCHEDULE_TOTAL`` steps (the base rate alone without a schedule)."""
    optimizer, scheduler = task.optimizers_for([torch.nn.Parameter(torch.zeros(1))], SCHEDULE_TOTAL)
    if scheduler is None:
        return [float(optimizer.param_groups[0]["lr"])]
    rates = []
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", ".*lr_scheduler.step.*")
        for step in range(max(SCHEDULE_STEPS) + 1):
            if step in SCHEDULE_STEPS:
                rates.append(float(optimizer.param_groups[0]["lr"]))
            scheduler.step()
    return rates


def _computed(module: torch.nn.Module) -> Any:
    """The computed values of the metrics in ``module`` (a torchmetrics Metric or a container of them)."""
    from torchmetrics import Metric

    with warnings.catch_warnings():  # a metric of a branch the row does not have: computed as it is, on purpose
        warnings.filterwarnings("ignore", ".*was called before the ``update`` method.*")
        values = [m.compute() for m in module.modules() if isinstance(m, Metric)]
    return [_numbers(v) for v in values]


def _numbers(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _numbers(v) for k, v in value.items() if torch.is_tensor(v) or isinstance(v, (int, float, dict))}
    return value


def timed(cfg: DictConfig) -> tuple[dict[str, list[float]], float]:
    """:func:`compute` and its wall time in seconds."""
    start = time.perf_counter()
    fingerprint = compute(cfg)
    return fingerprint, time.perf_counter() - start
