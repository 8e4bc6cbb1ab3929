"""Sessions in the workspace frame, cut into submaps of driving, and the submap pairs to register.

A session's map is cut by distance driven (each point goes with the keyframe that made it), so a
submap is a stretch of road and its correction can be blended with its neighbours' along the
drive (:mod:`mapkit.multisession.corrections`). Pairs are the submaps of different sessions whose
trajectory centres are close (:func:`candidate_pairs`).

A session's LiDAR map (``lidar_map/``, where the build made one) is cut by the same submaps
(:class:`LidarSubmaps`): each voxel goes with the distance driven at the pose nearest to it among
those of the time it was seen (:func:`voxel_arc_m`), and moves with the correction there.
"""

from __future__ import annotations

import json
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from mapkit.core.errors import InputWarning
from mapkit.core.geodesy import LocalFrame
from mapkit.core.runio import DONE_MARKER, config_hash, marker_hash
from mapkit.core.workspace import SessionDirs
from mapkit.mapping.lidar_map import load_voxel_stats
from mapkit.mapping.semidense import SemiDenseMap
from mapkit.mapping.trajectory import Trajectory
from mapkit.mapping.voxel_map import VoxelStats


@dataclass
class LidarSubmaps:
    """A session's LiDAR map in the workspace frame (voxel centroids and normals moved by the session's frame change),
    each voxel with the distance driven it is corrected at and, once cut, its submap."""

    stats: VoxelStats
    arc_m: np.ndarray  # (V,) distance driven at the voxel's pose (voxel_arc_m)
    map_dir: Path
    map_hash: str  # of the LiDAR map's build and its files: the key of registrations made on it
    submap_of_point: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    @property
    def points(self) -> np.ndarray:
        return self.stats.centroid


@dataclass
class SessionData:
    """One session in the workspace frame: trajectory, map, and the cut into submaps."""

    name: str
    stamps_ns: np.ndarray
    poses: np.ndarray  # (T, 4, 4) enu_from_base
    arc_m: np.ndarray  # (T,) distance driven at each pose
    points: np.ndarray  # (N, 3) ENU
    point_arc_m: np.ndarray  # (N,) distance driven when the point's source keyframe was taken
    map_dir: Path
    map_hash: str
    # the cut into submaps, set by cut_submaps (empty until then); (N,) int
    submap_of_point: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    # (S, 3) trajectory position at each submap's middle
    centres: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    # (S-1, 3) positions where consecutive submaps meet
    boundaries: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    # (S, 3) unit driving direction at each centre
    directions: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    # (S+1,) distance driven where submaps start and end
    submap_edges_m: np.ndarray = field(default_factory=lambda: np.zeros(0))
    smap: SemiDenseMap | None = field(default=None, repr=False)  # the map as built (session frame)
    ws_from_session: np.ndarray = field(default_factory=lambda: np.eye(4))
    fused: bool = False  # the trajectory is the factor graph's (georef.fuse), not the rigid GPS fit of kiss-icp's
    lidar: LidarSubmaps | None = None  # the session's LiDAR map, where the build made one

    @property
    def n_submaps(self) -> int:
        return len(self.centres)


def _arc_length(positions: np.ndarray) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(positions, axis=0), axis=1))])


def position_at_arc(arc: np.ndarray, positions: np.ndarray, s: np.ndarray) -> np.ndarray:
    return np.stack([np.interp(s, arc, positions[:, k]) for k in range(3)], axis=-1)


def load_session(sdir: SessionDirs | Path, ws_frame: LocalFrame, length_m: float) -> SessionData | None:
    """A built session (its folders, or their root) in the workspace frame, or None (with a
    warning) if it cannot be aligned."""

    dirs = sdir if isinstance(sdir, SessionDirs) else SessionDirs(Path(sdir))
    ga_path = dirs.gps_alignment
    if not dirs.has("georef") or not dirs.has("map"):
        stages = json.loads(dirs.metrics.read_text()).get("stages", {}) if dirs.metrics.is_file() else {}
        skipped = (stages.get("semidense") or {}).get("skipped")
        what = (
            f"has no semi-dense map (skipped at build: {skipped})"
            if skipped
            else "is not fully built (georef and map stages)"
        )
        warnings.warn(f"{dirs.root}: session {what}; skipped", InputWarning, stacklevel=2)
        return None
    ga = json.loads(ga_path.read_text())
    if not ga.get("georeferenced"):
        warnings.warn(
            f"{ga_path}: session is not georeferenced ({ga.get('reason', 'no reason given')}); skipped",
            InputWarning,
            stacklevel=2,
        )
        return None
    traj = Trajectory.load(dirs.enu_trajectory)
    smap = SemiDenseMap.load(dirs.map)
    ws_from_session = LocalFrame.from_dict(ga).to_frame(ws_frame)
    poses = ws_from_session @ traj.world_from_base
    pts = smap.points_world @ ws_from_session[:3, :3].T + ws_from_session[:3, 3]
    arc = _arc_length(poses[:, :3, 3])
    kf_stamp = dict(zip(smap.keyframe_ids.tolist(), smap.keyframe_stamps_ns.tolist(), strict=True))
    src_stamp = np.array([kf_stamp[int(k)] for k in smap.source_keyframe], np.float64) if len(pts) else np.zeros(0)
    point_arc = np.interp(src_stamp, traj.stamps_ns.astype(np.float64), arc)
    done = json.loads((dirs.map / DONE_MARKER).read_text())
    s = SessionData(
        dirs.name,
        traj.stamps_ns,
        poses,
        arc,
        pts,
        point_arc,
        dirs.map,
        marker_hash(done) or "",  # of a migrated marker, the hash the cached registrations know its map by
        smap=smap,
        ws_from_session=ws_from_session,
        fused=dirs.fused_trajectory.is_dir(),
    )
    if dirs.has("lidar_map"):
        s.lidar = _load_lidar(dirs, s, traj.stamps_ns)
    cut_submaps(s, length_m)
    return s


