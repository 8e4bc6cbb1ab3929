"""One session's trajectory on a GTSAM factor graph: LiDAR odometry, GPS and the IMU fused, with covariances.

Keyframes are taken from the odometry every ``keyframe_distance_m`` or ``keyframe_interval_s``
(whichever comes first). The graph over their poses holds:

- the odometry as kiss-icp errs: a random walk of its frame in the distance driven plus a per-pose
  registration jitter that does not accumulate (scan-to-map: the next scan is registered to the
  map, not to this pose; against the tiny town's truth its error barely grows from 0.5 m to 32 m
  steps). A chain of odometry-frame poses ``e_k`` linked by ``BetweenFactorPose3`` with the
  odometry's relative motions and the walk's covariance (``sigma^2 = walk^2 d`` per base axis),
  and each pose ``x_k = e_k exp(w_k)`` with white jitter ``w_k``. Independent steps with a
  per-step floor would let the floor accumulate as drift (0.4 deg of pitch over a tiny drive) that
  the real odometry does not have. kiss-icp reports no per-scan registration quality through its
  Python API, so the rates are a stated model fitted against the synthetic town's truth by
  ``bench/factor_graph_budget.py``, not a per-scan covariance;
- the odometry's slips: kiss-icp on a street of flat facades sees a corridor and loses metres
  along it in a second (braking), and lags when starting from rest. A slip is not
  random-walk drift, so no honest Gaussian describes it; the odometry's factors carry a
  redescending robust loss (``odom_robust``: Cauchy) and the IMU, millimetre-exact over a second,
  carries the graph through. Runs of keyframe steps whose translation the solution moves beyond
  ``odom_slip_sigmas`` of the odometry model, by more than ``odom_slip_min_m`` in all, are reported
  as slips (``stats['odom_slip_spans_s']``). Inflating the along-track variance everywhere instead
  would throw away the odometry's along-track precision on every street it does not slip on, and
  a detector of ICP/IMU velocity disagreement would need the velocity the graph estimates;
- the IMU, preintegrated between keyframes (gtsam's ``CombinedImuFactor``, Forster et al.,
  "On-Manifold Preintegration for Real-Time Visual-Inertial Odometry", T-RO 2017), with a velocity
  and a gyro/accelerometer bias state at every keyframe and the biases' random walk inside the
  factor, its noise from ``imu_*`` (continuous-time densities, as Kalibr states them). With an IMU
  the graph's pose states are the IMU's (``world_from_imu``, the base-from-IMU mount from the log's
  transforms): gtsam's own ``body_P_sensor`` takes out the lever arm's centripetal term but not its
  tangential one (``dw/dt x r``), which over a 90-degree turn with the synthetic car's 1.2 m arm
  misplaces the base by metres; states in the IMU frame make the preintegration exact and move the
  mount into the odometry, GPS and output poses instead. Keyframe intervals the IMU does not cover
  (a dropout) get no IMU factor; each covered run has its own bias prior;
- with the IMU, the car's non-holonomic constraint (``nhc_sigma_m_s``): between consecutive keyframes
  the base (the rear axle) moves along the chord of its arc, at half the odometry's heading change,
  and not across it. Why: a constant pitch offset of the states, an accelerometer x bias of g times it
  and a climb along the route are one direction that the IMU alone sees only weakly (the gyro, in turns),
  and odometry steps pointing off the car's heading (the sideways errors of kiss-icp's registrations: in
  a turn, a crab of about a degree) push the solution along it, so that the drive's height drifts on a
  flat road. With the constraint the car travels where it heads (its rotation, from the IMU and the
  odometry), not where the odometry's sideways steps put it. Known answer:
  ``tests/test_factor_graph.py::test_flat_road_keeps_its_height_when_the_odometry_crabs_in_a_turn``; on
  the synthetic town, ``bench/factor_graph_budget.py`` against ``--set nhc_sigma_m_s=0``;
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
- without the IMU's samples, gravity (roll and pitch) where given: a factor per observation of the
  up direction in the base frame (:func:`gravity_from_imu` derives them from the IMU and the
  odometry's speed), with a Cauchy loss, sharing one ``Point3`` state for the accelerometer's bias
  (a constant tilt of the measured up vector, prior ``gravity_bias_sigma_rad``), since one constant
  bias on every factor would otherwise be averaged away as if it were white noise. With the IMU
  preintegrated they are not added (the same accelerometer, counted twice);
- a weak prior on the first keyframe's attitude (the initial guess's) so that a straight drive
  without gravity still solves; without GPS a tight prior on the first pose keeps the odometry's frame;
- loop closures where given (:mod:`mapkit.mapping.loop_closure`: proposed by position, verified by
  ICP of LiDAR local maps): both poses made keyframes, a ``BetweenFactorPose3`` of the two state
  poses per edge (the base's relative pose and covariance moved into the state frame, as the
  odometry's) under a Cauchy loss (``loop_robust_k``). Far out, a Cauchy factor pulls with
  ``k^2 / residual`` whatever its sigma, so a loop holds where the rest of the graph is within about
  ``2k`` of its own sigmas of it and gives way beyond; ``stats['loop_residuals']`` says where each
  edge ended.

Solved with Levenberg-Marquardt (sparse QR: the IMU makes the system stiff, condition 1e13, where
Cholesky gives up) from the rigid GPS fit (``align_to_gps`` in ``yaw`` mode). Poses between
keyframes follow the IMU from the earlier keyframe's solved state where it covers them (the
odometry may be slipping there), else the odometry from both neighbouring keyframes, blended by
time. Covariances are 6x6 over (rotation in ENU axes, rad; position in ENU, m): gtsam's
right-perturbation marginals (by QR, from an iSAM2 built at the solution) moved from the state
frame to the base's and rotated into the world frame, ``diag(R, R) Sigma diag(R, R)^T``.
``stats['end_minus_start_sigma_enu_m']`` is the solution's own uncertainty of the last keyframe's
position against the first's (its height drift, say), from their joint marginal.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal

import numpy as np
from pydantic import Field

from mapkit.core.config import MapkitConfig
from mapkit.core.errors import InputError, InputWarning
from mapkit.core.geometry import interpolate_poses, invert_pose, rotation_angle_rad, skew
from mapkit.mapping.gps_align import align_to_gps, associate_fixes

if TYPE_CHECKING:
    import gtsam

#: a fix is an inlier of the solution below this whitened residual (chi-square, 3 dof, 99%; as gps_align's gate)
GPS_INLIER_SIGMAS = 3.37
#: a 6-dof factor the robust loss down-weighted: whitened residual beyond 3 sigmas per dof
DOWNWEIGHTED_SIGMAS = 3.0 * np.sqrt(6.0)


class FactorGraphConfig(MapkitConfig):
    keyframe_distance_m: float = Field(1.0, description="A keyframe every this many metres driven.")
    keyframe_interval_s: float = Field(
        0.5, description="... or every this many seconds, whichever comes first (standing still)."
    )
    # kiss-icp's error as the sum of a random walk of its frame in the distance driven and a per-pose jitter that does
    # not accumulate (scan-to-map registration: the next scan is registered to the map, not to this pose). Per base
    # axis: rotation about x (roll), y (pitch), z (yaw); translation along x (forward), y (left), z (up). Defaults:
    # kiss-icp on tiny-sunny at 512 columns, fitted against the truth by bench/factor_graph_budget.py (robust spread
    # over 0.5-32 m steps, start and final braking left out); tiny-night and tiny-rainy, not used for the choice, fit
    # within a factor 1.6.
    odom_rotation_walk_rad_per_sqrt_m: tuple[float, float, float] = Field(
        (1.6e-4, 6e-5, 9e-5), description="Odometry drift, rotation per axis: sigma over d metres = this * sqrt(d)."
    )
    odom_translation_walk_m_per_sqrt_m: tuple[float, float, float] = Field(
        (0.007, 0.008, 0.002), description="Odometry drift, translation per axis: sigma over d metres = this * sqrt(d)."
    )
    odom_rotation_jitter_rad: tuple[float, float, float] = Field(
        (2.2e-4, 1.8e-4, 4.5e-4), description="Odometry registration noise of one pose, rotation per axis (white)."
    )
    odom_translation_jitter_m: tuple[float, float, float] = Field(
        (0.017, 0.015, 0.003), description="Odometry registration noise of one pose, translation per axis (white)."
    )
    gps_robust: Literal["cauchy", "huber", "none"] = Field(
        "cauchy",
        description="Robust loss on GPS fixes: Cauchy (redescending: multipath jumps of several metres barely pull), "
        "Huber, or none.",
    )
    gps_robust_k: float = Field(
        2.0, description="The loss's scale in sigmas (Cauchy: 2.385 is the 95%-efficiency choice; 2 cuts harder)."
    )
    gps_white_min_sigma_m: float = Field(
        0.5, description="Floor of a fix's white-noise sigma (horizontal) once the bias variance is taken out."
    )
    gps_unknown_sigma_m: float = Field(
        2.5, description="Reported horizontal sigma assumed for fixes without a covariance."
    )
    gps_vertical_sigma_factor: float = Field(
        2.0, description="GNSS vertical sigma as a multiple of the horizontal (white and bias)."
    )
    gps_bias: bool = Field(True, description="Estimate a slowly varying GPS bias (random walk between bias nodes).")
    gps_bias_sigma_m: float = Field(
        2.0, description="Horizontal standard deviation of the GPS bias (consumer GNSS: metres; synth tiny: 2 m)."
    )
    gps_bias_tau_s: float = Field(
        300.0, description="Correlation time of the bias (ionosphere, satellite geometry: minutes)."
    )
    bias_interval_s: float = Field(5.0, description="A bias node every this many seconds.")
    gravity_sigma_rad: float = Field(
        0.003,
        description="White noise of one up-direction observation (accelerometer noise and "
        "odometry acceleration over the averaging window).",
    )
    gravity_bias_sigma_rad: float = Field(
        0.002,
        description="Constant tilt of the measured up vector: accelerometer bias / g "
        "(consumer MEMS: 0.02 m/s^2, synth tiny's accel_bias_m_s2) plus mount calibration.",
    )
    gravity_robust_k: float = Field(
        2.0,
        description="Cauchy loss on gravity factors, in sigmas: windows where the odometry's speed "
        "is wrong (kiss-icp slipping) give a tilted up and are down-weighted.",
    )
    odom_robust: Literal["huber", "cauchy", "none"] = Field(
        "cauchy",
        description="Robust loss on the odometry's drift and jitter factors: a registration that slipped (kiss-icp "
        "locking onto too little motion from standstill, or along a corridor of flat facades) gives way to the IMU and "
        "GPS. Cauchy, not Huber: a slip of metres is hundreds of sigmas, and Huber's bounded but constant pull still "
        "drags the speed around it (tiny-sunny, bench/factor_graph_budget.py: error across its braking slip 1.16 m "
        "with Huber, 0.26 m with Cauchy, both at k = 2).",
    )
    odom_robust_k: float = Field(
        2.0,
        description="The odometry loss's scale, in sigmas (chosen on tiny-sunny from 1, 1.5, 2, 3 "
        "and 5: smaller cuts kiss-icp's systematic pitch drift harder but takes more iterations).",
    )
    odom_slip_sigmas: float = Field(
        4.03,
        description="A keyframe step whose translation the solution moves by more than this many "
        "sigmas of the odometry model is off the odometry (chi-square, 3 dof, 99.9%).",
    )
    odom_slip_min_m: float = Field(
        0.3,
        description="A run of steps off the odometry is reported as a slip when the solution moves "
        "the odometry's motion across it by more than this (less is kiss-icp's heavy-tailed registration "
        "noise: tiny-sunny, RMS 0.034 m against a robust spread of 0.022 m over 1 m steps).",
    )
    imu_gyro_noise_density: float = Field(
        2.4e-4,
        description="Gyro white noise, rad/s/sqrt(Hz) (continuous time; per-sample sigma = this * sqrt(rate)). "
        "ADIS16448 datasheet (the EuRoC / VI-sensor MEMS IMU): 0.0135 deg/s/sqrt(Hz).",
    )
    imu_accel_noise_density: float = Field(
        2.3e-3, description="Accelerometer white noise, m/s^2/sqrt(Hz). ADIS16448 datasheet: 0.23 mg/sqrt(Hz)."
    )
    imu_gyro_random_walk: float = Field(
        4.0e-6, description="Gyro bias random walk, rad/s^2/sqrt(Hz). Kalibr's example IMU file (ADIS16448)."
    )
    imu_accel_random_walk: float = Field(
        2.0e-4, description="Accelerometer bias random walk, m/s^3/sqrt(Hz). Kalibr's example IMU file (ADIS16448)."
    )
    imu_gyro_bias_sigma: float = Field(
        0.005,
        description="Prior sigma of the gyro's turn-on bias, rad/s (mapkit choice: about 0.3 deg/s, loose for consumer "
        "MEMS; the drive refines it).",
    )
    imu_accel_bias_sigma: float = Field(
        0.1,
        description="Prior sigma of the accelerometer's turn-on bias, m/s^2 (mapkit choice: about 10 mg, loose for "
        "consumer MEMS).",
    )
    imu_gravity_m_s2: float = Field(
        9.80665,
        description="Magnitude of gravity (standard gravity; a local difference of mm/s^2 goes "
        "into the accelerometer bias).",
    )
    imu_max_gap_s: float = Field(
        0.1,
        description="Keyframe intervals where IMU samples are further apart than this get no IMU factor (a dropout).",
    )
    # the car's non-holonomic constraint: without it the graph's height drifts on a flat road. Its sigma is fitted on
    # tiny-sunny's truth only; tiny-night and tiny-rainy were not used for the choice
    nhc_sigma_m_s: float = Field(
        0.005,
        ge=0,
        description="With the IMU preintegrated: a car's rear axle rolls, it does not slide. Between consecutive "
        "keyframes the base moves along the chord of its arc, at half the odometry's heading change from its earlier "
        "heading; its displacement across that chord is zero with sigma = this times the keyframes' time apart, m/s "
        "(0: off). The base frame's origin is taken for the rear axle's centre: a base elsewhere (the car's centre, "
        "the front axle) moves sideways in every turn. Synthetic town, tiny-sunny: the truth's displacement across the "
        "chord of the odometry's heading change, rms 0.0047 m/s times dt (robust spread 0.0019; the truth's own, with "
        "its heading: 0.0025, lane wander); eight other synthetic drives, not used for the choice: 0.0039-0.0059.",
    )
    nhc_robust_k: float = Field(
        2.0,
        gt=0,
        description="Cauchy loss on those factors, in sigmas (a skid; the odometry's heading "
        "change off where it slips).",
    )
    first_attitude_sigma_rad: float = Field(
        0.2, description="Weak prior on the first keyframe's attitude (the initial guess's)."
    )
    max_pose_gap_s: float = Field(1.0, description="A fix between odometry poses further apart than this is not used.")
    max_iterations: int = Field(100, description="Levenberg-Marquardt iterations.")
    # loop closures (mapping/loop_closure.py): proposed by position, verified by ICP of local maps. Gates and floors set
    # on two synthetic loop drives (tiny preset's town generated around a 294 m rounded rectangle driven from rest a lap
    # and 30 m on, LiDAR at 10 and 5 Hz) and on ICP of sweeps ray cast in the tiny town; tests/test_loop_closure.py's
    # end-to-end drive (another town and route) was not used for any choice
    loop_closures: bool = Field(
        True,
        description="Close loops where the session revisits a place (mapkit build: logs with "
        "a LiDAR stream; the graph takes the accepted ones as robust between factors).",
    )
    loop_radius_m: float = Field(
        6.0,
        gt=0,
        description="Propose keyframe pairs whose positions lie this close horizontally "
        "(two lanes apart, 3.5 m, plus the GPS-fused estimate's error where the drive comes back, "
        "1.4-2.3 m on the synthetic loops); the odometry's drift over the distance driven "
        "between them is added (loop_proposal_sigmas).",
    )
    loop_proposal_sigmas: float = Field(
        3.0,
        gt=0,
        description="... plus this many sigmas of the odometry model's horizontal "
        "drift over the distance driven between the pair (odom_*_walk).",
    )
    loop_min_travel_m: float = Field(
        50.0,
        gt=0,
        description="A pair is a loop only when this much was driven between them: "
        "closer keyframes are the same pass, which the odometry already ties (mapkit choice: half "
        "the LiDAR's useful range).",
    )
    loop_min_separation_m: float = Field(
        10.0,
        gt=0,
        description="At most one candidate (the nearest) per this much route on "
        "either pass: neighbouring pairs see the same scene and add cost, not information.",
    )
    loop_local_scans: int = Field(
        2,
        ge=0,
        description="A keyframe's local map: its scan and this many on each side, placed "
        "(and deskewed) with the fused trajectory (synthetic loop, ICP's edges against the truth: "
        "2-7 cm and 0.02-0.33 deg with 2, 4-20 cm with 5: the placement's own errors grow with the "
        "span; 0 leaves single sweeps, 3-14 cm).",
    )
    loop_local_radius_m: float = Field(
        40.0,
        gt=0,
        description="Local maps keep points within this horizontal distance of their "
        "keyframe (the scene both passes see; far returns are sparse and noisy).",
    )
    loop_min_range_m: float = Field(
        2.0,
        ge=0,
        description="Returns closer to the scanner than this are dropped (the vehicle body; kiss-icp's min_range).",
    )
    loop_icp_voxels_m: tuple[float, ...] = Field(
        (1.0, 0.5, 0.2), description="Voxel size of each coarse-to-fine ICP level."
    )
    loop_icp_max_correspondence_m: tuple[float, ...] = Field(
        (4.0, 1.5, 0.5),
        description="Largest correspondence distance of each level; the first bounds the error of the "
        "estimate ICP can pull in.",
    )
    loop_icp_iterations: int = Field(30, ge=1, description="ICP iterations per level.")
    loop_eval_distance_m: float = Field(
        0.3,
        gt=0,
        description="Correspondence distance at which overlap (fitness), RMSE and "
        "conditioning are measured (the fine level).",
    )
    loop_min_points: int = Field(
        1000, ge=10, description="A local map with fewer points (after the fine voxel) is not registered."
    )
    loop_min_fitness: float = Field(
        0.5,
        ge=0,
        le=1,
        description="Accept only when this fraction of one local map lies within "
        "loop_eval_distance_m of the other's surfaces (one place seen twice: 0.90-0.99 on the "
        "synthetic loops; another place ICP fitted anyway: 0.41-0.64).",
    )
    loop_max_rmse_m: float = Field(
        0.08,
        gt=0,
        description="... and their point-to-plane RMSE over those is below this "
        "(one place: 0.016-0.052 m; another place: 0.073-0.086 m).",
    )
    loop_min_constraint: float = Field(
        0.03,
        gt=0,
        le=1,
        description="... and every direction of translation is held: the "
        "smallest eigenvalue of the point-to-plane Hessian's translation block (rotation "
        "marginalised) per correspondence, at least this; between 0 (a street of flat "
        "facades holds nothing along itself) and 1/3 (one place: 0.06-0.12; another place: "
        "0.008-0.025).",
    )
    loop_max_correction_m: float = Field(
        4.0,
        gt=0,
        description="Reject when ICP moves the pair's relative position further "
        "than this from the estimate (the first level's reach).",
    )
    loop_max_rotation_deg: float = Field(5.0, gt=0, description="... or turns it by more than this.")
    loop_floor_rotation_rad: float = Field(
        0.003,
        gt=0,
        description="Added to a loop edge's rotation sigma per axis: its "
        "local maps are placed with an estimate whose errors over their span no support "
        "removes (synthetic loop: ICP's edges off the truth by 0.02-0.33 deg).",
    )
    loop_floor_translation_m: float = Field(
        0.05, gt=0, description="... and to its translation sigma per axis (synthetic loop: 2-7 cm)."
    )
    loop_robust_k: float = Field(
        4.0,
        gt=0,
        description="Cauchy loss on the loop factors, in sigmas of the edge's covariance. "
        "Far out a Cauchy factor pulls with k^2 / (its residual) whatever its sigma, so a loop holds "
        "when the rest of the graph lies within about 2k of its own sigmas of it, and gives way "
        "beyond. Chosen from 2, 3, 4, 5 and 10 on two synthetic loop drives (tiny preset, 294 m "
        "rounded rectangle, LiDAR at 10 and 5 Hz), where the graph without loops is 3-7 of its "
        "sigmas off at the revisit (median error of the motion between the passes 1.52 / 2.48 m): "
        "2 left 0.77 / -, 3 0.10 / 1.70, 4 0.12 / 0.22, 5 0.12 / 0.19 m; and on "
        "tests/test_loop_closure.py's GPS-held drive, where a loop 12 m off across the road moves "
        "the solution 0.44 m with 3, 0.80 m with 4, and one 5 m off wins with 4.",
    )


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
class ImuObservations:
    """IMU samples in the IMU's own frame: angular rate (rad/s) and specific force (m/s^2) at ``stamps_ns``, and its
    mount."""

    stamps_ns: np.ndarray
    gyro_rad_s: np.ndarray
    accel_m_s2: np.ndarray
    base_from_imu: np.ndarray = field(default_factory=lambda: np.eye(4))

    @classmethod
    def from_samples(cls, samples: list, base_from_imu: np.ndarray) -> ImuObservations:
        """From a log's ``ImuSample`` records (``DriveLog.records(StreamKind.IMU)``) and the IMU's mount."""
        return cls(
            np.array([s.stamp_ns for s in samples], np.int64),
            np.stack([s.angular_velocity_rad_s for s in samples]),
            np.stack([s.linear_acceleration_m_s2 for s in samples]),
            np.asarray(base_from_imu, np.float64),
        )


@dataclass
class LoopEdge:
    """A loop closure: the base's pose at ``stamp_b_ns`` seen from its pose at ``stamp_a_ns`` (``a_from_b``), with the
    6x6 covariance of the right perturbation ``a_from_b exp(xi)`` (gtsam's Pose3 tangent: rotation, translation; base
    b's axes). Both stamps are poses of the odometry."""

    stamp_a_ns: int
    stamp_b_ns: int
    a_from_b: np.ndarray
    covariance: np.ndarray


@dataclass
class LoopClosures:
    """The loop closures of one session: the accepted edges and, one reason each, the candidates that were rejected."""

    edges: list[LoopEdge] = field(default_factory=list)
    rejected: list[str] = field(default_factory=list)


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
    # the graph's solved values: where a re-solve of the same keyframes starts (``start``)
    solution: gtsam.Values | None = None


# --- gravity -----------------------------------------------------------------------------------------


def gravity_from_imu(
    imu_stamps_ns: np.ndarray,
    gyro_rad_s: np.ndarray,
    accel_m_s2: np.ndarray,
    base_from_imu: np.ndarray,
    stamps_ns: np.ndarray,
    world_from_base: np.ndarray,
    query_ns: np.ndarray,
    window_s: float = 1.0,
    speed_baseline_s: float = 1.0,
) -> GravityObservations:
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
        ends = np.stack(
            [
                np.interp(np.concatenate([t - hb, t + hb]).astype(np.float64), stamps.astype(np.float64), p[:, k])
                for k in range(3)
            ],
            axis=1,
        ).reshape(2, len(t), 3)
        return np.linalg.norm(ends[1] - ends[0], axis=1) / (2 * hb * 1e-9)

    v_imu = speed(imu_t.clip(stamps[0] + hb, stamps[-1] - hb))
    # per sample: centripetal v w_z (lateral) and the lever arm's w x (w x r)
    a_turn = np.column_stack([np.zeros(len(imu_t)), v_imu * w_b[:, 2], np.zeros(len(imu_t))]) + np.cross(
        w_b, np.cross(w_b, r)
    )
    csum = lambda x: np.vstack([np.zeros(x.shape[1]), np.cumsum(x, axis=0)])  # noqa: E731 (a one-line helper local to this function)
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
            H[0] = np.hstack([-R @ skew(lever), R])
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
            H[0] = np.hstack([skew(v), np.zeros((3, 3))])
            H[1] = np.eye(3)
        return v + bias - up_meas

    return error


# --- the graph ---------------------------------------------------------------------------------------


def select_keyframes(
    stamps_ns: np.ndarray, world_from_base: np.ndarray, distance_m: float, interval_s: float
) -> np.ndarray:
    """Indices of keyframes: the first pose, every pose ``distance_m`` or ``interval_s`` past the last keyframe, the
    last pose."""
    p = world_from_base[:, :3, 3]
    keys = [0]
    for i in range(1, len(stamps_ns)):
        k = keys[-1]
        if np.linalg.norm(p[i] - p[k]) >= distance_m or (stamps_ns[i] - stamps_ns[k]) * 1e-9 >= interval_s:
            keys.append(i)
    if keys[-1] != len(stamps_ns) - 1:
        keys.append(len(stamps_ns) - 1)
    return np.asarray(keys, np.int64)


def _robust(gtsam, base, kind: str, k: float):
    """``base`` under the robust loss ``kind`` ("cauchy", "huber" or "none") of scale ``k`` sigmas."""
    if kind == "none":
        return base
    est = gtsam.noiseModel.mEstimator
    m = est.Cauchy.Create(k) if kind == "cauchy" else est.Huber.Create(k)
    return gtsam.noiseModel.Robust.Create(m, base)


def _world_cov(cov_local: np.ndarray, R: np.ndarray) -> np.ndarray:
    A = np.zeros((6, 6))
    A[:3, :3] = R
    A[3:, 3:] = R
    return A @ cov_local @ A.T


def _adjoint(T: np.ndarray) -> np.ndarray:
    """Adjoint of a pose on gtsam's Pose3 tangent (rotation, translation): T exp(xi) = exp(Ad_T xi) T."""
    R, t = T[:3, :3], T[:3, 3]
    A = np.zeros((6, 6))
    A[:3, :3] = R
    A[3:, 3:] = R
    A[3:, :3] = skew(t) @ R
    return A


def _drift_covariance(rel: np.ndarray, cfg: FactorGraphConfig) -> np.ndarray:
    """6x6 covariance (base frame, gtsam's tangent order) of the odometry frame's drift over one step: a random walk
    in the distance driven (a step counts at least 1 cm, so that standing still is not a singular constraint)."""
    d = max(float(np.linalg.norm(rel[:3, 3])), 0.01)
    return np.diag(
        np.concatenate([cfg.odom_rotation_walk_rad_per_sqrt_m, cfg.odom_translation_walk_m_per_sqrt_m]) ** 2 * d
    )


def _odom_loss(gtsam, noise, cfg: FactorGraphConfig):
    return _robust(gtsam, noise, cfg.odom_robust, cfg.odom_robust_k)


def _add_nhc(
    gtsam,
    graph,
    odom_rel: list[np.ndarray],
    kf_stamps: np.ndarray,
    state_from_base: np.ndarray,
    cfg: FactorGraphConfig,
    X,
) -> int:
    """The non-holonomic constraint over each keyframe step: the base's displacement, in the earlier keyframe's base
    axes, has no component across the chord direction (half the odometry's heading change ``dpsi`` from the x axis),
    within ``nhc_sigma_m_s * dt``; nothing else about the step is said (the information is that one direction, moved
    into the state frame as the odometry's). Neither the odometry's distance nor its sideways motion enters, only its
    heading change (kiss-icp's distance slips and its steps' sideways errors, 16-172 mm rms per 0.1 s step on the tiny
    town, do not). A ``BetweenFactorPose3`` with that rank-one information (plus 1e-8 on the other directions), not a
    Python factor: gtsam's Python factors cost a call into the interpreter per factor and solver step, which doubled the
    graph's time in a trial with a velocity form of the constraint. Returns the number of factors."""
    base_from_state = invert_pose(state_from_base)
    Ad_bs = _adjoint(base_from_state)
    for k, rel in enumerate(odom_rel):
        dt = max(float(kf_stamps[k + 1] - kf_stamps[k]) * 1e-9, 1e-3)
        half = 0.5 * float(np.arctan2(rel[1, 0], rel[0, 0]))
        across = np.array([-np.sin(half), np.cos(half), 0.0])  # across the chord, in keyframe k's base axes
        meas = rel.copy()
        meas[:3, 3] = np.array([np.cos(half), np.sin(half), 0.0]) * float(np.hypot(rel[0, 3], rel[1, 3])) + [
            0.0,
            0.0,
            rel[2, 3],
        ]
        m = rel[:3, :3].T @ across  # the between factor's translation error is in the measured pose's axes
        info = np.zeros((6, 6))
        info[3:, 3:] = np.outer(m, m) / (cfg.nhc_sigma_m_s * dt) ** 2  # base tangent (rotation, translation)
        # in the state frame; a negligible information on the other five directions keeps it positive definite
        info = Ad_bs.T @ info @ Ad_bs + 1e-8 * np.eye(6)
        noise = _robust(gtsam, gtsam.noiseModel.Gaussian.Information(0.5 * (info + info.T)), "cauchy", cfg.nhc_robust_k)
        graph.add(
            gtsam.BetweenFactorPose3(X(k), X(k + 1), gtsam.Pose3(state_from_base @ meas @ base_from_state), noise)
        )
    return len(odom_rel)


def fuse_session(
    stamps_ns: np.ndarray,
    world_from_base_odom: np.ndarray,
    gps: GpsObservations | None = None,
    gravity: GravityObservations | None = None,
    cfg: FactorGraphConfig | None = None,
    enu_from_odom: np.ndarray | None = None,
    source: str = "session",
    *,
    imu: ImuObservations | None = None,
    loops: LoopClosures | None = None,
    start: FusedTrajectory | None = None,
) -> FusedTrajectory:
    """Fuse one session's odometry with GPS and the IMU (preintegrated, or its gravity direction);
    poses of the base in ENU.

    ``enu_from_odom`` is the initial guess (a rigid transform); by default the robust rigid GPS fit
    (``align_to_gps``, ``yaw`` mode). Without GPS (or with fewer than 3 fixes inside the trajectory,
    or fixes too close together to fix a heading) the first pose is held where the initial guess
    puts it (the odometry's own frame when none is given): the result is the odometry, levelled by
    gravity or the IMU when given, with covariances growing along the drive; ``stats['gps']`` says why.
    With ``imu`` the gravity observations are not used (``stats['gravity']`` says so). ``loops``: loop closures
    (:mod:`mapkit.mapping.loop_closure`), their poses made keyframes and their edges robust between factors when
    ``cfg.loop_closures``; the stats count candidates, accepted and rejected ones and give each edge's residual.
    ``start``: an earlier solution of the same data and keyframes (the same graph without the loops, say), which the
    solver starts from instead of the initial guess (ignored when its keyframes differ).
    """
    import gtsam

    cfg = cfg or FactorGraphConfig()
    t_start = time.perf_counter()
    stamps = np.asarray(stamps_ns, np.int64)
    odom = np.asarray(world_from_base_odom, np.float64)
    if len(stamps) < 2 or np.any(np.diff(stamps) <= 0):
        raise InputError(source, "the odometry needs at least 2 poses with increasing stamps", field="trajectory")
    kf = select_keyframes(stamps, odom, cfg.keyframe_distance_m, cfg.keyframe_interval_s)
    edges = loops.edges if loops is not None and cfg.loop_closures else []
    kf = _with_loop_keyframes(kf, stamps, edges, source)
    stats: dict = {"poses": int(len(stamps)), "keyframes": int(len(kf))}
    imu = _check_imu(imu, source) if imu is not None else None
    # the graph's pose states: the IMU's frame when it is preintegrated (exact lever arm), else the base's
    base_from_state = np.asarray(imu.base_from_imu, np.float64) if imu is not None else np.eye(4)
    state_from_base = invert_pose(base_from_state)
    fixes, enu_from_odom = _fixes_on_trajectory(gps, stamps, odom, enu_from_odom, cfg, source, stats)
    T0 = np.eye(4) if enu_from_odom is None else np.asarray(enu_from_odom, np.float64)
    initial_poses = T0 @ odom[kf] @ base_from_state

    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    X = lambda i: gtsam.symbol("x", i)  # noqa: E731 (a one-line helper local to this function)
    B = lambda j: gtsam.symbol("b", j)  # noqa: E731 (a one-line helper local to this function)
    G = gtsam.symbol("g", 0)
    for k, T in enumerate(initial_poses):
        values.insert(X(k), gtsam.Pose3(T))
    odom_rel = [invert_pose(odom[kf[k]]) @ odom[kf[k + 1]] for k in range(len(kf) - 1)]
    chain_factors, jitter_factors = _add_odometry(
        gtsam, graph, values, odom_rel, initial_poses, state_from_base, base_from_state, cfg, X
    )
    # without the IMU it changed nothing measurable (tiny town: height drift, ATE within 0.01 m) and cost time
    if imu is not None and cfg.nhc_sigma_m_s > 0:
        stats["nhc_factors"] = _add_nhc(gtsam, graph, odom_rel, stamps[kf], state_from_base, cfg, X)
    loop_factors = _add_loops(gtsam, graph, edges, stamps, kf, state_from_base, cfg, X)
    _anchor_to_enu(gtsam, graph, values, fixes, gps, stamps, odom, kf, initial_poses, state_from_base, cfg, X, B, stats)
    imu_runs = _add_inertial(
        gtsam, graph, values, imu, gravity, stamps, kf, initial_poses, state_from_base, cfg, X, G, stats
    )

    if start is not None and start.solution is not None and np.array_equal(start.keyframes, kf):
        values.update(start.solution)
        stats["started_from"] = "an earlier solution"
    result = _optimize(gtsam, graph, values, cfg, stats, t_start)

    kf_poses = np.stack([result.atPose3(X(k)).matrix() for k in range(len(kf))]) @ state_from_base
    kf_cov = _keyframe_covariances(gtsam, graph, result, kf_poses, base_from_state, X, stats)
    poses, covs = _densify(stamps, odom, kf, kf_poses, kf_cov)
    if imu is not None and imu_runs:  # between keyframes the IMU knows the motion (the odometry may be slipping there)
        _densify_imu(poses, stamps, kf, imu_runs, imu, result, state_from_base, cfg)
    inliers = _solution_stats(gtsam, graph, result, fixes is not None, imu_runs, cfg, B, G, stats)
    stats.update(_slips(graph, result, chain_factors, jitter_factors, odom, kf, kf_poses, stamps[kf], cfg))
    if loops is not None:
        stats.update(_loop_stats(graph, result, loop_factors, edges, loops, stamps[kf], kf_poses, cfg))
    stats["seconds"] = time.perf_counter() - t_start
    mid = int(np.argmin(np.abs(stamps[kf] - (stamps[0] + stamps[-1]) // 2)))
    return FusedTrajectory(stamps, poses, covs, kf, kf_cov[mid], inliers, stats, result)


#: GPS fixes on the trajectory: (stamps_ns, enu, sigma_m, antenna positions in the odometry frame)
_Fixes = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def _fixes_on_trajectory(
    gps: GpsObservations | None,
    stamps: np.ndarray,
    odom: np.ndarray,
    enu_from_odom: np.ndarray | None,
    cfg: FactorGraphConfig,
    source: str,
    stats: dict,
) -> tuple[_Fixes | None, np.ndarray | None]:
    """(the GPS fixes the graph uses, the initial guess ``enu_from_odom``): the fixes associated with the
    trajectory (an unknown sigma taken as ``gps_unknown_sigma_m``), and without a given guess the robust rigid
    fit to them. None for the fixes when GPS cannot be used, with the reason in ``stats['gps']``."""
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
                warnings.warn(f"{exc}; fused without GPS", InputWarning, stacklevel=3)
                stats["gps"] = f"not used: {exc.what}"
                fixes = None
    elif gps is not None:
        stats["gps"] = "not used: no fixes"
    else:
        stats["gps"] = "not used: no GPS"
    if fixes is not None and len(fixes[0]) < 3:
        stats["gps"] = f"not used: {len(fixes[0])} fixes overlap the trajectory"
        fixes = None
    return fixes, enu_from_odom


def _add_odometry(
    gtsam,
    graph,
    values,
    odom_rel: list[np.ndarray],
    initial_poses: np.ndarray,
    state_from_base: np.ndarray,
    base_from_state: np.ndarray,
    cfg: FactorGraphConfig,
    X,
) -> tuple[list[int], list[int]]:
    """The odometry's factors; returns the indices in the graph of its drift chain's factors and of its jitter
    factors.

    Odometry = its drifting frame + per-pose jitter: a chain of odometry-frame poses E_k (kiss-icp's poses without
    their registration noise) whose relative motions are the odometry's up to a random walk (slips break it: robust
    loss), and each pose X_k = E_k exp(w_k) with white jitter w_k. Independent steps with a per-step floor instead
    would let the floor accumulate as drift (0.4 deg of pitch over the tiny drive), which the real odometry does not
    do."""
    E = lambda i: gtsam.symbol("e", i)  # noqa: E731 (a one-line helper local to this function)
    Ad_sb = _adjoint(state_from_base)
    jitter = np.diag(np.concatenate([cfg.odom_rotation_jitter_rad, cfg.odom_translation_jitter_m]) ** 2)
    jitter_noise = _odom_loss(gtsam, gtsam.noiseModel.Gaussian.Covariance(Ad_sb @ jitter @ Ad_sb.T), cfg)
    chain_factors, jitter_factors = [], []
    for k, T in enumerate(initial_poses):
        values.insert(E(k), gtsam.Pose3(T))
        jitter_factors.append(graph.size())
        graph.add(gtsam.BetweenFactorPose3(E(k), X(k), gtsam.Pose3(), jitter_noise))
    for k, rel in enumerate(odom_rel):
        noise = _odom_loss(
            gtsam, gtsam.noiseModel.Gaussian.Covariance(Ad_sb @ _drift_covariance(rel, cfg) @ Ad_sb.T), cfg
        )
        chain_factors.append(graph.size())
        graph.add(gtsam.BetweenFactorPose3(E(k), E(k + 1), gtsam.Pose3(state_from_base @ rel @ base_from_state), noise))
    return chain_factors, jitter_factors


def _anchor_to_enu(
    gtsam,
    graph,
    values,
    fixes: _Fixes | None,
    gps: GpsObservations | None,
    stamps: np.ndarray,
    odom: np.ndarray,
    kf: np.ndarray,
    initial_poses: np.ndarray,
    state_from_base: np.ndarray,
    cfg: FactorGraphConfig,
    X,
    B,
    stats: dict,
) -> None:
    """What holds the graph in ENU: the GPS fixes (with a loose prior on the first pose, which holds its attitude),
    or without them the first pose fixed where the initial guess puts it."""
    if fixes is None:
        graph.add(
            gtsam.PriorFactorPose3(X(0), gtsam.Pose3(initial_poses[0]), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6))
        )
        return
    a = cfg.first_attitude_sigma_rad
    prior = gtsam.noiseModel.Diagonal.Sigmas(np.array([a, a, a, 1e3, 1e3, 1e3]))
    graph.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(initial_poses[0]), prior))
    assert gps is not None  # the fixes came from it
    n_bias = _add_gps(gtsam, graph, values, fixes, stamps, odom, kf, gps.base_from_antenna, state_from_base, cfg, X, B)
    stats["gps_bias_nodes"] = n_bias


def _add_inertial(
    gtsam,
    graph,
    values,
    imu: ImuObservations | None,
    gravity: GravityObservations | None,
    stamps: np.ndarray,
    kf: np.ndarray,
    initial_poses: np.ndarray,
    state_from_base: np.ndarray,
    cfg: FactorGraphConfig,
    X,
    G,
    stats: dict,
) -> list[list[int]]:
    """The IMU preintegrated between keyframes, or without it the gravity observations; returns the IMU's runs of
    keyframes (none without it)."""
    if imu is None:
        stats["imu"] = "not used: no IMU"
        if gravity is not None and len(gravity.stamps_ns):
            stats["gravity_factors"] = _add_gravity(
                gtsam, graph, values, gravity, stamps, kf, state_from_base, cfg, X, G
            )
        return []
    imu_runs = _add_imu(gtsam, graph, values, imu, stamps[kf], initial_poses, cfg)
    stats["imu_factors"] = int(sum(len(r) - 1 for r in imu_runs))
    if gravity is not None and len(gravity.stamps_ns):
        stats["gravity"] = "not used: the IMU is preintegrated"
    return imu_runs


def _optimize(gtsam, graph, values, cfg: FactorGraphConfig, stats: dict, t_start: float):
    """The graph solved by Levenberg-Marquardt from ``values``; its iterations, errors and time into ``stats``."""
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(cfg.max_iterations)
    params.setLinearSolverType("MULTIFRONTAL_QR")  # the IMU makes the system stiff (condition 1e13): Cholesky loses it
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    result = optimizer.optimize()
    stats.update(
        iterations=int(optimizer.iterations()),
        error_initial=float(graph.error(values)),
        error_final=float(graph.error(result)),
        solve_s=time.perf_counter() - t_start,
    )
    return result


def _keyframe_covariances(
    gtsam, graph, result, kf_poses: np.ndarray, base_from_state: np.ndarray, X, stats: dict
) -> np.ndarray:
    """(K, 6, 6) covariances of the keyframes' base poses (rotation in ENU axes, position ENU) at the solution;
    the sigmas of the drive's end against its start into ``stats``."""
    # marginals by QR (an iSAM2 built at the solution): gtsam.Marginals' Cholesky finds the IMU's graph indeterminate
    isam_params = gtsam.ISAM2Params()
    isam_params.setFactorization("QR")
    marginals = gtsam.ISAM2(isam_params)
    marginals.update(graph, result)
    Ad_bs = _adjoint(base_from_state)  # right perturbation of the state pose, seen on the base pose
    n = len(kf_poses)
    kf_cov = np.stack(
        [_world_cov(Ad_bs @ marginals.marginalCovariance(X(k)) @ Ad_bs.T, kf_poses[k, :3, :3]) for k in range(n)]
    )
    stats["end_minus_start_sigma_enu_m"] = _relative_sigma(
        gtsam, marginals, X(0), X(n - 1), kf_poses[0], kf_poses[-1], Ad_bs
    ).tolist()
    return kf_cov


def _solution_stats(
    gtsam, graph, result, with_gps: bool, imu_runs: list[list[int]], cfg: FactorGraphConfig, B, G, stats: dict
) -> np.ndarray:
    """The GPS fixes that the solution leaves within ``GPS_INLIER_SIGMAS`` (none without GPS); the GPS outliers
    and the estimated biases (GPS, gravity tilt, the IMU's at the end) into ``stats``."""
    inliers = np.zeros(0, bool)
    if with_gps:
        inliers = _gps_residual_sigmas(graph, result) < GPS_INLIER_SIGMAS
        stats.update(gps="used", gps_fixes_outliers=int((~inliers).sum()))
        if cfg.gps_bias:
            b = np.stack([result.atPoint3(B(j)) for j in range(stats["gps_bias_nodes"])])
            stats["gps_bias_enu_m"] = {
                "mean": b.mean(axis=0).tolist(),
                "min": b.min(axis=0).tolist(),
                "max": b.max(axis=0).tolist(),
            }
    if "gravity_factors" in stats:
        stats["gravity_tilt_bias_rad"] = result.atPoint3(G).tolist()
    if imu_runs:
        C = lambda i: gtsam.symbol("c", i)  # noqa: E731 (a one-line helper local to this function)
        bias = [result.atConstantBias(C(r[-1])) for r in imu_runs]
        stats["imu_bias_end"] = {
            "gyro_rad_s": bias[-1].gyroscope().tolist(),
            "accel_m_s2": bias[-1].accelerometer().tolist(),
        }
    return inliers


def _relative_sigma(
    gtsam, isam, key_a: int, key_b: int, pose_a: np.ndarray, pose_b: np.ndarray, Ad_bs: np.ndarray
) -> np.ndarray:
    """Standard deviations (ENU, m) of the last keyframe's base position minus the first's, from their joint marginal:
    how far the solution's own uncertainty lets the drive's end move against its start (its height drift, say)."""
    cov = isam.jointMarginalCovariance([key_a, key_b]).fullMatrix()
    sel = np.hstack([np.zeros((3, 3)), np.eye(3)])  # translation of gtsam's Pose3 tangent: the position moves by R dt
    J = np.hstack([-pose_a[:3, :3] @ sel @ Ad_bs, pose_b[:3, :3] @ sel @ Ad_bs])
    return np.sqrt(np.diag(J @ cov @ J.T))


def _slips(
    graph,
    result,
    chain_factors: list,
    jitter_factors: list,
    odom: np.ndarray,
    kf: np.ndarray,
    kf_poses: np.ndarray,
    kf_stamps: np.ndarray,
    cfg: FactorGraphConfig,
) -> dict:
    """Where the solution left the odometry. Keyframe steps whose translation the solution moves by more than
    ``odom_slip_sigmas`` (3-dof chi-square) of the model's step spread (jitter at both ends plus the walk) are merged
    into spans, whichever factor gave way (the drift chain for a lasting loss, the jitter for a few poses); a span is a
    slip when the solution moves the odometry's motion across it by more than ``odom_slip_min_m``. Also how many drift
    and jitter factors the robust loss down-weighted (whitened residual beyond 3 sigmas per dof)."""
    jt = np.asarray(cfg.odom_translation_jitter_m)
    wt = np.asarray(cfg.odom_translation_walk_m_per_sqrt_m)
    off = []
    for k in range(len(kf) - 1):
        rel = invert_pose(odom[kf[k]]) @ odom[kf[k + 1]]
        diff = (invert_pose(kf_poses[k]) @ kf_poses[k + 1])[:3, 3] - rel[:3, 3]
        if np.linalg.norm(diff / np.sqrt(2 * jt**2 + wt**2 * np.linalg.norm(rel[:3, 3]))) > cfg.odom_slip_sigmas:
            off.append((k, k + 1))
    t = (kf_stamps - kf_stamps[0]) * 1e-9
    spans, moved = [], []
    for a, b in _merge_spans(off):
        a, b = int(a), int(b)
        diff = (invert_pose(kf_poses[a]) @ kf_poses[b])[:3, 3] - (invert_pose(odom[kf[a]]) @ odom[kf[b]])[:3, 3]
        if np.linalg.norm(diff) > cfg.odom_slip_min_m:
            spans.append([float(t[a]), float(t[b])])
            moved.append(float(np.linalg.norm(diff)))
    whitened = lambda idx: np.array([float(np.linalg.norm(_whitened(graph.at(i), result))) for i in idx])  # noqa: E731 (a one-line helper local to this function)
    return {
        "odom_slips": len(spans),
        "odom_slip_m": moved,
        "odom_slip_spans_s": spans,
        "odom_drift_downweighted": int((whitened(chain_factors) > DOWNWEIGHTED_SIGMAS).sum()),
        "odom_jitter_downweighted": int((whitened(jitter_factors) > DOWNWEIGHTED_SIGMAS).sum()),
    }


# --- loop closures -----------------------------------------------------------------------------------


def _with_loop_keyframes(kf: np.ndarray, stamps: np.ndarray, edges: list[LoopEdge], source: str) -> np.ndarray:
    """The keyframes with both poses of every loop edge among them; an InputError names an edge whose stamp is no
    pose."""
    if not edges:
        return kf
    ends = np.array([[e.stamp_a_ns, e.stamp_b_ns] for e in edges], np.int64).ravel()
    idx = np.clip(np.searchsorted(stamps, ends), 0, len(stamps) - 1)
    bad = stamps[idx] != ends
    if bad.any():
        raise InputError(
            source, f"loop closure at stamp {int(ends[bad][0])} is not a pose of the odometry", field="loops"
        )
    return np.union1d(kf, idx)


def _add_loops(
    gtsam,
    graph,
    edges: list[LoopEdge],
    stamps: np.ndarray,
    kf: np.ndarray,
    state_from_base: np.ndarray,
    cfg: FactorGraphConfig,
    X,
) -> list[int]:
    """A between factor of the state poses per loop edge (the base's relative pose and covariance moved to the state
    frame, as the odometry's) under a Cauchy loss; returns their indices in the graph."""
    Ad_sb = _adjoint(state_from_base)
    base_from_state = invert_pose(state_from_base)
    key = {int(s): k for k, s in enumerate(stamps[kf])}
    out = []
    for e in edges:
        cov = Ad_sb @ np.asarray(e.covariance, np.float64) @ Ad_sb.T
        noise = _robust(gtsam, gtsam.noiseModel.Gaussian.Covariance(0.5 * (cov + cov.T)), "cauchy", cfg.loop_robust_k)
        out.append(graph.size())
        graph.add(
            gtsam.BetweenFactorPose3(
                X(key[int(e.stamp_a_ns)]),
                X(key[int(e.stamp_b_ns)]),
                gtsam.Pose3(state_from_base @ e.a_from_b @ base_from_state),
                noise,
            )
        )
    return out


def _loop_stats(
    graph,
    result,
    loop_factors: list[int],
    edges: list[LoopEdge],
    loops: LoopClosures,
    kf_stamps: np.ndarray,
    kf_poses: np.ndarray,
    cfg: FactorGraphConfig,
) -> dict:
    """Candidates, accepted and rejected (by reason) loop closures, and each edge's residual at the solution: how far
    (m, deg; base b's frame) the solution's relative pose is from the edge's, and in sigmas of its covariance (before
    the loss)."""
    key = {int(s): k for k, s in enumerate(kf_stamps)}
    residuals = []
    for i, e in zip(loop_factors, edges, strict=True):
        a, b = kf_poses[key[int(e.stamp_a_ns)]], kf_poses[key[int(e.stamp_b_ns)]]
        off = invert_pose(e.a_from_b) @ invert_pose(a) @ b
        residuals.append(
            {
                "stamps_ns": [int(e.stamp_a_ns), int(e.stamp_b_ns)],
                "translation_m": float(np.linalg.norm(off[:3, 3])),
                "rotation_deg": float(np.degrees(rotation_angle_rad(off[:3, :3]))),
                "sigmas": float(np.linalg.norm(_whitened(graph.at(i), result))),
            }
        )
    out = {
        **loop_counts(loops),
        "loop_residuals": residuals,
        "loop_downweighted": int(sum(r["sigmas"] > DOWNWEIGHTED_SIGMAS for r in residuals)),
    }
    if loops.edges and not cfg.loop_closures:
        out["loops"] = "not used: loop_closures is off"
    return out


def loop_counts(loops: LoopClosures) -> dict:
    """The stats' count of loop closures: candidates, accepted, rejected by reason."""
    by_reason: dict[str, int] = {}
    for r in loops.rejected:
        by_reason[r] = by_reason.get(r, 0) + 1
    return {
        "loop_candidates": len(loops.edges) + len(loops.rejected),
        "loop_accepted": len(loops.edges),
        "loop_rejected_by_reason": by_reason,
    }


def _merge_spans(spans: list) -> list[list]:
    out: list[list] = []
    for a, b in spans:
        if out and a <= out[-1][1]:
            out[-1][1] = max(out[-1][1], b)
        else:
            out.append([a, b])
    return out


def _whitened(factor, values) -> np.ndarray:
    """A factor's residual whitened by its Gaussian noise (before any robust loss)."""
    import gtsam

    nm = factor.noiseModel()
    base = nm.noise() if isinstance(nm, gtsam.noiseModel.Robust) else nm
    return base.whiten(factor.unwhitenedError(values))


# --- IMU ---------------------------------------------------------------------------------------------


def _check_imu(imu: ImuObservations, source: str) -> ImuObservations:
    """Sorted, finite samples; an InputError naming the field when they cannot be used."""
    t = np.asarray(imu.stamps_ns, np.int64)
    w = np.asarray(imu.gyro_rad_s, np.float64)
    f = np.asarray(imu.accel_m_s2, np.float64)
    if w.shape != (len(t), 3) or f.shape != (len(t), 3):
        raise InputError(source, f"IMU samples: {len(t)} stamps, gyro {w.shape}, accel {f.shape}", field="imu")
    ok = np.isfinite(w).all(axis=1) & np.isfinite(f).all(axis=1)
    if not ok.all():
        warnings.warn(
            f"{source}: {int((~ok).sum())} IMU samples with non-finite values skipped", InputWarning, stacklevel=3
        )
    t, w, f = t[ok], w[ok], f[ok]
    if len(t) < 2 or np.any(np.diff(t) <= 0):
        raise InputError(source, "the IMU needs at least 2 samples with increasing stamps", field="imu")
    return ImuObservations(t, w, f, np.asarray(imu.base_from_imu, np.float64))


def imu_params(cfg: FactorGraphConfig):
    """gtsam's preintegration parameters (z up, as the ENU frame) from the configured noise densities."""
    import gtsam

    p = gtsam.PreintegrationCombinedParams.MakeSharedU(cfg.imu_gravity_m_s2)
    p.setGyroscopeCovariance(cfg.imu_gyro_noise_density**2 * np.eye(3))
    p.setAccelerometerCovariance(cfg.imu_accel_noise_density**2 * np.eye(3))
    p.setIntegrationCovariance(1e-8 * np.eye(3))  # position from velocity: exact but for rounding
    p.setBiasOmegaCovariance(cfg.imu_gyro_random_walk**2 * np.eye(3))
    p.setBiasAccCovariance(cfg.imu_accel_random_walk**2 * np.eye(3))
    return p


def preintegrate(imu: ImuObservations, t_from_ns: int, t_to_ns: int, params, bias=None):
    """gtsam's preintegrated measurements between two stamps: the rates are linear between samples and each
    sub-interval is integrated at its midpoint value (second order in the sample interval)."""
    import gtsam

    t = imu.stamps_ns
    pim = gtsam.PreintegratedCombinedMeasurements(params, bias if bias is not None else gtsam.imuBias.ConstantBias())
    lo, hi = np.searchsorted(t, t_from_ns, side="right"), np.searchsorted(t, t_to_ns, side="left")
    knots = np.concatenate([[t_from_ns], t[lo:hi], [t_to_ns]]).astype(np.int64)
    tf = (t - t[0]).astype(np.float64)
    kf = (knots - t[0]).astype(np.float64)
    w = np.stack([np.interp(kf, tf, imu.gyro_rad_s[:, k]) for k in range(3)], axis=1)
    f = np.stack([np.interp(kf, tf, imu.accel_m_s2[:, k]) for k in range(3)], axis=1)
    dts = np.diff(knots) * 1e-9
    for i, dt in enumerate(dts):
        if dt > 0:
            pim.integrateMeasurement(0.5 * (f[i] + f[i + 1]), 0.5 * (w[i] + w[i + 1]), float(dt))
    return pim


def _add_imu(
    gtsam, graph, values, imu: ImuObservations, kf_stamps: np.ndarray, initial_poses: np.ndarray, cfg: FactorGraphConfig
) -> list[list[int]]:
    """A CombinedImuFactor between consecutive keyframes the IMU covers without a gap; velocity (``v``) and bias (``c``)
    states at their keyframes, a bias prior at the start of every covered run. Returns the runs (keyframe indices)."""
    X = lambda i: gtsam.symbol("x", i)  # noqa: E731 (a one-line helper local to this function)
    V = lambda i: gtsam.symbol("v", i)  # noqa: E731 (a one-line helper local to this function)
    C = lambda i: gtsam.symbol("c", i)  # noqa: E731 (a one-line helper local to this function)
    t = imu.stamps_ns
    gap = int(cfg.imu_max_gap_s * 1e9)
    # an interval is covered when samples bracket it and none of the gaps inside it is too long
    big = np.nonzero(np.diff(t) > gap)[0]  # sample i .. i+1 is a gap
    covered = []
    for k in range(len(kf_stamps) - 1):
        a, b = int(kf_stamps[k]), int(kf_stamps[k + 1])
        inside = t[0] <= a and b <= t[-1]
        if inside and len(big):
            gi = np.searchsorted(t, a, side="right") - 1
            gj = np.searchsorted(t, b, side="left")
            inside = not np.any((big >= gi) & (big < gj))
        covered.append(inside)
    runs: list[list[int]] = []
    for k, ok in enumerate(covered):
        if ok:
            if runs and runs[-1][-1] == k:
                runs[-1].append(k + 1)
            else:
                runs.append([k, k + 1])
    if not runs:
        warnings.warn("no keyframe interval is covered by IMU samples; the IMU is not used", InputWarning, stacklevel=3)
        return runs
    params = imu_params(cfg)
    p = initial_poses[:, :3, 3]
    ts = (kf_stamps - kf_stamps[0]) * 1e-9
    vel = np.gradient(p, ts, axis=0) if len(ts) > 1 else np.zeros_like(p)
    bias_prior = gtsam.noiseModel.Diagonal.Sigmas(
        np.array([cfg.imu_accel_bias_sigma] * 3 + [cfg.imu_gyro_bias_sigma] * 3)
    )
    zero = gtsam.imuBias.ConstantBias()
    for run in runs:
        for k in run:
            values.insert(V(k), vel[k])
            values.insert(C(k), zero)
        graph.add(gtsam.PriorFactorConstantBias(C(run[0]), zero, bias_prior))
        for k in run[:-1]:
            pim = preintegrate(imu, int(kf_stamps[k]), int(kf_stamps[k + 1]), params)
            graph.add(gtsam.CombinedImuFactor(X(k), V(k), X(k + 1), V(k + 1), C(k), C(k + 1), pim))
    return runs


# --- GPS and gravity ---------------------------------------------------------------------------------


def _add_gps(
    gtsam, graph, values, fixes, stamps, odom, kf, base_from_antenna, state_from_base, cfg: FactorGraphConfig, X, B
) -> int:
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
        graph.add(
            gtsam.PriorFactorPoint3(B(0), np.zeros(3), gtsam.noiseModel.Diagonal.Sigmas(np.array([sb, sb, vf * sb])))
        )
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
        lever = (state_from_base @ invert_pose(odom[kf[k]]) @ odom_at_fix[i] @ base_from_antenna)[:3, 3]
        sw = np.sqrt(white_var[i])
        noise = _robust(
            gtsam, gtsam.noiseModel.Diagonal.Sigmas(np.array([sw, sw, vf * sw])), cfg.gps_robust, cfg.gps_robust_k
        )
        if n_bias:
            u = (f_stamps[i] - f_stamps.min()) / max(1, int(f_stamps.max() - f_stamps.min())) * (n_bias - 1)
            j = min(int(u), n_bias - 2)
            keys = [X(k), B(j), B(j + 1)]
            a = float(u - j)
        else:
            keys, a = [X(k)], 0.0
        graph.add(gtsam.CustomFactor(noise, keys, _gps_error(f_enu[i], lever, a, keys)))
    return n_bias


def _add_gravity(
    gtsam, graph, values, gravity: GravityObservations, stamps, kf, state_from_base, cfg: FactorGraphConfig, X, G
) -> int:
    """Up-direction factors on the keyframe nearest each observation (within half a keyframe interval), sharing the tilt
    bias."""
    kf_stamps = stamps[kf]
    g_stamps = np.asarray(gravity.stamps_ns, np.int64)
    j = np.clip(np.searchsorted(g_stamps, kf_stamps), 1, max(1, len(g_stamps) - 1))
    j = np.where(
        np.abs(g_stamps[j - 1] - kf_stamps) <= np.abs(g_stamps[np.minimum(j, len(g_stamps) - 1)] - kf_stamps),
        j - 1,
        np.minimum(j, len(g_stamps) - 1),
    )
    close = np.abs(g_stamps[j] - kf_stamps) <= int(cfg.keyframe_interval_s * 0.5e9)
    values.insert(G, np.zeros(3))
    graph.add(gtsam.PriorFactorPoint3(G, np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(3, cfg.gravity_bias_sigma_rad)))
    noise = gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Cauchy.Create(cfg.gravity_robust_k),
        gtsam.noiseModel.Isotropic.Sigma(3, cfg.gravity_sigma_rad),
    )
    R_sb = state_from_base[:3, :3]
    for k in np.nonzero(close)[0]:
        up = R_sb @ np.asarray(gravity.up_base[j[k]], np.float64)
        graph.add(gtsam.CustomFactor(noise, [X(int(k)), G], _gravity_error(up / np.linalg.norm(up))))
    return int(close.sum())


