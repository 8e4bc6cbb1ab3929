"""Monte Carlo visual localization (MCVL, section III and Algorithm 1): a particle filter over poses.

Each particle is a 6-DoF pose ``s = [r, Omega]`` of the VEHICLE: position ``r`` (3,) m in the map
frame and Euler angles ``Omega`` (3,) rad of ``R_world_from_body``, where the body is the vehicle's
base frame (REP-103: x forward, y left, z up), not the camera. The filter is vectorised over
particles; a step is :func:`predict` (eqs. 1-2), :func:`weigh` (eqs. 3-4), :func:`estimate` and
:func:`sus_resample` (section III-C), and :class:`MonteCarloLocalizer` chains them.

Why the base and not the camera
-------------------------------
Section IV-A's covariances assume a state whose third Euler angle is the heading: the initial
Euler covariance ``(0.001, 0.001, 1)``, ``Sigma_psi = (1e-4, 1e-5, 1e-2)`` and ``Sigma_o``'s
angles ``(1e-4, 1e-4, 1e-3)`` are tight on the first two angles (roll, pitch) and loose on the
third. For an upright base, ``Rx(a) Ry(b) Rz(c)`` has small ``a, b`` and ``c`` is the heading;
``b`` never comes near the gimbal lock at +-90 deg. A camera's optical frame (x right, y down, z
forward) is the wrong state: its heading lands in the second angle, which reaches +-90 deg
(gimbal lock) whenever the vehicle drives east or west and gets the pitch's tiny variances, while
the heading noise goes to the optical roll. Retrieval gives camera poses (the database's
``world_from_cam``), so the caller converts them with the rig's mount, :class:`CameraMount`
(``base_from_camera``), before the update and converts the estimates back
(:mod:`mapkit.localization.localize` does both). On a 1.4 km route with 90 deg turns and camera-pose
measurements 2 m per axis and 0.01 rad off (3.2 m, 0.9 deg mean error), the paper's filter errs by
15-16 m and 15-16 deg on the optical state and by 2.3-2.4 m and 0.65 deg on the base state (3 seeds;
tests/test_mcl.py).

Conventions
-----------
* Euler angles: ``Omega = (a, b, c)``, ``R_world_from_body = Rx(a) @ Ry(b) @ Rz(c)`` (intrinsic
  x-y'-z'', scipy ``"XYZ"``), the same as :attr:`mapkit.retrieval.measurement.Measurement.euler`. The paper's
  DCM ``phi(Omega)`` is ``R_world_from_body.T`` (body_from_world; MATLAB ``angle2dcm(a, b, c,
  'XYZ')``, which the authors' code uses), so eq. 2, ``phi(Omega_t) = phi(psi) phi(Omega_{t-1})``,
  is ``R_t = R_{t-1} @ R(psi)``: the angular increment ``psi`` acts in the body frame (its third
  component turns the vehicle about its own up axis).
* A step is one query frame; velocities are per step (the paper has no time step; its queries
  are at 4 Hz, section IV-B).
* Linear velocity: eq. 2 adds ``v`` to ``r`` directly, so the paper's ``mu_v = (0.1, 0.1, 0.01)``
  is in the world (map) frame; that is the default. ``velocity_frame="body"`` rotates ``v`` by
  the particle's previous orientation instead (then ``mu_v`` is e.g. ``(speed, 0, 0)``: forward).

Where the paper and the authors' released MATLAB code differ, the paper is followed: the
covariances of section IV-A are variances (the code's ``euler_sigma(2) = 1e-5`` is a standard
deviation, i.e. variance 1e-10 where the paper says 1e-5); eq. 3 keeps its factor 1/2 (the code
drops it); angle differences in eq. 3 are wrapped to (-pi, pi] (the code does not wrap). The pose
estimate is taken from the weighted particles before resampling (the code averages after, with
equal weights: same expectation, more Monte Carlo noise).

Beyond the paper, and off by default (:class:`OdometryMotionConfig`, :class:`RecoveryConfig`,
:class:`MultiHypothesisConfig`, ``MclConfig.estimate`` and ``MclConfig.resample_min_ess_fraction``):
an odometry-driven motion model; re-injection of particles around the measurement when the track
is lost; a multi-hypothesis measurement model that weighs particles by a mixture over all top-k
retrieved poses (:func:`mixture_likelihood`) instead of the one mean-shift cluster, with
initialisation and re-injection drawn from that mixture; the pose estimate as the densest mode of
the particles instead of their mean; resampling only when the effective sample size drops.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np
from pydantic import Field, NonNegativeFloat, PositiveFloat, PositiveInt

from mapkit.core.config import MapkitConfig
from mapkit.core.errors import ConfigError
from mapkit.core.geometry import invert_pose, is_rotation, make_pose
from mapkit.retrieval.measurement import Measurement, PoseHypotheses, euler_from_matrix, matrix_from_euler

Vec3 = tuple[float, float, float]
Var3 = tuple[NonNegativeFloat, NonNegativeFloat, NonNegativeFloat]
Var6 = tuple[PositiveFloat, PositiveFloat, PositiveFloat, PositiveFloat, PositiveFloat, PositiveFloat]


# --- configuration ------------------------------------------------------------------------------------


class OdometryMotionConfig(MapkitConfig):
    """BEYOND THE PAPER: motion from odometry (relative pose between consecutive frames) plus noise.

    Used for the steps at which the caller passes odometry; the paper's constant-velocity model
    (eqs. 1-2) is used for the others.
    """

    enabled: bool = Field(
        False,
        description="Beyond the paper (MCVL uses eqs. 1-2 only): drive the motion model by odometry when the caller "
        "supplies it.",
    )
    translation_sigma_m: Var3 = Field(
        (0.2, 0.2, 0.05),
        description="Beyond the paper (mapkit choice): std of the noise added to the odometry translation, per step, "
        "in the base frame: x forward, y left, z up (m).",
    )
    rotation_sigma_rad: Var3 = Field(
        (0.002, 0.002, 0.01),
        description="Beyond the paper (mapkit choice): std of the noise added to the odometry rotation, per step, as "
        "XYZ Euler angles of the base: roll, pitch, heading (rad).",
    )


class RecoveryConfig(MapkitConfig):
    """BEYOND THE PAPER: lost-track recovery by re-injecting particles around the measurement."""

    enabled: bool = Field(
        False,
        description="Beyond the paper (MCVL has no recovery): re-inject particles when the measurement stays far from "
        "all of them.",
    )
    distance_m: PositiveFloat = Field(
        25.0,
        description="Beyond the paper (mapkit choice, ~11 sigma of the position part of Sigma_o): the track counts as "
        "lost at a step when no particle is this close to the measured position (m).",
    )
    consecutive_steps: PositiveInt = Field(
        3,
        description="Beyond the paper (mapkit choice): re-inject after this many lost steps in a row (one outlier "
        "retrieval must not reset the filter).",
    )
    fraction: float = Field(
        0.2,
        gt=0.0,
        le=1.0,
        description="Beyond the paper (mapkit choice): share of the particles replaced by draws from the initial "
        "distribution around the measurement.",
    )


class MultiHypothesisConfig(MapkitConfig):
    """BEYOND THE PAPER: weigh particles by a mixture over the top-k retrieved poses.

    MCVL (Sec. III-B) keeps only the largest mean-shift cluster of the top-R poses as z_t. When
    retrieval is mostly wrong (night, snow) that cluster is mostly a wrong place while the right
    place is often still among the R hits. The mixture likelihood (:func:`mixture_likelihood`)
    ``L(s) = floor + (1 - floor) sum_j pi_j K(s, h_j)`` keeps every hit as a hypothesis; with an
    odometry-driven motion model only the hypothesis that stays consistent with the motion keeps
    collecting weight over the steps.
    """

    enabled: bool = Field(
        False,
        description="Beyond the paper (MCVL weighs by the largest mean-shift cluster, eq. 3): weigh by a mixture over "
        "all retrieved poses.",
    )
    kernel_position_cov_m2: Var3 | None = Field(
        None,
        description="Beyond the paper: diagonal position covariance of each hit's kernel, m^2; None = the position "
        "part of Sigma_o (MCVL Sec. IV-A).",
    )
    kernel_rotation_sigma_rad: PositiveFloat | None = Field(
        None,
        description="Beyond the paper: std of the (isotropic, geodesic) rotation part of each hit's kernel, rad; None "
        "= the square root of Sigma_o's largest Euler variance (MCVL Sec. IV-A: the heading's, 1e-3 rad^2).",
    )
    hit_weighting: Literal["uniform", "rank", "distance"] = Field(
        "uniform",
        description="Beyond the paper (mapkit choice): prior weight pi_j of the hits: equal, exp(-rank/scale), or "
        "exp(-(d_j - d_0)/scale) for descriptor distances d.",
    )
    hit_weight_scale: PositiveFloat = Field(
        5.0,
        description="Beyond the paper: the scale of hit_weighting 'rank' (ranks) or 'distance' (squared L2 between "
        "unit descriptors).",
    )
    floor: float = Field(
        0.05,
        gt=0.0,
        lt=1.0,
        description="Beyond the paper (mapkit choice): uniform floor of the likelihood for 'every hit is wrong', "
        "relative to a kernel's peak of 1.",
    )
    init_from_hits: bool = Field(
        True,
        description="Beyond the paper: draw the initial particles from the mixture over the first query's hits (MCVL: "
        "a Gaussian around the first z_t).",
    )
    reinject_below: float = Field(
        0.0,
        ge=0.0,
        lt=1.0,
        description="Beyond the paper: count a step as lost when the cloud's support on its best hit, max_j sum_i w_i "
        "K_ij (see cloud_support), is below this (0 = never re-inject).",
    )
    reinject_consecutive_steps: PositiveInt = Field(
        3, description="Beyond the paper: re-inject after this many lost steps in a row."
    )
    reinject_fraction: float = Field(
        0.1,
        gt=0.0,
        le=1.0,
        description="Beyond the paper: share of the particles, the least likely under the current hits, replaced by "
        "draws from the mixture over those hits.",
    )


class MclConfig(MapkitConfig):
    """Monte Carlo visual localization; defaults are MCVL section IV-A (variances, per step).

    The state is the vehicle's base pose (x forward, y left, z up), so the Euler angles are roll,
    pitch and heading, in that order: the paper's tight variances fall on roll and pitch, its loose
    ones on the heading (see the module docstring).
    """

    n_particles: PositiveInt = Field(1000, description="Number of particles N (MCVL Sec. IV-A: fixed to 1000).")
    init_position_cov_m2: Var3 = Field(
        (10.0, 10.0, 10.0),
        description="Diagonal covariance of the initial positions around the first measurement, m^2 (MCVL Sec. IV-A).",
    )
    init_euler_cov_rad2: Var3 = Field(
        (0.001, 0.001, 1.0),
        description="Diagonal covariance of the initial Euler angles (roll, pitch, heading of the base) around the "
        "first measurement, rad^2 (MCVL Sec. IV-A: large on the heading only).",
    )
    velocity_mean_m: Vec3 = Field(
        (0.1, 0.1, 0.01),
        description="mu_v, mean linear velocity per step, m (MCVL Sec. IV-A; world frame as in eq. 2, x east, y north, "
        "z up in mapkit's ENU).",
    )
    velocity_cov_m2: Var3 = Field((1.0, 1.0, 0.01), description="Sigma_v diagonal, m^2 per step (MCVL Sec. IV-A).")
    velocity_frame: Literal["world", "body"] = Field(
        "world",
        description="Frame of v: 'world' adds it to r as eq. 2 does (MCVL Sec. III-A); 'body' rotates it by the "
        "particle's base orientation first, x forward (mapkit option).",
    )
    angular_velocity_mean_rad: Vec3 = Field(
        (0.001, 0.00001, 0.01),
        description="mu_psi, mean Euler increment per step, rad: roll, pitch, heading of the base, composed in the "
        "base frame (MCVL Sec. IV-A, eq. 2).",
    )
    angular_velocity_cov_rad2: Var3 = Field(
        (0.0001, 0.00001, 0.01),
        description="Sigma_psi diagonal, rad^2 per step: roll, pitch, heading (MCVL Sec. IV-A; the authors' code draws "
        "the second angle with std 1e-5, i.e. variance 1e-10).",
    )
    measurement_cov: Var6 = Field(
        (5.0, 5.0, 5.0, 0.0001, 0.0001, 0.001),
        description="Sigma_o diagonal: position m^2, then the base's roll, pitch, heading rad^2 (MCVL Sec. IV-A, eq. "
        "3; the authors' code uses (20, 20, 20, 0.001, 0.001, 0.01) on the 10 km RobotCar route).",
    )
    odometry: OdometryMotionConfig = Field(
        default_factory=OdometryMotionConfig, description="Beyond the paper: odometry-driven motion model (off)."
    )
    recovery: RecoveryConfig = Field(
        default_factory=RecoveryConfig, description="Beyond the paper: lost-track recovery (off)."
    )
    multi_hypothesis: MultiHypothesisConfig = Field(
        default_factory=MultiHypothesisConfig,
        description="Beyond the paper: mixture measurement model over the top-k retrieved poses (off).",
    )
    estimate: Literal["mean", "mode"] = Field(
        "mean",
        description="Pose estimate: 'mean' of the weighted particles (MCVL Sec. III-C); 'mode' = beyond the paper: the "
        "mean of the particles within mode_radius_m of the densest place.",
    )
    mode_radius_m: PositiveFloat = Field(
        10.0,
        description="Beyond the paper (mapkit choice: ~4.5 position stds of Sigma_o, narrower than the tens of metres "
        "between wrong hypotheses): radius of the 'mode' estimate and its grid cell, m.",
    )
    resample_min_ess_fraction: float = Field(
        1.0,
        gt=0.0,
        le=1.0,
        description="Resample when the effective sample size is at most this share of N; 1 = every step (MCVL "
        "Algorithm 1); below 1, beyond the paper: weights carry over the steps in between.",
    )


# --- particles and estimates --------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Particles:
    """N particles: ``positions`` (N, 3) m, ``euler`` (N, 3) rad (the state: the vehicle base's
    roll, pitch, heading), and ``rotations`` (N, 3, 3) = ``matrix_from_euler(euler)``,
    ``R_world_from_body`` (body = base), kept alongside to save work."""

    positions: np.ndarray
    euler: np.ndarray
    rotations: np.ndarray

    @classmethod
    def from_euler(cls, positions: np.ndarray, euler: np.ndarray) -> Particles:
        # through the matrix, so that the stored angles are canonical (b in [-pi/2, pi/2])
        return cls.from_rotations(positions, matrix_from_euler(euler))

    @classmethod
    def from_rotations(cls, positions: np.ndarray, rotations: np.ndarray) -> Particles:
        # the matrices are kept as given, not rebuilt from the angles (that would cost a third of a
        # step): products of rotations stay orthonormal to rounding, which grows ~1e-16 per step
        R = np.asarray(rotations, dtype=np.float64)
        return cls(np.asarray(positions, dtype=np.float64), euler_from_matrix(R), R)

    def __len__(self) -> int:
        return len(self.positions)

    def take(self, indices: np.ndarray) -> Particles:
        # np.take: a third of the time of fancy indexing for (N, 3, 3) rows
        return Particles(
            np.take(self.positions, indices, 0), np.take(self.euler, indices, 0), np.take(self.rotations, indices, 0)
        )


@dataclass(frozen=True, eq=False)
class Estimate:
    """The filter's pose at one step: the vehicle's ``world_from_body`` (body = base) position (3,)
    m, rotation (3, 3), Euler angles (3,) rad (:meth:`CameraMount.to_camera` gives the camera's);
    the weighted spread of particle positions per axis (m); the effective sample size
    ``1 / sum(w^2)`` of the weights it was computed with; whether a measurement was used; how many
    particles were re-injected (recovery, beyond the paper)."""

    position: np.ndarray
    rotation: np.ndarray
    euler: np.ndarray
    position_std_m: np.ndarray
    n_eff: float
    measured: bool = True
    reinjected: int = 0


# --- the state's frame: camera poses in, camera poses out -------------------------------------------

#: ``base_from_camera`` rotation of a camera looking straight ahead: optical z (forward) = base x,
#: optical x (right) = base -y, optical y (down) = base -z (REP-103 base: x forward, y left, z up)
FORWARD_CAMERA_ROTATION = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


@dataclass(frozen=True, eq=False)
class CameraMount:
    """The rig's camera mount ``base_from_camera`` (4, 4): the rigid motion between the camera
    poses retrieval gives and the base poses the filter runs on.

    ``world_from_base = world_from_camera @ inv(base_from_camera)`` and back. Poses are converted
    one by one, so the mean-shift measurement is computed over camera positions and converted
    afterwards: its rotation is the same either way (the chordal mean commutes with a fixed right
    factor); its translation differs from the mean of the base positions by ``(mean R -
    chordal mean R) t_mount``, second order in the spread of the cluster's rotations (about 1 cm
    for a 0.1 rad spread and a 2 m lever arm).
    """

    base_from_camera: np.ndarray

    def __post_init__(self):
        T = np.array(self.base_from_camera, dtype=np.float64)
        if T.shape != (4, 4) or not np.allclose(T[3], [0, 0, 0, 1]) or not is_rotation(T[:3, :3], atol=1e-5):
            raise ValueError(f"base_from_camera must be a rigid 4x4 pose, got {T.tolist()}")
        U, _, Vt = np.linalg.svd(T[:3, :3])  # exactly orthonormal: a mount typed with 6 decimals is not
        T[:3, :3] = U @ Vt
        object.__setattr__(self, "base_from_camera", T)

    @classmethod
    def forward(cls, translation_m: Sequence[float] = (0.0, 0.0, 0.0)) -> CameraMount:
        """A camera looking straight ahead (:data:`FORWARD_CAMERA_ROTATION`) at ``translation_m`` in the base."""
        return cls(make_pose(FORWARD_CAMERA_ROTATION, np.asarray(translation_m, dtype=np.float64)))

    @property
    def rotation(self) -> np.ndarray:
        return self.base_from_camera[:3, :3]

    @property
    def translation(self) -> np.ndarray:
        return self.base_from_camera[:3, 3]

    def to_base(self, positions: np.ndarray, rotations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``world_from_camera`` positions (..., 3) and rotations (..., 3, 3) -> ``world_from_base``."""
        R = np.asarray(rotations, dtype=np.float64) @ self.rotation.T
        return np.asarray(positions, dtype=np.float64) - R @ self.translation, R

    def to_camera(self, positions: np.ndarray, rotations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``world_from_base`` positions (..., 3) and rotations (..., 3, 3) -> ``world_from_camera``
        (NaN rows stay NaN)."""
        R = np.asarray(rotations, dtype=np.float64)
        return np.asarray(positions, dtype=np.float64) + R @ self.translation, R @ self.rotation

    def measurement_to_base(self, z: Measurement) -> Measurement:
        """A camera-pose measurement as the base pose it implies (cluster fields kept)."""
        t, R = self.to_base(z.translation, z.rotation)
        return replace(z, translation=t, rotation=R, euler=euler_from_matrix(R))

    def hypotheses_to_base(self, h: PoseHypotheses) -> PoseHypotheses:
        """Retrieved camera poses as base poses, weights kept."""
        t, R = self.to_base(h.translations, h.rotations)
        return PoseHypotheses(t, R, h.weights)

    def odometry_to_base(self, camera_prev_from_curr: np.ndarray) -> np.ndarray:
        """The camera's relative motion ``cam_{t-1} <- cam_t`` (4, 4) as the base's,
        ``base_from_camera @ T @ camera_from_base``."""
        return (
            self.base_from_camera
            @ np.asarray(camera_prev_from_curr, dtype=np.float64)
            @ invert_pose(self.base_from_camera)
        )


# --- the functional core ------------------------------------------------------------------------------


def wrap_angle(x: np.ndarray) -> np.ndarray:
    """Angles wrapped to (-pi, pi]."""
    x = np.asarray(x, dtype=np.float64)
    return x + (2.0 * np.pi) * np.floor((np.pi - x) * (0.5 / np.pi))  # 4x faster than np.mod here


def init_particles(
    measurement: Measurement, cfg: MclConfig, rng: np.random.Generator, n: int | None = None
) -> Particles:
    """Particles drawn from a Gaussian around a measurement (MCVL Sec. IV-A)."""
    n = cfg.n_particles if n is None else n
    noise = rng.standard_normal((n, 6))
    positions = measurement.translation + noise[:, :3] * np.sqrt(cfg.init_position_cov_m2)
    euler = measurement.euler + noise[:, 3:] * np.sqrt(cfg.init_euler_cov_rad2)
    return Particles.from_euler(positions, euler)


def predict(
    particles: Particles, cfg: MclConfig, rng: np.random.Generator, odometry_prev_from_curr: np.ndarray | None = None
) -> Particles:
    """Move every particle one step.

    Without odometry, the paper's model: ``v ~ N(mu_v, Sigma_v)``, ``psi ~ N(mu_psi, Sigma_psi)``
    (eq. 1), ``r_t = r_{t-1} + v`` and ``phi(Omega_t) = phi(psi) phi(Omega_{t-1})`` (eq. 2).

    BEYOND THE PAPER: with ``odometry_prev_from_curr`` (4, 4), the relative pose ``body_{t-1} <-
    body_t`` measured by odometry, each particle moves by it plus Gaussian noise in its own body
    frame: ``R_t = R_{t-1} dR R(eps_R)``, ``r_t = r_{t-1} + R_{t-1} (dt + eps_t)``.
    """
    n = len(particles)
    noise = rng.standard_normal((n, 6))
    R_prev = particles.rotations
    if odometry_prev_from_curr is None:
        v = np.asarray(cfg.velocity_mean_m) + noise[:, :3] * np.sqrt(cfg.velocity_cov_m2)  # eq. 1
        psi = np.asarray(cfg.angular_velocity_mean_rad) + noise[:, 3:] * np.sqrt(cfg.angular_velocity_cov_rad2)
        if cfg.velocity_frame == "body":
            v = np.einsum("nij,nj->ni", R_prev, v)
        positions = particles.positions + v  # eq. 2, position
        rotations = R_prev @ matrix_from_euler(psi)  # eq. 2 with phi = R.T: (Psi^T R_prev^T)^T
    else:
        T = np.asarray(odometry_prev_from_curr, dtype=np.float64)
        if T.shape != (4, 4):
            raise ValueError(f"odometry must be one 4x4 pose prev_from_curr, got shape {T.shape}")
        od = cfg.odometry
        t_body = T[:3, 3] + noise[:, :3] * np.asarray(od.translation_sigma_m)
        dR = T[:3, :3] @ matrix_from_euler(noise[:, 3:] * np.asarray(od.rotation_sigma_rad))
        positions = particles.positions + np.einsum("nij,nj->ni", R_prev, t_body)
        rotations = R_prev @ dR
    return Particles.from_rotations(positions, rotations)


def log_likelihood(particles: Particles, measurement: Measurement, cfg: MclConfig) -> np.ndarray:
    """Log of eq. 3 per particle: ``-1/2 (z - s)^T Sigma_o^-1 (z - s)``, angle differences wrapped."""
    d = np.empty((len(particles), 6))
    d[:, :3] = measurement.translation - particles.positions
    d[:, 3:] = wrap_angle(measurement.euler - particles.euler)
    return -0.5 * ((d * d) @ (1.0 / np.asarray(cfg.measurement_cov)))


def _normalised_weights(log_w: np.ndarray) -> np.ndarray:
    """Weights (N,) summing to 1 from log-weights.

    Subtracting the largest log-weight before exponentiating keeps the best particle at weight 1
    before normalisation, so a measurement far from every particle (all eq. 3 values underflow to
    0 in linear space) still gives valid weights.
    """
    w = np.exp(log_w - log_w.max())
    w /= w.sum()
    return w


def weigh(
    particles: Particles, measurement: Measurement, cfg: MclConfig, prior: np.ndarray | None = None
) -> np.ndarray:
    """Normalised weights (N,) of eqs. 3-4, computed in log space: eq. 3's likelihood of each
    particle, times its ``prior`` weight when the particles carry weights (not resampled at the
    last step; None: equal weights)."""
    log_w = log_likelihood(particles, measurement, cfg)
    if prior is not None:
        log_w = log_w + np.log(prior)
    return _normalised_weights(log_w)


def sus_resample(weights: np.ndarray, rng: np.random.Generator, n: int | None = None) -> np.ndarray:
    """Indices drawn by stochastic universal sampling (Baker 1987; MCVL Sec. III-C).

    One uniform offset ``u ~ U[0, 1/n)`` and ``n`` equally spaced pointers ``u + k/n`` on the
    cumulative weights: particle ``i`` is drawn ``floor(n w_i)`` or ``ceil(n w_i)`` times.
    """
    w = np.asarray(weights, dtype=np.float64)
    n = len(w) if n is None else n
    cum = np.cumsum(w)
    cum /= cum[-1]
    pointers = (rng.random() + np.arange(n)) / n
    return np.minimum(np.searchsorted(cum, pointers, side="right"), len(w) - 1)


def chordal_mean_rotation(rotations: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Weighted chordal L2 mean: the rotation nearest (Frobenius) to ``sum w_i R_i``, by SVD.

    The same minimiser as :func:`mapkit.core.geometry.average_rotations` (Markley's quaternion average
    minimises the same weighted chordal cost), at ~20 us instead of ~0.8 ms for 1,000 rotations,
    which the per-step budget of the filter needs.
    """
    R = np.asarray(rotations, dtype=np.float64)
    M = (np.asarray(weights, dtype=np.float64) @ R.reshape(len(R), 9)).reshape(3, 3)
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])  # no reflection
    return U @ D @ Vt


