"""What every task's LightningModule shares: the optimiser and LR schedule from config, a loud NaN check, training
corruptions drawn per weight update, and testing under a list of conditions (DGFN, seed 002 §IV)."""

from __future__ import annotations

import copy
import inspect
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any, cast

import lightning as L
import torch
from omegaconf import DictConfig, ListConfig, OmegaConf
from torch import nn
from torchmetrics import Metric

from ablate.tasks.conditions import EvalConditions, TrainCorruptions
from ablate.tasks.quiet import silence

if TYPE_CHECKING:
    from matplotlib.figure import Figure

silence()  # among them Lightning's remark on the batch hook, which applies the training corruptions


class NonFiniteLossError(FloatingPointError):
    """The training loss became NaN or infinite; the job stops at once."""


def poly_lr(
    optimizer: torch.optim.Optimizer, total_steps: int, power: float = 0.9, warmup_steps: int = 0
) -> torch.optim.lr_scheduler.LRScheduler:
    """Poly learning rate, SMoE eq. 6: lr = base_lr * (1 - step / total_steps) ** power (power = gamma = 0.9).

    ``warmup_steps`` > 0 ramps the factor linearly from 1/3 to 1 over the first steps, as YOLACT's training does
    (SMoE trains its YOLACT-style head from that code base but does not state a warm-up; 0 turns it off).
    """
    total = max(int(total_steps), 1)

    def factor(step: int) -> float:
        poly = max(1.0 - step / total, 0.0) ** power
        if step < warmup_steps:
            poly *= 1.0 / 3.0 + (2.0 / 3.0) * step / warmup_steps
        return poly

    return torch.optim.lr_scheduler.LambdaLR(optimizer, factor)


def to_float32(tree: Any) -> Any:
    """``tree`` (tensors in dicts, lists, tuples) with every lower-precision floating tensor cast to fp32."""
    if isinstance(tree, torch.Tensor):
        return tree.float() if tree.is_floating_point() and tree.dtype in (torch.bfloat16, torch.float16) else tree
    if isinstance(tree, dict):
        return {key: to_float32(value) for key, value in tree.items()}
    if isinstance(tree, tuple) and hasattr(tree, "_fields"):  # a named tuple
        return type(tree)(*(to_float32(value) for value in tree))
    if isinstance(tree, (list, tuple)):
        return type(tree)(to_float32(value) for value in tree)
    return tree


