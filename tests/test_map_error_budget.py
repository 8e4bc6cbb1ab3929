"""bench/map_error_budget.py's scratch sessions: each variant's poses are the ones the mapper reads.

No log is opened: a stage that runs again would open it (and fail), so a builder that returns the
variant's trajectory took both reused stages as finished.
"""

from __future__ import annotations

import importlib.util
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from mapkit.core.geometry import make_pose
from mapkit.core.runio import is_done, mark_done
from mapkit.mapping.build import BuildConfig, SessionBuilder, _stage_hash
from mapkit.mapping.trajectory import Trajectory

BENCH = Path(__file__).resolve().parents[1] / "bench" / "map_error_budget.py"


@pytest.fixture(scope="module")
def meb():
    spec = importlib.util.spec_from_file_location("map_error_budget_under_test", BENCH)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _traj(n: int, x0: float) -> Trajectory:
    poses = np.stack([make_pose(np.eye(3), [x0 + i, 0.0, 0.0]) for i in range(n)])
    return Trajectory(np.arange(n, dtype=np.int64) * 100_000_000, poses, "lidar:/points", frame="enu")


def _built_workspace(root: Path, fused: bool) -> Path:
    """A workspace whose session ``s`` has finished trajectory and georef stages, marked with a config hash
    the current code no longer computes (as when a config section gained a field since the build)."""
    s = root / "sessions" / "s"
    _traj(20, 0.0).save(s / "trajectory")
    mark_done(s / "trajectory", "stale-trajectory", inputs={"log": {}}, outputs=True)
    _traj(20, 100.0).save(s / "georef" / "trajectory_enu")
    if fused:
        _traj(20, 200.0).save(s / "georef" / "trajectory_fused")
    mark_done(s / "georef", "stale-georef", inputs={"log": {}, "trajectory": "x"}, outputs=True)
    (root / "origin.json").write_text('{"lat_deg": 0.0, "lon_deg": 0.0, "alt_m": 0.0}')
    return s


def _log(root: Path) -> Path:
    log = root / "log" / "s"
    log.mkdir(parents=True)
    (log / "s_0.mcap").write_bytes(b"not read")
    old = 1_000_000_000
    os.utime(log / "s_0.mcap", (old, old))  # settled: the fingerprint does not wait for a writer
    return log


@pytest.mark.parametrize("fused", [True, False])
def test_variant_poses_are_the_mapped_trajectory(meb, tmp_path, fused):
    sdir = _built_workspace(tmp_path / "ws", fused)
    cfg = BuildConfig(georef={"fuse": fused})
    builder = SessionBuilder(_log(tmp_path), tmp_path / "scratch", cfg, progress=False, name="s")
    try:
        meb._copy_stages(builder, sdir, ("trajectory", "georef"))
        mapped = builder.dirs.enu_trajectory
        assert mapped == (builder.dirs.fused_trajectory if fused else builder.dirs.georef_trajectory)
        # the workspace's markers copied as they are: the builder would run georef again
        h = _stage_hash(builder.cfg, "georef")
        assert not is_done(builder.dirs.georef, h, inputs=builder._inputs(builder.dirs.trajectory), verify=True)

        variant = _traj(15, -50.0)
        shutil.rmtree(mapped)
        variant.save(mapped)
        meb._mark_finished(builder, ("trajectory", "georef"))
        used = builder.enu_trajectory()
    finally:
        builder.close()
    np.testing.assert_array_equal(used.stamps_ns, variant.stamps_ns)
    np.testing.assert_array_equal(used.world_from_base, variant.world_from_base)
    assert (tmp_path / "scratch" / "origin.json").is_file()