def estimate(
    particles: Particles, weights: np.ndarray | None = None, measured: bool = True, reinjected: int = 0
) -> Estimate:
    """Weighted mean position and chordal mean rotation of the particles (equal weights if None)."""
    n = len(particles)
    w = np.full(n, 1.0 / n) if weights is None else np.asarray(weights, dtype=np.float64) / np.sum(weights)
    position = w @ particles.positions
    R = chordal_mean_rotation(particles.rotations, w)
    std = np.sqrt(w @ (particles.positions - position) ** 2)
    return Estimate(position, R, euler_from_matrix(R), std, float(1.0 / (w @ w)), measured, reinjected)


def reinject(
    particles: Particles, measurement: Measurement, cfg: MclConfig, rng: np.random.Generator, fraction: float
) -> tuple[Particles, int]:
    """BEYOND THE PAPER: replace a random ``fraction`` of the particles by initial draws around the measurement."""
    n = len(particles)
    k = min(n, max(1, int(round(fraction * n))))
    idx = rng.choice(n, size=k, replace=False)
    fresh = init_particles(measurement, cfg, rng, n=k)
    pos, eul, rot = particles.positions.copy(), particles.euler.copy(), particles.rotations.copy()
    pos[idx], eul[idx], rot[idx] = fresh.positions, fresh.euler, fresh.rotations
    return Particles(pos, eul, rot), k


