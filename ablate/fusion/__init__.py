"""Fusion operators and fusion stages.

``build(name, channels, num_inputs=2, **options)`` makes an operator from ``OPERATORS``;
``FusionModel`` places it at a stage from ``STAGES``.
"""
from ablate.fusion import ops_bifnet  # noqa: F401  (registers cbf, lidcamnet, plard)
from ablate.fusion.ops import OPERATORS, FusionOp, build, register, sharpen

__all__ = ["OPERATORS", "FusionOp", "build", "register", "sharpen"]