class FusionTask(L.LightningModule):
    """Base LightningModule: ``model`` maps a batch dict to a dict of raw outputs; subclasses add loss and metrics.

    ``optimizer`` is a partial taking ``params``; ``scheduler`` a partial taking ``optimizer`` (and
    ``total_steps`` when its signature has it, as :func:`poly_lr` does), stepped every optimisation step.
    ``feature_cache``: when set (:func:`ablate.jobs.experts.feature_cache`, for the fit of a model on frozen experts),
    ``forward`` takes the experts' features from it instead of running them.

    Conditions (:mod:`ablate.tasks.conditions`), for a subclass that passes these options on:

    * ``train_corruptions``: ``{choices, seed, severity}`` of :class:`TrainCorruptions`, one drawn per weight
      update and applied to the training batch before it reaches the device.
    * ``eval_conditions`` (name -> spec), ``eval_severities``, ``eval_pooled``, ``eval_seed``: the test runs once
      per condition of :class:`EvalConditions` over every test batch, and what the subclass logs as
      ``test/<metric>`` is logged as ``test/<condition>/<metric>``. The protocol a subclass follows: its test
      metrics are child modules named ``test_*`` (torchmetrics ``Metric``, or containers of them) updated by
      ``_eval_step(batch, "test")`` and logged and reset by ``_eval_end("test")``; the base gives each condition
      its own copies of them, and the pooled result the merge of every named condition's copies.
    """

    def __init__(
        self,
        model: nn.Module,
        optimizer: Callable[..., torch.optim.Optimizer],
        scheduler: Callable[..., Any] | None = None,
        monitor: str = "val/loss",
        train_corruptions: dict | None = None,
        eval_conditions: dict | None = None,
        eval_severities: list[float] | None = None,
        eval_pooled: str | None = None,
        eval_seed: int = 0,
    ) -> None:
        super().__init__()
        self.model = model
        self.optimizer_factory = optimizer
        self.scheduler_factory = scheduler
        self.monitor = monitor
        self.feature_cache = None
        train_corruptions = _plain(train_corruptions)
        if train_corruptions is not None and not isinstance(train_corruptions, dict):
            raise ValueError(
                f"task.train_corruptions: expected {{choices: [...], seed, severity}}, got {train_corruptions!r}"
            )
        self.train_corruptions = TrainCorruptions(**train_corruptions) if train_corruptions else None
        self.eval_conditions = (
            EvalConditions(_plain(eval_conditions), _plain(eval_severities) or (), eval_pooled, eval_seed)
            if eval_conditions
            else None
        )
        self._condition: str | None = None
        self._condition_metrics: dict[str, dict[str, nn.Module]] = {}
        #: What the test metric needs per test frame, for the tables' resampling of the test set
        #: (:mod:`ablate.tables.frames`): one dict per (frame, condition), filled by a subclass whose metric
        #: decomposes over frames (:meth:`keep_frame_counts`); empty for the others.
        self.frame_counts: list[dict[str, Any]] = []
        #: What re-accumulating an AP metric over any set of test frames needs (:mod:`ablate.metrics.accumulate`):
        #: its rows per (frame, condition), filled by a subclass whose metric is an AP (:meth:`keep_frame_rows`).
        self.frame_detections: list[dict[str, Any]] = []
        self._test_frames: dict[str, list[str]] = {}

    def forward(self, batch: dict) -> dict:
        """The model's outputs, in fp32 whatever the autocast precision (ablate.hardware): losses, metrics and NMS
        scores read them in fp32."""
        if self.feature_cache is not None:
            return to_float32(self.model(batch, features=self.feature_cache(self.model, batch)))
        return to_float32(self.model(batch))

    def check_finite(self, loss: torch.Tensor) -> torch.Tensor:
        """Raise :class:`NonFiniteLossError` naming the epoch and step if ``loss`` is NaN or infinite."""
        if not torch.isfinite(loss).all():
            raise NonFiniteLossError(
                f"training loss is {loss.detach().float().item()} at epoch {self.current_epoch}, step "
                f"{self.global_step}; lower task.optimizer.lr or check the input data"
            )
        return loss

    def optimizers_for(self, params: list[torch.Tensor], total_steps: int) -> tuple[torch.optim.Optimizer, Any]:
        """The configured optimiser over ``params`` and its scheduler (None without one) for a schedule of
        ``total_steps`` optimiser steps: the one place both are built, under a trainer or outside one (the
        fingerprint's schedule, the paper-scale measurement, the benchmarks)."""
        optimizer = self.optimizer_factory(params=params)
        if self.scheduler_factory is None:
            return optimizer, None
        target = getattr(self.scheduler_factory, "func", self.scheduler_factory)
        kwargs = {"total_steps": total_steps} if "total_steps" in inspect.signature(target).parameters else {}
        return optimizer, self.scheduler_factory(optimizer=optimizer, **kwargs)

    def trainable(self) -> list[torch.Tensor]:
        """The parameters the optimiser updates (frozen experts' are left out)."""
        return [p for p in self.parameters() if p.requires_grad]

    def configure_optimizers(self) -> Any:
        optimizer, scheduler = self.optimizers_for(self.trainable(), self.trainer.estimated_stepping_batches)
        if scheduler is None:
            return optimizer
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": scheduler, "interval": "step"}}

    # Validation and test share one path: ``_eval_step(batch, stage)`` updates the stage's metrics,
    # ``_eval_end(stage)`` logs and resets them (stage is "val" or "test").
    def _eval_step(self, batch: dict, stage: str) -> None:
        raise NotImplementedError

    def _eval_end(self, stage: str) -> None:
        raise NotImplementedError

    def validation_step(self, batch: dict, batch_idx: int) -> None:
        self._eval_step(batch, "val")

    def on_validation_epoch_end(self) -> None:
        self._eval_end("val")

    def test_step(self, batch: dict, batch_idx: int) -> None:
        if self.eval_conditions is None:
            self._eval_step(batch, "test")
            return
        for name in self.eval_conditions.names:
            with self.under(name):
                self._eval_step(self.eval_conditions.apply(batch, name), "test")

    def keep_frame_counts(self, frames: list[str], counts: torch.Tensor) -> None:
        """Keep ``counts`` (one row of integers per frame of ``frames``) for the frames of a test batch, under the
        condition being tested (``""`` without conditions)."""
        condition = self._condition or ""
        for frame, row in zip(frames, counts.tolist()):
            self.frame_counts.append({"frame": str(frame), "condition": condition, "counts": [int(c) for c in row]})

    def keep_frame_names(self, frames: list[str]) -> None:
        """The test frames of a batch, in the order the condition's test metric receives them."""
        self._test_frames.setdefault(self._condition or "", []).extend(str(f) for f in frames)

    def keep_frame_rows(self, rows: list[dict[str, Any]]) -> None:
        """Keep an AP metric's rows per image (:mod:`ablate.metrics.accumulate`; ``index``: the image in the order
        the metric received them) under the condition being tested, each named by its frame."""
        condition = self._condition or ""
        names = self._test_frames.get(condition, [])
        for row in rows:
            if row["index"] < len(names):
                self.frame_detections.append(row | {"frame": names[row["index"]], "condition": condition})

    def on_test_epoch_start(self) -> None:
        self.frame_counts, self.frame_detections, self._test_frames = [], [], {}
        if self.eval_conditions is None:
            return
        names = self._test_metric_names()
        if not names:
            raise TypeError(
                f"{type(self).__name__} keeps no test metrics as `test_*` modules, so it cannot be "
                "tested under task.eval_conditions"
            )
        self._condition_metrics = {c: {n: _fresh(getattr(self, n)) for n in names} for c in self.eval_conditions.names}

    def on_test_epoch_end(self) -> None:
        if self.eval_conditions is None:
            self._eval_end("test")
            return
        pooled = self.eval_conditions.pooled
        if pooled:
            base = self.eval_conditions.base
            self._condition_metrics[pooled] = {n: _fresh(m) for n, m in self._condition_metrics[base[0]].items()}
            for condition in base:
                for n, m in self._condition_metrics[condition].items():
                    _merge(self._condition_metrics[pooled][n], m)
            self._test_frames[pooled] = [f for c in base for f in self._test_frames.get(c, [])]  # merged in this order
        for name in [*([pooled] if pooled else []), *self.eval_conditions.names]:
            with self.under(name):
                self._eval_end("test")

    def _test_metric_names(self) -> list[str]:
        return [n for n, m in self.named_children() if n.startswith("test_") and _has_metric(m)]

    @contextmanager
    def under(self, condition: str) -> Iterator[None]:
        """Within it, the test metrics are ``condition``'s copies and ``test/`` logs go to ``test/<condition>/``."""
        originals = {n: getattr(self, n) for n in self._condition_metrics.get(condition, {})}
        for n, m in self._condition_metrics.get(condition, {}).items():
            setattr(self, n, m)
        self._condition = condition
        try:
            yield
        finally:
            self._condition = None
            for n, m in originals.items():
                setattr(self, n, m)

    def log(self, name: str, value: Any, *args: Any, **kwargs: Any) -> None:
        if self._condition is not None and name.startswith("test/"):
            name = f"test/{self._condition}/{name[len('test/') :]}"
        super().log(name, value, *args, **kwargs)

    def on_before_batch_transfer(self, batch: Any, dataloader_idx: int = 0) -> Any:
        """A training batch under the corruption drawn for this weight update (``train_corruptions``)."""
        if self.train_corruptions is not None and isinstance(batch, dict) and self.trainer.training:
            return self.train_corruptions.apply(batch, self.global_step)
        return batch

    def forward_eval(self, batch: dict) -> dict:
        """The model's outputs on ``batch``'s tensors, in eval mode without gradients (figures)."""
        device = next(self.model.parameters()).device
        inputs = {k: v.to(device) for k, v in batch.items() if torch.is_tensor(v)}
        was_training = self.model.training
        self.model.eval()
        try:
            with torch.no_grad():
                return self.model(inputs)
        finally:
            self.model.train(was_training)

    def image_size(self, batch: dict) -> tuple[int, int]:
        """(H, W) of the model's inputs in ``batch``."""
        names = list(getattr(self.model, "modalities", None) or [])
        for key in names or [k for k, v in batch.items() if torch.is_tensor(v) and v.ndim == 4]:
            if key in batch:
                return tuple(batch[key].shape[-2:])
        raise KeyError(f"{type(self).__name__}: batch has no image tensor (need one of {names}); got {sorted(batch)}")

    def figure(self, batch: dict) -> Figure | None:
        """A matplotlib figure of predictions on ``batch`` (fixed test frames), or None."""
        return None

    def gate_figure(self, batch: dict) -> Figure | None:
        """A figure of the fusion gates' weights on ``batch``, for a model with gated fusion, or None."""
        return None

    def figures(self, batch: dict) -> dict[str, Figure]:
        """The figures a job's run keeps, by artifact name: its predictions on ``batch`` and, where the model's
        fusion is gated, its gates."""
        made = {"predictions.png": self.figure(batch), "gates.png": self.gate_figure(batch)}
        return {name: figure for name, figure in made.items() if figure is not None}

    @property
    def evaluator(self) -> str | None:
        """The evaluators its metrics follow (their ``evaluator``, e.g. ``kitti_object_devkit_2017``; see
        :mod:`ablate.metrics`), comma-separated: the run's ``evaluator`` tag. None when no metric names one."""
        names = {getattr(m, "evaluator", None) for m in self.modules() if isinstance(m, Metric)}
        return ", ".join(sorted(cast("set[str]", names - {None}))) or None


def _plain(value: Any) -> Any:
    """OmegaConf containers as plain dicts and lists."""
    return OmegaConf.to_container(value, resolve=True) if isinstance(value, (DictConfig, ListConfig)) else value


def _has_metric(module: nn.Module) -> bool:
    return any(isinstance(m, Metric) for m in module.modules())


def _fresh(module: nn.Module) -> nn.Module:
    """A copy of a metric module (or container of metrics) with every metric reset."""
    out = copy.deepcopy(module)
    for m in out.modules():
        if isinstance(m, Metric):
            m.reset()
    return out


def _merge(into: nn.Module, other: nn.Module) -> None:
    """Add the states of ``other``'s metrics to ``into``'s (same structure): one metric over both inputs."""
    for (_, a), (_, b) in zip(_metrics(into), _metrics(other)):
        a.merge_state(b)
        a._update_count += b._update_count  # merge_state leaves the count that ``update_count`` reports
        a._computed = None


def _metrics(module: nn.Module) -> list[tuple[str, Metric]]:
    return [(n, m) for n, m in module.named_modules() if isinstance(m, Metric)]