# --- BEYOND THE PAPER: the multi-hypothesis measurement model ----------------------------------------


def _kernel(cfg: MclConfig) -> tuple[np.ndarray, float]:
    """Position variances (3,) m^2 and rotation variance rad^2 of each hit's kernel."""
    mh = cfg.multi_hypothesis
    pos = np.asarray(
        cfg.measurement_cov[:3] if mh.kernel_position_cov_m2 is None else mh.kernel_position_cov_m2, dtype=np.float64
    )
    rot = (
        float(max(cfg.measurement_cov[3:])) if mh.kernel_rotation_sigma_rad is None else mh.kernel_rotation_sigma_rad**2
    )
    return pos, rot


def kernel_matrix(
    particles: Particles, hypotheses: PoseHypotheses, position_var_m2: np.ndarray, rotation_var_rad2: float
) -> np.ndarray:
    """``K[i, j] = exp(-1/2 d_ij^T S^-1 d_ij - (3 - tr(R_i^T H_j)) / (2 s_R^2))`` (N, k), in (0, 1].

    ``d_ij`` is particle i's position minus hypothesis j's, ``S = diag(position_var_m2)``.
    ``3 - tr(R_i^T H_j) = 2 (1 - cos theta_ij)``, ``theta`` the angle between the two rotations,
    is ``theta^2`` to second order: the rotation part is a Gaussian in the geodesic angle with
    variance ``s_R^2`` that needs no Euler angles (so no gimbal lock, no wrapping). Both parts are
    matrix products, (N, 3) x (3, k) and (N, 9) x (9, k). Values below exp(-60) are returned as exp(-60).
    """
    inv_sd = 1.0 / np.sqrt(position_var_m2)
    c = hypotheses.translations.mean(axis=0)  # centred: no cancellation in |a|^2 + |b|^2 - 2ab
    A = (particles.positions - c) * inv_sd
    B = (hypotheses.translations - c) * inv_sd
    kappa = 0.5 / rotation_var_rad2
    E = A @ B.T
    E += particles.rotations.reshape(-1, 9) @ (kappa * hypotheses.rotations.reshape(-1, 9)).T  # kappa tr(R_i^T H_j)
    E -= 0.5 * np.einsum("ij,ij->i", A, A)[:, None]
    E -= 0.5 * np.einsum("ij,ij->i", B, B)[None, :] + 3.0 * kappa
    # exp(-60) ~ 1e-26 is 0 beside any floor; clipping also spares exp its slow path for underflows
    return np.exp(np.clip(E, -60.0, 0.0, out=E), out=E)


