"""The retrieval measurement z_t of MCVL: mean shift over the poses of the retrieved images.

MCVL (Monte Carlo visual localization, ../shared/papers/), section III-B: the top R database
images are retrieved for a query (R = 20, section IV-A), mean shift is run over the translations
of their poses, and the mean translation and rotation of the largest cluster are the noisy
measurement ``z_t`` that weighs the particles (eq. 3).

Pure numpy/scipy. Poses are ``world_from_body``: ``translation`` is the body's position in the
map frame (m), ``rotation`` the 3x3 matrix ``R_world_from_body``.

Euler convention (shared with :mod:`mapkit.localization.mcl`): ``euler = (a, b, c)`` rad are intrinsic
x-y'-z'' angles of ``R_world_from_body = Rx(a) @ Ry(b) @ Rz(c)`` (scipy ``"XYZ"``, upper case),
canonical with ``a, c`` in (-pi, pi] and ``b`` in [-pi/2, pi/2]. This is the orientation the
authors' code reads with ``quat2eul(q, 'XYZ')``; the paper's DCM ``phi(euler)`` is its transpose
(``angle2dcm(a, b, c, 'XYZ')``, body_from_world). For a vehicle body frame with z up or down, ``c``
is the heading, which is why the initial covariance of section IV-A is large on the third angle.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from mapkit.core.geometry import average_rotations, quat_wxyz_to_matrix

# --- Euler angles <-> rotation matrices -------------------------------------------------------------
# Written out instead of scipy's Rotation.from_euler/as_euler: those cost ~1.6 ms / 0.6 ms for 1,000
# rotations on the target machine (scipy 1.17), more than a whole filter step's budget.


def matrix_from_euler(euler: np.ndarray) -> np.ndarray:
    """``R = Rx(a) @ Ry(b) @ Rz(c)`` for Euler angles (..., 3) -> (..., 3, 3); scipy ``"XYZ"``."""
    e = np.asarray(euler, dtype=np.float64)
    ca, cb, cc = np.cos(e[..., 0]), np.cos(e[..., 1]), np.cos(e[..., 2])
    sa, sb, sc = np.sin(e[..., 0]), np.sin(e[..., 1]), np.sin(e[..., 2])
    R = np.empty(e.shape[:-1] + (3, 3))
    R[..., 0, 0] = cb * cc
    R[..., 0, 1] = -cb * sc
    R[..., 0, 2] = sb
    R[..., 1, 0] = ca * sc + sa * sb * cc
    R[..., 1, 1] = ca * cc - sa * sb * sc
    R[..., 1, 2] = -sa * cb
    R[..., 2, 0] = sa * sc - ca * sb * cc
    R[..., 2, 1] = sa * cc + ca * sb * sc
    R[..., 2, 2] = ca * cb
    return R


def euler_from_matrix(R: np.ndarray) -> np.ndarray:
    """Inverse of :func:`matrix_from_euler`: (..., 3, 3) -> canonical (..., 3) angles.

    At gimbal lock (``b = +-pi/2``) only ``a +- c`` is defined; ``c = 0`` is returned there.
    """
    R = np.asarray(R, dtype=np.float64)
    cb = np.hypot(R[..., 0, 0], R[..., 0, 1])
    b = np.arctan2(R[..., 0, 2], cb)  # not arcsin(R02): that loses precision near +-pi/2
    a = np.arctan2(-R[..., 1, 2], R[..., 2, 2])
    c = np.arctan2(-R[..., 0, 1], R[..., 0, 0])
    locked = cb < 1e-9
    if np.any(locked):
        a = np.where(locked, np.arctan2(R[..., 2, 1], R[..., 1, 1]), a)
        c = np.where(locked, 0.0, c)
    return np.stack([a, b, c], axis=-1)


# --- the measurement ----------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Measurement:
    """One noisy pose measurement ``z_t`` (section III-B), from a cluster of retrieved poses.

    ``translation`` (3,) m and ``rotation`` (3, 3) are ``world_from_body``; ``euler`` (3,) rad is
    ``rotation`` in the module's Euler convention. ``members`` are indices into the retrieval list
    (rank order) of the images in the chosen cluster; ``spread_m`` is their RMS distance to
    ``translation``.
    """

    translation: np.ndarray
    rotation: np.ndarray
    euler: np.ndarray
    cluster_size: int
    n_retrieved: int
    spread_m: float
    members: np.ndarray

    @classmethod
    def from_pose(cls, translation: np.ndarray, rotation: np.ndarray) -> Measurement:
        """A measurement from one pose (e.g. a GPS/INS fix or a synthetic test), no clustering."""
        R = np.asarray(rotation, dtype=np.float64)
        return cls(
            translation=np.asarray(translation, dtype=np.float64).reshape(3),
            rotation=R,
            euler=euler_from_matrix(R),
            cluster_size=1,
            n_retrieved=1,
            spread_m=0.0,
            members=np.zeros(1, np.int64),
        )


def mean_shift_measurement(
    translations: np.ndarray,
    rotations: np.ndarray,
    bandwidth: float = 5.0,
    weights: np.ndarray | None = None,
    max_iter: int = 300,
) -> Measurement:
    """The measurement ``z_t`` from R retrieved poses, given in retrieval rank order (best first).

    Flat-kernel mean shift over ``translations`` (R, 3) m, with the authors' radius of 5 m, done as
    sklearn's ``MeanShift`` does it: a seed at every point, each shifted to the mean of the points
    within ``bandwidth`` until it moves less than 1e-3 * bandwidth; modes are taken in order of how
    many points lie within ``bandwidth`` of them (ties: the best-ranked seed first) and a mode
    closer than ``bandwidth`` to one already kept is merged into it; every point joins its nearest
    kept mode. (The authors' Piotr-toolbox ``meanShift`` instead groups points whose own modes are
    closer than the radius; the two differ only for points between clusters.) The largest cluster
    wins; on a tie, the one holding the best-ranked image. Its mean translation and chordal L2
    rotation mean (sign-consistent, :func:`mapkit.core.geometry.average_rotations`) are the measurement.

    ``rotations`` are (R, 3, 3) matrices or (R, 4) ``wxyz`` quaternions (either sign).
    ``weights`` (R,) >= 0, e.g. retrieval similarities, weight the kernel means, the cluster sizes
    that pick the winner, and the winner's translation and rotation means (zero-weight images seed
    no mode); ``None`` = all equal. ``cluster_size`` is always the winner's number of images.
    """
    X = np.asarray(translations, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3 or len(X) == 0:
        raise ValueError(f"translations must be (R>=1, 3), got {X.shape}")
    n = len(X)
    Rots = _as_matrices(rotations, n)
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    if w.shape != (n,) or np.any(w < 0) or not np.isfinite(w).all() or w.sum() <= 0:
        raise ValueError(f"weights must be {n} finite non-negative numbers with a positive sum")
    if not bandwidth > 0:
        raise ValueError(f"bandwidth must be positive, got {bandwidth}")

    modes = _flat_mean_shift(X, w, bandwidth, max_iter)
    labels = _merge_and_assign(X, w, modes, bandwidth)

    size = np.bincount(labels, weights=w)
    best_rank = np.full(len(size), n)
    np.minimum.at(best_rank, labels, np.arange(n))
    winner = np.lexsort((best_rank, -size))[0]
    members = np.flatnonzero(labels == winner)

    wm = w[members] / size[winner]  # the winner has the largest, hence positive, weight
    t = wm @ X[members]
    R = average_rotations(Rots[members], weights=wm)
    spread = float(np.sqrt(wm @ np.sum((X[members] - t) ** 2, axis=1)))
    return Measurement(
        translation=t,
        rotation=R,
        euler=euler_from_matrix(R),
        cluster_size=int(len(members)),
        n_retrieved=n,
        spread_m=spread,
        members=members,
    )


def _as_matrices(rotations: np.ndarray, n: int) -> np.ndarray:
    r = np.asarray(rotations, dtype=np.float64)
    if r.shape == (n, 3, 3):
        return r
    if r.shape == (n, 4):
        return quat_wxyz_to_matrix(r / np.linalg.norm(r, axis=1, keepdims=True))
    raise ValueError(f"rotations must be ({n}, 3, 3) matrices or ({n}, 4) wxyz quaternions, got {r.shape}")


def _flat_mean_shift(X: np.ndarray, w: np.ndarray, bandwidth: float, max_iter: int) -> np.ndarray:
    """Modes reached from a seed at every point of positive weight, all seeds shifted at once.

    A flat-kernel (weighted) mean of the points within the bandwidth always has one of them within
    the bandwidth, so no seed is ever left without points. Seeds that have converged are shifted
    with the others (a flat kernel reaches its fixed point exactly): cheaper than masking them.
    """
    bw2 = bandwidth * bandwidth
    tol2 = (1e-3 * bandwidth) ** 2  # sklearn's stop_thresh
    modes = X[w > 0].copy()
    for _ in range(max_iter):
        diff = modes[:, None, :] - X[None, :, :]
        K = (np.einsum("ijk,ijk->ij", diff, diff) <= bw2) * w
        moved = (K @ X) / K.sum(axis=1, keepdims=True)
        shift2 = np.max(np.sum((moved - modes) ** 2, axis=1))
        modes = moved
        if shift2 <= tol2:
            break
    return modes


def _merge_and_assign(X: np.ndarray, w: np.ndarray, modes: np.ndarray, bandwidth: float) -> np.ndarray:
    """Cluster label of every point after merging modes closer than ``bandwidth``."""
    bw2 = bandwidth * bandwidth
    within = np.sum((modes[:, None, :] - X[None, :, :]) ** 2, axis=-1) <= bw2
    intensity = within @ w
    # seeds are in rank order, so on equal intensity the mode of the best-ranked seed comes first
    order = np.lexsort((np.arange(len(modes)), -intensity))
    close = np.sum((modes[:, None, :] - modes[None, :, :]) ** 2, axis=-1) <= bw2
    suppressed = np.zeros(len(modes), bool)
    kept: list[int] = []
    for i in order:
        if not suppressed[i]:
            kept.append(int(i))
            suppressed |= close[i]
    centres = modes[kept]
    return np.argmin(np.sum((X[:, None, :] - centres[None, :, :]) ** 2, axis=-1), axis=1)


# --- BEYOND THE PAPER: the retrieved poses as a mixture of hypotheses ---------------------------------

HitWeighting = Literal["uniform", "rank", "distance"]


def hit_weights(distances: np.ndarray, weighting: HitWeighting = "uniform", scale: float = 1.0) -> np.ndarray:
    """Prior weights (k,) of the retrieved images, summing to 1, best-ranked first.

    ``uniform``: 1/k each. ``rank``: ``exp(-j / scale)`` for rank ``j = 0, 1, ...`` (``scale`` in
    ranks). ``distance``: ``exp(-(d_j - d_0) / scale)`` for the descriptor distances ``d`` (squared
    L2 between unit vectors, 0 to 4; ``scale`` in the same unit). Non-finite distances (padding)
    get weight 0.
    """
    d = np.asarray(distances, dtype=np.float64).reshape(-1)
    if len(d) == 0:
        raise ValueError("no retrieved images")
    if not scale > 0:
        raise ValueError(f"scale must be positive, got {scale}")
    ok = np.isfinite(d)
    if not ok.any():
        raise ValueError("no retrieved image has a finite distance")
    if weighting == "uniform":
        w = ok.astype(np.float64)
    elif weighting == "rank":
        w = np.where(ok, np.exp(-np.arange(len(d)) / scale), 0.0)
    elif weighting == "distance":
        w = np.where(ok, np.exp(-(np.where(ok, d, 0.0) - d[ok].min()) / scale), 0.0)
    else:
        raise ValueError(f"unknown hit weighting {weighting!r}")
    return w / w.sum()


@dataclass(frozen=True, eq=False)
class PoseHypotheses:
    """BEYOND THE PAPER: the top-k retrieved poses kept as k hypotheses instead of one cluster mean.

    ``translations`` (k, 3) m and ``rotations`` (k, 3, 3) ``world_from_body``, best-ranked first;
    ``weights`` (k,) prior weights summing to 1 (:func:`hit_weights`). The particle filter
    weighs particles by the mixture of one kernel per hypothesis (:func:`mapkit.localization.mcl.mixture_likelihood`).
    """

    translations: np.ndarray
    rotations: np.ndarray
    weights: np.ndarray

    def __post_init__(self):
        k = len(self.translations)
        if (
            k == 0
            or self.translations.shape != (k, 3)
            or self.rotations.shape != (k, 3, 3)
            or self.weights.shape != (k,)
        ):
            raise ValueError(
                f"hypotheses need (k, 3) translations, (k, 3, 3) rotations and (k,) weights with k >= 1, got "
                f"{self.translations.shape}, {self.rotations.shape}, {self.weights.shape}"
            )

    def __len__(self) -> int:
        return len(self.translations)

    @classmethod
    def from_retrieval(
        cls,
        translations: np.ndarray,
        rotations: np.ndarray,
        distances: np.ndarray | None = None,
        weighting: HitWeighting = "uniform",
        scale: float = 1.0,
    ) -> PoseHypotheses:
        """From retrieved poses in rank order; rotations as matrices or ``wxyz`` quaternions.
        Hypotheses of weight 0 (padding, non-finite distance) are dropped."""
        X = np.asarray(translations, dtype=np.float64).reshape(-1, 3)
        n = len(X)
        d = np.arange(n, dtype=np.float64) if distances is None else np.asarray(distances, dtype=np.float64)
        if distances is None and weighting == "distance":
            raise ValueError("distance weighting needs the descriptor distances")
        w = hit_weights(d, weighting, scale)
        keep = w > 0
        return cls(X[keep], _as_matrices(rotations, n)[keep], w[keep] / w[keep].sum())

    @classmethod
    def from_measurement(cls, measurement: Measurement) -> PoseHypotheses:
        """One hypothesis: the measurement's pose."""
        return cls(measurement.translation[None].copy(), measurement.rotation[None].copy(), np.ones(1))
