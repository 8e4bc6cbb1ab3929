"""The one ICP loop of mapkit: coarse-to-fine point-to-plane ICP on open3d, whatever feeds it.

:func:`icp_coarse_to_fine` runs open3d's point-to-plane ICP over a list of levels (voxel size,
correspondence distance), each from the transform of the one before; the caller's ``level``
callback gives each level's clouds (it downsamples, crops and estimates normals as suits it).
Its users: submap pairs of ``mapkit align`` (:func:`mapkit.multisession.registration.register_clouds`),
triplet cells (:func:`mapkit.places.triplets.register_cell`) and a session's loop closures
(:func:`mapkit.mapping.loop_closure.verify_loop`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

#: open3d's own ICP stopping criterion (relative change of fitness and RMSE between iterations)
OPEN3D_RELATIVE_CHANGE = 1e-6


@dataclass(frozen=True)
class IcpClouds:
    """One ICP level: source and target points (relative to a centre the caller chose, so that
    rotations pivot there), and the target's normals (point-to-plane)."""

    source: np.ndarray  # (N, 3)
    target: np.ndarray  # (M, 3)
    target_normals: np.ndarray  # (M, 3)


def icp_coarse_to_fine(
    level: Callable[[float], IcpClouds | None],
    voxel_sizes_m: Sequence[float],
    max_correspondence_m: Sequence[float],
    max_iterations: int,
    relative_change: float = OPEN3D_RELATIVE_CHANGE,
    initial: np.ndarray | None = None,
) -> tuple[np.ndarray, IcpClouds | None]:
    """Point-to-plane ICP over the levels (voxel size, correspondence distance), each starting from
    the transform of the one before (the first from ``initial``, default the identity).
    ``level(voxel)`` gives a level's clouds, or None when there are too few points: ICP stops
    there. Returns the transform (target from source, in the clouds' coordinates) and the last
    level's clouds (None when it stopped early). ``relative_change``: a level stops when fitness
    and RMSE change by less than this between iterations (open3d's criteria)."""
    import open3d as o3d

    reg, vec = o3d.pipelines.registration, o3d.utility.Vector3dVector
    criteria = reg.ICPConvergenceCriteria(relative_change, relative_change, max_iterations)
    T = np.eye(4) if initial is None else np.asarray(initial, np.float64)
    clouds = None
    for voxel, max_d in zip(voxel_sizes_m, max_correspondence_m, strict=True):
        clouds = level(voxel)
        if clouds is None:
            break
        src = o3d.geometry.PointCloud(vec(clouds.source))
        tgt = o3d.geometry.PointCloud(vec(clouds.target))
        tgt.normals = vec(clouds.target_normals)
        with open3d_one_thread():  # the same pair gives the same transform to the bit on every run
            T = np.asarray(
                reg.registration_icp(
                    src, tgt, max_d, T, reg.TransformationEstimationPointToPlane(), criteria
                ).transformation
            )
    return T, clouds


def point_to_plane(
    moved: np.ndarray, target: np.ndarray, target_normals: np.ndarray, max_distance: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """How registered points sit on a target's surfaces: ``hit`` (N,) whether a target point lies within
    ``max_distance`` of each of ``moved`` (source points already transformed), ``j`` the nearest target
    point of each hit, and the hits' signed point-to-plane residuals along that point's normal. What ICP's
    acceptance gates score (:func:`mapkit.multisession.registration.evaluate_alignment`,
    :func:`mapkit.mapping.loop_closure.support`)."""
    d, j = cKDTree(target).query(moved, distance_upper_bound=max_distance)
    hit = np.isfinite(d)
    j = j[hit]
    return hit, j, np.einsum("ij,ij->i", moved[hit] - target[j], target_normals[j])


@contextmanager
def open3d_one_thread() -> Iterator[None]:
    """open3d (TBB) on one thread for a while: its ICP reduces over threads in a varying order, so
    with more than one thread two runs of the same pair differ in the last bits (measured, 0.20)."""
    import open3d as o3d

    util = o3d.utility
    if not hasattr(util, "set_max_threads"):  # open3d < 0.20: no control; workers still run one per core
        yield
        return
    before = util.get_max_threads()
    util.set_max_threads(1)
    try:
        yield
    finally:
        util.set_max_threads(before)
