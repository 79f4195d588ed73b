"""The global random generators a job's checkpoint carries, so a resumed job draws what it would have drawn.

A job seeds torch's, NumPy's and Python's global generators once, at its start (``seed_everything``). Augmentation
and dropout draw from torch's as training goes on. A job resumed from a checkpoint seeds them again at its start,
so without more it would draw from the first epoch's states. :class:`GlobalGenerators` saves their states in every
checkpoint the trainer writes and restores them when training starts from one, before the first batch is fetched;
the training order is saved and restored beside them (:class:`~ablate.data.order.ResumableLoader`).

From a checkpoint written at an epoch's end (``last.ckpt`` after each validation) a resumed job draws exactly
what the uninterrupted job drew. From one written mid-epoch (a stop, :class:`~ablate.jobs.preempt.SaveOnStop`)
the training step's draws (dropout) are exact too. Augmentation's are not: its draws for the batch the loader had
fetched ahead were already taken when the checkpoint was written, and are taken again on resume. Loader workers
(``data.num_workers`` > 0) draw augmentation from generators of their own, seeded as they start, which a resumed
job's workers start again: their draws are not restored. CUDA's generators are saved where a GPU trains.
"""

from __future__ import annotations

import random
from typing import Any

import numpy as np
import torch
from lightning.pytorch.callbacks import Callback

from ablate.data.order import ResumableLoader


def states() -> dict[str, Any]:
    """The global generators' states: torch's, CUDA's (where there is a GPU), NumPy's and Python's."""
    numpy = np.random.get_state(legacy=False)  # plain types and one array, as a list: a weights-only load reads it
    numpy["state"]["key"] = numpy["state"]["key"].tolist()
    out: dict[str, Any] = {"torch": torch.get_rng_state(), "numpy": numpy, "python": random.getstate()}
    if torch.cuda.is_available():
        out["cuda"] = torch.cuda.get_rng_state_all()
    return out


def restore(saved: dict[str, Any]) -> None:
    """Set the global generators to ``saved`` (:func:`states`); CUDA's only where both have a GPU."""
    torch.set_rng_state(saved["torch"])
    numpy = dict(saved["numpy"], state=dict(saved["numpy"]["state"]))
    numpy["state"]["key"] = np.asarray(numpy["state"]["key"], dtype=np.uint32)
    np.random.set_state(numpy)
    random.setstate(saved["python"])
    if "cuda" in saved and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(saved["cuda"])


def train_loader(trainer: Any) -> ResumableLoader | None:
    """The trainer's training loader where it is a :class:`~ablate.data.order.ResumableLoader`."""
    loaders = getattr(trainer, "train_dataloader", None)
    found = (
        loaders.values() if isinstance(loaders, dict) else loaders if isinstance(loaders, list | tuple) else [loaders]
    )
    return next((loader for loader in found if isinstance(loader, ResumableLoader)), None)


class GlobalGenerators(Callback):
    """Saves the global generators' states and the training order's (:class:`~ablate.data.order.ResumableLoader`)
    in each checkpoint (``checkpoint["generators"]``), and gives both back when training starts from one: after
    the loader is built and before it draws."""

    KEY = "generators"

    def __init__(self) -> None:
        self.pending: dict[str, Any] | None = None

    def on_save_checkpoint(self, trainer: Any, pl_module: Any, checkpoint: dict[str, Any]) -> None:
        loader = train_loader(trainer)
        checkpoint[self.KEY] = {"global": states(), "order": loader.state_dict() if loader is not None else None}

    def on_load_checkpoint(self, trainer: Any, pl_module: Any, checkpoint: dict[str, Any]) -> None:
        self.pending = checkpoint.get(self.KEY)

    def on_train_start(self, trainer: Any, pl_module: Any) -> None:
        saved, self.pending = self.pending, None
        if saved is None:  # a fresh job, or a checkpoint written before the generators were saved
            return
        loader = train_loader(trainer)
        if loader is not None and saved.get("order") is not None:
            loader.load_state_dict(saved["order"])
        restore(saved["global"])
