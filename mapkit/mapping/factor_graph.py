"""One session's trajectory on a GTSAM factor graph: LiDAR odometry, GPS and gravity fused, with covariances.

Keyframes are taken from the odometry every ``keyframe_distance_m`` or ``keyframe_interval_s``
(whichever comes first). The graph over their ``enu_from_base`` poses holds:

- a ``BetweenFactorPose3`` per odometry step, with a random-walk drift model: the variance of each
  rotation and translation component grows linearly with the distance driven (``sigma^2 = q d +
  floor^2``), so the model does not depend on the keyframe spacing, with a Huber loss for
  registrations that slipped. kiss-icp reports no per-scan
  registration quality through its Python API, so the rates are a stated model (measured against
  the synthetic town's truth by ``bench/factor_graph_budget.py``), not a per-scan covariance;
- a GPS factor per fix (a ``CustomFactor``: antenna position = pose * lever arm + bias), attached to
  the nearest keyframe with the odometry's motion to the fix time folded into the lever arm, with a
  robust noise model (Cauchy or Huber) on the fix's white noise;
- a slowly varying GPS bias: ``Point3`` nodes every ``bias_interval_s``, the fix seeing the linear
  interpolation of its two neighbours, a prior of ``gps_bias_sigma_m`` on the first and a random walk
  matching a first-order Gauss-Markov process of correlation time ``gps_bias_tau_s`` between them.
  A receiver's reported sigma counts bias and white noise together, so the white part is what is
  left once the bias variance is taken out. The bias is what ties the frame to WGS84: it is
  unobservable from one session, so it goes into every pose's absolute covariance, which is what
  makes the 95% ellipses honest against the truth;
- gravity (roll and pitch) where given: a factor per observation of the up direction in the base
  frame (:func:`gravity_from_imu` derives them from the IMU and the odometry's speed), with a Cauchy
  loss, sharing one
  ``Point3`` state for the accelerometer's bias (a constant tilt of the measured up vector, prior
  ``gravity_bias_sigma_rad``), since one constant bias on every factor would otherwise be averaged
  away as if it were white noise;
- a weak prior on the first keyframe's attitude (the initial guess's) so that a straight drive
  without gravity still solves; without GPS a tight prior on the first pose keeps the odometry's frame.

Solved with Levenberg-Marquardt from the rigid GPS fit (``align_to_gps`` in ``yaw`` mode). Poses
between keyframes follow the odometry from both neighbouring keyframes, blended by time.
Covariances are 6x6 over (rotation in ENU axes, rad; position in ENU, m): gtsam's right-perturbation
marginals rotated into the world frame, ``diag(R, R) Sigma diag(R, R)^T``.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field
from typing import Literal, Optional

import numpy as np
from pydantic import Field

from mapkit.core.config import MapkitConfig
from mapkit.core.errors import InputError, InputWarning
from mapkit.core.geometry import interpolate_poses, invert_pose
from mapkit.mapping.gps_align import align_to_gps, associate_fixes

#: a fix is an inlier of the solution below this whitened residual (chi-square, 3 dof, 99%; as gps_align's gate)
GPS_INLIER_SIGMAS = 3.37


class FactorGraphConfig(MapkitConfig):
    keyframe_distance_m: float = Field(1.0, description="A keyframe every this many metres driven (issue 24's brief: 1 m).")
    keyframe_interval_s: float = Field(0.5, description="... or every this many seconds, whichever comes first (standing still).")
    odom_rotation_sigma_rad_per_sqrt_m: float = Field(
        0.0015, description="Odometry drift, rotation (per axis): sigma over d metres = this * sqrt(d). kiss-icp on the tiny town: "
        "see bench/factor_graph_budget.py, which prints the measured rate.")
    odom_translation_sigma_m_per_sqrt_m: float = Field(
        0.01, description="Odometry drift, translation (per axis): sigma over d metres = this * sqrt(d).")
    odom_rotation_floor_rad: float = Field(5e-4, description="Odometry rotation sigma of a step of no motion (registration noise).")
    odom_translation_floor_m: float = Field(0.005, description="Odometry translation sigma of a step of no motion.")
    gps_robust: Literal["cauchy", "huber", "none"] = Field(
        "cauchy", description="Robust loss on GPS fixes: Cauchy (redescending: multipath jumps of several metres barely pull), Huber, or none.")
    gps_robust_k: float = Field(2.0, description="The loss's scale in sigmas (Cauchy: 2.385 is the 95%-efficiency choice; 2 cuts harder).")
    gps_white_min_sigma_m: float = Field(0.5, description="Floor of a fix's white-noise sigma (horizontal) once the bias variance is taken out.")
    gps_unknown_sigma_m: float = Field(2.5, description="Reported horizontal sigma assumed for fixes without a covariance.")
    gps_vertical_sigma_factor: float = Field(2.0, description="GNSS vertical sigma as a multiple of the horizontal (white and bias).")
    gps_bias: bool = Field(True, description="Estimate a slowly varying GPS bias (random walk between bias nodes).")
    gps_bias_sigma_m: float = Field(2.0, description="Horizontal standard deviation of the GPS bias (consumer GNSS: metres; synth tiny: 2 m).")
    gps_bias_tau_s: float = Field(300.0, description="Correlation time of the bias (ionosphere, satellite geometry: minutes).")
    bias_interval_s: float = Field(5.0, description="A bias node every this many seconds.")
    gravity_sigma_rad: float = Field(0.003, description="White noise of one up-direction observation (accelerometer noise and "
                                     "odometry acceleration over the averaging window).")
    gravity_bias_sigma_rad: float = Field(0.002, description="Constant tilt of the measured up vector: accelerometer bias / g "
                                          "(consumer MEMS: 0.02 m/s^2, synth tiny's accel_bias_m_s2) plus mount calibration.")
    gravity_robust_k: float = Field(2.0, description="Cauchy loss on gravity factors, in sigmas: windows where the odometry's speed "
                                    "is wrong (kiss-icp slipping) give a tilted up and are down-weighted.")
    odom_robust: Literal["huber", "none"] = Field(
        "huber", description="Huber loss on odometry factors: a registration that slipped (kiss-icp locking onto too little motion "
        "from standstill, in a turn) gives way to GPS instead of bending the whole drive.")
    odom_robust_k: float = Field(3.0, description="The odometry loss's scale, in sigmas.")
    first_attitude_sigma_rad: float = Field(0.2, description="Weak prior on the first keyframe's attitude (the initial guess's).")
    max_pose_gap_s: float = Field(1.0, description="A fix between odometry poses further apart than this is not used.")
    max_iterations: int = Field(100, description="Levenberg-Marquardt iterations.")


@dataclass
class GpsObservations:
    """Fixes in the workspace ENU frame: ``enu[i]`` at ``stamps_ns[i]``, reported horizontal sigma (NaN = unknown)."""

    stamps_ns: np.ndarray
    enu: np.ndarray
    sigma_m: np.ndarray
    base_from_antenna: np.ndarray = field(default_factory=lambda: np.eye(4))


@dataclass
class GravityObservations:
    """Up directions measured in the base frame: ``up_base[i]`` (unit) at ``stamps_ns[i]``."""

    stamps_ns: np.ndarray
    up_base: np.ndarray


@dataclass
class FusedTrajectory:
    """The fused trajectory at every odometry stamp, with 6x6 covariances (rotation ENU rad, position ENU m)."""

    stamps_ns: np.ndarray
    enu_from_base: np.ndarray
    covariances: np.ndarray
    keyframes: np.ndarray  # indices into stamps_ns
    georef_covariance: np.ndarray  # 6x6 of the keyframe at the drive's middle: how well the session is tied to ENU
    gps_inliers: np.ndarray  # (n fixes used,) whitened residual below GPS_INLIER_SIGMAS at the solution
    stats: dict

    def position_sigmas_m(self) -> np.ndarray:
        """(N, 3) standard deviations of east, north, up."""
        return np.sqrt(np.diagonal(self.covariances[:, 3:, 3:], axis1=1, axis2=2))


# --- gravity -----------------------------------------------------------------------------------------


def gravity_from_imu(imu_stamps_ns: np.ndarray, gyro_rad_s: np.ndarray, accel_m_s2: np.ndarray, base_from_imu: np.ndarray,
                     stamps_ns: np.ndarray, world_from_base: np.ndarray, query_ns: np.ndarray, window_s: float = 1.0,
                     speed_baseline_s: float = 1.0) -> GravityObservations:
    """Up in the base frame at ``query_ns``: the accelerometer's specific force less the car's own acceleration.

    The specific force is ``f = a + R^T g up`` (body frame). A car does not slide: its base (the
    rear axle) moves along its x axis, so in the base frame ``a = (dv/dt, v w_z, 0)`` from the speed
    ``v`` alone, plus the IMU's lever arm terms ``w x (w x r) + dw/dt x r``. The speed comes from
    the odometry (a distance over ``speed_baseline_s``, insensitive to its rotation drift and to the
    jitter of single registrations), the turn rate from the gyro. Both sides are averaged over
    ``window_s``. Queries whose window is not covered by IMU samples and odometry are dropped.
    """
    imu_t = np.asarray(imu_stamps_ns, np.int64)
    stamps = np.asarray(stamps_ns, np.int64)
    R_bi, r = np.asarray(base_from_imu, np.float64)[:3, :3], np.asarray(base_from_imu, np.float64)[:3, 3]
    w_b = np.asarray(gyro_rad_s, np.float64) @ R_bi.T  # gyro and specific force in base axes
    f_b = np.asarray(accel_m_s2, np.float64) @ R_bi.T
    half, hb = int(window_s * 0.5e9), int(speed_baseline_s * 0.5e9)
    q = np.asarray(query_ns, np.int64)
    q = q[(q - half - hb >= max(stamps[0], imu_t[0])) & (q + half + hb <= min(stamps[-1], imu_t[-1]))]
    p = world_from_base[:, :3, 3]

    def speed(t: np.ndarray) -> np.ndarray:
        ends = np.stack([np.interp(np.concatenate([t - hb, t + hb]).astype(np.float64), stamps.astype(np.float64), p[:, k])
                         for k in range(3)], axis=1).reshape(2, len(t), 3)
        return np.linalg.norm(ends[1] - ends[0], axis=1) / (2 * hb * 1e-9)

    v_imu = speed(imu_t.clip(stamps[0] + hb, stamps[-1] - hb))
    # per sample: centripetal v w_z (lateral) and the lever arm's w x (w x r)
    a_turn = np.column_stack([np.zeros(len(imu_t)), v_imu * w_b[:, 2], np.zeros(len(imu_t))]) + np.cross(w_b, np.cross(w_b, r))
    csum = lambda x: np.vstack([np.zeros(x.shape[1]), np.cumsum(x, axis=0)])  # noqa: E731
    cf, ca, cw = csum(f_b), csum(a_turn), csum(w_b)
    lo, hi = np.searchsorted(imu_t, q - half), np.searchsorted(imu_t, q + half, side="right")
    keep = hi - lo >= 3
    q, lo, hi = q[keep], lo[keep], hi[keep]
    n = (hi - lo)[:, None]
    # dv/dt and dw/dt over the window: speeds and turn rates at its ends (the turn rate over a tenth of it)
    dv = (speed(q + half) - speed(q - half)) / (2 * half * 1e-9)
    m = max(1, int(round(0.1 * (hi - lo).min())))
    dw = ((cw[hi] - cw[hi - m]) - (cw[lo + m] - cw[lo])) / m / (2 * half * 1e-9)
    a_mean = (ca[hi] - ca[lo]) / n + np.column_stack([dv, np.zeros(len(q)), np.zeros(len(q))]) + np.cross(dw, r)
    up = (cf[hi] - cf[lo]) / n - a_mean
    return GravityObservations(q, up / np.linalg.norm(up, axis=1, keepdims=True))


# --- factors -----------------------------------------------------------------------------------------


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _gps_error(z: np.ndarray, lever: np.ndarray, a: float, keys: list[int]):
    """Antenna = t + R lever + (1-a) b0 + a b1 (keys: pose[, b0, b1]); gtsam's Pose3 tangent is (rotation, translation),
    right-perturbed: d(R lever)/dw = -R [lever]x, dt = R dt_local."""

    def error(this, values, H):
        pose = values.atPose3(this.keys()[0])
        R = pose.rotation().matrix()
        pred = pose.translation() + R @ lever
        if len(keys) == 3:
            b0, b1 = values.atPoint3(this.keys()[1]), values.atPoint3(this.keys()[2])
            pred = pred + (1 - a) * b0 + a * b1
        if H is not None:
            H[0] = np.hstack([-R @ _skew(lever), R])
            if len(keys) == 3:
                H[1] = (1 - a) * np.eye(3)
                H[2] = a * np.eye(3)
        return pred - z

    return error


def _gravity_error(up_meas: np.ndarray):
    """Predicted up in the base frame (R^T z) plus the shared tilt bias, minus the measured one;
    R' = R exp(w) gives d(R^T z)/dw = [R^T z]x."""

    def error(this, values, H):
        pose = values.atPose3(this.keys()[0])
        bias = values.atPoint3(this.keys()[1])
        v = pose.rotation().matrix().T @ np.array([0.0, 0.0, 1.0])
        if H is not None:
            H[0] = np.hstack([_skew(v), np.zeros((3, 3))])
            H[1] = np.eye(3)
        return v + bias - up_meas

    return error


