"""The per-session factor graph (mapkit.mapping.factor_graph) against synthetic drives with known truth.

Truth is a planar drive (a rounded rectangle at 10 m/s, 10 Hz poses, gentle hills); the odometry is
the truth's relative motions with a known drift (a pitch bias per metre, a scale error), GPS is the
true antenna position plus white noise, a bias and outliers, gravity is the true up direction.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mapkit.core.geometry import invert_pose, make_pose
from mapkit.mapping.factor_graph import (
    FactorGraphConfig,
    GpsObservations,
    GravityObservations,
    fuse_session,
    gravity_from_imu,
    select_keyframes,
)

pytest.importorskip("gtsam")

GPS_SIGMA_REPORTED = 2.5  # white 1.5 m and bias 2.0 m, as the synthetic town's receiver reports them
CHI2_95_3DOF = 7.815


def true_drive(length_m: float = 300.0, speed: float = 10.0, rate_hz: float = 10.0, straight: bool = False):
    """(stamps_ns, world_from_base) of a drive: a rounded rectangle (or a straight line), heading along the path,
    pitch following a gentle hill profile."""
    s = np.arange(0.0, length_m, speed / rate_hz)
    if straight:
        xy = np.stack([s, np.zeros_like(s)], axis=1)
        yaw = np.zeros_like(s)
    else:
        # a 110 x 60 m loop with 15 m corner radius, driven once and a bit
        yaw = 2 * np.pi * s / 340.0 + 0.4 * np.sin(2 * np.pi * s / 85.0)
        xy = np.cumsum(np.stack([np.cos(yaw), np.sin(yaw)], axis=1) * (speed / rate_hz), axis=0)
    z = 1.5 * np.sin(2 * np.pi * s / 200.0)
    pitch = -np.arctan(np.gradient(z, s))  # nose up on a climb: a negative rotation about y
    R = Rotation.from_euler("ZYX", np.stack([yaw, pitch, np.zeros_like(s)], axis=1)).as_matrix()
    stamps = (np.arange(len(s)) * 1e9 / rate_hz).astype(np.int64) + 1_000_000_000
    return stamps, make_pose(R, np.column_stack([xy, z]))


def drifted_odometry(truth: np.ndarray, pitch_rad_per_m: float = 0.0, roll_rad_per_m: float = 0.0, scale: float = 1.0,
                     rng: np.random.Generator | None = None, rot_sigma_per_sqrt_m: float = 0.0, trans_sigma_per_sqrt_m: float = 0.0):
    """The truth's relative motions, each rotated by a drift proportional to its length (plus random-walk
    noise) and scaled, chained from the identity (the odometry's frame is the first pose's)."""
    out = [np.eye(4)]
    for a, b in zip(truth[:-1], truth[1:]):
        rel = invert_pose(a) @ b
        d = float(np.linalg.norm(rel[:3, 3]))
        rv = np.array([roll_rad_per_m, pitch_rad_per_m, 0.0]) * d
        dt = np.zeros(3)
        if rng is not None:
            rv = rv + rng.standard_normal(3) * rot_sigma_per_sqrt_m * np.sqrt(d)
            dt = rng.standard_normal(3) * trans_sigma_per_sqrt_m * np.sqrt(d)
        rel = rel.copy()
        rel[:3, 3] = scale * rel[:3, 3] + dt
        rel[:3, :3] = rel[:3, :3] @ Rotation.from_rotvec(rv).as_matrix()
        out.append(out[-1] @ rel)
    return np.stack(out)


def gps_fixes(stamps, truth, rng, bias=np.zeros(3), outliers: int = 0, white: float = 1.5, rate_hz: float = 2.0):
    """Fixes at ``rate_hz``: true position + bias + white noise (vertical twice the horizontal); ``outliers`` of them moved 25 m."""
    step = int(round(10 / rate_hz))
    idx = np.arange(0, len(stamps), step)
    enu = truth[idx, :3, 3] + bias + rng.standard_normal((len(idx), 3)) * white * np.array([1, 1, 2])
    bad = rng.choice(len(idx), outliers, replace=False) if outliers else np.zeros(0, int)
    enu[bad, :2] += 25.0 * np.stack([np.cos(bad), np.sin(bad)], axis=1)
    return GpsObservations(stamps[idx], enu, np.full(len(idx), GPS_SIGMA_REPORTED)), bad


def true_gravity(stamps, truth):
    return GravityObservations(stamps, truth[:, 2, :3].copy())  # R^T z = the third row of R


def fused_errors(fused, truth) -> np.ndarray:
    return fused.enu_from_base[:, :3, 3] - truth[:, :3, 3]


def test_drift_removed_and_outliers_downweighted():
    """Odometry with a pitch drift of 0.02 deg/m and 1% scale error climbs metres off the true path;
    fused with GPS (bias 1.8 m, 6 fixes 25 m off) and gravity, its shape error is below 0.25 m in height
    and 0.5 m horizontally (part of the scale error is taken for a varying GPS bias),
    the outliers carry almost no weight, and the absolute error is the GPS bias within its sigma."""
    rng = np.random.default_rng(3)
    stamps, truth = true_drive()
    odom = drifted_odometry(truth, pitch_rad_per_m=np.radians(0.02), scale=1.01)
    bias = np.array([1.2, -0.8, 1.0])
    gps, bad = gps_fixes(stamps, truth, rng, bias=bias, outliers=6)
    fused = fuse_session(stamps, odom, gps, true_gravity(stamps, truth))

    # the odometry as today's rigid fit leaves it: its own shape against the truth's
    from mapkit.mapping.gps_align import fit_transform

    T = fit_transform(odom[:, :3, 3], truth[:, :3, 3], mode="yaw")
    e_odom = (T[:3, :3] @ odom[:, :3, 3].T).T + T[:3, 3] - truth[:, :3, 3]
    e = fused_errors(fused, truth)
    shape = e - e.mean(axis=0)
    assert np.sqrt(np.mean(e_odom[:, 2] ** 2)) > 1.5  # the drift the graph has to remove: metres in height
    assert np.sqrt(np.mean(shape[:, 2] ** 2)) < 0.25
    assert np.sqrt(np.mean(np.sum(shape[:, :2] ** 2, axis=1))) < 0.5
    assert np.sqrt(np.mean(np.sum(shape**2, axis=1))) < 0.25 * np.sqrt(np.mean(np.sum(e_odom**2, axis=1)))
    # the absolute offset is the GPS bias, which one session cannot observe: inside its stated sigma (3 sigma)
    sig = np.sqrt(np.diag(fused.georef_covariance)[3:])
    assert np.all(np.abs(e.mean(axis=0)) < 3 * sig)
    # outliers: every one found, and few good fixes down-weighted
    assert set(bad) <= set(np.nonzero(~fused.gps_inliers)[0])
    assert (~fused.gps_inliers).sum() <= len(bad) + 3
    # without the outliers the solution barely moves
    rng = np.random.default_rng(3)
    clean, _ = gps_fixes(stamps, truth, rng, bias=bias)
    clean_fused = fuse_session(stamps, odom, clean, true_gravity(stamps, truth))
    assert np.max(np.linalg.norm(clean_fused.enu_from_base[:, :3, 3] - fused.enu_from_base[:, :3, 3], axis=1)) < 0.5


def test_pitch_fixed_by_gravity():
    """The fused pitch follows the true hills within 0.1 deg; the odometry's drifts more than 1 deg off."""
    stamps, truth = true_drive()
    odom = drifted_odometry(truth, pitch_rad_per_m=np.radians(0.01))
    gps, _ = gps_fixes(stamps, truth, np.random.default_rng(4))
    fused = fuse_session(stamps, odom, gps, true_gravity(stamps, truth))
    pitch = lambda P: np.degrees(np.arcsin(P[:, 2, 0]))  # noqa: E731
    assert np.max(np.abs(pitch(odom) - pitch(truth))) > 1.0
    assert np.max(np.abs(pitch(fused.enu_from_base) - pitch(truth))) < 0.1


