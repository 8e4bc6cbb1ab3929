"""Shared fixtures: the real data beside the project, and deterministic seeds."""

from __future__ import annotations

import mapkit  # noqa: F401  (imported first: it names OpenBLAS's kernel before numpy loads; mapkit.core.blas)

# isort: split
import os
import shutil
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


@pytest.fixture(scope="module")
def clip12(kitti_clip, tmp_path_factory) -> Path:
    """The first 12 frames of the real KITTI clip as a KITTI odometry folder, with its calibration, poses and times."""
    d = tmp_path_factory.mktemp("kitti12") / "clip12"
    (d / "image_l").mkdir(parents=True)
    for i in range(12):
        shutil.copy(kitti_clip / "image_l" / f"{i:06d}.png", d / "image_l")
    shutil.copy(kitti_clip / "calib.txt", d)
    lines = (kitti_clip / "poses.txt").read_text().splitlines()[:12]
    (d / "poses.txt").write_text("\n".join(lines) + "\n")
    (d / "times.txt").write_text("".join(f"{0.1 * i:.6e}\n" for i in range(12)))
    return d


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


#: the test files whose module fixtures run longest (`pytest --durations`: the two tiny chains of test_demo.py alone
#: take five minutes), started first so that the other worker is never left idle while one of them runs at the end
LONGEST_FIRST = ("test_demo.py", "test_loop_closure.py", "test_eval_align.py", "test_executor.py")


def pytest_collection_modifyitems(items: list) -> None:
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: the rest keep their order
