"""A session's LiDAR map as the stages that cut patches read a semi-dense map: points, and the frames that saw them.

The semi-dense map's points come with observation lists (the camera frames that saw each point) and posed
keyframes; patches are yaw-normalised towards a keypoint's first observer (:mod:`mapkit.places.patches`), the
structure index votes for every frame that observed a matched keypoint (:mod:`mapkit.places.index_structure`)
and the triplets name a patch by its first observer frame (:mod:`mapkit.places.triplets`). A LiDAR map
(``lidar_map/``: voxel centroids with the first and last stamp of the scans that hit them) has no such lists.
Its equivalent, :func:`lidar_observations`:

- the points are the voxel centroids;
- the frames are poses of the session's trajectory (the vehicle's body, not a camera), one every
  ``LIDAR_FRAME_SPACING_M`` of driving; a frame's id is the pose's index in the trajectory, so ids grow with time
  as camera frame ids do, and every frame is posed (a keyframe);
- a frame observed a voxel when it lies within ``LIDAR_OBSERVE_RADIUS_M`` (horizontally) of it and its stamp
  within the time the voxel was seen (from the last frame at or before ``first_ns`` to the first at or after
  ``last_ns``); a voxel that no frame observed so (seen only from farther away) is observed by that first frame.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from mapkit.core.errors import InputWarning
from mapkit.core.runio import config_hash, sha256_file
from mapkit.mapping.lidar_map import load_voxel_stats
from mapkit.mapping.semidense import map_size
from mapkit.mapping.trajectory import Trajectory
from mapkit.mapping.voxel_map import VoxelStats, pack_voxel_keys, packable

#: frames along the trajectory; mapkit choice: a semi-dense map's keyframes come about every metre or two
LIDAR_FRAME_SPACING_M = 2.0
#: a frame observed the voxels this close to it (m, horizontal); mapkit choice: about where a 32-beam scanner's
#: returns from the road and the facades beside it are dense, and a patch's reach (the CNN's cube, 14 m)
LIDAR_OBSERVE_RADIUS_M = 15.0
LIDAR_MAP_FILES = ("points.ply", "voxels.npz")


@dataclass
class LidarObservations:
    """The fields of :class:`~mapkit.mapping.semidense.SemiDenseMap` that patches, the structure index and triplets
    read, made from a LiDAR map (see the module's docstring)."""

    points_world: np.ndarray  # (V, 3) voxel centroids
    obs_indptr: np.ndarray  # (V + 1,) CSR over obs_frame_ids
    obs_frame_ids: np.ndarray  # frame ids (trajectory pose indices), sorted within each voxel
    keyframe_ids: np.ndarray  # (F,) every frame, posed
    keyframe_stamps_ns: np.ndarray  # (F,)
    keyframe_world_from_cam: np.ndarray  # (F, 4, 4) the body's pose (world_from_base)
    frame_ids: np.ndarray | None = None  # every frame is a keyframe: no other frame to time
    frame_stamps_ns: np.ndarray | None = None

    def __len__(self) -> int:
        return int(len(self.points_world))

    def stats(self) -> dict:
        """What :meth:`~mapkit.mapping.semidense.SemiDenseMap.stats` says of a map's size: points (voxels), frames,
        the frames' path and points per 100 m of it, and observations (voxel-frame pairs)."""
        return {**map_size(len(self), self.keyframe_world_from_cam), "observations": int(len(self.obs_frame_ids))}


def lidar_observations(
    stats: VoxelStats,
    trajectory: Trajectory,
    spacing_m: float = LIDAR_FRAME_SPACING_M,
    radius_m: float = LIDAR_OBSERVE_RADIUS_M,
) -> LidarObservations:
    """The LiDAR map ``stats`` with the frames of ``trajectory`` (in the map's frame) that observed each voxel."""
    P = trajectory.world_from_base[:, :3, 3]
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))])
    fidx = np.unique(np.searchsorted(arc, np.arange(0.0, arc[-1] + 1e-9, spacing_m)).clip(0, len(P) - 1))
    fst = trajectory.stamps_ns[fidx]
    n = len(stats.centroid)
    lo = np.clip(np.searchsorted(fst, stats.first_ns, side="right") - 1, 0, len(fidx) - 1)
    hi = np.clip(np.searchsorted(fst, stats.last_ns, side="left"), 0, len(fidx) - 1)
    hits = cKDTree(stats.centroid[:, :2]).query_ball_point(P[fidx, :2], radius_m, return_sorted=False)
    counts = np.array([len(h) for h in hits], np.int64)
    voxel = np.concatenate([np.asarray(h, np.int64) for h in hits]) if counts.sum() else np.zeros(0, np.int64)
    frame = np.repeat(np.arange(len(fidx)), counts)
    inside = (frame >= lo[voxel]) & (frame <= hi[voxel])
    voxel, frame = voxel[inside], frame[inside]
    unseen = np.setdiff1d(np.arange(n), voxel)
    voxel, frame = np.concatenate([voxel, unseen]), np.concatenate([frame, lo[unseen]])
    order = np.lexsort((frame, voxel))
    indptr = np.zeros(n + 1, np.int64)
    np.cumsum(np.bincount(voxel, minlength=n), out=indptr[1:])
    return LidarObservations(
        np.asarray(stats.centroid, np.float64),
        indptr,
        fidx[frame[order]].astype(np.int64),
        fidx.astype(np.int64),
        fst.astype(np.int64),
        trajectory.world_from_base[fidx],
    )


