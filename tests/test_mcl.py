"""The MCVL particle filter against hand-computed cases and synthetic tracks with known truth."""

from dataclasses import dataclass

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mapkit.core.config import defaults_yaml, load_config
from mapkit.core.errors import ConfigError, InputError
from mapkit.core.geometry import average_rotations, is_rotation, make_pose, yaw_rotation
from mapkit.localization.mcl import (
    FORWARD_CAMERA_ROTATION,
    CameraMount,
    MclConfig,
    MonteCarloLocalizer,
    Particles,
    chordal_mean_rotation,
    estimate,
    init_particles,
    log_likelihood,
    pose_errors,
    predict,
    sus_resample,
    weigh,
    wrap_angle,
)
from mapkit.retrieval.measurement import Measurement, PoseHypotheses, matrix_from_euler, mean_shift_measurement

ZERO3 = (0.0, 0.0, 0.0)


@dataclass
class Track:
    positions: np.ndarray  # (T, 3) m, world; NaN before the first measurement
    rotations: np.ndarray  # (T, 3, 3) world_from_body; NaN there too
    valid: np.ndarray  # (T,) bool: the localizer gave an estimate
    reinjected: np.ndarray  # (T,) int: particles drawn afresh at that step


def run_filter(measurements, cfg=None, seed=0, odometry=None, hypotheses=None) -> Track:
    """Run :class:`MonteCarloLocalizer` over a sequence (None: no measurement at that step), as
    ``mapkit localize`` does per query: ``odometry[t]`` is the 4x4 motion into step t,
    ``hypotheses[t]`` the retrieved poses at step t."""
    T = len(measurements)
    loc = MonteCarloLocalizer(cfg, seed)
    track = Track(np.full((T, 3), np.nan), np.full((T, 3, 3), np.nan), np.zeros(T, bool), np.zeros(T, np.int64))
    for t, z in enumerate(measurements):
        odo = None if odometry is None or not loc.initialized else odometry[t]
        est = loc.step(z, odo, None if hypotheses is None else hypotheses[t])
        if est is not None:
            track.positions[t], track.rotations[t], track.valid[t] = est.position, est.rotation, True
            track.reinjected[t] = est.reinjected
    return track


def _noiseless(**kw) -> MclConfig:
    return MclConfig(velocity_cov_m2=ZERO3, angular_velocity_cov_rad2=ZERO3, **kw)


def _straight_track(T: int, rng, sigma_m: float = 5.0, sigma_yaw_rad: float = 0.03):
    gt_pos = np.stack([np.arange(T, dtype=float), np.zeros(T), np.zeros(T)], axis=1)  # 1 m/step along x, yaw 0
    meas = [
        Measurement.from_pose(
            gt_pos[t] + rng.normal(scale=sigma_m, size=3), yaw_rotation(rng.normal(scale=sigma_yaw_rad))
        )
        for t in range(T)
    ]
    return gt_pos, np.broadcast_to(np.eye(3), (T, 3, 3)), meas


def test_defaults_are_the_papers():
    cfg = MclConfig()
    assert cfg.n_particles == 1000
    assert cfg.init_position_cov_m2 == (10, 10, 10) and cfg.init_euler_cov_rad2 == (0.001, 0.001, 1)
    assert cfg.velocity_mean_m == (0.1, 0.1, 0.01) and cfg.velocity_cov_m2 == (1, 1, 0.01)
    assert cfg.angular_velocity_mean_rad == (0.001, 0.00001, 0.01) and cfg.angular_velocity_cov_rad2 == (
        0.0001,
        0.00001,
        0.01,
    )
    assert cfg.measurement_cov == (5, 5, 5, 0.0001, 0.0001, 0.001)
    assert cfg.velocity_frame == "world" and not cfg.odometry.enabled and not cfg.recovery.enabled
    assert "Beyond the paper" in defaults_yaml(MclConfig)
    with pytest.raises(ConfigError):
        load_config(MclConfig, overrides={"n_partcles": 10})  # typo
    with pytest.raises(ConfigError):
        load_config(MclConfig, overrides={"measurement_cov": [5, 5, 5, 0, 1, 1]})  # Sigma_o must be invertible


def test_motion_model_keeps_rotations_valid_over_many_steps():
    cfg = MclConfig(n_particles=200, angular_velocity_cov_rad2=(0.05, 0.05, 0.5))  # tumbling, all angles visited
    rng = np.random.default_rng(0)
    p = init_particles(Measurement.from_pose(ZERO3, np.eye(3)), cfg, rng)
    for _ in range(2000):
        p = predict(p, cfg, rng)
    assert is_rotation(p.rotations, atol=1e-12)
    np.testing.assert_allclose(matrix_from_euler(p.euler), p.rotations, atol=1e-12)
    assert np.all(np.abs(p.euler[:, 1]) <= np.pi / 2) and np.all(np.abs(p.euler[:, [0, 2]]) <= np.pi)


