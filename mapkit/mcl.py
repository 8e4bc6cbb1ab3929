"""Monte Carlo visual localization (MCVL, section III and Algorithm 1): a particle filter over poses.

Each particle is a 6-DoF pose ``s = [r, Omega]``: position ``r`` (3,) m in the map frame and
Euler angles ``Omega`` (3,) rad of ``R_world_from_body``. The filter is vectorised over particles;
a step is :func:`predict` (eqs. 1-2), :func:`weigh` (eqs. 3-4), :func:`estimate` and
:func:`sus_resample` (section III-C), and :class:`MonteCarloLocalizer` chains them.

Conventions
-----------
* Euler angles: ``Omega = (a, b, c)``, ``R_world_from_body = Rx(a) @ Ry(b) @ Rz(c)`` (intrinsic
  x-y'-z'', scipy ``"XYZ"``), the same as :attr:`mapkit.measurement.Measurement.euler`. The paper's
  DCM ``phi(Omega)`` is ``R_world_from_body.T`` (body_from_world; MATLAB ``angle2dcm(a, b, c,
  'XYZ')``, which the authors' code uses), so eq. 2, ``phi(Omega_t) = phi(psi) phi(Omega_{t-1})``,
  is ``R_t = R_{t-1} @ R(psi)``: the angular increment ``psi`` acts in the body frame.
* A step is one query frame; velocities are per step (the paper has no time step; its queries
  are at 4 Hz, section IV-B).
* Linear velocity: eq. 2 adds ``v`` to ``r`` directly, so the paper's ``mu_v = (0.1, 0.1, 0.01)``
  is in the world (map) frame; that is the default. ``velocity_frame="body"`` rotates ``v`` by
  the particle's previous orientation instead (then ``mu_v`` is e.g. ``(speed, 0, 0)``).

Where the paper and the authors' released MATLAB code differ, the paper is followed: the
covariances of section IV-A are variances (the code's ``euler_sigma(2) = 1e-5`` is a standard
deviation, i.e. variance 1e-10 where the paper says 1e-5); eq. 3 keeps its factor 1/2 (the code
drops it); angle differences in eq. 3 are wrapped to (-pi, pi] (the code does not wrap). The pose
estimate is taken from the weighted particles before resampling (the code averages after, with
equal weights: same expectation, more Monte Carlo noise).

Beyond the paper, and off by default (:class:`OdometryMotionConfig`, :class:`RecoveryConfig`):
an odometry-driven motion model, and re-injection of particles around the measurement when the
track is lost.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Optional, Sequence

import numpy as np
from pydantic import Field, NonNegativeFloat, PositiveFloat, PositiveInt

from .config import MapkitConfig
from .errors import ConfigError
from .measurement import Measurement, euler_from_matrix, matrix_from_euler

Vec3 = tuple[float, float, float]
Var3 = tuple[NonNegativeFloat, NonNegativeFloat, NonNegativeFloat]
Var6 = tuple[PositiveFloat, PositiveFloat, PositiveFloat, PositiveFloat, PositiveFloat, PositiveFloat]


# --- configuration ------------------------------------------------------------------------------------

class OdometryMotionConfig(MapkitConfig):
    """BEYOND THE PAPER: motion from odometry (relative pose between consecutive frames) plus noise.

    Used for the steps at which the caller passes odometry; the paper's constant-velocity model
    (eqs. 1-2) is used for the others.
    """

    enabled: bool = Field(False, description="Beyond the paper (MCVL uses eqs. 1-2 only): drive the motion model by odometry when the caller supplies it.")
    translation_sigma_m: Var3 = Field(
        (0.2, 0.2, 0.05), description="Beyond the paper (mapkit choice): std of the noise added to the odometry translation, per step, body-frame x/y/z (m)."
    )
    rotation_sigma_rad: Var3 = Field(
        (0.002, 0.002, 0.01), description="Beyond the paper (mapkit choice): std of the noise added to the odometry rotation, per step, as XYZ Euler angles (rad)."
    )


class RecoveryConfig(MapkitConfig):
    """BEYOND THE PAPER: lost-track recovery by re-injecting particles around the measurement."""

    enabled: bool = Field(False, description="Beyond the paper (MCVL has no recovery): re-inject particles when the measurement stays far from all of them.")
    distance_m: PositiveFloat = Field(
        25.0, description="Beyond the paper (mapkit choice, ~11 sigma of the position part of Sigma_o): the track counts as lost at a step when no particle is this close to the measured position (m)."
    )
    consecutive_steps: PositiveInt = Field(3, description="Beyond the paper (mapkit choice): re-inject after this many lost steps in a row (one outlier retrieval must not reset the filter).")
    fraction: float = Field(
        0.2, gt=0.0, le=1.0, description="Beyond the paper (mapkit choice): share of the particles replaced by draws from the initial distribution around the measurement."
    )


class MclConfig(MapkitConfig):
    """Monte Carlo visual localization; defaults are MCVL section IV-A (variances, per step)."""

    n_particles: PositiveInt = Field(1000, description="Number of particles N (MCVL Sec. IV-A: fixed to 1000).")
    init_position_cov_m2: Var3 = Field((10.0, 10.0, 10.0), description="Diagonal covariance of the initial positions around the first measurement, m^2 (MCVL Sec. IV-A).")
    init_euler_cov_rad2: Var3 = Field((0.001, 0.001, 1.0), description="Diagonal covariance of the initial Euler angles around the first measurement, rad^2 (MCVL Sec. IV-A).")
    velocity_mean_m: Vec3 = Field((0.1, 0.1, 0.01), description="mu_v, mean linear velocity per step, m (MCVL Sec. IV-A; world frame as in eq. 2).")
    velocity_cov_m2: Var3 = Field((1.0, 1.0, 0.01), description="Sigma_v diagonal, m^2 per step (MCVL Sec. IV-A).")
    velocity_frame: Literal["world", "body"] = Field(
        "world", description="Frame of v: 'world' adds it to r as eq. 2 does (MCVL Sec. III-A); 'body' rotates it by the particle's orientation first (mapkit option)."
    )
    angular_velocity_mean_rad: Vec3 = Field((0.001, 0.00001, 0.01), description="mu_psi, mean Euler increment per step, rad (MCVL Sec. IV-A).")
    angular_velocity_cov_rad2: Var3 = Field((0.0001, 0.00001, 0.01), description="Sigma_psi diagonal, rad^2 per step (MCVL Sec. IV-A; the authors' code draws the second angle with std 1e-5, i.e. variance 1e-10).")
    measurement_cov: Var6 = Field(
        (5.0, 5.0, 5.0, 0.0001, 0.0001, 0.001), description="Sigma_o diagonal: position m^2, then Euler angles rad^2 (MCVL Sec. IV-A, eq. 3; the authors' code uses (20, 20, 20, 0.001, 0.001, 0.01) on the 10 km RobotCar route)."
    )
    odometry: OdometryMotionConfig = Field(default_factory=OdometryMotionConfig, description="Beyond the paper: odometry-driven motion model (off).")
    recovery: RecoveryConfig = Field(default_factory=RecoveryConfig, description="Beyond the paper: lost-track recovery (off).")


# --- particles and estimates --------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class Particles:
    """N particles: ``positions`` (N, 3) m, ``euler`` (N, 3) rad (the state), and ``rotations``
    (N, 3, 3) = ``matrix_from_euler(euler)``, ``R_world_from_body``, kept alongside to save work."""

    positions: np.ndarray
    euler: np.ndarray
    rotations: np.ndarray

    @classmethod
    def from_euler(cls, positions: np.ndarray, euler: np.ndarray) -> "Particles":
        # through the matrix, so that the stored angles are canonical (b in [-pi/2, pi/2])
        return cls.from_rotations(positions, matrix_from_euler(euler))

    @classmethod
    def from_rotations(cls, positions: np.ndarray, rotations: np.ndarray) -> "Particles":
        # the matrices are kept as given, not rebuilt from the angles (that would cost a third of a
        # step): products of rotations stay orthonormal to rounding, which grows ~1e-16 per step
        R = np.asarray(rotations, dtype=np.float64)
        return cls(np.asarray(positions, dtype=np.float64), euler_from_matrix(R), R)

    def __len__(self) -> int:
        return len(self.positions)

    def take(self, indices: np.ndarray) -> "Particles":
        # np.take: a third of the time of fancy indexing for (N, 3, 3) rows
        return Particles(np.take(self.positions, indices, 0), np.take(self.euler, indices, 0), np.take(self.rotations, indices, 0))


@dataclass(frozen=True, eq=False)
class Estimate:
    """The filter's pose at one step: ``world_from_body`` position (3,) m, rotation (3, 3), Euler
    angles (3,) rad; the weighted spread of particle positions per axis (m); the effective sample
    size ``1 / sum(w^2)`` of the weights it was computed with; whether a measurement was used;
    how many particles were re-injected (recovery, beyond the paper)."""

    position: np.ndarray
    rotation: np.ndarray
    euler: np.ndarray
    position_std_m: np.ndarray
    n_eff: float
    measured: bool = True
    reinjected: int = 0


# --- the functional core ------------------------------------------------------------------------------

def wrap_angle(x: np.ndarray) -> np.ndarray:
    """Angles wrapped to (-pi, pi]."""
    x = np.asarray(x, dtype=np.float64)
    return x + (2.0 * np.pi) * np.floor((np.pi - x) * (0.5 / np.pi))  # 4x faster than np.mod here


def init_particles(measurement: Measurement, cfg: MclConfig, rng: np.random.Generator, n: Optional[int] = None) -> Particles:
    """Particles drawn from a Gaussian around a measurement (MCVL Sec. IV-A)."""
    n = cfg.n_particles if n is None else n
    noise = rng.standard_normal((n, 6))
    positions = measurement.translation + noise[:, :3] * np.sqrt(cfg.init_position_cov_m2)
    euler = measurement.euler + noise[:, 3:] * np.sqrt(cfg.init_euler_cov_rad2)
    return Particles.from_euler(positions, euler)


def predict(
    particles: Particles, cfg: MclConfig, rng: np.random.Generator, odometry_prev_from_curr: Optional[np.ndarray] = None
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


def weigh(particles: Particles, measurement: Measurement, cfg: MclConfig) -> np.ndarray:
    """Normalised weights (N,) of eqs. 3-4, computed in log space.

    Subtracting the largest log-likelihood before exponentiating keeps the best particle at
    weight 1 before normalisation, so a measurement far from every particle (all eq. 3 values
    underflow to 0 in linear space) still gives valid weights.
    """
    ll = log_likelihood(particles, measurement, cfg)
    w = np.exp(ll - ll.max())
    return w / w.sum()


def sus_resample(weights: np.ndarray, rng: np.random.Generator, n: Optional[int] = None) -> np.ndarray:
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

    The same minimiser as :func:`mapkit.geometry.average_rotations` (Markley's quaternion average
    minimises the same weighted chordal cost), at ~20 us instead of ~0.8 ms for 1,000 rotations,
    which the per-step budget of the filter needs.
    """
    R = np.asarray(rotations, dtype=np.float64)
    M = (np.asarray(weights, dtype=np.float64) @ R.reshape(len(R), 9)).reshape(3, 3)
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])  # no reflection
    return U @ D @ Vt


