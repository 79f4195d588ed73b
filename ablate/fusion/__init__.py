"""Fusion operators and fusion stages.

``build(name, channels, num_inputs=2, **options)`` makes an operator from ``OPERATORS``;
``FusionModel`` places it at one of ``STAGES``.
"""
from ablate.fusion import ops_bifnet  # noqa: F401  (registers cbf, lidcamnet, plard)
from ablate.fusion.ops import OPERATORS, FusionOp, build, register, sharpen
from ablate.fusion.stages import STAGES, FusionModel

__all__ = ["OPERATORS", "STAGES", "FusionModel", "FusionOp", "build", "register", "sharpen"]