# --- the graph ---------------------------------------------------------------------------------------


def select_keyframes(stamps_ns: np.ndarray, world_from_base: np.ndarray, distance_m: float, interval_s: float) -> np.ndarray:
    """Indices of keyframes: the first pose, every pose ``distance_m`` or ``interval_s`` past the last keyframe, the last pose."""
    p = world_from_base[:, :3, 3]
    keys = [0]
    for i in range(1, len(stamps_ns)):
        k = keys[-1]
        if np.linalg.norm(p[i] - p[k]) >= distance_m or (stamps_ns[i] - stamps_ns[k]) * 1e-9 >= interval_s:
            keys.append(i)
    if keys[-1] != len(stamps_ns) - 1:
        keys.append(len(stamps_ns) - 1)
    return np.asarray(keys, np.int64)


def _robust(gtsam, base, cfg: FactorGraphConfig):
    if cfg.gps_robust == "none":
        return base
    est = gtsam.noiseModel.mEstimator
    m = est.Cauchy.Create(cfg.gps_robust_k) if cfg.gps_robust == "cauchy" else est.Huber.Create(cfg.gps_robust_k)
    return gtsam.noiseModel.Robust.Create(m, base)


def _world_cov(cov_local: np.ndarray, R: np.ndarray) -> np.ndarray:
    A = np.zeros((6, 6))
    A[:3, :3] = R
    A[3:, 3:] = R
    return A @ cov_local @ A.T


