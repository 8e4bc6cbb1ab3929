"""GPS alignment: the similarity that maps a session's trajectory frame into the local ENU frame.

Pure numpy. Fixes are associated to the trajectory by timestamp (poses interpolated, never
extrapolated), then a robust estimate is made in two steps: RANSAC on minimal samples rejects
multipath jumps and outliers, and iteratively reweighted least squares (Cauchy weights scaled by
each fix's reported sigma) refines on the inliers. The default model is gravity-aware: yaw about
the vertical, translation and scale (5 parameters), for trajectories whose z axis is already
vertical (LiDAR odometry started level, INS); ``yaw`` keeps the trajectory's own metric scale
(4 parameters), which is what a build does with LiDAR or INS poses (see ``mapkit.mapping.build``), and
still reports the scale GPS would have chosen.

``sim3`` estimates all 7 parameters and needs no levelled frame: structure from motion has an
arbitrary orientation and scale. Every length it judges is in GPS metres (the trajectory's extent,
its spread off the path axis), never in the trajectory's own units. When the drive is too straight
for GPS to fix the rotation about its direction of travel (the predicted standard deviation of that
roll exceeds ``max_roll_sigma_deg``), a gravity hint fixes that one angle: ``up_map``, a direction of
the trajectory frame that is roughly up (for a camera trajectory the cameras' mean -y, as cameras
are mounted roughly level). Without a hint the full Sim3 is kept and the roll is reported as
unobservable (or, ``strict``, refused).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from typing import Literal

import numpy as np
from scipy.spatial.transform import Rotation

from mapkit.core.errors import InputError, InputWarning
from mapkit.core.geometry import interpolate_poses, make_sim3, sim3_scale, transform_points, umeyama, yaw_rotation

Mode = Literal["yaw_scale", "sim3", "yaw"]
Gravity = Literal["level frame", "gps", "up hint", "unobservable"]


@dataclass
class GpsAlignment:
    """Result: ``enu_from_map`` (4x4 similarity) and the evidence for it."""

    enu_from_map: np.ndarray
    mode: str
    inliers: np.ndarray  # (N,) bool over the associated fixes
    residuals_m: np.ndarray  # (N,) horizontal+vertical residual of every associated fix after the fit
    stamps_ns: np.ndarray  # (N,) stamps of the associated fixes
    rejected: list[dict] = field(default_factory=list)  # index, stamp, reason, residual
    notes: list[str] = field(default_factory=list)
    free_scale: float | None = None  # in ``yaw`` mode: the scale a ``yaw_scale`` fit of the inliers gives
    extent_m: float = float("nan")  # the trajectory's extent along its main axis where GPS overlaps it, in GPS metres
    # what fixed the rotation about the direction of travel: the frame's own gravity (yaw modes), GPS
    # (the path bends enough), the up hint, or nothing (reported as unobservable)
    gravity: Gravity = "level frame"
    roll_sigma_deg: float | None = (
        None  # sim3: predicted 1-sigma of that roll from GPS alone (fix sigmas, geometry); <= 180
    )
    up_tilt_deg: float | None = None  # sim3 with an up hint: angle between the hint, once aligned, and ENU up

    @property
    def scale(self) -> float:
        return sim3_scale(self.enu_from_map)

    @property
    def yaw_rad(self) -> float:
        R = self.enu_from_map[:3, :3] / self.scale
        return float(np.arctan2(R[1, 0], R[0, 0]))

    def stats(self) -> dict:
        r = self.residuals_m[self.inliers]
        return {
            "mode": self.mode,
            "fixes_associated": int(len(self.residuals_m)),
            "fixes_used": int(self.inliers.sum()),
            "fixes_rejected": int((~self.inliers).sum()),
            "residual_rmse_m": float(np.sqrt(np.mean(r**2))) if len(r) else None,
            "residual_median_m": float(np.median(r)) if len(r) else None,
            "residual_p95_m": float(np.percentile(r, 95)) if len(r) else None,
            "scale": self.scale,
            "yaw_deg": float(np.degrees(self.yaw_rad)),
            "scale_if_estimated": self.free_scale,
            "extent_m": self.extent_m,
            "gravity": self.gravity,
            "roll_sigma_deg": self.roll_sigma_deg,
            "up_tilt_deg": self.up_tilt_deg,
            "notes": list(self.notes),
        }


def associate_fixes(
    traj_stamps_ns: np.ndarray,
    world_from_base: np.ndarray,
    fix_stamps_ns: np.ndarray,
    base_from_antenna: np.ndarray | None = None,
    max_gap_ns: int = 1_000_000_000,
) -> tuple[np.ndarray, np.ndarray]:
    """Antenna positions in the trajectory frame at each fix time, and which fixes got one.

    A fix is used only when it falls between two trajectory poses at most ``max_gap_ns`` apart,
    so a gap in the trajectory is never bridged by interpolation and its ends never extrapolated.
    """
    stamps = np.asarray(traj_stamps_ns, np.int64)
    q = np.asarray(fix_stamps_ns, np.int64)
    poses, inside = interpolate_poses(stamps, world_from_base, q)
    j = np.clip(np.searchsorted(stamps, q), 1, len(stamps) - 1)
    gap_ok = (stamps[j] - stamps[j - 1]) <= max_gap_ns
    ok = inside & gap_ok
    poses = poses[gap_ok[inside]]
    lever = np.zeros(3) if base_from_antenna is None else np.asarray(base_from_antenna)[:3, 3]
    antenna = np.einsum("nij,j->ni", poses[:, :3, :3], lever) + poses[:, :3, 3]
    return antenna, ok


def _principal_axis(points: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(weighted centroid, unit direction of largest weighted spread)."""
    wn = w / w.sum()
    mu = wn @ points
    _, _, vt = np.linalg.svd((points - mu) * np.sqrt(wn)[:, None], full_matrices=False)
    return mu, vt[0]


