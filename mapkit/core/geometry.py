"""Rigid and similarity transforms, rotations, pose interpolation and time association.

Pure numpy/scipy: nothing here does I/O. Quaternions are scalar-first (``wxyz``) at every public
boundary of mapkit; scipy's scalar-last convention stays inside this module. Poses are 4x4
matrices named ``a_from_b``; stacks of them have shape (N, 4, 4).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation, Slerp

# --- quaternions and rotations ------------------------------------------------------------------


def quat_wxyz_to_matrix(q_wxyz: np.ndarray) -> np.ndarray:
    q = np.asarray(q_wxyz, dtype=np.float64)
    return Rotation.from_quat(q[..., [1, 2, 3, 0]]).as_matrix()


def matrix_to_quat_wxyz(R: np.ndarray) -> np.ndarray:
    """Rotation matrix (or stack) to unit quaternion(s), sign fixed so that w >= 0."""
    q = Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_quat()[..., [3, 0, 1, 2]]
    return np.where(q[..., :1] < 0, -q, q)


def rotation_angle_rad(R: np.ndarray) -> np.ndarray:
    """Angle of rotation(s), robust near 0 and pi (via the quaternion, not arccos of the trace)."""
    return Rotation.from_matrix(np.asarray(R, dtype=np.float64)).magnitude()


def pose_difference(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """(metres between the positions, degrees between the rotations) of two 4x4 poses."""
    m = float(np.linalg.norm(a[:3, 3] - b[:3, 3]))
    return m, float(np.degrees(rotation_angle_rad(a[:3, :3].T @ b[:3, :3])))


def yaw_rotation(yaw_rad: float | np.ndarray) -> np.ndarray:
    """Rotation(s) about +z by ``yaw_rad``."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    z, o = np.zeros_like(c), np.ones_like(c)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def average_rotations(R: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Chordal L2 mean of rotations (Markley's quaternion average; sign-consistent by design)."""
    return Rotation.from_matrix(np.asarray(R, dtype=np.float64)).mean(weights=weights).as_matrix()


# --- SE(3) ----------------------------------------------------------------------------------------


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix [v]x of a 3-vector, (3, 3), or of each of a stack of them, (..., 3) -> (..., 3, 3):
    [v]x w = v x w."""
    v = np.asarray(v, dtype=np.float64)
    S = np.zeros(v.shape + (3,))
    S[..., 0, 1], S[..., 0, 2], S[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    S[..., 1, 0], S[..., 2, 0], S[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    return S


def make_pose(R: ArrayLike, t: ArrayLike) -> np.ndarray:
    """Stack rotation(s) (..., 3, 3) and translation(s) (..., 3) into homogeneous (..., 4, 4)."""
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    T = np.zeros(R.shape[:-2] + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def pose_from_quat_wxyz(t: np.ndarray, q_wxyz: np.ndarray) -> np.ndarray:
    return make_pose(quat_wxyz_to_matrix(q_wxyz), t)


def invert_pose(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transform(s) without a general matrix inverse."""
    T = np.asarray(T, dtype=np.float64)
    R = T[..., :3, :3]
    Rt = np.swapaxes(R, -1, -2)
    return make_pose(Rt, -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3]))


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply one 4x4 (similarity or rigid) transform to (N, 3) points."""
    T = np.asarray(T)
    return points @ T[:3, :3].T + T[:3, 3]


def is_rotation(R: np.ndarray, atol: float = 1e-6) -> bool:
    R = np.asarray(R, dtype=np.float64)
    eye = np.broadcast_to(np.eye(3), R.shape)
    return bool(
        np.allclose(np.swapaxes(R, -1, -2) @ R, eye, atol=atol) and np.allclose(np.linalg.det(R), 1.0, atol=atol)
    )


# --- Sim(3) ---------------------------------------------------------------------------------------


def make_sim3(scale: float, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    S = make_pose(R, t)
    S[:3, :3] *= scale
    return S


def sim3_scale(S: np.ndarray) -> float:
    return float(np.cbrt(np.linalg.det(np.asarray(S)[:3, :3])))


def transform_poses(S: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """(N, 4, 4) rigid poses moved by a similarity ``S``: rotated, and their positions scaled and
    translated, so that rotations stay rotations (the scale goes into positions only)."""
    S = np.asarray(S)
    out = np.array(poses, dtype=np.float64, copy=True)
    out[:, :3, :3] = (S[:3, :3] / sim3_scale(S)) @ out[:, :3, :3]
    out[:, :3, 3] = transform_points(S, out[:, :3, 3])
    return out


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True, weights: np.ndarray | None = None) -> np.ndarray:
    """Least-squares similarity (or rigid) transform ``dst_from_src`` (Umeyama 1991, eqs. 34-43).

    ``src`` and ``dst`` are corresponding (N, 3) points, N >= 3 and not collinear.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or src.shape[0] < 3:
        raise ValueError(f"umeyama needs two (N>=3, 3) arrays of equal shape, got {src.shape} and {dst.shape}")
    w = np.ones(len(src)) if weights is None else np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    mu_s = w @ src
    mu_d = w @ dst
    xs = src - mu_s
    xd = dst - mu_d
    cov = (xd * w[:, None]).T @ xs
    U, d, Vt = np.linalg.svd(cov)
    Sgn = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        Sgn[2, 2] = -1.0
    R = U @ Sgn @ Vt
    var_s = float(w @ np.sum(xs * xs, axis=1))
    scale = float(np.trace(np.diag(d) @ Sgn) / var_s) if with_scale else 1.0
    t = mu_d - scale * R @ mu_s
    return make_sim3(scale, R, t)