def mixture_likelihood(particles: Particles, hypotheses: PoseHypotheses, cfg: MclConfig, return_kernel: bool = False):
    """Per particle (N,): ``L = floor + (1 - floor) sum_j pi_j K(s, h_j)``, in [floor, 1].

    One kernel (:func:`kernel_matrix`) per retrieved pose ``h_j`` with prior weight ``pi_j``; the
    floor is the likelihood under "every hit is wrong", so a particle far from all hits keeps
    weight ``floor`` instead of 0 and a true hypothesis survives a step at which retrieval misses.
    With ``return_kernel``, also the (N, k) kernel matrix.
    """
    floor = cfg.multi_hypothesis.floor
    pos_var, rot_var = _kernel(cfg)
    K = kernel_matrix(particles, hypotheses, pos_var, rot_var)
    L = floor + (1.0 - floor) * (K @ hypotheses.weights)
    return (L, K) if return_kernel else L


def cloud_support(weights: np.ndarray, kernel: np.ndarray) -> float:
    """How well the cloud sits on its best-supported hit: ``max_j sum_i w_i K_ij``, in [0, 1].

    About 1 when the particles gather on one hit, near 0 when no hit is near them: the trigger
    of re-injection. Unlike the mean likelihood it does not depend on k or on the hits' weights.
    """
    return float(np.max(weights @ kernel))


