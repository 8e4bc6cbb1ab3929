"""GPS alignment recovers a known similarity despite noise and multipath jumps."""

import numpy as np
import pytest

from mapkit.core.errors import InputError, InputWarning
from mapkit.core.geometry import make_pose, make_sim3, transform_points, yaw_rotation
from mapkit.mapping.gps_align import align_to_gps, associate_fixes


def _curvy_drive(n=400):
    """A 1.2 km drive with two turns, in a level trajectory frame."""
    s = np.linspace(0, 1200, n)
    x = np.where(s < 400, s, 400 + 150 * np.sin((s - 400) / 300))
    y = np.where(s < 400, 0.0, (s - 400) * 0.8)
    z = 0.5 * np.sin(s / 200)
    return np.stack([x, y, z], axis=1)


TRUE = make_sim3(1.03, yaw_rotation(np.radians(37.0)), [250.0, -120.0, 4.0])


@pytest.mark.parametrize("mode", ["yaw_scale", "sim3"])
def test_recovers_known_transform_despite_multipath(rng, mode):
    p_map = _curvy_drive()
    p_enu = transform_points(TRUE, p_map) + rng.normal(scale=[3.0, 3.0, 5.0], size=p_map.shape)
    jumps = rng.choice(len(p_map), size=40, replace=False)  # 10% multipath: 25-60 m off
    direction = rng.normal(size=(40, 2))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    p_enu[jumps, :2] += direction * rng.uniform(25, 60, size=(40, 1))
    res = align_to_gps(p_map, p_enu, sigma_m=np.full(len(p_map), 3.0), mode=mode)
    assert res.scale == pytest.approx(1.03, abs=0.005)
    assert np.degrees(res.yaw_rad) == pytest.approx(37.0, abs=0.5)
    # the aligned trajectory is far closer to truth than GPS itself (several metres)
    err = np.linalg.norm(transform_points(res.enu_from_map, p_map) - transform_points(TRUE, p_map), axis=1)
    assert np.sqrt(np.mean(err**2)) < 1.0
    # every jump is rejected, and few clean fixes are
    assert set(jumps.tolist()) <= {r["index"] for r in res.rejected}
    assert len(res.rejected) < 40 + 10
    assert res.stats()["fixes_used"] == int(res.inliers.sum())


def test_yaw_mode_keeps_the_trajectory_scale_and_reports_the_free_one(rng):
    """A metric trajectory under a rigid 4-DoF transform: ``yaw`` recovers it with scale exactly 1,
    and the scale a free fit would have chosen is reported, not applied."""
    rigid = make_sim3(1.0, yaw_rotation(np.radians(-52.0)), [40.0, 310.0, -2.0])
    p_map = _curvy_drive()
    p_enu = transform_points(rigid, p_map) + rng.normal(scale=[1.5, 1.5, 3.0], size=p_map.shape)
    p_enu[:, :2] += 2.0 * np.sin(np.linspace(0, 1.5, len(p_map)))[:, None]  # a slowly drifting bias
    res = align_to_gps(p_map, p_enu, sigma_m=np.full(len(p_map), 1.5), mode="yaw")
    assert res.scale == 1.0 and res.mode == "yaw"
    assert np.degrees(res.yaw_rad) == pytest.approx(-52.0, abs=0.5)
    s = res.stats()["scale_if_estimated"]
    assert s != 1.0 and s == pytest.approx(1.0, abs=0.01)
    assert align_to_gps(p_map, p_enu, mode="yaw_scale").stats()["scale_if_estimated"] is None


def test_straight_drive_falls_back_from_sim3_or_errors_when_strict(rng):
    s = np.linspace(0, 500, 200)
    p_map = np.stack([s, np.zeros_like(s), np.zeros_like(s)], axis=1)
    p_enu = transform_points(TRUE, p_map) + rng.normal(scale=1.0, size=p_map.shape)
    with pytest.warns(InputWarning, match="too straight"):
        res = align_to_gps(p_map, p_enu, mode="sim3")
    assert res.mode == "yaw_scale" and np.degrees(res.yaw_rad) == pytest.approx(37.0, abs=0.5)
    with pytest.raises(InputError, match="too straight"):
        align_to_gps(p_map, p_enu, mode="sim3", strict=True)


def test_too_short_drive_is_an_error():
    p = np.stack([np.linspace(0, 5, 20), np.zeros(20), np.zeros(20)], axis=1)
    with pytest.raises(InputError, match="spans 5.0 m"):
        align_to_gps(p, p)


def test_association_interpolates_and_never_extrapolates_or_bridges_gaps():
    stamps = np.array([0, 1, 2, 10, 11], dtype=np.int64) * 1_000_000_000  # a 8 s gap between 2 and 10
    poses = np.stack([make_pose(np.eye(3), [float(t) / 1e9, 0, 0]) for t in stamps])
    lever = make_pose(np.eye(3), [0.0, 0.5, 1.0])
    fixes = np.array([-1, 0.5, 1.5, 5, 10.5, 12], dtype=np.float64)
    antenna, ok = associate_fixes(stamps, poses, (fixes * 1e9).astype(np.int64), base_from_antenna=lever)
    assert ok.tolist() == [False, True, True, False, True, False]
    np.testing.assert_allclose(antenna, [[0.5, 0.5, 1.0], [1.5, 0.5, 1.0], [10.5, 0.5, 1.0]])
