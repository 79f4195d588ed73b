"""Fusion operators behind one registry.

Every operator is built by ``build(name, channels, num_inputs=2, **options)`` and has
``forward(features: list[Tensor[B,C,H,W]]) -> Tensor[B,C,H,W]``. ``features[0]`` is the camera f_i,
``features[1]`` the LiDAR f_j, further entries any other modality, all of one shape.

Gated operators keep ``last_gates``: a list with one detached tensor per input (the gate or weight
multiplied onto that input in the last forward), for plots such as DGFN Fig. 5.

Every operator has a natural N-way form (documented per class), so each accepts N >= 2.
The BiFNet operators (cbf, lidcamnet, plard) live in ``ops_bifnet.py`` and register here.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from functools import reduce
from typing import Any, TypeVar

import torch
import torch.nn.functional as F
from torch import Tensor, nn

OPERATORS: dict[str, type[FusionOp]] = {}
_Class = TypeVar("_Class", bound=type)


def registry(table: dict[str, _Class], kind: str, attribute: str) -> Callable[[str], Callable[[_Class], _Class]]:
    """A class decorator factory: ``@reg(name)`` adds the class to ``table`` under ``name`` and sets
    ``cls.<attribute> = name``; a name registered twice is an error naming ``kind``."""

    def reg(name: str) -> Callable[[_Class], _Class]:
        def add(cls: _Class) -> _Class:
            if name in table:
                raise ValueError(f"{kind} {name!r} registered twice")
            setattr(cls, attribute, name)
            table[name] = cls
            return cls

        return add

    return reg


#: Class decorator adding a fusion operator to ``OPERATORS`` under a name.
register = registry(OPERATORS, "fusion operator", "op_name")


def build(name: str, channels: int, num_inputs: int = 2, **options: Any) -> nn.Module:
    """Build the fusion operator ``name`` for ``num_inputs`` inputs of ``channels`` channels."""
    if name not in OPERATORS:
        raise ValueError(f"unknown fusion operator {name!r}; valid: {', '.join(sorted(OPERATORS))}")
    cls = OPERATORS[name]
    allowed = [p for p in inspect.signature(cls.__init__).parameters if p not in ("self", "channels", "num_inputs")]
    bad = sorted(set(options) - set(allowed))
    if bad:
        raise TypeError(f"fusion operator {name!r} has no option {', '.join(bad)}; options: {allowed or 'none'}")
    return cls(channels=channels, num_inputs=num_inputs, **options)


class FusionOp(nn.Module):
    """Base class: checks the input list; subclasses implement ``fuse``."""

    op_name = "?"

    def __init__(self, channels: int, num_inputs: int = 2) -> None:
        super().__init__()
        if channels < 1:
            raise ValueError(f"fusion operator {self.op_name!r}: channels must be >= 1, got {channels}")
        if num_inputs < 2:
            raise ValueError(f"fusion operator {self.op_name!r}: num_inputs must be >= 2, got {num_inputs}")
        self.channels, self.num_inputs = channels, num_inputs
        self.last_gates: list[Tensor] | None = None

    def forward(self, features: list[Tensor]) -> Tensor:
        if len(features) != self.num_inputs:
            raise ValueError(
                f"fusion operator {self.op_name!r} built for {self.num_inputs} inputs, got {len(features)}"
            )
        shape = features[0].shape
        if len(shape) != 4 or shape[1] != self.channels or any(f.shape != shape for f in features):
            raise ValueError(
                f"fusion operator {self.op_name!r} expects {self.num_inputs} tensors "
                f"[B,{self.channels},H,W] of one shape, got {[tuple(f.shape) for f in features]}"
            )
        return self.fuse(list(features))

    def fuse(self, features: list[Tensor]) -> Tensor:
        raise NotImplementedError

    def extra_repr(self) -> str:
        return f"channels={self.channels}, num_inputs={self.num_inputs}"


@register("sum")
class Sum(FusionOp):
    """Elementwise sum (SMoE Table 1 "Sum fusion"); N-way: sum of all inputs."""

    def fuse(self, features: list[Tensor]) -> Tensor:
        return reduce(torch.add, features)


@register("mean")
class Mean(FusionOp):
    """Elementwise average; N-way: mean of all inputs."""

    def fuse(self, features: list[Tensor]) -> Tensor:
        return reduce(torch.add, features) / len(features)


@register("max")
class Max(FusionOp):
    """Elementwise maximum (SMoE Table 1 "Maximum fusion"); N-way: maximum over all inputs."""

    def fuse(self, features: list[Tensor]) -> Tensor:
        return reduce(torch.maximum, features)


@register("concat")
class Concat(FusionOp):
    """Channel concatenation then a 1x1 conv (with bias, no activation) from N*C back to C."""

    def __init__(self, channels: int, num_inputs: int = 2) -> None:
        super().__init__(channels, num_inputs)
        self.conv = nn.Conv2d(num_inputs * channels, channels, 1)

    def fuse(self, features: list[Tensor]) -> Tensor:
        return self.conv(torch.cat(features, 1))


def sharpen(features: list[Tensor], a: float) -> Tensor:
    """Sharpening fusion, SMoE eq. 4-5 (after Tong et al. [17]).

    t = mean(f_i + f_j) per sample over C, H, W (eq. 4: one "global" threshold per sample);
    f_p = max(f_i, f_j); output a * f_p where f_p > t, else f_i + f_j (eq. 5).
    N-way: the sum and the maximum run over all N inputs.
    """
    total = reduce(torch.add, features)
    t = total.mean(dim=(1, 2, 3), keepdim=True)
    f_p = reduce(torch.maximum, features)
    return torch.where(f_p > t, a * f_p, total)


@register("sharpen")
class Sharpen(FusionOp):
    """Sharpening fusion on the raw inputs, SMoE eq. 4-5 (Table 1 "Sharpening fusion").

    The gain ``a`` is not given in SMoE. Default 2.0: the smallest gain for which a strong feature is
    never weaker than under sum fusion when features are non-negative (f_i + f_j <= 2 * max(f_i, f_j)),
    so "strengthen the strong features" holds; with N inputs the same argument gives a = N.
    """

    def __init__(self, channels: int, num_inputs: int = 2, a: float = 2.0) -> None:
        super().__init__(channels, num_inputs)
        self.a = float(a)

    def fuse(self, features: list[Tensor]) -> Tensor:
        return sharpen(features, self.a)

    def extra_repr(self) -> str:
        return f"{super().extra_repr()}, a={self.a}"


class Gate(nn.Module):
    """SMoE gating network, eq. 2-3.

    N = 2 (the paper): W = sigmoid(Conv1x1(concat(f_i, f_j))), one conv from 2C to C channels;
    gates [W, 1 - W]. N > 2: the conv maps N*C to N*C channels, read as N maps of C channels, and a
    softmax over the N maps gives the gates. For N = 2 this softmax equals the sigmoid form
    (softmax([z1, z2])[0] = sigmoid(z1 - z2)), so the paper's C-channel conv is kept there.
    """

    def __init__(self, channels: int, num_inputs: int) -> None:
        super().__init__()
        self.num_inputs = num_inputs
        out = channels if num_inputs == 2 else num_inputs * channels
        self.conv = nn.Conv2d(num_inputs * channels, out, 1)

    def forward(self, features: list[Tensor]) -> list[Tensor]:
        z = self.conv(torch.cat(features, 1))
        if self.num_inputs == 2:
            w = torch.sigmoid(z)
            return [w, 1 - w]
        b, _, h, w = z.shape
        return list(z.view(b, self.num_inputs, -1, h, w).softmax(1).unbind(1))


class MoE(FusionOp):
    """Gating network (SMoE eq. 2-3) weighting each input, then a combination of the weighted inputs."""

    def __init__(self, channels: int, num_inputs: int = 2) -> None:
        super().__init__(channels, num_inputs)
        self.gate = Gate(channels, num_inputs)

    def fuse(self, features: list[Tensor]) -> Tensor:
        gates = self.gate(features)
        self.last_gates = [g.detach() for g in gates]
        return self.combine([g * f for g, f in zip(gates, features)])

    def combine(self, weighted: list[Tensor]) -> Tensor:
        raise NotImplementedError


@register("moe_sum")
class MoESum(MoE):
    """SMoE Table 1 "MoE+Sum fusion": f_i^g + f_j^g (eq. 3 then sum); N-way: sum of the N weighted inputs."""

    def combine(self, weighted: list[Tensor]) -> Tensor:
        return reduce(torch.add, weighted)


@register("moe_max")
class MoEMax(MoE):
    """SMoE Table 1 "MoE+Maximum fusion": max(f_i^g, f_j^g); N-way: maximum over the N weighted inputs."""

    def combine(self, weighted: list[Tensor]) -> Tensor:
        return reduce(torch.maximum, weighted)


@register("smoe")
class SMoE(MoE):
    """SMoE (sharpening mixture of experts): gating eq. 2-3, then sharpening eq. 4-5 on f_i^g, f_j^g.

    Default gain ``a`` = 2.0 for the reason given in ``Sharpen``.
    """

    def __init__(self, channels: int, num_inputs: int = 2, a: float = 2.0) -> None:
        super().__init__(channels, num_inputs)
        self.a = float(a)

    def combine(self, weighted: list[Tensor]) -> Tensor:
        return sharpen(weighted, self.a)

    def extra_repr(self) -> str:
        return f"{super().extra_repr()}, a={self.a}"


@register("gfu")
class GFU(FusionOp):
    """Gated fusion unit, DGFN eq. 5-9.

    F_G = concat(F_C, F_L) (eq. 5); w_k = sigmoid(Conv3x3_k(F_G) -> 1 channel) with its own conv and
    bias per input (eq. 6-7); F_F = concat(F_k * w_k) (eq. 8); F_J = ReLU(Conv1x1(F_F) -> C) (eq. 9).
    Concatenation follows the input order (camera first); the order only permutes conv weights.
    ``gated=False`` is DGFN's baseline "without GFU" (§IV-B: weight maps fixed to one): concat, 1x1, ReLU.
    N-way: one independent sigmoid gate per input, as the two DGFN gates are independent (not a softmax).
    """

    def __init__(self, channels: int, num_inputs: int = 2, gated: bool = True) -> None:
        super().__init__(channels, num_inputs)
        self.gated = bool(gated)
        n = num_inputs if self.gated else 0
        self.gates = nn.ModuleList(nn.Conv2d(num_inputs * channels, 1, 3, padding=1) for _ in range(n))
        self.joint = nn.Conv2d(num_inputs * channels, channels, 1)

    def fuse(self, features: list[Tensor]) -> Tensor:
        f_g = torch.cat(features, 1)
        if not self.gated:
            self.last_gates = [f_g.new_ones(f_g.shape[0], 1, *f_g.shape[2:]) for _ in features]
            return F.relu(self.joint(f_g))
        w = [torch.sigmoid(conv(f_g)) for conv in self.gates]
        self.last_gates = [wk.detach() for wk in w]
        f_f = torch.cat([f * wk for f, wk in zip(features, w)], 1)
        return F.relu(self.joint(f_f))

    def extra_repr(self) -> str:
        return f"{super().extra_repr()}, gated={self.gated}"