def test_eq2_composes_the_increment_in_the_body_frame():
    # noiseless: psi = mu_psi exactly, so R_t = R_{t-1} R(mu_psi),
    # i.e. phi(Omega_t) = phi(psi) phi(Omega_{t-1}) with phi = R^T
    cfg = _noiseless(angular_velocity_mean_rad=(0.2, 0.0, 0.0))
    R0 = yaw_rotation(np.pi / 2)
    p = Particles.from_rotations(np.zeros((1, 3)), R0[None])
    q = predict(p, cfg, np.random.default_rng(0))
    np.testing.assert_allclose(q.rotations[0], R0 @ matrix_from_euler([0.2, 0, 0]), atol=1e-12)

    def phi(e):  # the paper's DCM
        return matrix_from_euler(e).T

    np.testing.assert_allclose(phi(q.euler[0]), phi([0.2, 0, 0]) @ phi(p.euler[0]), atol=1e-12)
    # the body x axis (now world +y) is the roll axis: a world-frame increment would differ
    assert not np.allclose(q.rotations[0], matrix_from_euler([0.2, 0, 0]) @ R0, atol=1e-3)
    np.testing.assert_allclose(q.positions[0], cfg.velocity_mean_m, atol=1e-15)  # world frame, eq. 2


def test_body_frame_velocity_option():
    cfg = _noiseless(velocity_mean_m=(2.0, 0.0, 0.0), angular_velocity_mean_rad=ZERO3, velocity_frame="body")
    p = Particles.from_rotations(np.zeros((1, 3)), yaw_rotation(np.pi / 2)[None])
    q = predict(p, cfg, np.random.default_rng(0))
    np.testing.assert_allclose(q.positions[0], [0, 2, 0], atol=1e-12)


def test_odometry_motion_moves_each_particle_in_its_body_frame():
    cfg = MclConfig(odometry={"enabled": True, "translation_sigma_m": ZERO3, "rotation_sigma_rad": ZERO3})
    yaws = np.array([0.0, np.pi / 2, np.pi])
    p = Particles.from_rotations(np.zeros((3, 3)), yaw_rotation(yaws))
    odo = make_pose(yaw_rotation(0.1), [1.0, 0.0, 0.0])
    q = predict(p, cfg, np.random.default_rng(0), odo)
    np.testing.assert_allclose(q.positions, [[1, 0, 0], [0, 1, 0], [-1, 0, 0]], atol=1e-12)
    np.testing.assert_allclose(q.rotations, yaw_rotation(yaws + 0.1), atol=1e-12)


def test_sus_counts_for_known_weights():
    for seed in range(50):
        idx = sus_resample(np.array([0.5, 0.25, 0.25]), np.random.default_rng(seed), n=4)
        np.testing.assert_array_equal(np.bincount(idx, minlength=3), [2, 1, 1])


def test_sus_counts_are_floor_or_ceil_and_skip_zero_weights():
    rng = np.random.default_rng(3)
    for _ in range(200):
        w = rng.random(37) * (rng.random(37) > 0.3)
        w /= w.sum()
        n = int(rng.integers(1, 300))
        counts = np.bincount(sus_resample(w, rng, n=n), minlength=37)
        assert counts.sum() == n
        assert np.all((counts == np.floor(n * w)) | (counts == np.ceil(n * w)))
        assert np.all(counts[w == 0] == 0)


def test_weights_match_a_hand_computed_case():
    cfg = MclConfig()
    z = Measurement.from_pose([10.0, 0.0, 0.0], matrix_from_euler([0.0, 0.0, 0.5]))
    p = Particles.from_euler(
        np.array([[10.0, 0.0, 0.0], [12.0, 1.0, 0.0]]), np.array([[0.0, 0.0, 0.5], [0.01, 0.0, 0.45]])
    )
    # eq. 3: -1/2 d^T Sigma_o^-1 d with Sigma_o = diag(5, 5, 5, 1e-4, 1e-4, 1e-3)
    ll1 = -0.5 * (2.0**2 / 5 + 1.0**2 / 5 + 0.01**2 / 1e-4 + 0.05**2 / 1e-3)
    np.testing.assert_allclose(log_likelihood(p, z, cfg), [0.0, ll1], atol=1e-9)
    w = weigh(p, z, cfg)
    np.testing.assert_allclose(w, np.array([1.0, np.exp(ll1)]) / (1.0 + np.exp(ll1)), rtol=1e-9)


def test_angle_differences_wrap_across_pi():
    np.testing.assert_allclose(
        wrap_angle([np.pi, -np.pi, 1.5 * np.pi, -1.5 * np.pi, 0.1]), [np.pi, np.pi, -0.5 * np.pi, 0.5 * np.pi, 0.1]
    )
    cfg = MclConfig()
    z = Measurement.from_pose(ZERO3, yaw_rotation(np.pi - 0.01))
    # yaw -pi + 0.01 is 0.02 rad from the measurement across the cut; pi - 0.03 is as close on the other side
    p = Particles.from_euler(np.zeros((2, 3)), np.array([[0, 0, -np.pi + 0.01], [0, 0, np.pi - 0.03]]))
    ll = log_likelihood(p, z, cfg)
    np.testing.assert_allclose(ll, -0.5 * 0.02**2 / 1e-3, rtol=1e-6)