def sample_hypotheses(
    hypotheses: PoseHypotheses, cfg: MclConfig, rng: np.random.Generator, n: int | None = None
) -> Particles:
    """``n`` particles drawn from the mixture: a hypothesis by SUS on ``pi`` (each gets
    ``floor(n pi_j)`` or ``ceil(n pi_j)`` particles), then its kernel's Gaussian noise (rotation
    noise in the body frame)."""
    n = cfg.n_particles if n is None else n
    pos_var, rot_var = _kernel(cfg)
    j = sus_resample(hypotheses.weights, rng, n)
    noise = rng.standard_normal((n, 6))
    positions = hypotheses.translations[j] + noise[:, :3] * np.sqrt(pos_var)
    rotations = hypotheses.rotations[j] @ matrix_from_euler(noise[:, 3:] * np.sqrt(rot_var))
    return Particles.from_rotations(positions, rotations)


def _replace(particles: Particles, idx: np.ndarray, fresh: Particles) -> Particles:
    pos, eul, rot = particles.positions.copy(), particles.euler.copy(), particles.rotations.copy()
    pos[idx], eul[idx], rot[idx] = fresh.positions, fresh.euler, fresh.rotations
    return Particles(pos, eul, rot)


def mode_estimate(
    particles: Particles, weights: np.ndarray | None, radius_m: float, measured: bool = True, reinjected: int = 0
) -> Estimate:
    """BEYOND THE PAPER: the pose of the densest place of a multimodal cloud.

    The weighted particles are binned on a horizontal grid of ``radius_m`` cells; from the weighted mean of
    the heaviest cell, two flat-kernel mean-shift iterations of radius ``radius_m``; the estimate
    is the weighted mean position and chordal mean rotation of the particles within the radius.
    The spread and effective sample size are those of the whole cloud. With one mode this is the
    mean of :func:`estimate`; with two it is the heavier one instead of a point between them.
    """
    n = len(particles)
    w = np.full(n, 1.0 / n) if weights is None else np.asarray(weights, dtype=np.float64) / np.sum(weights)
    P = particles.positions
    cells = np.floor(P[:, :2] * (1.0 / radius_m)).astype(np.int64)  # horizontal cells: the vehicle is on the ground
    _, inverse = np.unique(cells[:, 0] * 1_000_003 + cells[:, 1], return_inverse=True)  # one integer per cell
    ws = w * (inverse == np.argmax(np.bincount(inverse, weights=w)))
    r2 = radius_m * radius_m
    for _ in range(3):  # the heaviest cell's mean, then two mean-shift moves
        centre = (ws @ P) / ws.sum()
        d = P - centre
        ws = w * (np.einsum("ij,ij->i", d, d) <= r2)
    ws /= ws.sum()
    position = ws @ P
    R = chordal_mean_rotation(particles.rotations, ws)
    mean = w @ P
    std = np.sqrt(w @ (P - mean) ** 2)
    return Estimate(position, R, euler_from_matrix(R), std, float(1.0 / (w @ w)), measured, reinjected)