def _roll_from_up(T: np.ndarray, src: np.ndarray, dst: np.ndarray, w: np.ndarray, up_src: np.ndarray) -> np.ndarray:
    """``T`` with its rotation about the path axis (the principal axis of ``src``) replaced by the one
    that turns ``up_src`` closest to ENU up; scale and translation re-fitted (weighted least squares)
    for that rotation. The axis direction, the only part of the rotation a straight path fixes, is kept."""
    s = sim3_scale(T)
    R = T[:3, :3] / s
    mu_s, a = _principal_axis(src, w)
    g = R.T @ np.array([0.0, 0.0, 1.0])  # ENU up in the source frame
    u_perp = up_src - (up_src @ a) * a
    g_perp = g - (g @ a) * a
    if np.linalg.norm(u_perp) < 1e-9 or np.linalg.norm(g_perp) < 1e-9:
        return T  # the hint (or up) lies along the path: it says nothing about the roll
    R = R @ Rotation.from_rotvec(a * float(np.arctan2(a @ np.cross(u_perp, g_perp), u_perp @ g_perp))).as_matrix()
    wn = w / w.sum()
    mu_d = wn @ dst
    xs, xd = src - mu_s, dst - mu_d
    var_s = float(wn @ np.sum(xs**2, axis=1))
    s = float(np.trace(R.T @ ((xd * wn[:, None]).T @ xs)) / var_s) if var_s > 0 else s
    return make_sim3(s, R, mu_d - s * R @ mu_s)


def fit_transform(
    src: np.ndarray,
    dst: np.ndarray,
    w: np.ndarray | None = None,
    mode: Mode = "yaw_scale",
    up_src: np.ndarray | None = None,
) -> np.ndarray:
    """Weighted least-squares ``dst_from_src``: ``sim3``, or gravity-aware ``yaw_scale`` / ``yaw`` (rigid, 4 DoF).

    ``up_src`` (``sim3`` only): a unit vector of the source frame that is roughly up; it fixes the
    rotation about the principal axis of ``src``, which a straight path leaves free.
    """
    w = np.ones(len(src)) if w is None else np.asarray(w, np.float64)
    if mode == "sim3":
        T = umeyama(src, dst, with_scale=True, weights=w)
        return T if up_src is None else _roll_from_up(T, src, dst, w, up_src)
    # gravity-aware: 2D Procrustes (Umeyama in the plane) for yaw and scale, z by the weighted mean
    wn = w / w.sum()
    mu_s, mu_d = wn @ src, wn @ dst
    xs, xd = src[:, :2] - mu_s[:2], dst[:, :2] - mu_d[:2]
    cov = (xd * wn[:, None]).T @ xs
    a = cov[0, 0] + cov[1, 1]
    b = cov[1, 0] - cov[0, 1]
    yaw = np.arctan2(b, a)
    var_s = float(wn @ np.sum(xs**2, axis=1))
    scale = float(np.hypot(a, b) / var_s) if mode == "yaw_scale" and var_s > 0 else 1.0
    R = yaw_rotation(yaw)
    t = mu_d - scale * R @ mu_s
    return make_sim3(scale, R, t)


