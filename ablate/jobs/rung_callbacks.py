"""The Lightning callbacks of a tuning trial's rungs (:mod:`ablate.jobs.rungs`): stop at the rung's epoch, and keep
the validation value per epoch. Apart from :mod:`ablate.jobs.rungs` so that what reads rungs without training (the
sweep's plan, the report) does not import Lightning."""

from __future__ import annotations

import json

import lightning as L
from lightning.pytorch.callbacks import Callback

from ablate.store import VAL_CURVE


class StopAtRung(Callback):
    """Stop the fit after epoch ``epoch`` (counted from 1), the learning rate's schedule left the recipe's."""

    def __init__(self, epoch: int) -> None:
        self.epoch = epoch

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if trainer.current_epoch + 1 >= self.epoch:
            trainer.should_stop = True


class ValCurve(Callback):
    """The value of the task's validation ``monitor`` at the end of each epoch of this fit ({epoch: value}, epochs
    from 1)."""

    def __init__(self, monitor: str) -> None:
        self.monitor = monitor
        self.values: dict[int, float] = {}

    def on_validation_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        value = trainer.callback_metrics.get(self.monitor)
        if value is not None and not trainer.sanity_checking:
            self.values[trainer.current_epoch + 1] = float(value)

    def tag(self) -> dict[str, str]:
        """The run's ``val_curve`` tag: rounded to 6 significant digits (a tag holds a few thousand characters)."""
        return {VAL_CURVE: json.dumps({str(e): float(f"{v:.6g}") for e, v in sorted(self.values.items())})}