def estimate(particles: Particles, weights: Optional[np.ndarray] = None, measured: bool = True, reinjected: int = 0) -> Estimate:
    """Weighted mean position and chordal mean rotation of the particles (equal weights if None)."""
    n = len(particles)
    w = np.full(n, 1.0 / n) if weights is None else np.asarray(weights, dtype=np.float64) / np.sum(weights)
    position = w @ particles.positions
    R = chordal_mean_rotation(particles.rotations, w)
    std = np.sqrt(w @ (particles.positions - position) ** 2)
    return Estimate(position, R, euler_from_matrix(R), std, float(1.0 / (w @ w)), measured, reinjected)


def reinject(particles: Particles, measurement: Measurement, cfg: MclConfig, rng: np.random.Generator, fraction: float) -> tuple[Particles, int]:
    """BEYOND THE PAPER: replace a random ``fraction`` of the particles by initial draws around the measurement."""
    n = len(particles)
    k = min(n, max(1, int(round(fraction * n))))
    idx = rng.choice(n, size=k, replace=False)
    fresh = init_particles(measurement, cfg, rng, n=k)
    pos, eul, rot = particles.positions.copy(), particles.euler.copy(), particles.rotations.copy()
    pos[idx], eul[idx], rot[idx] = fresh.positions, fresh.euler, fresh.rotations
    return Particles(pos, eul, rot), k


