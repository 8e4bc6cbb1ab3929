"""GPS alignment: the similarity that maps a session's trajectory frame into the local ENU frame.

Pure numpy. Fixes are associated to the trajectory by timestamp (poses interpolated, never
extrapolated), then a robust estimate is made in two steps: RANSAC on minimal samples rejects
multipath jumps and outliers, and iteratively reweighted least squares (Cauchy weights scaled by
each fix's reported sigma) refines on the inliers. The default model is gravity-aware: yaw about
the vertical, translation and scale (5 parameters), for trajectories whose z axis is already
vertical (LiDAR odometry started level, INS); ``yaw`` keeps the trajectory's own metric scale
(4 parameters), which is what a build does with LiDAR or INS poses (see ``mapkit.mapping.build``), and
still reports the scale GPS would have chosen. ``sim3`` estimates all 7 parameters (camera-only
reconstructions have an arbitrary orientation); when the drive is too straight for the rotation
about its direction of travel to be observable, it falls back to the gravity-aware model with a
warning, or raises if asked to be strict.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import Literal, Optional

import numpy as np

from mapkit.core.errors import InputError, InputWarning
from mapkit.core.geometry import interpolate_poses, make_sim3, sim3_scale, transform_points, umeyama, yaw_rotation

Mode = Literal["yaw_scale", "sim3", "yaw"]


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
    free_scale: Optional[float] = None  # in ``yaw`` mode: the scale a ``yaw_scale`` fit of the inliers gives

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
            "notes": list(self.notes),
        }


def associate_fixes(
    traj_stamps_ns: np.ndarray,
    world_from_base: np.ndarray,
    fix_stamps_ns: np.ndarray,
    base_from_antenna: Optional[np.ndarray] = None,
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


def fit_transform(src: np.ndarray, dst: np.ndarray, w: np.ndarray | None = None, mode: Mode = "yaw_scale") -> np.ndarray:
    """Weighted least-squares ``dst_from_src``: ``sim3``, or gravity-aware ``yaw_scale`` / ``yaw`` (rigid, 4 DoF)."""
    w = np.ones(len(src)) if w is None else np.asarray(w, np.float64)
    if mode == "sim3":
        return umeyama(src, dst, with_scale=True, weights=w)
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


def align_to_gps(
    p_map: np.ndarray,
    p_enu: np.ndarray,
    sigma_m: Optional[np.ndarray] = None,
    stamps_ns: Optional[np.ndarray] = None,
    mode: Mode = "yaw_scale",
    inlier_sigmas: float = 3.37,
    vertical_sigma_factor: float = 2.0,
    min_inlier_threshold_m: float = 2.0,
    ransac_iters: int = 300,
    min_extent_m: float = 20.0,
    min_straightness_ratio: float = 0.02,
    strict: bool = False,
    seed: int = 0,
    source: str = "gps",
) -> GpsAlignment:
    """Robust ``enu_from_map`` from corresponding antenna positions (map frame) and GPS fixes (ENU).

    ``sigma_m`` is each fix's horizontal standard deviation (NaN or None = unknown, taken as the
    median of the known ones, or 3 m); the vertical sigma is ``vertical_sigma_factor`` times it.
    A fix is an inlier when its normalised residual is below ``inlier_sigmas`` (3.37: the 99%
    bound of a chi-square with 3 degrees of freedom); the horizontal gate is never tighter than
    ``min_inlier_threshold_m``.
    """
    p_map = np.asarray(p_map, np.float64)
    p_enu = np.asarray(p_enu, np.float64)
    n = len(p_map)
    stamps = np.arange(n, dtype=np.int64) if stamps_ns is None else np.asarray(stamps_ns, np.int64)
    notes: list[str] = []
    if n < 3:
        raise InputError(source, f"only {n} GPS fixes overlap the trajectory; at least 3 are needed", field="gps")
    extent, ratio = planarity(p_map[:, :2] if mode != "sim3" else p_map)
    if extent < min_extent_m:
        raise InputError(
            source, f"the trajectory spans {extent:.1f} m where GPS overlaps it; at least {min_extent_m:.0f} m are needed "
            "to observe heading and scale", field="gps",
        )
    if mode == "sim3":
        _, ratio3 = planarity(p_map)
        if ratio3 < min_straightness_ratio:
            msg = (f"the drive is too straight (second/first principal axis {ratio3:.3f} < {min_straightness_ratio}) "
                   "for the rotation about its direction to be observable from GPS")
            if strict:
                raise InputError(source, msg, field="gps")
            warnings.warn(f"{source}: {msg}; falling back to the gravity-aware yaw+scale model", InputWarning, stacklevel=2)
            notes.append(msg + "; fell back to yaw_scale")
            mode = "yaw_scale"
    sig = np.full(n, np.nan) if sigma_m is None else np.asarray(sigma_m, np.float64).copy()
    known = np.isfinite(sig) & (sig > 0)
    sig[~known] = np.median(sig[known]) if known.any() else 3.0
    # a residual is measured in sigmas: horizontal by the fix's sigma (floored so that an
    # over-optimistic receiver cannot reject good fixes), vertical by a multiple of it
    sig_h = np.maximum(sig, min_inlier_threshold_m / inlier_sigmas)
    sig_v = vertical_sigma_factor * sig_h

    def normalised(T: np.ndarray) -> np.ndarray:
        d = transform_points(T, p_map) - p_enu
        return np.sqrt((d[:, 0] ** 2 + d[:, 1] ** 2) / sig_h**2 + d[:, 2] ** 2 / sig_v**2)

    # RANSAC: minimal samples, spread apart in time so the sample spans the trajectory
    rng = np.random.default_rng(seed)
    k = _min_sample(mode)
    best_inl, best_score = None, -1.0
    for _ in range(ransac_iters):
        idx = np.sort(rng.choice(n, size=k, replace=False))
        if np.linalg.norm(p_map[idx[-1], :2] - p_map[idx[0], :2]) < 0.1 * extent:
            continue
        try:
            T = fit_transform(p_map[idx], p_enu[idx], np.ones(k), mode)
        except (np.linalg.LinAlgError, ValueError):
            continue
        u = normalised(T)
        inl = u < inlier_sigmas
        score = inl.sum() - 1e-3 * np.sum(np.minimum(u, inlier_sigmas)) / n
        if score > best_score:
            best_inl, best_score = inl, score
    if best_inl is None or best_inl.sum() < k:
        raise InputError(source, "no consistent subset of GPS fixes was found", field="gps")

    # IRLS on the inliers with Cauchy weights on the normalised residual, then re-classify
    inl = best_inl
    T = fit_transform(p_map[inl], p_enu[inl], 1.0 / sig_h[inl] ** 2, mode)
    for _ in range(10):
        u = normalised(T)
        inl_new = u < inlier_sigmas
        if inl_new.sum() < k:
            break
        w = 1.0 / (1.0 + u[inl_new] ** 2) / sig_h[inl_new] ** 2
        T_new = fit_transform(p_map[inl_new], p_enu[inl_new], w, mode)
        converged = np.array_equal(inl_new, inl) and np.allclose(T_new, T, atol=1e-9)
        T, inl = T_new, inl_new
        if converged:
            break
    u = normalised(T)
    res = np.linalg.norm(transform_points(T, p_map) - p_enu, axis=1)
    rejected = [
        {"index": int(i), "stamp_ns": int(stamps[i]), "residual_m": float(res[i]), "residual_sigmas": float(u[i]),
         "reason": "residual above threshold (outlier or multipath jump)"}
        for i in np.nonzero(~inl)[0]
    ]
    free_scale = None
    if mode == "yaw":  # a check on the odometry's scale, not applied
        free_scale = sim3_scale(fit_transform(p_map[inl], p_enu[inl], 1.0 / sig_h[inl] ** 2, "yaw_scale"))
    return GpsAlignment(T, mode, inl, res, stamps, rejected, notes, free_scale)