def test_weights_survive_a_measurement_far_from_every_particle():
    cfg = MclConfig(n_particles=100)
    rng = np.random.default_rng(0)
    p = init_particles(Measurement.from_pose(ZERO3, np.eye(3)), cfg, rng)
    w = weigh(p, Measurement.from_pose([1e4, 0, 0], np.eye(3)), cfg)  # eq. 3 underflows to 0 for all
    assert np.all(np.isfinite(w)) and w.sum() == pytest.approx(1.0)
    assert np.argmax(w) == np.argmax(p.positions[:, 0])


def test_chordal_mean_equals_average_rotations(rng):
    R = (Rotation.from_euler("z", 0.7) * Rotation.from_rotvec(rng.normal(scale=0.3, size=(300, 3)))).as_matrix()
    w = rng.random(300)
    np.testing.assert_allclose(chordal_mean_rotation(R, w / w.sum()), average_rotations(R, w), atol=1e-9)
    e = estimate(Particles.from_rotations(rng.normal(size=(300, 3)), R), w)
    assert is_rotation(e.rotation) and e.n_eff < 300


def test_filter_beats_the_measurements_on_a_straight_track():
    T = 100
    gt_pos, gt_rot, meas = _straight_track(T, np.random.default_rng(1))
    track = run_filter(meas, MclConfig(), seed=2)
    raw = pose_errors(
        np.stack([m.translation for m in meas]), np.stack([m.rotation for m in meas]), gt_pos, gt_rot
    ).summary()
    filt = pose_errors(track.positions, track.rotations, gt_pos, gt_rot).summary()
    assert raw["mean_translation_m"] > 7.0  # 5 m per axis
    assert filt["mean_translation_m"] < 0.6 * raw["mean_translation_m"]
    assert filt["mean_rotation_deg"] < 3.0
    assert track.valid.all() and is_rotation(track.rotations)


def _town_mount() -> CameraMount:
    """The synthetic town's front camera (mapkit.synth defaults): 1.6 m ahead of and 1.55 m above
    the base origin, pitched 3 deg down."""
    return CameraMount(
        make_pose(Rotation.from_euler("y", 3.0, degrees=True).as_matrix() @ FORWARD_CAMERA_ROTATION, [1.6, 0.0, 1.55])
    )


def test_camera_mount_known_answers():
    fwd = CameraMount.forward()
    # a forward camera facing east is a base with heading 0, facing north one with heading 90 deg
    for heading in (0.0, np.pi / 2, np.pi, -np.pi / 2):
        t, R = fwd.to_base(np.array([5.0, 6.0, 7.0]), yaw_rotation(heading) @ FORWARD_CAMERA_ROTATION)
        np.testing.assert_allclose(R, yaw_rotation(heading), atol=1e-15)
        np.testing.assert_allclose(Measurement.from_pose(t, R).euler, [0.0, 0.0, heading], atol=1e-12)
    # the camera driving 1 m along its optical z is the base driving 1 m forward
    np.testing.assert_allclose(
        fwd.odometry_to_base(make_pose(np.eye(3), [0, 0, 1.0])), make_pose(np.eye(3), [1.0, 0, 0]), atol=1e-15
    )
    # the town's mount: a camera at (1.6, 0, 1.55) pitched 3 deg down sits on a base at the origin
    town = _town_mount()
    cam = town.base_from_camera
    t, R = town.to_base(cam[:3, 3], cam[:3, :3])
    np.testing.assert_allclose(t, 0.0, atol=1e-12)
    np.testing.assert_allclose(R, np.eye(3), atol=1e-12)
    # round trips, NaN rows kept, measurement and hypotheses converted alike
    rng = np.random.default_rng(0)
    pos, rot = rng.normal(size=(5, 3)), Rotation.random(5, random_state=1).as_matrix()
    back = town.to_camera(*town.to_base(pos, rot))
    np.testing.assert_allclose(back[0], pos, atol=1e-12)
    np.testing.assert_allclose(back[1], rot, atol=1e-12)
    assert np.isnan(town.to_camera(np.full(3, np.nan), np.full((3, 3), np.nan))[0]).all()
    z = mean_shift_measurement(pos, rot, bandwidth=100.0)
    zb = town.measurement_to_base(z)
    np.testing.assert_allclose(zb.rotation, z.rotation @ town.rotation.T, atol=1e-12)
    np.testing.assert_allclose(zb.translation, z.translation - zb.rotation @ town.translation, atol=1e-12)
    assert zb.cluster_size == z.cluster_size and np.allclose(matrix_from_euler(zb.euler), zb.rotation)
    hb = town.hypotheses_to_base(PoseHypotheses.from_retrieval(pos, rot))
    np.testing.assert_allclose(hb.rotations, town.to_base(pos, rot)[1], atol=1e-12)
    # the odometry of the base is the camera's seen through the mount
    T0, T1 = make_pose(rot[0], pos[0]), make_pose(rot[1], pos[1])
    B0, B1 = (make_pose(*town.to_base(T[:3, 3], T[:3, :3])[::-1]) for T in (T0, T1))
    np.testing.assert_allclose(town.odometry_to_base(np.linalg.inv(T0) @ T1), np.linalg.inv(B0) @ B1, atol=1e-12)
    with pytest.raises(ValueError):
        CameraMount(np.diag([1.0, 1.0, 2.0, 1.0]))


