"""bench/false_positives.py's surface map: each generated frame's scene cast again names every pixel as the frame
written from that scene shows it (the sky where it has no depth, the road where its road mask is)."""

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from ablate.data.generate import render_frame

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
try:
    from false_positives import SURFACES, shares, surface_map
finally:
    sys.path.pop(0)


@pytest.mark.parametrize("furniture", [False, True])
def test_the_surface_map_recasts_the_frame_it_names(furniture):
    furnished = []
    for index in (3, 11):
        frame = render_frame(0, index, 64, 208, furniture=furniture)
        surface = surface_map(0, index, 64, 208, furniture)
        named = {name: surface == SURFACES.index(name) for name in SURFACES}
        assert np.array_equal(named["sky"], frame["depth"] == 0)
        on_road = named["road"] | named["road in shadow"] | named["lane marking"]
        assert np.array_equal(on_road, frame["road"])
        assert named["object"][frame["instance"] > 0].all()  # every labelled pixel is an object's
        furnished.append(bool(named["furniture"].any()))
    assert any(furnished) == furniture  # street furniture is named only in the frames that have it


def test_a_masks_shares_sum_to_one_over_the_surfaces():
    surface = np.array([[0, 1], [1, 7]])
    got = shares(torch.tensor([[True, True], [True, False]]), surface)
    assert got.sum() == pytest.approx(1.0) and got[1] == pytest.approx(2 / 3) and got[0] == pytest.approx(1 / 3)
    assert shares(torch.zeros(2, 2, dtype=torch.bool), surface).sum() == 0
