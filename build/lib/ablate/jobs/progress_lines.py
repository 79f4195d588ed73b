"""Progress a person can read where the output is not a terminal (a log file, a redirected sweep, a batch system):
Lightning's progress bar there writes a carriage-return refresh per step, megabytes of them in a long sweep's log.

``trainer.enable_progress_bar: auto`` (the default) keeps Lightning's bar on a terminal and, elsewhere, turns it off
for :class:`ProgressLines`: one line at most every ``every_s`` seconds, and at each epoch's end, with the epoch, the
step, the latest training loss and an estimate of the time to the end of the fit from the steps done so far
(tqdm's ``disable=None`` and Lightning's ``TQDMProgressBar(refresh_rate=...)`` answer the same need).
"""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Callable
from typing import Any

import lightning as L
from lightning.pytorch.callbacks import Callback

log = logging.getLogger(__name__)


def progress_bar(option: Any, tty: Callable[[], bool] = lambda: sys.stdout.isatty()) -> bool:
    """``trainer.enable_progress_bar``: true, false, or ``auto`` (Lightning's bar on a terminal only)."""
    if option == "auto":
        return bool(tty())
    if isinstance(option, bool):
        return option
    raise ValueError(f"trainer.enable_progress_bar={option!r}: expected true, false or auto")


class ProgressLines(Callback):
    """A progress line at most every ``every_s`` seconds and at each epoch's end: ``epoch e/E, step s/S, loss x,
    about m min left``."""

    def __init__(self, every_s: float = 30.0, clock: Callable[[], float] = time.monotonic) -> None:
        self.every_s, self.clock = every_s, clock
        self.started: float | None = None
        self.last = 0.0
        self.first_step = 0

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.started = self.last = self.clock()
        self.first_step = trainer.global_step

    def on_train_batch_end(
        self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any, batch_idx: int
    ) -> None:
        if self.clock() - self.last >= self.every_s:
            self.report(trainer)

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.report(trainer)

    def report(self, trainer: L.Trainer) -> None:
        self.last = now = self.clock()
        step, total = trainer.global_step, trainer.estimated_stepping_batches
        loss = trainer.callback_metrics.get("train/loss")
        shown = "" if loss is None else f", loss {float(loss):.4g}"
        done = step - self.first_step
        left = ""
        if done > 0 and self.started is not None and total and total != float("inf"):
            left = f", about {(now - self.started) / done * max(total - step, 0) / 60:.1f} min left"
        log.info("epoch %d/%d, step %d/%s%s%s", trainer.current_epoch + 1, trainer.max_epochs, step, total, shown, left)
