"""Shared fixtures. Real KITTI frames are read from ../shared/kitti, never copied into the repo."""

from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
SHARED_KITTI = REPO.parent / "shared" / "kitti"

torch.set_num_threads(1)


@pytest.fixture(scope="session")
def kitti_root() -> Path:
    """Root of the real KITTI sample frames (object/ and road/ layouts)."""
    if not (SHARED_KITTI / "object" / "training").is_dir():
        pytest.skip(f"real KITTI frames not found at {SHARED_KITTI}")
    return SHARED_KITTI
