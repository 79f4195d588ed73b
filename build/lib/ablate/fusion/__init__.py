"""Fusion operators, fusion stages and space transforms.

``build(name, channels, num_inputs=2, **options)`` makes an operator from ``OPERATORS``;
``FusionModel`` places it at one of ``STAGES``; ``build_space(name)`` makes a camera <-> BEV space transform from
``SPACES`` (BiFNet's DST, SHPL), and ``BidirectionalFusion`` fuses across the two spaces with any operator.
"""

from ablate.fusion import ops_bifnet  # noqa: F401  (registers cbf, lidcamnet, plard)
from ablate.fusion.bidirectional import BidirectionalFusion, WithContext
from ablate.fusion.ops import OPERATORS, FusionOp, build, register, sharpen
from ablate.fusion.space import SPACES, build_space
from ablate.fusion.stages import STAGES, FusionModel

__all__ = [
    "OPERATORS",
    "SPACES",
    "STAGES",
    "BidirectionalFusion",
    "FusionModel",
    "FusionOp",
    "WithContext",
    "build",
    "build_space",
    "register",
    "sharpen",
]
