"""Nested dicts and lists of tensors, as samples, batches and the frozen experts' features are: a function mapped
over their tensors, and their tensors listed. Any other value (a frame's name, a number) is a leaf left as it is."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

import torch


def tree_map(fn: Callable[[torch.Tensor], torch.Tensor], tree: Any) -> Any:
    """``tree`` with ``fn`` applied to each of its tensors (lists and tuples become lists)."""
    if torch.is_tensor(tree):
        return fn(tree)
    if isinstance(tree, dict):
        return {k: tree_map(fn, v) for k, v in tree.items()}
    if isinstance(tree, (list, tuple)):
        return [tree_map(fn, v) for v in tree]
    return tree


def tree_tensors(tree: Any) -> Iterator[torch.Tensor]:
    """The tensors of ``tree``, depth first."""
    if torch.is_tensor(tree):
        yield tree
    elif isinstance(tree, dict):
        for value in tree.values():
            yield from tree_tensors(value)
    elif isinstance(tree, (list, tuple)):
        for value in tree:
            yield from tree_tensors(value)