def test_covariances_consistent_over_many_drives():
    """Drift, GPS bias and noise drawn from the model itself: the NEES of the middle pose over 30 independent
    drives lies in the two-sided 95% chi-square band (90 dof), and the 95% ellipses hold 80-100% of them."""
    cfg = FactorGraphConfig(gps_robust="none")
    stamps, truth = true_drive(length_m=150.0)
    rng = np.random.default_rng(7)
    nees = []
    sb = cfg.gps_bias_sigma_m
    white = np.sqrt(GPS_SIGMA_REPORTED**2 - sb**2)
    for _ in range(30):
        odom = drifted_odometry(truth, rng=rng, rot_sigma_per_sqrt_m=cfg.odom_rotation_sigma_rad_per_sqrt_m,
                                trans_sigma_per_sqrt_m=cfg.odom_translation_sigma_m_per_sqrt_m)
        bias = rng.standard_normal(3) * sb * np.array([1, 1, cfg.gps_vertical_sigma_factor])
        gps, _ = gps_fixes(stamps, truth, rng, bias=bias, white=white)
        fused = fuse_session(stamps, odom, gps, None, cfg)
        i = len(stamps) // 2
        e = fused_errors(fused, truth)[i]
        nees.append(float(e @ np.linalg.solve(fused.covariances[i, 3:, 3:], e)))
    nees = np.asarray(nees)
    # chi-square with 90 dof: 2.5% and 97.5% quantiles 65.6 and 118.1
    assert 65.6 <= nees.sum() <= 118.1, nees.sum()
    assert np.mean(nees <= CHI2_95_3DOF) >= 0.8