# --- time -----------------------------------------------------------------------------------------


def associate(stamps_a_ns: np.ndarray, stamps_b_ns: np.ndarray, max_dt_ns: int) -> tuple[np.ndarray, np.ndarray]:
    """Nearest-timestamp association, one-to-one, of two sorted stamp arrays.

    Returns index arrays (ia, ib) of the pairs whose time difference is at most ``max_dt_ns``.
    """
    a = np.asarray(stamps_a_ns, dtype=np.int64)
    b = np.asarray(stamps_b_ns, dtype=np.int64)
    if len(a) == 0 or len(b) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    j = np.clip(np.searchsorted(b, a), 1, len(b) - 1) if len(b) > 1 else np.zeros(len(a), np.int64)
    if len(b) > 1:
        left_closer = np.abs(a - b[j - 1]) <= np.abs(b[j] - a)
        j = np.where(left_closer, j - 1, j)
    dt = np.abs(a - b[j])
    ok = dt <= max_dt_ns
    ia, ib, dt = np.nonzero(ok)[0], j[ok], dt[ok]
    # one-to-one: where several a map to one b, keep the closest
    order = np.lexsort((dt, ib))
    ib_sorted = ib[order]
    first = np.ones(len(order), bool)
    first[1:] = ib_sorted[1:] != ib_sorted[:-1]
    keep = np.sort(order[first])
    return ia[keep], ib[keep]


def interpolate_poses(stamps_ns: np.ndarray, poses: np.ndarray, query_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Poses at ``query_ns`` by linear interpolation of translation and slerp of rotation.

    Never extrapolates: returns (poses (M, 4, 4) for the valid queries, mask (len(query_ns),) of
    which queries fell inside [stamps_ns[0], stamps_ns[-1]]). ``stamps_ns`` must increase.
    """
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    query = np.asarray(query_ns, dtype=np.int64)
    poses = np.asarray(poses, dtype=np.float64)
    if len(stamps) < 2:
        mask = np.isin(query, stamps)
        return np.repeat(poses[:1], int(mask.sum()), axis=0), mask
    if np.any(np.diff(stamps) <= 0):
        raise ValueError("interpolate_poses needs strictly increasing stamps")
    mask = (query >= stamps[0]) & (query <= stamps[-1])
    q = query[mask]
    # times relative to the first stamp, in seconds as float64: ns resolution is kept over days
    t0 = stamps[0]
    ts = (stamps - t0).astype(np.float64) * 1e-9
    tq = (q - t0).astype(np.float64) * 1e-9
    slerp = Slerp(ts, Rotation.from_matrix(poses[:, :3, :3]))
    R = slerp(tq).as_matrix()
    t = np.stack([np.interp(tq, ts, poses[:, k, 3]) for k in range(3)], axis=-1)
    return make_pose(R, t), mask