def _gps_residual_sigmas(graph, result) -> np.ndarray:
    """The whitened residual (sigmas of the fix's white noise, before the robust loss) of every GPS factor at the
    solution."""
    import gtsam

    r = []
    for i in range(graph.size()):
        f = graph.at(i)
        if not isinstance(f, gtsam.CustomFactor) or gtsam.Symbol(f.keys()[-1]).chr() == ord("g"):
            continue
        r.append(float(np.linalg.norm(_whitened(f, result))))
    return np.asarray(r)


def _densify_imu(
    poses: np.ndarray,
    stamps: np.ndarray,
    kf: np.ndarray,
    runs: list[list[int]],
    imu: ImuObservations,
    result,
    state_from_base: np.ndarray,
    cfg: FactorGraphConfig,
) -> None:
    """Poses between keyframes of an IMU-covered interval, in place: the IMU's prediction from the earlier keyframe's
    solved state (pose, velocity, bias), with the small mismatch left at the later keyframe spread over the interval."""
    import gtsam

    params = imu_params(cfg)
    X, V, C = (lambda i: gtsam.symbol("x", i)), (lambda i: gtsam.symbol("v", i)), (lambda i: gtsam.symbol("c", i))  # noqa: E731 (a one-line helper local to this function)
    for run in runs:
        for k in run[:-1]:
            a, b = int(kf[k]), int(kf[k + 1])
            if b - a < 2:
                continue
            bias = result.atConstantBias(C(k))
            start = gtsam.NavState(result.atPose3(X(k)), result.atVector(V(k)))
            end_pred = preintegrate(imu, int(stamps[a]), int(stamps[b]), params, bias).predict(start, bias).pose()
            mismatch = gtsam.Pose3.Logmap(end_pred.between(result.atPose3(X(k + 1))))
            span = float(stamps[b] - stamps[a])
            for i in range(a + 1, b):
                pred = preintegrate(imu, int(stamps[a]), int(stamps[i]), params, bias).predict(start, bias).pose()
                w = float(stamps[i] - stamps[a]) / span
                poses[i] = pred.compose(gtsam.Pose3.Expmap(w * mismatch)).matrix() @ state_from_base


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
        poses[i] = interpolate_poses(
            np.array([0, 1_000_000], np.int64), both, np.array([int(round(w * 1e6))], np.int64)
        )[0][0]
        covs[i] = (1 - w) * kf_cov[k] + w * kf_cov[k + 1]
    poses[:, 3] = np.array([0.0, 0.0, 0.0, 1.0])
    return poses, covs


__all__ = [
    "FactorGraphConfig",
    "FusedTrajectory",
    "GpsObservations",
    "GravityObservations",
    "ImuObservations",
    "LoopClosures",
    "LoopEdge",
    "fuse_session",
    "gravity_from_imu",
    "imu_params",
    "loop_counts",
    "preintegrate",
    "select_keyframes",
]
