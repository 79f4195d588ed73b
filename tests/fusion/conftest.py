"""Fixtures for the fusion tests: a tiny task head and a tiny FusionModel factory."""

import functools

import pytest
from torch import nn

from ablate.fusion import FusionModel, build

MODALITIES = {"rgb": 3, "dense_depth": 1}
BACKBONE = {"depth": 18, "width": 0.125}


class TinyHead(nn.Module):
    """A head shaped like a YOLACT one: per-level class maps plus one prototype map."""

    def __init__(self, in_channels: int, num_levels: int, classes: int = 3) -> None:
        super().__init__()
        self.out_channels = {"cls": [classes] * num_levels, "proto": 4}
        self.cls = nn.ModuleList(nn.Conv2d(in_channels, classes, 3, padding=1) for _ in range(num_levels))
        self.proto = nn.Conv2d(in_channels, 4, 1)

    def forward(self, levels):
        return {"cls": [c(p) for c, p in zip(self.cls, levels)], "proto": self.proto(levels[0])}


def model(stage, op="sum", modalities=MODALITIES, **kw):
    return FusionModel(
        stage=stage,
        modalities=modalities,
        fusion=functools.partial(build, name=op),
        head=TinyHead,
        backbone=BACKBONE,
        fpn_channels=8,
        single="rgb",
        **kw,
    )


@pytest.fixture
def tiny_head():
    return TinyHead


@pytest.fixture
def make_model():
    return model