def test_no_gps_keeps_the_odometry_with_growing_covariance():
    stamps, truth = true_drive(length_m=120.0)
    odom = drifted_odometry(truth, pitch_rad_per_m=np.radians(0.02))
    fused = fuse_session(stamps, odom, None)
    assert np.allclose(fused.enu_from_base, odom, atol=1e-6)
    var = np.trace(fused.covariances[:, 3:, 3:], axis1=1, axis2=2)
    kv = var[fused.keyframes]
    assert var[0] < 1e-9 and kv[-1] > 0.05
    assert np.all(np.diff(kv) > 0)
    assert fused.stats["gps"] == "not used: no GPS"


def test_straight_drive_roll_fixed_by_gravity():
    """On a straight road GPS cannot see roll: the odometry rolls 0.03 deg/m; gravity holds it to the truth's."""
    stamps, truth = true_drive(length_m=200.0, straight=True)
    odom = drifted_odometry(truth, roll_rad_per_m=np.radians(0.03))
    gps, _ = gps_fixes(stamps, truth, np.random.default_rng(5))
    fused = fuse_session(stamps, odom, gps, true_gravity(stamps, truth))
    roll_err = np.degrees(np.abs(Rotation.from_matrix(np.swapaxes(truth[:, :3, :3], 1, 2) @ fused.enu_from_base[:, :3, :3])
                                 .as_euler("ZYX")[:, 2]))
    assert np.degrees(np.radians(0.03) * 200) > 5.0
    assert roll_err.max() < 0.1
    assert np.all(np.isfinite(fused.covariances))


def test_gravity_from_imu_takes_out_the_motion():
    """The specific force of a car speeding up, braking and turning (IMU 1.2 m ahead of the base) gives the
    true up in the base frame within 0.6 deg (median 0.2), where the raw accelerometer is off by degrees; the odometry's
    rotation drift does not enter (only its speed does)."""
    stamps, truth = true_drive(length_m=150.0, rate_hz=100.0)
    speed_scale = 1 + 0.3 * np.sin(np.arange(len(stamps)) / 300.0)  # the same path at a varying speed
    t = np.concatenate([[0.0], np.cumsum(1.0 / (100.0 * speed_scale[:-1]))])
    stamps = (t * 1e9).astype(np.int64) + 1_000_000_000
    base_from_imu = make_pose(np.eye(3), np.array([1.2, 0.0, 0.5]))
    world_from_imu = truth @ base_from_imu
    acc = np.gradient(np.gradient(world_from_imu[:, :3, 3], t, axis=0), t, axis=0)
    accel = np.einsum("nji,nj->ni", world_from_imu[:, :3, :3], acc + np.array([0, 0, 9.80665]))
    rel = np.swapaxes(world_from_imu[:-1, :3, :3], 1, 2) @ world_from_imu[1:, :3, :3]
    gyro = Rotation.from_matrix(rel).as_rotvec() / np.diff(t)[:, None]
    gyro = np.vstack([gyro, gyro[-1]])
    odom = drifted_odometry(truth, pitch_rad_per_m=np.radians(0.02))
    q = stamps[100:-100:25]
    g = gravity_from_imu(stamps, gyro, accel, base_from_imu, stamps, odom, q)
    i = np.searchsorted(stamps, g.stamps_ns)
    true_up = truth[i, 2, :3]
    naive = accel[i] / np.linalg.norm(accel[i], axis=1, keepdims=True)
    ang = np.degrees(np.arccos(np.clip(np.sum(g.up_base * true_up, axis=1), -1, 1)))
    naive_ang = np.degrees(np.arccos(np.clip(np.sum(naive * true_up, axis=1), -1, 1)))
    assert len(g.stamps_ns) > 0.9 * len(q)
    assert naive_ang.max() > 3.0
    assert np.median(ang) < 0.2 and ang.max() < 0.6


def test_keyframes_by_distance_and_time():
    stamps = np.arange(0, 40) * 100_000_000
    x = np.concatenate([np.zeros(20), np.arange(1, 21) * 0.4])  # 2 s standing, then 0.4 m a pose
    poses = np.repeat(np.eye(4)[None], 40, axis=0)
    poses[:, 0, 3] = x
    kf = select_keyframes(stamps, poses, 1.0, 0.5)
    assert kf[0] == 0 and kf[-1] == 39
    assert list(kf[:5]) == [0, 5, 10, 15, 20]  # every 0.5 s while standing
    assert np.all(np.diff(x[kf[5:-1]]) >= 1.0 - 1e-9)
