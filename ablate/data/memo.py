"""Decoded frames kept in memory from one epoch to the next (``data.memo_gb``).

A frame of a split without augmentation is the same sample in every epoch: its condition, corruption and LiDAR
weather come from a per-frame seeded generator (:class:`ablate.data.dataset.KittiDataset`), so reading it again
decodes the same PNGs, the same scan and the same derived LiDAR modalities to the same tensors. A second epoch
therefore needs none of that work: the memo keeps each sample as first built and hands out a copy of it (tensors
cloned: a caller that changes a batch in place cannot change the next epoch's frame). The numbers a job logs are
those of a job without it (tests/data/test_memo.py compares them).

It is off where a frame changes between epochs or cannot be shared: a split with augmentation (a new view of the
frame every epoch), and inside a loader worker process (``data.num_workers`` > 0: each worker would keep its own
copy of every frame it met). Its size is bounded: frames beyond ``max_bytes``, or beyond what the machine has to
spare (:data:`RESERVE_SHARE`), are read from disk each time, as without it. The data module lets them go once its
fit ends (:meth:`ablate.data.datamodule.KittiDataModule.teardown`): a process that fits several times (a job's
experts, then its fused network) holds one fit's frames at a time.
"""

from __future__ import annotations

from typing import Any

import psutil
import torch

from ablate.data.trees import tree_map, tree_tensors

#: What the memo leaves the machine: it keeps no frame that would bring the memory available to all processes below
#: this share of the total, or below RESERVE_MIN bytes, whichever is more. Parallel jobs each keep their own frames
#: (2 jobs of BiFNet Table IV at the cpu scale about 1.5 GiB each); on a small machine the later frames are read from
#: disk instead of the jobs running out of memory.
RESERVE_SHARE = 0.2
RESERVE_MIN = 2 * 2**30


def spare_bytes() -> float:
    """Bytes the machine has available beyond the reserve (negative when short)."""
    memory = psutil.virtual_memory()
    return memory.available - max(RESERVE_SHARE * memory.total, RESERVE_MIN)


def tensor_bytes(tree: Any) -> int:
    """Bytes held by the tensors of a sample (:mod:`ablate.data.trees`)."""
    return sum(t.numel() * t.element_size() for t in tree_tensors(tree))


def copied(tree: Any) -> Any:
    """A sample with every tensor cloned (its other values are immutable: names, numbers)."""
    return tree_map(torch.clone, tree)


class FrameMemo:
    """Samples by index, up to ``max_bytes`` of tensors; :attr:`hits` and :attr:`misses` count the reads."""

    def __init__(self, max_bytes: float) -> None:
        self.max_bytes = max_bytes
        self.samples: dict[int, dict[str, Any]] = {}
        self.nbytes = 0
        self.hits = self.misses = 0

    def get(self, index: int) -> dict[str, Any] | None:
        """A copy of the sample kept for ``index``, or None (counted as a miss)."""
        sample = self.samples.get(index)
        if sample is None:
            self.misses += 1
            return None
        self.hits += 1
        return copied(sample)

    def clear(self) -> None:
        """Let every kept frame go (the counts stay)."""
        self.samples.clear()
        self.nbytes = 0

    def put(self, index: int, sample: dict[str, Any]) -> dict[str, Any]:
        """Keep a copy of ``sample`` for ``index`` while it fits within :attr:`max_bytes` and the machine's spare
        memory (:func:`spare_bytes`); returns ``sample`` itself."""
        size = tensor_bytes(sample)
        if index not in self.samples and self.nbytes + size <= self.max_bytes and size < spare_bytes():
            self.samples[index] = copied(sample)
            self.nbytes += size
        return sample