def _square_route(leg_m: float = 350.0, radius_m: float = 5.0):
    """A 1.4 km loop at 1 m per step: east, north, west, south legs joined by 90 deg arcs of
    ``radius_m``. Base poses (upright, heading = yaw): positions (T, 3), rotations (T, 3, 3)."""
    pos, yaw, out_p, out_y = np.zeros(2), 0.0, [], []
    legs = [leg_m - radius_m] + [leg_m - 2 * radius_m] * 2 + [leg_m - radius_m]
    arc_steps = round(np.pi / 2 * radius_m)  # ~1 m each
    for k, leg in enumerate(legs):
        for turn, steps in ((0.0, round(leg)), (np.pi / 2 / arc_steps, arc_steps if k < 3 else 0)):
            step_m = 1.0 if turn == 0 else 2 * radius_m * np.sin(turn / 2)  # the chord of the arc
            for _ in range(steps):
                out_p.append(pos.copy())
                out_y.append(yaw)
                pos = pos + step_m * np.array([np.cos(yaw + turn / 2), np.sin(yaw + turn / 2)])
                yaw += turn
    return np.c_[np.array(out_p), np.zeros(len(out_p))], yaw_rotation(np.array(out_y))


def _turn_route_errors(seed: int, filter_mount: CameraMount | None) -> tuple[dict, dict]:
    """Mean and median errors (camera poses) of the raw measurements and of the paper's filter on
    :func:`_square_route` seen by the town's camera (:func:`_town_mount`): measurements are the true
    camera pose + 2 m per axis and 0.01 rad. The filter runs on the base poses given by
    ``filter_mount``, its estimates converted back; ``None`` = on the camera poses themselves (an
    optical-frame state, the one the base state avoids)."""
    base_pos, base_rot = _square_route()
    cam_pos, cam_rot = _town_mount().to_camera(base_pos, base_rot)
    T = len(base_pos)
    rng = np.random.default_rng(seed)
    noise_R = Rotation.from_rotvec(rng.normal(scale=0.01, size=(T, 3))).as_matrix()
    meas = [
        Measurement.from_pose(cam_pos[t] + rng.normal(scale=2.0, size=3), cam_rot[t] @ noise_R[t]) for t in range(T)
    ]
    raw = pose_errors(
        np.stack([m.translation for m in meas]), np.stack([m.rotation for m in meas]), cam_pos, cam_rot
    ).summary()
    if filter_mount is None:
        track = run_filter(meas, MclConfig(), seed=seed)
        est = track.positions, track.rotations
    else:
        track = run_filter([filter_mount.measurement_to_base(z) for z in meas], MclConfig(), seed=seed)
        est = filter_mount.to_camera(track.positions, track.rotations)
    return raw, pose_errors(*est, cam_pos, cam_rot).summary()


def test_filter_on_base_poses_tracks_camera_measurements_through_90_degree_turns():
    """The state is the vehicle's base pose, whose third Euler angle is the heading
    (MCVL Sec. IV-A's covariances). Camera-pose measurements 2 m off along a 1.4 km route that
    drives east and west (there the optical frame's second Euler angle is +-90 deg: gimbal lock),
    paper defaults: on the base the filter beats the raw measurements; on the optical frame as
    the state it errs by more than 10 m and 10 deg."""
    base_pos, base_rot = _square_route()
    assert 1350 < len(base_pos) < 1450
    yaw = np.degrees(Rotation.from_matrix(base_rot).as_euler("ZYX")[:, 0])
    for heading in (0, 90, 180, -90):  # east, north, west and south are each driven for ~340 m
        assert np.sum(np.abs((yaw - heading + 180) % 360 - 180) < 1) > 300
    for seed in (0, 1, 2):
        raw, err = _turn_route_errors(seed, _town_mount())
        assert raw["mean_translation_m"] > 3.0  # 2 m per axis
        assert err["mean_translation_m"] < 3.0 and err["mean_translation_m"] < 0.85 * raw["mean_translation_m"]
        assert err["mean_rotation_deg"] < 1.0
    # the optical frame as the state: the same filter on the camera's poses loses the heading in the turns
    _, optical = _turn_route_errors(0, None)
    assert optical["mean_translation_m"] > 10.0 and optical["mean_rotation_deg"] > 10.0
    # the default mount (no pitch, no offset) on the town's rig only tilts and shifts the tracked base
    _, fwd = _turn_route_errors(0, CameraMount.forward())
    assert fwd["mean_translation_m"] < 3.0 and fwd["mean_rotation_deg"] < 1.0


