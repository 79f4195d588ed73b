"""Frozen parts of a model: their weights fixed and their BatchNorm statistics too (SMoE §4.3: the fusion network
is fine-tuned "with fixed weights of each expert network"; BiFNet §V-B trains its two networks separately first)."""

from __future__ import annotations

from torch import nn


class FreezableModel(nn.Module):
    """A model some of whose parts can be frozen (:meth:`freeze`): requires_grad off, and eval mode even under
    ``train()``, so that BatchNorm keeps the statistics the parts were trained with."""

    def __init__(self) -> None:
        super().__init__()
        self._frozen: list[nn.Module] = []

    def freeze(self, part: nn.Module) -> None:
        """Fix ``part``'s weights and BatchNorm statistics from now on."""
        part.requires_grad_(False)
        self._frozen.append(part)
        part.eval()

    def is_frozen(self, part: nn.Module) -> bool:
        return any(part is p for p in self._frozen)

    def train(self, mode: bool = True) -> FreezableModel:
        super().train(mode)
        for part in self._frozen:
            part.eval()
        return self