def coarsen(stats: VoxelStats, voxel_m: float) -> VoxelStats:
    """``stats`` merged into voxels of ``voxel_m`` (larger than its own): each coarse voxel's centroid is its fine
    voxels' centroid weighted by their point counts, its count their sum, its intensity their count-weighted mean
    (of those that had one), its first and last stamps the earliest and latest; normals and planarity, which the
    merged covariance would need, are NaN. Coarse voxels are sorted by key as the map's are."""
    if not voxel_m > stats.voxel_size_m:
        raise ValueError(f"coarsen to {voxel_m} m: not larger than the map's {stats.voxel_size_m} m voxels")
    keys = np.floor(stats.centroid / voxel_m).astype(np.int64)
    if packable(keys):  # one int64 per voxel sorts as the rows do
        uniq, inv = np.unique(pack_voxel_keys(keys), return_inverse=True)
    else:
        uniq, inv = np.unique(keys, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    n = len(uniq)
    w = stats.count.astype(np.float64)
    count = np.bincount(inv, w, n)
    centroid = np.stack([np.bincount(inv, w * stats.centroid[:, k], n) for k in range(3)], axis=1) / count[:, None]
    has = np.isfinite(stats.intensity)
    wi = np.bincount(inv, np.where(has, w, 0.0), n)
    with np.errstate(invalid="ignore", divide="ignore"):
        intensity = np.bincount(inv, np.where(has, w * stats.intensity, 0.0), n) / wi
    first = np.full(n, np.iinfo(np.int64).max, np.int64)
    last = np.full(n, np.iinfo(np.int64).min, np.int64)
    np.minimum.at(first, inv, stats.first_ns)
    np.maximum.at(last, inv, stats.last_ns)
    return VoxelStats(
        float(voxel_m),
        centroid,
        count.astype(np.int64),
        np.where(wi > 0, intensity, np.nan),
        np.full((n, 3), np.nan),
        np.full(n, np.nan),
        first,
        last,
    )


def load_lidar_observations(folder: Path, trajectory_dir: Path, voxel_m: float | None = None) -> LidarObservations:
    """The LiDAR map in ``folder`` with its observing frames, from the trajectory in ``trajectory_dir`` (the one the
    map lies on: :meth:`~mapkit.core.workspace.Workspace.map_trajectory`); with ``voxel_m``, its voxels merged into
    coarser ones first (:func:`coarsen`)."""
    stats = load_voxel_stats(folder)
    if voxel_m is not None and voxel_m > stats.voxel_size_m:
        stats = coarsen(stats, voxel_m)
    elif voxel_m is not None:
        warnings.warn(
            f"{folder}: lidar_voxel_m {voxel_m:g} is not above the map's {stats.voxel_size_m:g} m voxels; the map is "
            "used as built",
            InputWarning,
            stacklevel=2,
        )
    return lidar_observations(stats, Trajectory.load(trajectory_dir))


def lidar_map_checksum(folder: Path, trajectory_dir: Path, voxel_m: float | None = None) -> str:
    """sha256 over what :func:`load_lidar_observations` reads (the map's files, the trajectory's) and its rule."""
    return config_hash(
        {
            **{n: sha256_file(folder / n) for n in LIDAR_MAP_FILES},
            "trajectory": {p.name: sha256_file(p) for p in sorted(trajectory_dir.glob("*.npz"))},
            "frames": [LIDAR_FRAME_SPACING_M, LIDAR_OBSERVE_RADIUS_M],
            **({"voxel_m": float(voxel_m)} if voxel_m is not None else {}),
        }
    )


__all__ = [
    "LIDAR_FRAME_SPACING_M",
    "LIDAR_MAP_FILES",
    "LIDAR_OBSERVE_RADIUS_M",
    "LidarObservations",
    "lidar_map_checksum",
    "lidar_observations",
    "load_lidar_observations",
]