def test_localizer_steps_without_measurements_and_refuses_unrequested_odometry():
    loc = MonteCarloLocalizer(MclConfig(n_particles=50), seed=0)
    assert loc.step(None) is None and loc.particles is None
    e0 = loc.step(Measurement.from_pose([5.0, 0, 0], np.eye(3)))
    assert e0 is not None and len(loc.particles) == 50
    e1 = loc.step(None)  # predict only: the cloud drifts by mu_v on average
    assert not e1.measured
    assert e1.position[0] - e0.position[0] == pytest.approx(0.1, abs=0.5)
    with pytest.raises(ConfigError):
        loc.step(None, odometry=np.eye(4))


def test_no_estimate_before_the_first_measurement_and_errors_over_the_estimated_frames():
    meas = [None, None] + [Measurement.from_pose([float(t), 0, 0], np.eye(3)) for t in range(5)]
    track = run_filter(meas, MclConfig(n_particles=100), seed=0)
    np.testing.assert_array_equal(track.valid, [False, False, True, True, True, True, True])
    assert np.isnan(track.positions[:2]).all() and np.isfinite(track.positions[2:]).all()
    assert (
        pose_errors(
            track.positions, track.rotations, np.zeros((7, 3)), np.broadcast_to(np.eye(3), (7, 3, 3))
        ).summary()["frames"]
        == 5
    )


def test_odometry_driven_filter_tracks_a_turning_track():
    # beyond the paper: a circle of radius 20 m at 1 m/step, with exact odometry; the paper's
    # world-frame drift model lags behind the turn, the odometry-driven one does not
    T, radius = 120, 20.0
    yaw = np.arange(T) / radius
    gt_pos = np.stack([radius * np.sin(yaw), radius * (1 - np.cos(yaw)), np.zeros(T)], axis=1)
    gt_rot = yaw_rotation(yaw)
    rng = np.random.default_rng(5)
    meas = [
        Measurement.from_pose(
            gt_pos[t] + rng.normal(scale=3.0, size=3), gt_rot[t] @ yaw_rotation(rng.normal(scale=0.02))
        )
        for t in range(T)
    ]
    odo = [None] + [
        make_pose(gt_rot[t - 1].T @ gt_rot[t], gt_rot[t - 1].T @ (gt_pos[t] - gt_pos[t - 1])) for t in range(1, T)
    ]
    cfg = MclConfig(odometry={"enabled": True})
    with_odo = pose_errors(*_pr(run_filter(meas, cfg, seed=1, odometry=odo)), gt_pos, gt_rot).summary()
    paper = pose_errors(*_pr(run_filter(meas, MclConfig(), seed=1)), gt_pos, gt_rot).summary()
    assert with_odo["mean_translation_m"] < 2.0
    assert with_odo["mean_translation_m"] < paper["mean_translation_m"]


def _pr(track):
    return track.positions, track.rotations


def test_recovery_reinjects_after_a_jump():
    # beyond the paper: the measurements jump by 300 m (a kidnapped vehicle) and stay there
    T, jump_at = 60, 30
    gt_pos = np.stack([np.arange(T, dtype=float), np.zeros(T), np.zeros(T)], axis=1)
    gt_pos[jump_at:, 1] += 300.0
    rng = np.random.default_rng(2)
    meas = [Measurement.from_pose(gt_pos[t] + rng.normal(scale=2.0, size=3), np.eye(3)) for t in range(T)]
    off = run_filter(meas, MclConfig(), seed=0)
    on = run_filter(meas, MclConfig(recovery={"enabled": True}), seed=0)
    k = MclConfig().recovery.consecutive_steps
    assert on.reinjected[: jump_at + k - 1].sum() == 0 and on.reinjected[jump_at + k - 1] == 200
    err_on = np.linalg.norm(on.positions - gt_pos, axis=1)
    err_off = np.linalg.norm(off.positions - gt_pos, axis=1)
    assert err_on[jump_at + k + 2 :].max() < 15.0
    assert err_off[jump_at + k + 2] > 100.0