# --- the localizer ------------------------------------------------------------------------------------


class MonteCarloLocalizer:
    """MCVL's Algorithm 1 over a query sequence, one :meth:`step` per frame.

    The first measurement initialises the particles (Sec. IV-A). Then each step predicts (eqs.
    1-2), and with a measurement weighs (eqs. 3-4), estimates the pose from the weighted
    particles, and resamples by SUS; without one it only predicts.
    """

    def __init__(self, cfg: MclConfig | None = None, seed: int | None = 0):
        self.cfg = cfg if cfg is not None else MclConfig()
        self.rng = np.random.default_rng(seed)
        self._particles: Particles | None = None
        self._log_w: np.ndarray | None = None  # carried log-weights; None = equal (just resampled)
        self._lost_steps = 0

    @property
    def particles(self) -> Particles | None:
        """The current particles (equally weighted unless ``resample_min_ess_fraction`` < 1, see
        :attr:`weights`); None before the first measurement."""
        return self._particles

    @property
    def weights(self) -> np.ndarray | None:
        """Normalised weights of :attr:`particles` (equal after a resampling); None before the first measurement."""
        if self._particles is None:
            return None
        if self._log_w is None:
            return np.full(len(self._particles), 1.0 / len(self._particles))
        return _normalised_weights(self._log_w)

    @property
    def initialized(self) -> bool:
        return self._particles is not None

    def _estimate(self, particles: Particles, w: np.ndarray | None, measured: bool, reinjected: int = 0) -> Estimate:
        if self.cfg.estimate == "mode":
            return mode_estimate(particles, w, self.cfg.mode_radius_m, measured, reinjected)
        return estimate(particles, w, measured, reinjected)

    def step(
        self,
        measurement: Measurement | None = None,
        odometry: np.ndarray | None = None,
        hypotheses: PoseHypotheses | None = None,
    ) -> Estimate | None:
        """Advance one frame. ``odometry`` is the 4x4 ``prev_from_curr`` body motion since the last
        step (needs ``cfg.odometry.enabled``). ``hypotheses`` are the retrieved poses for the
        multi-hypothesis model (needs ``cfg.multi_hypothesis.enabled``; without them that model
        uses the measurement as its one hypothesis). Returns None until the first observation."""
        cfg, mh = self.cfg, self.cfg.multi_hypothesis
        if odometry is not None and not cfg.odometry.enabled:
            raise ConfigError("odometry was given to the MCL filter but its config has odometry.enabled = false")
        if hypotheses is not None and not mh.enabled:
            raise ConfigError(
                "retrieved hypotheses were given to the MCL filter but its config has multi_hypothesis.enabled = false"
            )
        if mh.enabled and hypotheses is None and measurement is not None:
            hypotheses = PoseHypotheses.from_measurement(measurement)
        observed = measurement is not None or hypotheses is not None
        # from here on, an observed step has hypotheses when the multi-hypothesis model is on
        # (the measurement stands in for them) and a measurement when it is off (hypotheses are
        # refused above): the asserts below state it for the type checker
        if self._particles is None:
            if not observed:
                return None
            if mh.enabled and mh.init_from_hits:
                assert hypotheses is not None
                self._particles = sample_hypotheses(hypotheses, cfg, self.rng)
            else:
                if measurement is None:
                    assert hypotheses is not None
                    best = int(np.argmax(hypotheses.weights))
                    measurement = Measurement.from_pose(hypotheses.translations[best], hypotheses.rotations[best])
                self._particles = init_particles(measurement, cfg, self.rng)
            self._log_w = None
            return self._estimate(self._particles, None, True)

        particles = predict(self._particles, cfg, self.rng, odometry)
        prior = self.weights
        assert prior is not None  # the particles exist
        if not observed:
            self._particles = particles
            return self._estimate(particles, prior, False)

        n_new = 0
        if mh.enabled:
            assert hypotheses is not None
            L, K = mixture_likelihood(particles, hypotheses, cfg, return_kernel=True)
            if mh.reinject_below > 0:
                self._lost_steps = self._lost_steps + 1 if cloud_support(prior, K) < mh.reinject_below else 0
                if self._lost_steps >= mh.reinject_consecutive_steps:
                    n = len(particles)
                    n_new = min(n, max(1, int(round(mh.reinject_fraction * n))))
                    # replace the particles this step's hits support least (a growing cloud on
                    # the right place is on a hit and stays), ties broken at random
                    idx = np.argsort(L + 1e-9 * self.rng.random(n), kind="stable")[:n_new]
                    particles = _replace(particles, idx, sample_hypotheses(hypotheses, cfg, self.rng, n_new))
                    # drawn from these hits, a fresh particle must not be rewarded by them as well
                    # (that would count this step's evidence twice): it starts with the average
                    # weight and the floor, as lost particles have, and earns weight from the next step
                    L[idx] = mh.floor
                    prior = prior.copy()
                    prior[idx] = 1.0 / n
                    self._lost_steps = 0
            w = _normalised_weights(np.log(prior) + np.log(L))
        else:
            assert measurement is not None
            if cfg.recovery.enabled:
                nearest_m = np.sqrt(np.min(np.sum((particles.positions - measurement.translation) ** 2, axis=1)))
                self._lost_steps = self._lost_steps + 1 if nearest_m > cfg.recovery.distance_m else 0
                if self._lost_steps >= cfg.recovery.consecutive_steps:
                    particles, n_new = reinject(particles, measurement, cfg, self.rng, cfg.recovery.fraction)
                    self._lost_steps = 0
            w = weigh(particles, measurement, cfg, None if self._log_w is None else prior)
        est = self._estimate(particles, w, True, n_new)
        if est.n_eff <= cfg.resample_min_ess_fraction * len(particles) * (1.0 + 1e-12):
            self._particles, self._log_w = particles.take(sus_resample(w, self.rng)), None
        else:
            self._particles, self._log_w = particles, np.log(np.maximum(w, 1e-300))
        return est