# --- the localizer ------------------------------------------------------------------------------------

class MonteCarloLocalizer:
    """MCVL's Algorithm 1 over a query sequence, one :meth:`step` per frame.

    The first measurement initialises the particles (Sec. IV-A). Then each step predicts (eqs.
    1-2), and with a measurement weighs (eqs. 3-4), estimates the pose from the weighted
    particles, and resamples by SUS; without one it only predicts.
    """

    def __init__(self, cfg: Optional[MclConfig] = None, seed: Optional[int] = 0):
        self.cfg = cfg if cfg is not None else MclConfig()
        self.rng = np.random.default_rng(seed)
        self._particles: Optional[Particles] = None
        self._lost_steps = 0

    @property
    def particles(self) -> Optional[Particles]:
        """The current (equally weighted) particles; None before the first measurement."""
        return self._particles

    @property
    def initialized(self) -> bool:
        return self._particles is not None

    def step(self, measurement: Optional[Measurement] = None, odometry: Optional[np.ndarray] = None) -> Optional[Estimate]:
        """Advance one frame. ``odometry`` is the 4x4 ``prev_from_curr`` body motion since the last
        step (needs ``cfg.odometry.enabled``). Returns None until the first measurement arrives."""
        if odometry is not None and not self.cfg.odometry.enabled:
            raise ConfigError("odometry was given to the MCL filter but its config has odometry.enabled = false")
        cfg = self.cfg
        if self._particles is None:
            if measurement is None:
                return None
            self._particles = init_particles(measurement, cfg, self.rng)
            return estimate(self._particles)

        particles = predict(self._particles, cfg, self.rng, odometry)
        if measurement is None:
            self._particles = particles
            return estimate(particles, measured=False)

        n_new = 0
        if cfg.recovery.enabled:
            nearest_m = np.sqrt(np.min(np.sum((particles.positions - measurement.translation) ** 2, axis=1)))
            self._lost_steps = self._lost_steps + 1 if nearest_m > cfg.recovery.distance_m else 0
            if self._lost_steps >= cfg.recovery.consecutive_steps:
                particles, n_new = reinject(particles, measurement, cfg, self.rng, cfg.recovery.fraction)
                self._lost_steps = 0

        w = weigh(particles, measurement, cfg)
        est = estimate(particles, w, measured=True, reinjected=n_new)
        self._particles = particles.take(sus_resample(w, self.rng))
        return est