def test_pose_errors_known_answers():
    est_R = np.stack([np.eye(3), yaw_rotation(np.pi / 2), matrix_from_euler([np.pi, 0, 0]), np.full((3, 3), np.nan)])
    gt_R = np.broadcast_to(np.eye(3), (4, 3, 3))
    est_c = np.array([[3.0, 4.0, 0.0], [0, 0, 0], [1, 1, 1], [np.nan] * 3])
    e = pose_errors(est_c, est_R, np.zeros((4, 3)), gt_R)
    np.testing.assert_allclose(e.translation_m[:3], [5.0, 0.0, np.sqrt(3)])
    np.testing.assert_allclose(e.rotation_deg[:3], [0.0, 90.0, 180.0], atol=1e-6)
    assert np.isnan(e.rotation_deg[3])
    s = e.summary()
    assert s["frames"] == 3 and s["median_rotation_deg"] == pytest.approx(90.0)
    # relative: gt at 30 deg yaw, estimate at 75 deg
    e2 = pose_errors(
        np.zeros((1, 3)), yaw_rotation(np.radians(75.0))[None], np.zeros((1, 3)), yaw_rotation(np.radians(30.0))[None]
    )
    assert e2.rotation_deg[0] == pytest.approx(45.0)


# --- beyond the paper: the multi-hypothesis measurement model -----------------------------------------


def _mh_config(**mh) -> MclConfig:
    return MclConfig(odometry={"enabled": True}, multi_hypothesis={"enabled": True, **mh}, estimate="mode")


def test_mixture_likelihood_hand_built_case():
    from mapkit.localization.mcl import mixture_likelihood

    cfg = _mh_config(floor=0.1)  # kernel: Sigma_o's position part (5 m^2), rotation std sqrt(1e-3) rad
    hyp = PoseHypotheses(
        np.array([[0.0, 0, 0], [500.0, 0, 0]]), yaw_rotation(np.array([0.0, 1.0])), np.array([0.75, 0.25])
    )
    theta = 0.02
    p = Particles.from_rotations(
        np.array([[0.0, 0, 0], [1.0, 2.0, 0], [0.0, 0, 0], [500.0, 0, 0], [250.0, 0, 0]]),
        yaw_rotation(np.array([0.0, 0.0, theta, 1.0, 0.5])),
    )
    L = mixture_likelihood(p, hyp, cfg)
    k_pos = np.exp(-0.5 * (1.0 + 4.0) / 5.0)
    k_rot = np.exp(-(1.0 - np.cos(theta)) / 1e-3)  # 3 - tr = 2 (1 - cos theta), over 2 sigma^2
    np.testing.assert_allclose(
        L, [0.1 + 0.9 * 0.75, 0.1 + 0.9 * 0.75 * k_pos, 0.1 + 0.9 * 0.75 * k_rot, 0.1 + 0.9 * 0.25, 0.1], rtol=1e-9
    )
    assert k_rot == pytest.approx(np.exp(-0.5 * theta**2 / 1e-3), rel=1e-4)  # a Gaussian in the angle to second order
    # a particle on the right place but facing the other way is as unlikely as one far away
    q = Particles.from_rotations(np.zeros((1, 3)), yaw_rotation(np.array([np.pi])))
    assert mixture_likelihood(q, hyp, cfg)[0] == pytest.approx(0.1)


def test_kernel_matrix_matches_a_direct_computation(rng):
    from mapkit.core.geometry import rotation_angle_rad
    from mapkit.localization.mcl import kernel_matrix

    p = Particles.from_rotations(
        1e3 + rng.normal(scale=3.0, size=(50, 3)),
        Rotation.from_rotvec(rng.normal(scale=0.05, size=(50, 3))).as_matrix(),
    )
    H = Rotation.from_rotvec(rng.normal(scale=0.05, size=(7, 3))).as_matrix()
    hyp = PoseHypotheses(1e3 + rng.normal(scale=3.0, size=(7, 3)), H, np.full(7, 1 / 7))
    var = np.array([4.0, 9.0, 1.0])
    K = kernel_matrix(p, hyp, var, 0.01)
    for i in range(50):
        for j in range(7):
            d = p.positions[i] - hyp.translations[j]
            a = rotation_angle_rad(p.rotations[i].T @ H[j])
            assert K[i, j] == pytest.approx(np.exp(-0.5 * d @ (d / var) - (1 - np.cos(a)) / 0.01), rel=1e-9)


def test_sampling_from_hypotheses_follows_their_weights():
    from mapkit.localization.mcl import sample_hypotheses

    cfg = _mh_config()
    hyp = PoseHypotheses(
        np.array([[0.0, 0, 0], [100.0, 0, 0], [0, 100.0, 0]]),
        yaw_rotation(np.array([0.0, 1.0, 2.0])),
        np.array([0.5, 0.3, 0.2]),
    )
    p = sample_hypotheses(hyp, cfg, np.random.default_rng(0), n=1000)
    j = np.argmin(np.linalg.norm(p.positions[:, None] - hyp.translations[None], axis=-1), axis=1)
    np.testing.assert_array_equal(np.bincount(j, minlength=3), [500, 300, 200])  # SUS: exact here
    np.testing.assert_allclose(np.std(p.positions[j == 0], axis=0), np.sqrt(5.0), rtol=0.15)
    yaw_err = np.abs(wrap_angle(p.euler[:, 2] - np.array([0.0, 1.0, 2.0])[j]))
    assert np.sqrt(np.mean(yaw_err**2)) < 2 * np.sqrt(1e-3)