def _min_sample(mode: Mode) -> int:
    return 3 if mode == "sim3" else 2


def planarity(points: np.ndarray) -> tuple[float, float]:
    """(extent of the largest principal axis, ratio of second to first singular value)."""
    x = points - points.mean(axis=0)
    _, s, vt = np.linalg.svd(x, full_matrices=False)
    extent = float(np.ptp(x @ vt[0]))
    return extent, float(s[1] / s[0]) if s[0] > 0 else 0.0


def gps_metres_per_unit(p_map: np.ndarray, p_enu: np.ndarray, max_points: int = 200) -> float:
    """GPS metres per trajectory unit: the median ratio of ENU to map distance over pairs of fixes far
    apart on the trajectory (at least half its largest distance), so GPS noise and outliers barely move it."""
    idx = np.unique(np.linspace(0, len(p_map) - 1, min(len(p_map), max_points)).astype(int))
    a, b = np.triu_indices(len(idx), k=1)
    d_map = np.linalg.norm(p_map[idx[a]] - p_map[idx[b]], axis=1)
    d_enu = np.linalg.norm(p_enu[idx[a]] - p_enu[idx[b]], axis=1)
    far = d_map >= 0.5 * d_map.max() if len(d_map) and d_map.max() > 0 else np.zeros(0, bool)
    return float(np.median(d_enu[far] / d_map[far])) if far.any() else 0.0


def roll_sigma_rad(p_map: np.ndarray, metres_per_unit: float, sigma_m: float) -> float:
    """Predicted 1-sigma (rad) of the rotation about the path's principal axis from GPS fixes of
    ``sigma_m``: a roll ``d`` moves a fix at distance ``r`` (metres) from the axis by ``r d``, so the
    least-squares information is ``sum r^2 / sigma^2``."""
    mu, a = _principal_axis(p_map, np.ones(len(p_map)))
    x = p_map - mu
    r2 = np.sum((x - np.outer(x @ a, a)) ** 2, axis=1) * metres_per_unit**2
    return float(sigma_m / np.sqrt(r2.sum())) if r2.sum() > 0 else float("inf")