@dataclass(frozen=True, eq=False)
class FilterTrack:
    """Per-step outputs of :func:`run_filter`; rows before the first measurement are NaN and
    ``valid`` is False there."""

    positions: np.ndarray  # (T, 3) m, world
    rotations: np.ndarray  # (T, 3, 3) world_from_body
    euler: np.ndarray  # (T, 3) rad
    position_std_m: np.ndarray  # (T, 3)
    n_eff: np.ndarray  # (T,)
    reinjected: np.ndarray  # (T,) int
    valid: np.ndarray  # (T,) bool


def run_filter(
    measurements: Sequence[Optional[Measurement]],
    cfg: Optional[MclConfig] = None,
    seed: Optional[int] = 0,
    odometry: Optional[Sequence[Optional[np.ndarray]]] = None,
) -> FilterTrack:
    """Run :class:`MonteCarloLocalizer` over a sequence (None = no measurement at that step).

    ``odometry[t]`` is the 4x4 ``body_{t-1} <- body_t`` motion into step ``t`` or None (beyond the
    paper; needs ``cfg.odometry.enabled``).
    """
    T = len(measurements)
    if odometry is not None and len(odometry) != T:
        raise ValueError(f"odometry has {len(odometry)} entries for {T} measurements")
    loc = MonteCarloLocalizer(cfg, seed)
    pos = np.full((T, 3), np.nan)
    rot = np.full((T, 3, 3), np.nan)
    eul = np.full((T, 3), np.nan)
    std = np.full((T, 3), np.nan)
    n_eff = np.full(T, np.nan)
    reinjected = np.zeros(T, np.int64)
    valid = np.zeros(T, bool)
    for t, z in enumerate(measurements):
        est = loc.step(z, None if odometry is None or not loc.initialized else odometry[t])
        if est is None:
            continue
        pos[t], rot[t], eul[t], std[t], n_eff[t] = est.position, est.rotation, est.euler, est.position_std_m, est.n_eff
        reinjected[t], valid[t] = est.reinjected, True
    return FilterTrack(pos, rot, eul, std, n_eff, reinjected, valid)


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
            return {"frames": 0, "mean_translation_m": None, "median_translation_m": None, "mean_rotation_deg": None, "median_rotation_deg": None}
        return {
            "frames": int(ok.sum()),
            "mean_translation_m": float(t.mean()),
            "median_translation_m": float(np.median(t)),
            "mean_rotation_deg": float(r.mean()),
            "median_rotation_deg": float(np.median(r)),
        }


def pose_errors(est_positions: np.ndarray, est_rotations: np.ndarray, gt_positions: np.ndarray, gt_rotations: np.ndarray) -> PoseErrors:
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