def test_mode_estimate_picks_the_heavier_mode():
    from mapkit.localization.mcl import mode_estimate

    rng = np.random.default_rng(0)
    pos = np.concatenate(
        [rng.normal(scale=1.0, size=(700, 3)) + [0.0, 0, 0], rng.normal(scale=1.0, size=(300, 3)) + [200.0, 0, 0]]
    )
    p = Particles.from_rotations(
        pos, np.concatenate([np.broadcast_to(np.eye(3), (700, 3, 3)), np.broadcast_to(yaw_rotation(2.0), (300, 3, 3))])
    )
    mode = mode_estimate(p, None, 10.0)
    mean = estimate(p)
    assert np.linalg.norm(mode.position) < 0.3 and np.allclose(mode.rotation, np.eye(3), atol=1e-9)
    assert mean.position[0] == pytest.approx(60.0, abs=1.0)  # the mean lies between the modes
    w = np.where(np.arange(1000) < 700, 0.2, 2.0)  # weights shift the balance to the other mode
    assert mode_estimate(p, w, 10.0).position[0] == pytest.approx(200.0, abs=0.3)


def test_paper_path_is_unchanged_by_the_new_options():
    # Algorithm 1 written out with the functional core: the localizer must draw the same numbers
    rng_track = np.random.default_rng(4)
    _, _, meas = _straight_track(20, rng_track)
    cfg = MclConfig(n_particles=300)
    rng = np.random.default_rng(9)
    p = init_particles(meas[0], cfg, rng)
    expected = []
    for z in meas[1:]:
        p = predict(p, cfg, rng)
        w = weigh(p, z, cfg)
        expected.append(estimate(p, w).position)
        p = p.take(sus_resample(w, rng))
    track = run_filter(meas, cfg, seed=9)
    np.testing.assert_allclose(track.positions[1:], np.array(expected), atol=1e-12)


def test_weights_carry_over_when_resampling_is_adaptive():
    # a measurement covariance wide against the cloud (the paper's 0.01 rad against an initial
    # heading spread of 1 rad leaves an effective sample size of ~2, which always resamples)
    cfg = MclConfig(n_particles=200, resample_min_ess_fraction=0.5, measurement_cov=(100, 100, 100, 10, 10, 10))
    loc = MonteCarloLocalizer(cfg, seed=0)
    loc.step(Measurement.from_pose(ZERO3, np.eye(3)))
    np.testing.assert_allclose(loc.weights, 1 / 200)
    e = loc.step(Measurement.from_pose([1.0, 0, 0], np.eye(3)))
    assert e.n_eff > 100  # measured 197: above half the particles, so not resampled ...
    # ... and the particles keep the step's weights: eq. 3 at the measurement (1, 0, 0), identity rotation
    p = loc.particles
    d = np.c_[p.positions - [1.0, 0.0, 0.0], Rotation.from_matrix(p.rotations).as_euler("XYZ")]
    expected = np.exp(-0.5 * (d**2 / np.asarray(cfg.measurement_cov)).sum(axis=1))
    np.testing.assert_allclose(loc.weights, expected / expected.sum(), rtol=1e-9)
    assert loc.weights.max() > 1.1 / 200 and loc.weights.min() < 0.9 / 200  # not the equal weights of a resampling
    e = loc.step(Measurement.from_pose([300.0, 0, 0], np.eye(3)))  # degenerate: must resample
    assert e.n_eff < 100
    np.testing.assert_allclose(loc.weights, 1 / 200)


def test_hypotheses_need_the_multi_hypothesis_model():
    loc = MonteCarloLocalizer(MclConfig(n_particles=20), seed=0)
    hyp = PoseHypotheses.from_measurement(Measurement.from_pose(ZERO3, np.eye(3)))
    with pytest.raises(ConfigError):
        loc.step(None, hypotheses=hyp)


def _preset_mcl(name: str) -> MclConfig:
    """The filter settings of configs/localize/NAME.yaml (the preset's odometry flag applied)."""
    from pathlib import Path

    from mapkit.localization.localize import LocalizeConfig

    cfg = load_config(LocalizeConfig, Path(__file__).resolve().parents[1] / "configs" / "localize" / f"{name}.yaml")
    return cfg.mcl.model_copy(update={"odometry": cfg.mcl.odometry.model_copy(update={"enabled": cfg.odometry})})


