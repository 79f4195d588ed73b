"""The training split's frame order, which a job resumed from its checkpoint takes up where it stopped.

A loader built with ``shuffle=True`` and a seeded generator (``DataLoader(..., generator=g)``) draws each epoch's
order from ``g`` when its iterator starts: one int64 (the iterator's base seed, which seeds loader workers), then
``torch.randperm(n, generator=g)``. A job resumed from a checkpoint builds a new loader, whose generator starts
again at its seed, so without more every later epoch would take the order of the epoch before it; and Lightning
starts a resumed epoch's loader at its first batch ("your dataloader is not resumable").

:class:`FrameOrder` draws exactly what that loader's sampler drew, from the same generator, so an uninterrupted job
trains on the frames in the same order as before. :class:`ResumableLoader`'s state (``state_dict``) is the
generator's state to go on from and the batches of the current epoch already trained: at an epoch's end, the
generator as it is; in the middle of one, the generator as the epoch started and the batches to skip (without
loading them). The count of trained batches comes from Lightning's loops (``progress``), not from the loader,
which may have fetched a batch ahead. :class:`~ablate.jobs.generators.GlobalGenerators` saves that state in every
checkpoint and gives it back on every resume, beside torch's, NumPy's and Python's global generators; Lightning
itself gives a loader's state back only after a mid-epoch checkpoint.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

import torch
from torch.utils.data import DataLoader, Sampler


def trained_batches(trainer: Any) -> tuple[int, float] | None:
    """The batches of the current epoch ``trainer`` has trained on (its loops' ``processed`` count, which a
    checkpoint written in ``on_train_batch_end`` already counts and ``completed`` does not yet) and the batches of
    its epoch (``num_training_batches``, which ``limit_train_batches`` may cut); None without a trainer."""
    if trainer is None:
        return None
    return int(trainer.fit_loop.epoch_loop.batch_progress.current.processed), float(trainer.num_training_batches)


class FrameOrder(Sampler[int]):
    """A shuffled order of ``n`` frames per epoch, drawn from ``generator`` as RandomSampler draws it (the loader's
    own int64 draw comes first, when its iterator starts); ``skip`` frames of the next epoch are left out, once (a
    resumed epoch's trained batches)."""

    def __init__(self, n: int, generator: torch.Generator) -> None:
        self.n, self.generator, self.skip = n, generator, 0

    def __len__(self) -> int:
        return self.n

    def __iter__(self) -> Iterator[int]:
        skip, self.skip = self.skip, 0
        yield from torch.randperm(self.n, generator=self.generator).tolist()[skip:]
        # RandomSampler's draw for num_samples % n, taken when its iterator is run past the epoch's last frame, as
        # a plain ``for`` loop and Lightning's loops do
        yield from torch.randperm(self.n, generator=self.generator).tolist()[:0]


class ResumableLoader(DataLoader):
    """The training split's loader: shuffled by :class:`FrameOrder`, and resumable (Lightning's ``_Stateful``).

    ``progress`` (optional) gives the batches of the current epoch the trainer has trained on and the batches of
    its epoch (:func:`trained_batches`), or None where no trainer runs; then the batches this loader has handed
    out count, of its length."""

    def __init__(
        self,
        dataset: Any,
        batch_size: int,
        generator: torch.Generator,
        progress: Callable[[], tuple[int, float] | None] | None = None,
        **kwargs: Any,
    ) -> None:
        self.order = FrameOrder(len(dataset), generator)
        super().__init__(dataset, batch_size, sampler=self.order, generator=generator, **kwargs)
        self.progress = progress
        self.handed_out = 0
        #: the generator's state as the current epoch's iterator began (None before the first)
        self.epoch_state: torch.Tensor | None = None

    def __iter__(self) -> Iterator[Any]:
        self.epoch_state = self.generator.get_state()
        self.handed_out = self.order.skip // int(self.batch_size or 1)
        for batch in super().__iter__():
            self.handed_out += 1
            yield batch

    def trained(self) -> tuple[int, float]:
        """Batches of the current epoch trained, and of the whole epoch: from ``progress`` where it answers."""
        answer = self.progress() if self.progress is not None else None
        return answer if answer is not None else (self.handed_out, float(len(self)))

    def state_dict(self) -> dict[str, Any]:
        """The generator's state to go on from and the batches of its epoch to skip: at an epoch's end the
        generator as it is (the next epoch draws from there), in the middle of one its state as the epoch began."""
        done, epoch = self.trained()
        if done >= min(epoch, len(self)) or self.epoch_state is None:
            return {"generator": self.generator.get_state(), "skip_batches": 0}
        return {"generator": self.epoch_state.clone(), "skip_batches": done}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.generator.set_state(state["generator"])
        self.order.skip = int(state["skip_batches"]) * int(self.batch_size or 1)