def align_to_gps(
    p_map: np.ndarray,
    p_enu: np.ndarray,
    sigma_m: np.ndarray | None = None,
    stamps_ns: np.ndarray | None = None,
    mode: Mode = "yaw_scale",
    inlier_sigmas: float = 3.37,
    vertical_sigma_factor: float = 2.0,
    min_inlier_threshold_m: float = 2.0,
    ransac_iters: int = 300,
    min_extent_m: float = 20.0,
    max_roll_sigma_deg: float = 2.0,
    up_map: np.ndarray | None = None,
    strict: bool = False,
    seed: int = 0,
    source: str = "gps",
) -> GpsAlignment:
    """Robust ``enu_from_map`` from corresponding antenna positions (map frame) and GPS fixes (ENU).

    ``sigma_m`` is each fix's horizontal standard deviation (NaN or None = unknown, taken as the
    median of the known ones, or 3 m); the vertical sigma is ``vertical_sigma_factor`` times it.
    A fix is an inlier when its normalised residual is below ``inlier_sigmas`` (3.37: the 99%
    bound of a chi-square with 3 degrees of freedom); the horizontal gate is never tighter than
    ``min_inlier_threshold_m``. The extent check (``min_extent_m``) is in GPS metres: the trajectory's
    extent times :func:`gps_metres_per_unit` (1 in ``yaw``, whose trajectory is metric by definition).

    ``sim3`` only: the rotation about the direction of travel is taken from GPS when its predicted
    sigma (vertical fix sigma over the root-sum-square distance of the fixes from the path axis, in
    metres: a roll of a level path moves its off-axis fixes up and down) is at most
    ``max_roll_sigma_deg``; else from ``up_map`` (a roughly-up unit vector of the map frame) when
    given; else it stays as the full Sim3 found it, reported as unobservable (an error if ``strict``).
    """
    p_map = np.asarray(p_map, np.float64)
    p_enu = np.asarray(p_enu, np.float64)
    n = len(p_map)
    stamps = np.arange(n, dtype=np.int64) if stamps_ns is None else np.asarray(stamps_ns, np.int64)
    notes: list[str] = []
    if n < 3:
        raise InputError(source, f"only {n} GPS fixes overlap the trajectory; at least 3 are needed", field="gps")
    dims = slice(None) if mode == "sim3" else slice(0, 2)  # the yaw models see the plane only
    extent_map, _ = planarity(p_map[:, dims])
    # in GPS metres, whatever the trajectory's units ('yaw' declares them metres: its scale is fixed at 1)
    metres_per_unit = 1.0 if mode == "yaw" else gps_metres_per_unit(p_map[:, dims], p_enu[:, dims])
    extent = extent_map * metres_per_unit
    if extent < min_extent_m:
        raise InputError(
            source,
            f"the trajectory spans {extent:.1f} m (GPS metres) where GPS overlaps it; at least {min_extent_m:.0f} m "
            "are needed to observe heading and scale",
            field="gps",
        )
    sig_h, sig_v = _fix_sigmas(sigma_m, n, inlier_sigmas, vertical_sigma_factor, min_inlier_threshold_m)
    gravity: Gravity = "level frame"
    roll_sigma: float | None = None
    up: np.ndarray | None = None
    if mode == "sim3":
        gravity, roll_sigma, up = _sim3_roll(
            p_map, metres_per_unit, sig_v, max_roll_sigma_deg, up_map, strict, source, notes
        )
    residuals = partial(_normalised_residuals, p_map=p_map, p_enu=p_enu, sig_h=sig_h, sig_v=sig_v)
    best_inl = _ransac(p_map, p_enu, residuals, mode, up, dims, extent_map, inlier_sigmas, ransac_iters, seed)
    if best_inl is None or best_inl.sum() < _min_sample(mode):
        raise InputError(source, "no consistent subset of GPS fixes was found", field="gps")
    T, inl = _irls(p_map, p_enu, sig_h, residuals, best_inl, mode, up, inlier_sigmas)
    u = residuals(T)
    res = np.linalg.norm(transform_points(T, p_map) - p_enu, axis=1)
    rejected = [
        {
            "index": int(i),
            "stamp_ns": int(stamps[i]),
            "residual_m": float(res[i]),
            "residual_sigmas": float(u[i]),
            "reason": "residual above threshold (outlier or multipath jump)",
        }
        for i in np.nonzero(~inl)[0]
    ]
    free_scale = None
    if mode == "yaw":  # a check on the odometry's scale, not applied
        free_scale = sim3_scale(fit_transform(p_map[inl], p_enu[inl], 1.0 / sig_h[inl] ** 2, "yaw_scale"))
    up_tilt = None
    if mode == "sim3" and up_map is not None:
        up_enu = T[:3, :3] @ (np.asarray(up_map, np.float64) / np.linalg.norm(up_map))
        up_tilt = float(np.degrees(np.arccos(np.clip(up_enu[2] / np.linalg.norm(up_enu), -1.0, 1.0))))
    return GpsAlignment(T, mode, inl, res, stamps, rejected, notes, free_scale, extent, gravity, roll_sigma, up_tilt)


def _fix_sigmas(
    sigma_m: np.ndarray | None,
    n: int,
    inlier_sigmas: float,
    vertical_sigma_factor: float,
    min_inlier_threshold_m: float,
) -> tuple[np.ndarray, np.ndarray]:
    """(horizontal, vertical) sigma of each fix that a residual is measured in: an unknown sigma is the median of
    the known ones (or 3 m); the horizontal one is floored so that an over-optimistic receiver cannot reject good
    fixes, the vertical one a multiple of it."""
    sig = np.full(n, np.nan) if sigma_m is None else np.asarray(sigma_m, np.float64).copy()
    known = np.isfinite(sig) & (sig > 0)
    sig[~known] = np.median(sig[known]) if known.any() else 3.0
    sig_h = np.maximum(sig, min_inlier_threshold_m / inlier_sigmas)
    return sig_h, vertical_sigma_factor * sig_h