def _aliased_retrieval(T: int, k: int, p_in: float, p_top: float, seed: int):
    """A circle of radius 80 m at 5 m/step with exact odometry; at each step k retrieved poses,
    mostly wrong: they fall around 4 random places of a 600 m square (aliased places, so that
    wrong hits form clusters too) with random headings. With probability ``p_in`` one of them
    is the true pose (1.5 m, 0.02 rad noise), and with ``p_top`` it is the top-1."""
    rng = np.random.default_rng(seed)
    yaw = np.arange(T) * 5.0 / 80.0
    gt_pos = np.stack([80.0 * np.sin(yaw), 80.0 * (1 - np.cos(yaw)), np.zeros(T)], axis=1)
    gt_rot = yaw_rotation(yaw)
    odo = [None] + [
        make_pose(gt_rot[t - 1].T @ gt_rot[t], gt_rot[t - 1].T @ (gt_pos[t] - gt_pos[t - 1])) for t in range(1, T)
    ]
    hyps, present, at_top = [], np.zeros(T, bool), np.zeros(T, bool)
    for t in range(T):
        centres = rng.uniform(-300, 300, size=(4, 3)) * [1, 1, 0]
        X = centres[rng.integers(0, 4, k)] + rng.normal(scale=2.0, size=(k, 3)) * [1, 1, 0.1]
        R = yaw_rotation(rng.uniform(-np.pi, np.pi, k))
        u = rng.random()
        if u < p_in:
            j = 0 if u < p_top else int(rng.integers(1, k))
            X[j] = gt_pos[t] + rng.normal(scale=1.5, size=3) * [1, 1, 0.1]
            R[j] = gt_rot[t] @ yaw_rotation(rng.normal(scale=0.02))
            present[t], at_top[t] = True, j == 0
        hyps.append(PoseHypotheses.from_retrieval(X, R))
    return gt_pos, gt_rot, odo, hyps, present, at_top


def test_multi_hypothesis_filter_finds_the_consistent_place_among_mostly_wrong_hits():
    T = 120
    gt_pos, gt_rot, odo, hyps, present, at_top = _aliased_retrieval(T, k=10, p_in=0.6, p_top=0.2, seed=3)
    assert 0.5 < present.mean() < 0.7 and 0.12 < at_top.mean() < 0.28  # the scenario is as stated
    top1 = np.stack([h.translations[0] for h in hyps])
    mean_shift = np.stack([mean_shift_measurement(h.translations, h.rotations).translation for h in hyps])
    for cfg in (_mh_config(reinject_below=0.05), _preset_mcl("odometry-multihypothesis")):
        track = run_filter([None] * T, cfg, seed=0, odometry=odo, hypotheses=hyps)
        err = pose_errors(track.positions, track.rotations, gt_pos, gt_rot).summary()
        assert err["median_translation_m"] < 3.0 and err["median_rotation_deg"] < 3.0
    # without re-injection the cloud, started on the first step's (wrong) hits, never finds the place
    assert not present[0]
    stuck = run_filter([None] * T, _mh_config(), seed=0, odometry=odo, hypotheses=hyps)
    assert np.median(np.linalg.norm(stuck.positions - gt_pos, axis=1)) > 30.0
    assert np.median(np.linalg.norm(top1 - gt_pos, axis=1)) > 100.0
    assert np.median(np.linalg.norm(mean_shift - gt_pos, axis=1)) > 100.0
    # the paper's measurement (largest mean-shift cluster), with the same odometry, cannot do it
    meas = [Measurement.from_pose(m, np.eye(3)) for m in mean_shift]
    single = run_filter(meas, MclConfig(odometry={"enabled": True}), seed=0, odometry=odo)
    assert np.median(np.linalg.norm(single.positions - gt_pos, axis=1)) > 30.0


def test_motion_model_estimated_from_training_drives_known_answer():
    """MCVL's mu_v and Sigma_v from drives (Sec. III-A: "estimated from training data"): a drive
    east at 4 m/s and one north at 4 m/s, sampled at 4 Hz, step 1 m along x then along y."""
    from mapkit.localization.localize import LocalizeConfig
    from mapkit.localization.motion import estimate_motion_model

    t = np.arange(0, 60 * 100 + 1) * 10_000_000  # 60 s at 100 Hz
    east = np.tile(np.eye(4), (len(t), 1, 1))
    east[:, 0, 3] = 4.0 * t * 1e-9
    north = np.tile(np.eye(4), (len(t), 1, 1))
    north[:, 1, 3] = 4.0 * t * 1e-9
    est = estimate_motion_model([(t, east), (t, north)], rate_hz=4.0)
    assert est.drives == 2 and est.steps == 2 * 240
    np.testing.assert_allclose(est.velocity_mean_m, (0.5, 0.5, 0.0), atol=1e-9)
    np.testing.assert_allclose(est.velocity_cov_m2, (0.25, 0.25, 1e-4), atol=1e-9)  # height never moves: the floor
    cfg = load_config(LocalizeConfig, None, est.overrides())
    assert cfg.mcl.velocity_cov_m2 == pytest.approx((0.25, 0.25, 1e-4))
    with pytest.raises(InputError):
        estimate_motion_model([(t[:2], east[:2])], rate_hz=4.0)