# --- evaluation ---------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class PoseErrors:
    """Per-frame errors (MCVL Sec. IV) and their mean and median over the finite frames."""

    translation_m: np.ndarray
    rotation_deg: np.ndarray

    def summary(self) -> dict:
        ok = np.isfinite(self.translation_m) & np.isfinite(self.rotation_deg)
        t, r = self.translation_m[ok], self.rotation_deg[ok]
        if not ok.any():
            return {
                "frames": 0,
                "mean_translation_m": None,
                "median_translation_m": None,
                "mean_rotation_deg": None,
                "median_rotation_deg": None,
            }
        return {
            "frames": int(ok.sum()),
            "mean_translation_m": float(t.mean()),
            "median_translation_m": float(np.median(t)),
            "mean_rotation_deg": float(r.mean()),
            "median_rotation_deg": float(np.median(r)),
        }


def pose_errors(
    est_positions: np.ndarray, est_rotations: np.ndarray, gt_positions: np.ndarray, gt_rotations: np.ndarray
) -> PoseErrors:
    """Translation error ``||c_est - c_gt||`` and orientation error ``|alpha|`` per frame, with
    ``2 cos|alpha| = trace(R_gt^-1 R_est) - 1`` (MCVL Sec. IV; the paper's text drops the -1).

    The arccos argument is clipped to [-1, 1]; NaN rows (frames without an estimate) stay NaN.
    """
    c_est, c_gt = np.asarray(est_positions, dtype=np.float64), np.asarray(gt_positions, dtype=np.float64)
    R_est, R_gt = np.asarray(est_rotations, dtype=np.float64), np.asarray(gt_rotations, dtype=np.float64)
    dt = np.linalg.norm(c_est - c_gt, axis=-1)
    trace = np.sum(R_gt * R_est, axis=(-2, -1))  # trace(R_gt^T R_est)
    alpha = np.degrees(np.arccos(np.clip(0.5 * (trace - 1.0), -1.0, 1.0)))
    return PoseErrors(dt, alpha)