def _sim3_roll(
    p_map: np.ndarray,
    metres_per_unit: float,
    sig_v: np.ndarray,
    max_roll_sigma_deg: float,
    up_map: np.ndarray | None,
    strict: bool,
    source: str,
    notes: list[str],
) -> tuple[Gravity, float, np.ndarray | None]:
    """Where a Sim3's rotation about the direction of travel comes from: (gravity source, the roll's predicted
    sigma in degrees, the up vector that fixes it or None). GPS when the predicted sigma is at most
    ``max_roll_sigma_deg``, else ``up_map``, else unobservable (an error if ``strict``); a note says which."""
    roll_sigma = min(float(np.degrees(roll_sigma_rad(p_map, metres_per_unit, float(np.median(sig_v))))), 180.0)
    if roll_sigma > max_roll_sigma_deg:
        msg = (
            f"the drive is too straight for GPS to fix the rotation about its direction of travel (predicted "
            f"sigma {roll_sigma:.1f} deg > {max_roll_sigma_deg:g} deg)"
        )
        if up_map is not None:
            notes.append(msg + "; that roll is taken from the up hint (the cameras' mean up)")
            return "up hint", roll_sigma, np.asarray(up_map, np.float64) / np.linalg.norm(up_map)
        if strict:
            raise InputError(source, msg, field="gps")
        warnings.warn(
            f"{source}: {msg}; kept the full Sim3, whose roll about the path is unobservable",
            InputWarning,
            stacklevel=3,
        )
        notes.append(msg + "; roll about the path axis unobservable (full Sim3 kept)")
        return "unobservable", roll_sigma, None
    return "gps", roll_sigma, None


def _normalised_residuals(
    T: np.ndarray, *, p_map: np.ndarray, p_enu: np.ndarray, sig_h: np.ndarray, sig_v: np.ndarray
) -> np.ndarray:
    """Each fix's residual under ``enu_from_map`` ``T`` in sigmas (horizontal and vertical, each by its own)."""
    d = transform_points(T, p_map) - p_enu
    return np.sqrt((d[:, 0] ** 2 + d[:, 1] ** 2) / sig_h**2 + d[:, 2] ** 2 / sig_v**2)


def _ransac(
    p_map: np.ndarray,
    p_enu: np.ndarray,
    residuals: Callable[[np.ndarray], np.ndarray],
    mode: Mode,
    up: np.ndarray | None,
    dims: slice,
    extent_map: float,
    inlier_sigmas: float,
    ransac_iters: int,
    seed: int,
) -> np.ndarray | None:
    """The inliers of the best transform fitted to minimal samples (None when no sample gave one). Samples are
    spread apart so that each spans the trajectory (judged in the map's own space, where positions are free of
    GPS noise and outliers); a transform scores its inliers, ties broken by the residuals."""
    n = len(p_map)
    rng = np.random.default_rng(seed)
    k = _min_sample(mode)
    best_inl, best_score = None, -1.0
    for _ in range(ransac_iters):
        idx = np.sort(rng.choice(n, size=k, replace=False))
        if np.linalg.norm(p_map[idx[-1], dims] - p_map[idx[0], dims]) < 0.1 * extent_map:
            continue
        try:
            T = fit_transform(p_map[idx], p_enu[idx], np.ones(k), mode, up)
        except (np.linalg.LinAlgError, ValueError):
            continue
        u = residuals(T)
        inl = u < inlier_sigmas
        score = inl.sum() - 1e-3 * np.sum(np.minimum(u, inlier_sigmas)) / n
        if score > best_score:
            best_inl, best_score = inl, score
    return best_inl


def _irls(
    p_map: np.ndarray,
    p_enu: np.ndarray,
    sig_h: np.ndarray,
    residuals: Callable[[np.ndarray], np.ndarray],
    inl: np.ndarray,
    mode: Mode,
    up: np.ndarray | None,
    inlier_sigmas: float,
) -> tuple[np.ndarray, np.ndarray]:
    """(transform, inliers): IRLS from the inliers ``inl`` with Cauchy weights on the normalised residual,
    re-classifying the fixes at each step, until the inliers and the transform stop changing (10 steps at most)."""
    k = _min_sample(mode)
    T = fit_transform(p_map[inl], p_enu[inl], 1.0 / sig_h[inl] ** 2, mode, up)
    for _ in range(10):
        u = residuals(T)
        inl_new = u < inlier_sigmas
        if inl_new.sum() < k:
            break
        w = 1.0 / (1.0 + u[inl_new] ** 2) / sig_h[inl_new] ** 2
        T_new = fit_transform(p_map[inl_new], p_enu[inl_new], w, mode, up)
        converged = np.array_equal(inl_new, inl) and np.allclose(T_new, T, atol=1e-9)
        T, inl = T_new, inl_new
        if converged:
            break
    return T, inl
