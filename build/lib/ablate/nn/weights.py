"""Load network weights from a local file only (``torch.load(..., weights_only=True)``); nothing is downloaded."""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn


class WeightsError(ValueError):
    """A weights file is missing, unreadable, or does not fit the network."""


def load_weights(module: nn.Module, path: str | Path, ignore: tuple[str, ...] = ()) -> None:
    """Load the state dict in ``path`` into ``module``, strictly.

    Keys starting with a prefix in ``ignore`` are dropped first (e.g. a classifier ``fc.`` the trunk does
    not have). A missing file, a missing or unexpected key, or a shape mismatch raises ``WeightsError``
    naming the file.
    """
    load_checked(module, read_state_dict(path, ignore), path)


def read_state_dict(path: str | Path, ignore: tuple[str, ...] = ()) -> dict[str, torch.Tensor]:
    """The state dict in ``path``: the file's dict, or the one under its ``state_dict`` / ``model`` key."""
    path = Path(path)
    if not path.is_file():
        raise WeightsError(f"weights file not found: {path}")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # unpickling errors come in several types
        raise WeightsError(f"weights file {path} could not be read as a state dict: {err}") from err
    for key in ("state_dict", "model"):
        if isinstance(state, dict) and isinstance(state.get(key), dict):
            state = state[key]
    if not isinstance(state, dict):
        raise WeightsError(f"weights file {path} holds {type(state).__name__}, not a state dict")
    return {k: v for k, v in state.items() if not k.startswith(tuple(ignore))}


def load_checked(module: nn.Module, state: dict[str, torch.Tensor], path: str | Path) -> None:
    """``module.load_state_dict(state)`` with one ``WeightsError`` naming ``path`` on any mismatch."""
    own = module.state_dict()
    missing, unexpected = sorted(set(own) - set(state)), sorted(set(state) - set(own))
    shapes = [
        f"{k}: file {tuple(state[k].shape)} vs network {tuple(own[k].shape)}"
        for k in sorted(set(own) & set(state))
        if tuple(state[k].shape) != tuple(own[k].shape)
    ]
    if missing or unexpected or shapes:
        parts = [
            f"missing {missing[:5]}{' ...' if len(missing) > 5 else ''}" if missing else "",
            f"unexpected {unexpected[:5]}{' ...' if len(unexpected) > 5 else ''}" if unexpected else "",
            f"shape mismatch {shapes[:3]}{' ...' if len(shapes) > 3 else ''}" if shapes else "",
        ]
        raise WeightsError(
            f"weights file {path} does not fit {type(module).__name__}: " + "; ".join(p for p in parts if p)
        )
    module.load_state_dict(state)


def adapt_first_conv(weight: torch.Tensor, in_channels: int) -> torch.Tensor:
    """A first-layer conv weight [O, I, k, k] made to take ``in_channels`` inputs.

    Averaged over its I inputs, repeated ``in_channels`` times and scaled by I / in_channels, so a grey
    input gives the response the original filter gives to that grey in all I channels.
    """
    return weight.mean(1, keepdim=True).repeat(1, in_channels, 1, 1) * (weight.shape[1] / in_channels)
