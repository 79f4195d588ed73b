"""Fusion operators from BiFNet (Li et al.): CBF (§IV-B) and the LidCamNet / PLARD fusion of §V-F.

Input order as everywhere: ``features[0]`` camera, ``features[1]`` LiDAR, further inputs other modalities.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import reduce

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ablate.fusion.ops import FusionOp, register


@register("cbf")
class CBF(FusionOp):
    """Context-based fusion, BiFNet eq. 9-11 (after SENet).

    eq. 9: z_k = global average pool of input k over H, W (the "feature representation ability", [B,C]);
    eq. 10: q = sigmoid(FC3(ReLU(FC2(ReLU(FC1(z)))))), the "context quality", one gain per channel;
    eq. 11: x~_c = q_c * x_c, and the reweighted features of all inputs are summed.

    Reading chosen where the converted text lost its symbols: the three-layer perceptron has three fully
    connected layers (ReLU after the first two, sigmoid at the output). With ``joint=True`` (default) one
    MLP sees the descriptors of all inputs concatenated ([B, N*C] -> [B, N*C]), so the gain of each sensor
    depends on the context seen by every sensor, which is how the prose motivates CBF (suppress the sensor
    that expresses the scene badly). ``joint=False`` gives each input its own MLP on its own descriptor
    (plain SE per sensor). Hidden width: max(in_features // reduction, 8), SENet's reduction ratio.
    N-way: N descriptors, N*C gains, sum of the N reweighted inputs.
    """

    def __init__(self, channels: int, num_inputs: int = 2, reduction: int = 16, joint: bool = True) -> None:
        super().__init__(channels, num_inputs)
        if reduction < 1:
            raise ValueError(f"fusion operator 'cbf': reduction must be >= 1, got {reduction}")
        self.joint = bool(joint)
        width = num_inputs * channels if self.joint else channels
        self.mlps = nn.ModuleList(
            self._mlp(width, max(width // reduction, 8)) for _ in range(1 if joint else num_inputs)
        )

    @staticmethod
    def _mlp(width: int, hidden: int) -> nn.Sequential:
        return nn.Sequential(
            nn.Linear(width, hidden),
            nn.ReLU(inplace=True),
            nn.Linear(hidden, hidden),
            nn.ReLU(inplace=True),
            nn.Linear(hidden, width),
            nn.Sigmoid(),
        )

    def fuse(self, features: list[Tensor]) -> Tensor:
        z = [f.mean(dim=(2, 3)) for f in features]
        if self.joint:
            q = list(self.mlps[0](torch.cat(z, 1)).chunk(self.num_inputs, 1))
        else:
            q = [mlp(zk) for mlp, zk in zip(self.mlps, z)]
        q = [qk[:, :, None, None] for qk in q]
        self.last_gates = [qk.detach() for qk in q]
        return reduce(torch.add, [qk * f for qk, f in zip(q, features)])


@register("lidcamnet")
class LidCamNet(FusionOp):
    """LidCamNet fusion as BiFNet §V-F describes it: f_i + alpha * f_j.

    "LidCamNet only learns the weights of LiDAR, and each fusion connection has only one value": one
    learnable scalar alpha on the LiDAR features per operator (= per fusion connection); the camera
    weight stays 1. ``init`` = 1.0 by default, so training starts from sum fusion.
    N-way: the camera input is the reference; every other input gets its own scalar.
    """

    def __init__(self, channels: int, num_inputs: int = 2, init: float = 1.0) -> None:
        super().__init__(channels, num_inputs)
        self.alpha = nn.Parameter(torch.full((num_inputs - 1,), float(init)))

    def fuse(self, features: list[Tensor]) -> Tensor:
        alphas = list(self.alpha.unbind(0))
        self.last_gates = [self.alpha.new_ones(1, 1, 1, 1)] + [a.detach().view(1, 1, 1, 1) for a in alphas]
        return reduce(torch.add, [features[0]] + [a * f for a, f in zip(alphas, features[1:])])


@register("plard")
class PLARD(FusionOp):
    """PLARD fusion as BiFNet §V-F describes it: f_i + w ⊙ f_j with one learnable weight per position.

    "It sets a learnable weight for each pixel position of the feature" and, as for LidCamNet, the weight
    is on the LiDAR side and does not depend on the sample. The weight map is [1, 1, size[0], size[1]]
    (one value per position, shared by the channels), initialised to ``init``. The operator is built
    before the feature size is known, so when a feature map is not of ``size`` the map is resampled to it
    bilinearly (align_corners=False); at ``size`` the weight is exactly one value per position.
    N-way: the camera input is the reference; every other input gets its own map.
    """

    def __init__(self, channels: int, num_inputs: int = 2, size: Sequence[int] = (48, 160), init: float = 1.0) -> None:
        super().__init__(channels, num_inputs)
        size = tuple(int(s) for s in size)
        if len(size) != 2 or min(size) < 1:
            raise ValueError(f"fusion operator 'plard': size must be (H, W) with H, W >= 1, got {size}")
        self.size = size
        self.weight = nn.Parameter(torch.full((num_inputs - 1, 1, *size), float(init)))

    def fuse(self, features: list[Tensor]) -> Tensor:
        h, w = features[0].shape[-2:]
        maps = (
            self.weight
            if (h, w) == self.size
            else F.interpolate(self.weight, size=(h, w), mode="bilinear", align_corners=False)
        )
        maps = [m[None] for m in maps.unbind(0)]
        self.last_gates = [torch.ones_like(maps[0]).detach()] + [m.detach() for m in maps]
        return reduce(torch.add, [features[0]] + [m * f for m, f in zip(maps, features[1:])])

    def extra_repr(self) -> str:
        return f"{super().extra_repr()}, size={self.size}"