def _load_lidar(dirs: SessionDirs, s: SessionData, stamps_ns: np.ndarray) -> LidarSubmaps:
    """Session ``s``'s LiDAR map (``dirs.lidar_map``, in the session's frame like its trajectory) in the workspace
    frame, each voxel with its distance driven (:func:`voxel_arc_m`)."""
    stats = load_voxel_stats(dirs.lidar_map)
    T = s.ws_from_session
    centroid = stats.centroid @ T[:3, :3].T + T[:3, 3]
    moved = VoxelStats(
        stats.voxel_size_m,
        centroid,
        stats.count,
        stats.intensity,
        rotate_normals(stats.normal, T[:3, :3]),
        stats.planarity,
        stats.first_ns,
        stats.last_ns,
    )
    done = json.loads((dirs.lidar_map / DONE_MARKER).read_text())
    key = config_hash([marker_hash(done) or "", done.get("outputs")])
    arc = voxel_arc_m(centroid, stats.first_ns, stats.last_ns, s.poses[:, :3, 3], stamps_ns, s.arc_m)
    return LidarSubmaps(moved, arc, dirs.lidar_map, key)


def rotate_normals(normals: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Unit normals (V, 3) rotated by ``R`` (3, 3), turned to point up (+z) as the voxel map keeps them; NaN stays
    NaN."""
    n = np.asarray(normals, np.float64) @ np.asarray(R, np.float64).T
    return np.where(n[:, 2:3] < 0, -n, n)


def voxel_arc_m(
    centroids: np.ndarray,
    first_ns: np.ndarray,
    last_ns: np.ndarray,
    positions: np.ndarray,
    stamps_ns: np.ndarray,
    arc_m: np.ndarray,
) -> np.ndarray:
    """The distance driven (V,) a voxel is corrected at: the trajectory's at the pose nearest to the voxel, its time
    clamped into the span the voxel was seen (``first_ns`` .. ``last_ns``). A semi-dense point goes with the keyframe
    that made it; a voxel is seen by many scans, up to 100 m away, and the pose beside it is the one whose
    correction fits it (the clamp keeps a voxel that a later pass drove past unseen with the pass that saw it)."""
    if not len(centroids):
        return np.zeros(0)
    _, k = cKDTree(positions).query(centroids)
    t = np.clip(stamps_ns[k], first_ns, last_ns).astype(np.float64)
    return np.interp(t, stamps_ns.astype(np.float64), arc_m)


def cut_submaps(s: SessionData, length_m: float) -> None:
    """Submap k holds the points whose source keyframe was taken in [k L, (k+1) L) of driving;
    the last piece joins the one before it when it is shorter than half a submap."""
    total = float(s.arc_m[-1])
    n = max(1, int(np.floor(total / length_m)))
    if total - n * length_m >= 0.5 * length_m:
        n += 1
    edges = (
        np.linspace(0.0, total, n + 1) if n * length_m > total else np.concatenate([np.arange(n) * length_m, [total]])
    )
    s.submap_of_point = np.clip(np.searchsorted(edges, s.point_arc_m, side="right") - 1, 0, n - 1)
    if s.lidar is not None:
        s.lidar.submap_of_point = np.clip(np.searchsorted(edges, s.lidar.arc_m, side="right") - 1, 0, n - 1)
    mids = 0.5 * (edges[:-1] + edges[1:])
    P = s.poses[:, :3, 3]
    s.centres = position_at_arc(s.arc_m, P, mids)
    s.boundaries = position_at_arc(s.arc_m, P, edges[1:-1])
    ahead = position_at_arc(s.arc_m, P, np.minimum(mids + 1.0, total))
    behind = position_at_arc(s.arc_m, P, np.maximum(mids - 1.0, 0.0))
    d = ahead - behind
    s.directions = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
    s.submap_edges_m = edges


# --- submap pairs --------------------------------------------------------------------------------


def candidate_pairs(sessions: list[SessionData], radius_m: float) -> list[tuple[int, int, int, int]]:
    """(session a, submap i, session b, submap j) with a < b whose centres are within ``radius_m``.

    One kd-tree over all submap centres: the work grows with the number of overlapping pairs, not
    with the square of the number of sessions.
    """
    if not sessions:
        return []
    owner = np.concatenate([np.full(s.n_submaps, k) for k, s in enumerate(sessions)])
    index = np.concatenate([np.arange(s.n_submaps) for s in sessions])
    centres = np.concatenate([s.centres for s in sessions])
    pairs = cKDTree(centres[:, :2]).query_pairs(radius_m, output_type="ndarray")
    out = []
    for p, q in pairs:
        if owner[p] == owner[q]:
            continue
        if owner[p] > owner[q]:
            p, q = q, p
        out.append((int(owner[p]), int(index[p]), int(owner[q]), int(index[q])))
    return sorted(out)


def submap_points(s: SessionData | SubmapClouds, idx: int, neighbours: int = 0) -> np.ndarray:
    """Points of submap ``idx`` and of ``neighbours`` submaps on each side of it."""
    lo, hi = idx - neighbours, idx + neighbours
    return s.points[(s.submap_of_point >= lo) & (s.submap_of_point <= hi)]


@dataclass
class SubmapClouds:
    """What registering a session's submaps needs (:func:`~mapkit.multisession.registration.register_pair`
    reads these fields only): shipped to workers once, without the rest of the session."""

    name: str
    points: np.ndarray
    submap_of_point: np.ndarray
    centres: np.ndarray
