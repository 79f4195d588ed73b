"""A tuning trial's rungs (``table.tune.halving``, :mod:`ablate.sweep.halving`): where it stops, and its validation
value per epoch.

A trial at rung ``rung=<fraction>`` trains the recipe as configured (``trainer.max_epochs``, so that its learning
rate's schedule is the full budget's) and stops once ``round(fraction * max_epochs)`` epochs (at least 1) are done
(:class:`ablate.jobs.rung_callbacks.StopAtRung`); its checkpoint folder is the trial's at every rung
(:func:`checkpoint_config`), so the next rung resumes it. Every trial keeps its validation value per epoch
(:class:`ablate.jobs.rung_callbacks.ValCurve`), recorded as its run's tag ``val_curve`` ({epoch: value}, epochs
counted from 1), the epochs it trained in this run only.

Nothing here imports Lightning: the sweep's plan, the report and the reproduction check read rungs and curves
without training, and Lightning (with torch) takes seconds to import.
"""

from __future__ import annotations

import copy
import json
import math
from typing import Any

from omegaconf import DictConfig, open_dict


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


def read_curve(text: Any) -> dict[int, float]:
    """A ``val_curve`` tag (or record) back as {epoch: value}; empty where there is none."""
    if not isinstance(text, str) or not text.strip():
        return {}
    return {int(e): (math.nan if v is None else float(v)) for e, v in json.loads(text).items()}
