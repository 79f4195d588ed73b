"""A tuning trial's rungs (``table.tune.halving``, :mod:`ablate.sweep.halving`): where it stops, and its validation
value per epoch.

A trial at rung ``rung=<fraction>`` trains the recipe as configured (``trainer.max_epochs``, so that its learning
rate's schedule is the full budget's) and stops once ``round(fraction * max_epochs)`` epochs (at least 1) are done
(:class:`StopAtRung`); its checkpoint folder is the trial's at every rung (:func:`checkpoint_config`), so the next
rung resumes it. Every trial keeps its validation value per epoch (:class:`ValCurve`), recorded as its run's tag
``val_curve`` ({epoch: value}, epochs counted from 1), the epochs it trained in this run only.
"""

from __future__ import annotations

import copy
import json
import math
from typing import Any

import lightning as L
from lightning.pytorch.callbacks import Callback
from omegaconf import DictConfig, open_dict

from ablate.store import VAL_CURVE


def stop_epoch(cfg: DictConfig) -> int | None:
    """The epoch a trial at a rung stops after (``rung`` × ``trainer.max_epochs``, rounded, at least 1); None
    without a rung: the recipe's epochs."""
    rung = cfg.get("rung")
    if rung is None:
        return None
    epochs = int(cfg.trainer.max_epochs)
    return max(1, min(epochs, round(float(rung) * epochs)))


def checkpoint_config(cfg: DictConfig) -> DictConfig:
    """The config a job's checkpoint folder is named by: its own, without a rung, so that every rung of a trial
    resumes the one before (the config hash itself, which names the run, keeps the rung). The key is added by the
    override (``++rung=...``) and absent from every other config, whose hashes stay as they were."""
    if "rung" not in cfg:
        return cfg
    out = copy.deepcopy(cfg)
    with open_dict(out):
        out.pop("rung")
    return out


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


def read_curve(text: Any) -> dict[int, float]:
    """A ``val_curve`` tag (or record) back as {epoch: value}; empty where there is none."""
    if not isinstance(text, str) or not text.strip():
        return {}
    return {int(e): (math.nan if v is None else float(v)) for e, v in json.loads(text).items()}