def fuse_session(stamps_ns: np.ndarray, world_from_base_odom: np.ndarray, gps: Optional[GpsObservations] = None,
                 gravity: Optional[GravityObservations] = None, cfg: Optional[FactorGraphConfig] = None,
                 enu_from_odom: Optional[np.ndarray] = None, source: str = "session") -> FusedTrajectory:
    """Fuse one session's odometry with GPS and gravity; poses of the base in the workspace ENU frame.

    ``enu_from_odom`` is the initial guess (a rigid transform); by default the robust rigid GPS fit
    (``align_to_gps``, ``yaw`` mode). Without GPS (or with fewer than 3 fixes inside the trajectory,
    or fixes too close together to fix a heading) the first pose is held where the initial guess
    puts it (the odometry's own frame when none is given): the result is the odometry, levelled by
    gravity when given, with covariances growing along the drive; ``stats['gps']`` says why.
    """
    import gtsam

    cfg = cfg or FactorGraphConfig()
    t_start = time.perf_counter()
    stamps = np.asarray(stamps_ns, np.int64)
    odom = np.asarray(world_from_base_odom, np.float64)
    if len(stamps) < 2 or np.any(np.diff(stamps) <= 0):
        raise InputError(source, "the odometry needs at least 2 poses with increasing stamps", field="trajectory")
    kf = select_keyframes(stamps, odom, cfg.keyframe_distance_m, cfg.keyframe_interval_s)
    stats: dict = {"poses": int(len(stamps)), "keyframes": int(len(kf))}

    # GPS fixes on the trajectory, and the initial guess
    fixes = None
    if gps is not None and len(gps.stamps_ns):
        antenna, ok = associate_fixes(stamps, odom, gps.stamps_ns, gps.base_from_antenna, int(cfg.max_pose_gap_s * 1e9))
        sig = np.asarray(gps.sigma_m, np.float64)[ok].copy()
        sig[~(np.isfinite(sig) & (sig > 0))] = cfg.gps_unknown_sigma_m
        fixes = (np.asarray(gps.stamps_ns, np.int64)[ok], np.asarray(gps.enu, np.float64)[ok], sig, antenna)
        stats["gps_fixes"] = int(ok.sum())
        if enu_from_odom is None:
            try:
                al = align_to_gps(antenna, fixes[1], sig, fixes[0], mode="yaw", source=source)
                enu_from_odom = al.enu_from_map
            except InputError as exc:
                warnings.warn(f"{exc}; fused without GPS", InputWarning, stacklevel=2)
                stats["gps"] = f"not used: {exc.what}"
                fixes = None
    elif gps is not None:
        stats["gps"] = "not used: no fixes"
    else:
        stats["gps"] = "not used: no GPS"
    if fixes is not None and len(fixes[0]) < 3:
        stats["gps"] = f"not used: {len(fixes[0])} fixes overlap the trajectory"
        fixes = None
    T0 = np.eye(4) if enu_from_odom is None else np.asarray(enu_from_odom, np.float64)
    initial_poses = T0 @ odom[kf]

    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    X = lambda i: gtsam.symbol("x", i)  # noqa: E731
    B = lambda j: gtsam.symbol("b", j)  # noqa: E731
    G = gtsam.symbol("g", 0)
    for k, T in enumerate(initial_poses):
        values.insert(X(k), gtsam.Pose3(T))

    # odometry: random-walk drift over the distance driven
    for k in range(len(kf) - 1):
        rel = invert_pose(odom[kf[k]]) @ odom[kf[k + 1]]
        d = float(np.linalg.norm(rel[:3, 3]))
        sr = np.sqrt(cfg.odom_rotation_sigma_rad_per_sqrt_m**2 * d + cfg.odom_rotation_floor_rad**2)
        st = np.sqrt(cfg.odom_translation_sigma_m_per_sqrt_m**2 * d + cfg.odom_translation_floor_m**2)
        noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([sr] * 3 + [st] * 3))
        if cfg.odom_robust == "huber":
            noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(cfg.odom_robust_k), noise)
        graph.add(gtsam.BetweenFactorPose3(X(k), X(k + 1), gtsam.Pose3(rel), noise))

    if fixes is None:
        graph.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(initial_poses[0]), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
    else:
        a = cfg.first_attitude_sigma_rad
        prior = gtsam.noiseModel.Diagonal.Sigmas(np.array([a, a, a, 1e3, 1e3, 1e3]))
        graph.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(initial_poses[0]), prior))
        n_bias = _add_gps(gtsam, graph, values, fixes, stamps, odom, kf, gps.base_from_antenna, cfg, X, B)
        stats["gps_bias_nodes"] = n_bias
    if gravity is not None and len(gravity.stamps_ns):
        n_grav = _add_gravity(gtsam, graph, values, gravity, stamps, kf, cfg, X, G)
        stats["gravity_factors"] = n_grav

    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(cfg.max_iterations)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    result = optimizer.optimize()
    stats.update(iterations=int(optimizer.iterations()), error_initial=float(graph.error(values)),
                 error_final=float(graph.error(result)), solve_s=time.perf_counter() - t_start)

    kf_poses = np.stack([result.atPose3(X(k)).matrix() for k in range(len(kf))])
    marginals = gtsam.Marginals(graph, result)
    kf_cov = np.stack([_world_cov(marginals.marginalCovariance(X(k)), kf_poses[k, :3, :3]) for k in range(len(kf))])
    poses, covs = _densify(stamps, odom, kf, kf_poses, kf_cov)
    inliers = np.zeros(0, bool)
    if fixes is not None:
        inliers = _gps_residual_sigmas(graph, result) < GPS_INLIER_SIGMAS
        stats.update(gps="used", gps_fixes_outliers=int((~inliers).sum()))
        if cfg.gps_bias:
            b = np.stack([result.atPoint3(B(j)) for j in range(stats["gps_bias_nodes"])])
            stats["gps_bias_enu_m"] = {"mean": b.mean(axis=0).tolist(), "min": b.min(axis=0).tolist(), "max": b.max(axis=0).tolist()}
    if gravity is not None and len(gravity.stamps_ns):
        stats["gravity_tilt_bias_rad"] = result.atPoint3(G).tolist()
    stats["seconds"] = time.perf_counter() - t_start
    mid = int(np.argmin(np.abs(stamps[kf] - (stamps[0] + stamps[-1]) // 2)))
    return FusedTrajectory(stamps, poses, covs, kf, kf_cov[mid], inliers, stats)


def _add_gps(gtsam, graph, values, fixes, stamps, odom, kf, base_from_antenna, cfg: FactorGraphConfig, X, B) -> int:
    """GPS factors on the nearest keyframe (the odometry's motion to the fix time in the lever arm) and the bias chain;
    returns the number of bias nodes (0 without a bias)."""
    f_stamps, f_enu, f_sig, _ = fixes
    kf_stamps = stamps[kf]
    near = np.clip(np.searchsorted(kf_stamps, f_stamps), 1, len(kf) - 1)
    near = np.where(np.abs(kf_stamps[near - 1] - f_stamps) <= np.abs(kf_stamps[near] - f_stamps), near - 1, near)
    odom_at_fix, _ = interpolate_poses(stamps, odom, np.clip(f_stamps, stamps[0], stamps[-1]))
    vf = cfg.gps_vertical_sigma_factor
    n_bias = 0
    if cfg.gps_bias:
        t0, t1 = int(f_stamps.min()), int(f_stamps.max())
        n_bias = max(2, int(np.ceil((t1 - t0) * 1e-9 / cfg.bias_interval_s)) + 1)
        node_t = np.linspace(t0, t1, n_bias)
        sb = cfg.gps_bias_sigma_m
        graph.add(gtsam.PriorFactorPoint3(B(0), np.zeros(3), gtsam.noiseModel.Diagonal.Sigmas(np.array([sb, sb, vf * sb]))))
        dt = (node_t[1] - node_t[0]) * 1e-9
        # Gauss-Markov increment over dt: sigma^2 (1 - exp(-2 dt / tau))
        s_step = sb * np.sqrt(1.0 - np.exp(-2.0 * dt / cfg.gps_bias_tau_s))
        step_noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([s_step, s_step, vf * s_step]))
        for j in range(n_bias):
            values.insert(B(j), np.zeros(3))
            if j:
                graph.add(gtsam.BetweenFactorPoint3(B(j - 1), B(j), np.zeros(3), step_noise))
        white_var = np.maximum(f_sig**2 - sb**2, cfg.gps_white_min_sigma_m**2)
    else:
        white_var = f_sig**2
    for i in range(len(f_stamps)):
        k = int(near[i])
        lever = (invert_pose(odom[kf[k]]) @ odom_at_fix[i] @ base_from_antenna)[:3, 3]
        sw = np.sqrt(white_var[i])
        noise = _robust(gtsam, gtsam.noiseModel.Diagonal.Sigmas(np.array([sw, sw, vf * sw])), cfg)
        if n_bias:
            u = (f_stamps[i] - f_stamps.min()) / max(1, int(f_stamps.max() - f_stamps.min())) * (n_bias - 1)
            j = min(int(u), n_bias - 2)
            keys = [X(k), B(j), B(j + 1)]
            a = float(u - j)
        else:
            keys, a = [X(k)], 0.0
        graph.add(gtsam.CustomFactor(noise, keys, _gps_error(f_enu[i], lever, a, keys)))
    return n_bias


def _add_gravity(gtsam, graph, values, gravity: GravityObservations, stamps, kf, cfg: FactorGraphConfig, X, G) -> int:
    """Up-direction factors on the keyframe nearest each observation (within half a keyframe interval), sharing the tilt bias."""
    kf_stamps = stamps[kf]
    g_stamps = np.asarray(gravity.stamps_ns, np.int64)
    j = np.clip(np.searchsorted(g_stamps, kf_stamps), 1, max(1, len(g_stamps) - 1))
    j = np.where(np.abs(g_stamps[j - 1] - kf_stamps) <= np.abs(g_stamps[np.minimum(j, len(g_stamps) - 1)] - kf_stamps),
                 j - 1, np.minimum(j, len(g_stamps) - 1))
    close = np.abs(g_stamps[j] - kf_stamps) <= int(cfg.keyframe_interval_s * 0.5e9)
    values.insert(G, np.zeros(3))
    graph.add(gtsam.PriorFactorPoint3(G, np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(3, cfg.gravity_bias_sigma_rad)))
    noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(cfg.gravity_robust_k),
                                           gtsam.noiseModel.Isotropic.Sigma(3, cfg.gravity_sigma_rad))
    for k in np.nonzero(close)[0]:
        up = np.asarray(gravity.up_base[j[k]], np.float64)
        graph.add(gtsam.CustomFactor(noise, [X(int(k)), G], _gravity_error(up / np.linalg.norm(up))))
    return int(close.sum())


def _gps_residual_sigmas(graph, result) -> np.ndarray:
    """The whitened residual (sigmas of the fix's white noise, before the robust loss) of every GPS factor at the solution."""
    import gtsam

    r = []
    for i in range(graph.size()):
        f = graph.at(i)
        if not isinstance(f, gtsam.CustomFactor) or gtsam.Symbol(f.keys()[-1]).chr() == ord("g"):
            continue
        nm = f.noiseModel()
        base = nm.noise() if isinstance(nm, gtsam.noiseModel.Robust) else nm
        r.append(float(np.linalg.norm(base.whiten(f.unwhitenedError(result)))))
    return np.asarray(r)


def _densify(stamps, odom, kf, kf_poses, kf_cov) -> tuple[np.ndarray, np.ndarray]:
    """Every odometry pose from its two keyframes (odometry from each, blended by time); covariances interpolated."""
    poses = np.empty_like(odom)
    covs = np.empty((len(stamps), 6, 6))
    seg = np.clip(np.searchsorted(kf, np.arange(len(stamps)), side="right") - 1, 0, len(kf) - 2)
    for i in range(len(stamps)):
        k = seg[i]
        a, b = kf[k], kf[k + 1]
        from_a = kf_poses[k] @ invert_pose(odom[a]) @ odom[i]
        from_b = kf_poses[k + 1] @ invert_pose(odom[b]) @ odom[i]
        w = float((stamps[i] - stamps[a]) / (stamps[b] - stamps[a]))
        both = np.stack([from_a, from_b])
        poses[i] = interpolate_poses(np.array([0, 1_000_000], np.int64), both, np.array([int(round(w * 1e6))], np.int64))[0][0]
        covs[i] = (1 - w) * kf_cov[k] + w * kf_cov[k + 1]
    poses[:, 3] = np.array([0.0, 0.0, 0.0, 1.0])
    return poses, covs


__all__ = ["FactorGraphConfig", "FusedTrajectory", "GpsObservations", "GravityObservations", "fuse_session", "gravity_from_imu",
           "select_keyframes"]
