"""Submap corrections blended along a session: each point and pose moves by the interpolation,
by distance driven, of its two neighbouring submaps' corrections (slerp for the rotation), so a
session's map does not tear where submaps meet. A LiDAR map's voxels move the same way, each at
its own distance driven (:func:`~mapkit.multisession.submaps.voxel_arc_m`), their normals turned
by the same rotation.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from mapkit.mapping.voxel_map import VoxelStats
from mapkit.multisession.submaps import LidarSubmaps, SessionData, position_at_arc, rotate_normals


def correction_at(
    s: SessionData, x_session: np.ndarray, arc_m: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rotation (M, 3, 3), centre (M, 3) and translation (M, 3) of the correction at ``arc_m``,
    blended between the submaps' corrections by distance driven (slerp / linear)."""
    edges = s.submap_edges_m
    mids = 0.5 * (edges[:-1] + edges[1:])
    arc_m = np.clip(arc_m, mids[0], mids[-1])
    rots = Rotation.from_rotvec(x_session[:, :3])
    if len(mids) == 1:
        R = np.repeat(rots.as_matrix(), len(arc_m), axis=0)
        return R, np.repeat(s.centres, len(arc_m), axis=0), np.repeat(x_session[:, 3:], len(arc_m), axis=0)
    R = Slerp(mids, rots)(arc_m).as_matrix()
    # the displacement field is blended, not (c, t) separately: a point at arc s moves by the
    # interpolation of what its two neighbouring submaps' corrections do to it
    c = position_at_arc(mids, s.centres, arc_m)
    k = np.clip(np.searchsorted(mids, arc_m, side="right") - 1, 0, len(mids) - 2)
    w = ((arc_m - mids[k]) / (mids[k + 1] - mids[k]))[:, None]
    disp_k = _disp(x_session[k], s.centres[k], c)
    disp_k1 = _disp(x_session[k + 1], s.centres[k + 1], c)
    t = (1 - w) * disp_k + w * disp_k1  # displacement of the blended centre itself
    return R, c, t


def _disp(x: np.ndarray, centre: np.ndarray, p: np.ndarray) -> np.ndarray:
    R = Rotation.from_rotvec(x[:, :3]).as_matrix()
    return np.einsum("mij,mj->mi", R, p - centre) + centre + x[:, 3:] - p


def apply_correction_points(s: SessionData, x_session: np.ndarray, points: np.ndarray, arc_m: np.ndarray) -> np.ndarray:
    R, c, t = correction_at(s, x_session, arc_m)
    return np.einsum("mij,mj->mi", R, points - c) + c + t


def apply_correction_poses(s: SessionData, x_session: np.ndarray) -> np.ndarray:
    R, c, t = correction_at(s, x_session, s.arc_m)
    out = s.poses.copy()
    out[:, :3, :3] = R @ s.poses[:, :3, :3]
    out[:, :3, 3] = np.einsum("mij,mj->mi", R, s.poses[:, :3, 3] - c) + c + t
    return out


def apply_correction_voxels(s: SessionData, x_session: np.ndarray, lidar: LidarSubmaps) -> VoxelStats:
    """Session ``s``'s LiDAR map under its submaps' corrections: centroids moved, normals rotated (still +z up),
    every other statistic as built."""
    st = lidar.stats
    # a voxel's distance driven is a pose's or a scan's (voxel_arc_m): the correction once per distinct one (a few
    # thousand slerps instead of one per voxel), the same figures handed to every voxel that shares it
    arcs, at = np.unique(lidar.arc_m, return_inverse=True)
    R, c, t = (v[at] for v in correction_at(s, x_session, arcs))
    centroid = np.einsum("mij,mj->mi", R, st.centroid - c) + c + t
    normal = rotate_normals(np.einsum("mij,mj->mi", R, st.normal), np.eye(3))
    return VoxelStats(st.voxel_size_m, centroid, st.count, st.intensity, normal, st.planarity, st.first_ns, st.last_ns)
