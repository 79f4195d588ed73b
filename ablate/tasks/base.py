"""What every task's LightningModule shares: the optimiser and LR schedule from config, and a loud NaN check."""
from __future__ import annotations

import inspect
from typing import Any, Callable

import lightning as L
import torch
from torch import nn


class NonFiniteLossError(FloatingPointError):
    """The training loss became NaN or infinite; the job stops at once."""


def poly_lr(optimizer: torch.optim.Optimizer, total_steps: int, power: float = 0.9,
            warmup_steps: int = 0) -> torch.optim.lr_scheduler.LRScheduler:
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


class FusionTask(L.LightningModule):
    """Base LightningModule: ``model`` maps a batch dict to a dict of raw outputs; subclasses add loss and metrics.

    ``optimizer`` is a partial taking ``params``; ``scheduler`` a partial taking ``optimizer`` (and
    ``total_steps`` when its signature has it, as :func:`poly_lr` does), stepped every optimisation step.
    ``feature_cache``: when set (:func:`ablate.experts.feature_cache`, for the fit of a model on frozen experts),
    ``forward`` takes the experts' features from it instead of running them.
    """

    def __init__(self, model: nn.Module, optimizer: Callable[..., torch.optim.Optimizer],
                 scheduler: Callable[..., Any] | None = None, monitor: str = "val/loss") -> None:
        super().__init__()
        self.model = model
        self.optimizer_factory = optimizer
        self.scheduler_factory = scheduler
        self.monitor = monitor
        self.feature_cache = None

    def forward(self, batch: dict) -> dict:
        if self.feature_cache is not None:
            return self.model(batch, features=self.feature_cache(self.model, batch))
        return self.model(batch)

    def check_finite(self, loss: torch.Tensor) -> torch.Tensor:
        """Raise :class:`NonFiniteLossError` naming the epoch and step if ``loss`` is NaN or infinite."""
        if not torch.isfinite(loss).all():
            raise NonFiniteLossError(
                f"training loss is {loss.detach().float().item()} at epoch {self.current_epoch}, step "
                f"{self.global_step}; lower task.optimizer.lr or check the input data")
        return loss

    def configure_optimizers(self) -> Any:
        params = [p for p in self.parameters() if p.requires_grad]
        optimizer = self.optimizer_factory(params=params)
        if self.scheduler_factory is None:
            return optimizer
        kwargs = {}
        target = getattr(self.scheduler_factory, "func", self.scheduler_factory)
        if "total_steps" in inspect.signature(target).parameters:
            kwargs["total_steps"] = self.trainer.estimated_stepping_batches
        scheduler = self.scheduler_factory(optimizer=optimizer, **kwargs)
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
        self._eval_step(batch, "test")

    def on_test_epoch_end(self) -> None:
        self._eval_end("test")

    def figure(self, batch: dict):
        """A matplotlib figure of predictions on ``batch`` (fixed test frames), or None."""
        return None
