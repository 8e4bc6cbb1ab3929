"""Shared fixtures: the real data beside the project, and deterministic seeds."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
# ../shared/data from the project's root; MAPKIT_SHARED_DATA overrides it
SHARED_DATA = Path(os.environ.get("MAPKIT_SHARED_DATA", REPO.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def kitti_clip() -> Path:
    """The real KITTI odometry clip (51 frames); the test is skipped with a reason when absent."""
    path = SHARED_DATA / "kitti-odometry-clip"
    if not (path / "poses.txt").is_file():
        pytest.skip(f"real data not found at {path} (expected ../shared/data/kitti-odometry-clip beside the project)")
    return path


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)
