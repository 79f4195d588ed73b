"""BiFNet's bidirectional fusion module (Li et al., seed 004 §IV-C, Fig. 4) and CBF's context gains in front of any
fusion operator.

The module has two groups, each DST -> DT -> CBF:

* the BEV group carries camera features into BEV space (space transform ``to_bev``), adapts them with DT and fuses
  them with the BEV features;
* the camera group carries BEV features into camera space (``to_cam``), adapts them and fuses them with the camera
  features. The camera-space branch's output is the network's prediction (Fig. 4).

DT, the domain transformation (eq. 12), is a 1x1 convolution from the source branch's channels to the target's
("realized by 1x1 convolution"; its kernel size was lost in the text copy, and 1x1 is the reading that only
"changes channels" without mixing positions the space transform placed). The fusion is any operator of the registry
(:func:`ablate.fusion.build`; CBF in the paper); its inputs are, as everywhere, camera first, LiDAR second.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor, nn

from ablate.fusion.geometry import Geometry
from ablate.fusion.ops import FusionOp
from ablate.fusion.space import SpaceTransform


class WithContext(nn.Module):
    """ "+CBF" (BiFNet §V-F) for an operator with fixed learned weights: CBF's context gains (eq. 9-10: global
    average pool per input, a three-layer MLP with ReLU in the middle and a sigmoid out, one gain per channel and
    input) multiply each input before the operator, ``op([q_1 * f_1, ..., q_N * f_N])``.

    Reading chosen for "applying CBF module to" LidCamNet and PLARD: their learned weights (a scalar per fusion
    point, a map per position) stay and CBF's per-sample channel gains act on top of them, so the weight each input
    gets changes with the scene, which is what §V-F says the fixed weights lack. (Replacing the weights outright
    would make both "+CBF" rows plain CBF, one network.) On ``sum`` this is exactly CBF (eq. 11). The MLP is CBF's
    (``ablate.fusion.ops_bifnet.CBF``: joint over the inputs' descriptors, hidden width max(N*C / reduction, 8)).
    ``forward(features: list[Tensor[B,C,H,W]]) -> Tensor[B,C,H,W]``; ``last_gates``: the gains of the last call.
    """

    def __init__(self, op: nn.Module, channels: int, num_inputs: int = 2, reduction: int = 16) -> None:
        super().__init__()
        from ablate.fusion.ops_bifnet import CBF

        self.op, self.num_inputs = op, num_inputs
        width = num_inputs * channels
        self.mlp = CBF._mlp(width, max(width // reduction, 8))
        self.last_gates: list[Tensor] | None = None

    def forward(self, features: list[Tensor]) -> Tensor:
        z = torch.cat([f.mean(dim=(2, 3)) for f in features], 1)
        q = [g[:, :, None, None] for g in self.mlp(z).chunk(self.num_inputs, 1)]
        self.last_gates = [g.detach() for g in q]
        return self.op([g * f for g, f in zip(q, features)])


def fusion_op(
    fusion: Callable[..., nn.Module], channels: int, num_inputs: int = 2, context: bool = False, reduction: int = 16
) -> nn.Module:
    """The operator ``fusion(channels=, num_inputs=)``, behind CBF's context gains when ``context`` ("+CBF")."""
    op = fusion(channels=channels, num_inputs=num_inputs)
    return WithContext(op, channels, num_inputs, reduction) if context else op


class BidirectionalFusion(nn.Module):
    """One bidirectional fusion module at one feature scale: ``forward(f_cam, f_bev, geometry) -> (fused camera
    features [B,C_cam,h,w], fused BEV features [B,C_bev,hb,wb])``.

    ``space``: a :class:`~ablate.fusion.space.SpaceTransform` (DST in the paper, SHPL as §V-E's baseline);
    ``stride``: the scale's stride in both spaces (the two backbones downsample alike); ``fusion``: builds an
    operator as ``fusion(channels=, num_inputs=2)``; ``context``: put CBF's gains in front of it (:class:`WithContext`).
    ``last_coverage``: per space, the fraction of positions the transform reached in the last call.
    """

    def __init__(
        self,
        cam_channels: int,
        bev_channels: int,
        space: SpaceTransform,
        stride: int,
        fusion: Callable[..., nn.Module],
        context: bool = False,
    ) -> None:
        super().__init__()
        self.space, self.stride = space, int(stride)
        self.dt_bev = nn.Conv2d(cam_channels, bev_channels, 1)  # DT of the BEV group: camera -> BEV channels
        self.dt_cam = nn.Conv2d(bev_channels, cam_channels, 1)  # DT of the camera group: BEV -> camera channels
        self.fuse_bev = fusion_op(fusion, bev_channels, 2, context)
        self.fuse_cam = fusion_op(fusion, cam_channels, 2, context)
        self.last_coverage: dict[str, float] = {}

    def forward(self, f_cam: Tensor, f_bev: Tensor, geometry: Geometry) -> tuple[Tensor, Tensor]:
        to_bev, to_cam = self.space.maps(geometry, tuple(f_cam.shape[-2:]), tuple(f_bev.shape[-2:]), self.stride)
        self.last_coverage = {name: float(m.coverage.float().mean()) for name, m in (("bev", to_bev), ("cam", to_cam))}
        cam_in_bev = self.dt_bev(to_bev(f_cam))
        bev_in_cam = self.dt_cam(to_cam(f_bev))
        return self.fuse_cam([f_cam, bev_in_cam]), self.fuse_bev([cam_in_bev, f_bev])

    def operators(self) -> list[nn.Module]:
        """The camera group's operator, then the BEV group's."""
        return [self.fuse_cam, self.fuse_bev]


def gains(module: nn.Module) -> list[Tensor] | None:
    """The per-channel gains of an operator's last call (CBF, or "+CBF"), one [B,C,1,1] per input, or None."""
    gates = getattr(module, "last_gates", None)
    if isinstance(module, FusionOp) and getattr(module, "op_name", "") != "cbf":
        return None
    return gates
