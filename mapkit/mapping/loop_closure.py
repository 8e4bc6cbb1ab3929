"""Loop closures of one session: where the drive comes back to a place, proposed by position and verified by ICP.

- Proposal (:func:`propose_loops`): keyframe pairs (a before b) whose horizontal positions in an
  estimate of the drive lie within ``loop_radius_m`` of each other, plus ``loop_proposal_sigmas``
  of the odometry model's horizontal drift over the distance driven between them, while that
  distance is above ``loop_min_travel_m`` (neighbours on one pass are not loops). Horizontal only:
  the odometry's height drift is one of the things a loop corrects, so it must not hide the
  revisit. ``mapkit build`` proposes on the fused trajectory without loops, not on the rigid GPS
  fit of the odometry: on a synthetic loop drive kiss-icp slipped 6.6 m while starting from rest,
  which left the rigid fit 8.2 m off where the drive came back and the fused one 1.4-2.3 m. Nearest first, at most one
  pair per ``loop_min_separation_m`` of route on each pass (a pair within that of a nearer one's first or second
  keyframe is left out).
- Local maps (:func:`read_scans`, :func:`local_map`): a keyframe's scan and ``loop_local_scans``
  on each side, deskewed as kiss-icp did (each point placed at its own firing time, the trajectory
  interpolated between the sweep's start and its end, whose pose kiss-icp reports), in the
  keyframe's base frame, cropped to ``loop_local_radius_m``. ``mapkit build`` places them with the
  fused trajectory too: where kiss-icp slipped its own poses smear a local map (ICP's edge was
  then 1.5 deg off the truth, against 0.3 deg placed with the fused poses).
- Verification (:func:`verify_loop`): open3d's point-to-plane ICP of b's local map onto a's, coarse
  to fine (``loop_icp_*``), from the estimate's relative pose. Accepted only when the maps overlap
  (fitness), fit (point-to-plane RMSE), hold every direction of translation (the smallest
  eigenvalue of the point-to-plane Hessian's translation block, rotation marginalised, per
  correspondence: a street of flat facades holds nothing along itself), and ICP moved the estimate
  by a plausible amount. Every rejection says which gate and by how much (:class:`LoopCheck`).
- The accepted edge's covariance is its support's: the point-to-plane RMSE squared times the
  inverse Hessian of the correspondences (rotation, translation; base b's frame), plus a floor
  (``loop_floor_*``): each local map is placed by an estimate of the trajectory, whose errors over
  a second no amount of support removes.

The edges go to :func:`mapkit.mapping.factor_graph.fuse_session` as robust between factors.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from enum import Enum

import numpy as np
from scipy.spatial import cKDTree

from mapkit.core.errors import InputWarning
from mapkit.core.geometry import interpolate_poses, invert_pose, rotation_angle_rad, transform_points
from mapkit.core.types import LidarScan
from mapkit.mapping.factor_graph import FactorGraphConfig, LoopClosures, LoopEdge
from mapkit.mapping.icp import IcpClouds, icp_coarse_to_fine, open3d_one_thread, point_to_plane

#: a scan's pose is the odometry's within this of the sweep's last point (kiss-icp's stamp) or of its header stamp
SCAN_POSE_TOLERANCE_NS = 1_000_000


class LoopReason(Enum):
    """The gate that decided a loop candidate (its value is the key the stats count rejections by)."""

    ACCEPTED = "accepted"
    SCANS_MISSING = "scans missing"
    TOO_FEW_POINTS = "too few points"
    FITNESS = "fitness"
    RMSE = "RMSE"
    DEGENERATE = "degenerate"
    CORRECTION = "correction"
    ROTATION = "rotation"


@dataclass(frozen=True)
class LoopCandidate:
    """Two keyframes (odometry pose indices, ``a`` the earlier) proposed as one place."""

    a: int
    b: int
    distance_m: float  # horizontal, in the estimate the proposal was made on
    travel_m: float  # driven from a to b


@dataclass
class LoopCheck:
    """A candidate after verification: the verdict, the relative pose ICP found (``a_from_b``, base frames) and its
    support."""

    candidate: LoopCandidate
    reason: LoopReason
    detail: str = ""
    a_from_b: np.ndarray | None = None
    covariance: np.ndarray | None = None  # 6x6, gtsam's Pose3 tangent (rotation, translation) in base b's frame
    fitness: float = 0.0
    rmse_m: float = float("nan")
    constraint: float = 0.0  # smallest eigenvalue of the translation Hessian per correspondence
    correction_m: float = 0.0
    correction_deg: float = 0.0
    seconds: float = 0.0

    @property
    def accepted(self) -> bool:
        return self.reason is LoopReason.ACCEPTED

    @property
    def text(self) -> str:
        return f"{self.reason.value} ({self.detail})" if self.detail else self.reason.value

    def edge(self, stamps_ns: np.ndarray) -> LoopEdge:
        """The factor graph's edge of an accepted check."""
        assert self.a_from_b is not None and self.covariance is not None, "an accepted check has a pose"
        c = self.candidate
        return LoopEdge(int(stamps_ns[c.a]), int(stamps_ns[c.b]), self.a_from_b, self.covariance)

    def to_dict(self, stamps_ns: np.ndarray) -> dict:
        c = self.candidate
        return {
            "stamps_ns": [int(stamps_ns[c.a]), int(stamps_ns[c.b])],
            "distance_m": c.distance_m,
            "travel_m": c.travel_m,
            "accepted": self.accepted,
            "reason": self.text,
            "fitness": self.fitness,
            "rmse_m": self.rmse_m,
            "constraint": self.constraint,
            "correction_m": self.correction_m,
            "correction_deg": self.correction_deg,
        }


def loop_closures(checks: list[LoopCheck], stamps_ns: np.ndarray) -> LoopClosures:
    """What the factor graph takes: the accepted checks as edges, the others' reasons."""
    edges = [c.edge(stamps_ns) for c in checks if c.accepted]
    return LoopClosures(edges, [c.reason.value for c in checks if not c.accepted])


# --- proposal ----------------------------------------------------------------------------------------


def horizontal_drift_sigma_m(travel_m: np.ndarray, cfg: FactorGraphConfig) -> np.ndarray:
    """The odometry model's horizontal position sigma after ``travel_m``: its translation walk (``w sqrt(d)``) and its
    heading walk carried along the path (a heading error growing as ``w sqrt(s)`` moves the end by
    ``w d^1.5 / sqrt(3)``)."""
    d = np.asarray(travel_m, np.float64)
    wt = float(np.hypot(*cfg.odom_translation_walk_m_per_sqrt_m[:2]))
    wy = float(cfg.odom_rotation_walk_rad_per_sqrt_m[2])
    return np.hypot(wt * np.sqrt(d), wy * d**1.5 / np.sqrt(3.0))


def propose_loops(world_from_base: np.ndarray, keyframes: np.ndarray, cfg: FactorGraphConfig) -> list[LoopCandidate]:
    """Keyframe pairs that may be one place seen twice (module notes), nearest first; ``world_from_base`` is any
    estimate of the drive's poses (all of them: the distance driven is summed over every pose)."""
    p = np.asarray(world_from_base, np.float64)[:, :3, 3]
    travel = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
    kf = np.asarray(keyframes, np.int64)
    reach = cfg.loop_radius_m + cfg.loop_proposal_sigmas * horizontal_drift_sigma_m(travel[-1], cfg)
    pairs = cKDTree(p[kf, :2]).query_pairs(float(reach), output_type="ndarray")
    if not len(pairs):
        return []
    a, b = kf[pairs.min(axis=1)], kf[pairs.max(axis=1)]
    dist = np.linalg.norm(p[a, :2] - p[b, :2], axis=1)
    driven = travel[b] - travel[a]
    ok = (driven > cfg.loop_min_travel_m) & (
        dist <= cfg.loop_radius_m + cfg.loop_proposal_sigmas * horizontal_drift_sigma_m(driven, cfg)
    )
    taken = np.zeros((0, 2))  # (route position of a, of b) of the pairs kept
    out = []
    for k in np.nonzero(ok)[0][np.argsort(dist[ok], kind="stable")]:
        at = np.array([travel[a[k]], travel[b[k]]])
        if np.any(np.abs(taken - at) < cfg.loop_min_separation_m):
            continue
        taken = np.vstack([taken, at])
        out.append(LoopCandidate(int(a[k]), int(b[k]), float(dist[k]), float(driven[k])))
    return out


def scans_needed(candidates: list[LoopCandidate], n_poses: int, cfg: FactorGraphConfig) -> np.ndarray:
    """The odometry poses whose scans the candidates' local maps are made of (sorted indices)."""
    span = np.arange(-cfg.loop_local_scans, cfg.loop_local_scans + 1)
    ends = np.array([[c.a, c.b] for c in candidates], np.int64).reshape(-1, 1)
    idx = (ends + span).ravel()
    return np.unique(idx[(idx >= 0) & (idx < n_poses)])


# --- local maps --------------------------------------------------------------------------------------


def read_scans(
    scans: Iterable[LidarScan],
    stamps_ns: np.ndarray,
    world_from_base: np.ndarray,
    needed: np.ndarray,
    base_from_lidar: Callable[[str], np.ndarray],
    cfg: FactorGraphConfig,
    source: str = "log",
) -> dict[int, np.ndarray]:
    """The ``needed`` poses' scans (pose index -> points in the frame of ``world_from_base``, the trajectory that places
    them, float32), read in one pass that stops after the last one. A scan belongs to the pose stamped at its sweep's
    last point (kiss-icp deskewed it to there: its points are deskewed here with the trajectory) or at its header stamp
    (not deskewed: placed rigidly). Needed poses whose scan is not found are left out with a warning."""
    stamps = np.asarray(stamps_ns, np.int64)
    want = set(int(i) for i in needed)
    out: dict[int, np.ndarray] = {}
    if not want:
        return out
    last = stamps[max(want)]
    for scan in scans:
        if scan.stamp_ns > last:
            break
        k, deskew = _pose_of_scan(scan, stamps)
        if k is None or k not in want:
            continue
        pts = _in_world(scan, k, deskew, stamps, world_from_base, base_from_lidar(scan.frame_id), cfg)
        out[k] = pts.astype(np.float32)
    missing = sorted(want - set(out))
    if missing:
        warnings.warn(
            f"{source}: no LiDAR scan found for {len(missing)} of the {len(want)} poses the loop closures' local "
            f"maps need (first at stamp {int(stamps[missing[0]])}); those maps are made without them",
            InputWarning,
            stacklevel=2,
        )
    return out


def _pose_of_scan(scan: LidarScan, stamps: np.ndarray) -> tuple[int | None, bool]:
    """(pose index, deskewed) of the odometry pose a scan gave: at its last point's time, else at its header stamp."""
    t = scan.point_time_s
    end = scan.stamp_ns + int(round(float(np.max(t)) * 1e9)) if t is not None and len(t) else scan.stamp_ns
    for stamp, deskew in ((end, end != scan.stamp_ns), (scan.stamp_ns, False)):
        k = int(np.clip(np.searchsorted(stamps, stamp), 0, len(stamps) - 1))
        for j in (k - 1, k):
            if 0 <= j < len(stamps) and abs(int(stamps[j]) - stamp) <= SCAN_POSE_TOLERANCE_NS:
                return j, deskew
    return None, False


def _in_world(
    scan: LidarScan,
    k: int,
    deskew: bool,
    stamps: np.ndarray,
    world_from_base: np.ndarray,
    base_from_lidar: np.ndarray,
    cfg: FactorGraphConfig,
) -> np.ndarray:
    """A scan's points in the trajectory's world frame; each at its firing time when ``deskew`` (the sweep runs from the
    previous pose to this one, as kiss-icp's constant-velocity deskewing has it)."""
    pts = np.asarray(scan.points_xyz, np.float64)
    keep = np.linalg.norm(pts, axis=1) >= cfg.loop_min_range_m
    pts = pts[keep]
    if (
        not deskew or k == 0 or stamps[k] - stamps[k - 1] > 2 * (stamps[k] - scan.stamp_ns)
    ):  # no pose at the sweep's start
        return transform_points(world_from_base[k] @ base_from_lidar, pts)
    t_ns = scan.stamp_ns + np.round(np.asarray(scan.point_time_s, np.float64)[keep] * 1e9).astype(np.int64)
    fire, which = np.unique(np.clip(t_ns, stamps[k - 1], stamps[k]), return_inverse=True)
    poses, _ = interpolate_poses(stamps[k - 1 : k + 1], world_from_base[k - 1 : k + 1], fire)
    world_from_lidar = poses @ base_from_lidar
    return np.einsum("nij,nj->ni", world_from_lidar[which, :3, :3], pts) + world_from_lidar[which, :3, 3]


def local_map(scans: dict[int, np.ndarray], k: int, world_from_base: np.ndarray, cfg: FactorGraphConfig) -> np.ndarray:
    """Keyframe ``k``'s local map: the points of its scans (``scans_needed``' span about it) in its base frame,
    cropped."""
    span = range(k - cfg.loop_local_scans, k + cfg.loop_local_scans + 1)
    parts = [scans[i] for i in span if i in scans]
    if not parts:
        return np.zeros((0, 3))
    pts = transform_points(invert_pose(world_from_base[k]), np.concatenate(parts).astype(np.float64))
    return pts[np.linalg.norm(pts[:, :2], axis=1) <= cfg.loop_local_radius_m]


# --- verification ------------------------------------------------------------------------------------


def _pcd(points: np.ndarray, voxel: float, normals: bool):
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64))).voxel_down_sample(voxel)
    if normals:
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=3.0 * voxel, max_nn=30))
    return pc


def register_local_maps(
    source: np.ndarray, target: np.ndarray, target_from_source: np.ndarray, cfg: FactorGraphConfig
) -> tuple[np.ndarray, IcpClouds | None]:
    """Point-to-plane ICP of ``source`` onto ``target`` over the ``loop_icp_*`` levels (mapkit's one ICP loop,
    :func:`mapkit.mapping.icp.icp_coarse_to_fine`, open3d on one thread so that a run repeats bit for bit); returns the
    transform and the fine level's clouds (None when a level had fewer than 10 points)."""

    def level(voxel: float) -> IcpClouds | None:
        src, tgt = _pcd(source, voxel, False), _pcd(target, voxel, True)
        if len(src.points) < 10 or len(tgt.points) < 10:
            return None
        return IcpClouds(np.asarray(src.points), np.asarray(tgt.points), np.asarray(tgt.normals))

    with open3d_one_thread():
        return icp_coarse_to_fine(
            level,
            cfg.loop_icp_voxels_m,
            cfg.loop_icp_max_correspondence_m,
            cfg.loop_icp_iterations,
            initial=target_from_source,
        )


def support(
    source: np.ndarray, target: np.ndarray, target_normals: np.ndarray, T: np.ndarray, max_distance: float
) -> tuple[float, float, np.ndarray, int]:
    """How ``T`` fits ``source`` onto ``target``: (fitness: the fraction of source points with a target point within
    ``max_distance``; point-to-plane RMSE over those; the 6x6 point-to-plane Hessian over those, for the right
    perturbation ``T exp(xi)`` (xi = rotation, translation, in the source's frame); how many)."""
    hit, j, r = point_to_plane(transform_points(T, source), target, target_normals, max_distance)
    if not hit.any():
        return 0.0, float("nan"), np.zeros((6, 6)), 0
    n_src = target_normals[j] @ T[:3, :3]  # the normals in the source's frame
    J = np.hstack([np.cross(source[hit], n_src), n_src])
    return float(hit.mean()), float(np.sqrt(np.mean(r**2))), J.T @ J, int(hit.sum())


def translation_constraint(H: np.ndarray, n: int) -> float:
    """The smallest eigenvalue of the translation block of a point-to-plane Hessian with the rotation marginalised (its
    Schur complement), per correspondence: between 0 (a direction nothing holds) and 1/3 (normals spread evenly)."""
    if n == 0:
        return 0.0
    S = H[3:, 3:] - H[3:, :3] @ np.linalg.pinv(H[:3, :3]) @ H[:3, 3:]
    return float(np.linalg.eigvalsh(S)[0] / n)


def verify_loop(
    candidate: LoopCandidate, scans: dict[int, np.ndarray], world_from_base: np.ndarray, cfg: FactorGraphConfig
) -> LoopCheck:
    """ICP of b's local map onto a's from the relative pose of ``world_from_base`` (the estimate the scans were placed
    with by :func:`read_scans`), judged by the gates of ``cfg`` (module notes)."""
    t0 = time.perf_counter()
    a, b = candidate.a, candidate.b
    check = lambda reason, detail, **kw: LoopCheck(candidate, reason, detail, seconds=time.perf_counter() - t0, **kw)  # noqa: E731 (a one-line helper local to this function)
    if a not in scans or b not in scans:
        return check(LoopReason.SCANS_MISSING, f"no scan at keyframe {'a' if a not in scans else 'b'}")
    guess = invert_pose(world_from_base[a]) @ world_from_base[b]
    # the fine level's voxels once: the coarser levels are made from them
    src, tgt = (
        np.asarray(_pcd(local_map(scans, k, world_from_base, cfg), cfg.loop_icp_voxels_m[-1], False).points)
        for k in (b, a)
    )
    if min(len(src), len(tgt)) < cfg.loop_min_points:
        return check(LoopReason.TOO_FEW_POINTS, f"{min(len(src), len(tgt))} points < {cfg.loop_min_points}")
    T, fine = register_local_maps(src, tgt, guess, cfg)
    if fine is None:
        return check(LoopReason.TOO_FEW_POINTS, "fewer than 10 points at an ICP level")
    fitness, rmse, H, n = support(fine.source, fine.target, fine.target_normals, T, cfg.loop_eval_distance_m)
    off = invert_pose(guess) @ T
    measured = dict(
        a_from_b=T,
        fitness=fitness,
        rmse_m=rmse,
        constraint=translation_constraint(H, n),
        correction_m=float(np.linalg.norm(off[:3, 3])),
        correction_deg=float(np.degrees(rotation_angle_rad(off[:3, :3]))),
    )
    verdict = _gate(measured, cfg)
    if verdict is not None:
        return check(*verdict, **measured)
    return check(LoopReason.ACCEPTED, "", covariance=edge_covariance(H, rmse, cfg), **measured)


def _gate(m: dict, cfg: FactorGraphConfig) -> tuple[LoopReason, str] | None:
    """The first gate a registration fails, with the figures, or None."""
    if m["fitness"] < cfg.loop_min_fitness:
        return LoopReason.FITNESS, f"fitness {m['fitness']:.2f} < {cfg.loop_min_fitness}"
    if not m["rmse_m"] <= cfg.loop_max_rmse_m:
        return LoopReason.RMSE, f"RMSE {m['rmse_m']:.3f} m > {cfg.loop_max_rmse_m} m"
    if m["constraint"] < cfg.loop_min_constraint:
        return LoopReason.DEGENERATE, f"weakest translation {m['constraint']:.3f} < {cfg.loop_min_constraint}"
    if m["correction_m"] > cfg.loop_max_correction_m:
        return LoopReason.CORRECTION, f"correction {m['correction_m']:.2f} m > {cfg.loop_max_correction_m} m"
    if m["correction_deg"] > cfg.loop_max_rotation_deg:
        return LoopReason.ROTATION, f"rotation {m['correction_deg']:.1f} deg > {cfg.loop_max_rotation_deg} deg"
    return None


def edge_covariance(H: np.ndarray, rmse_m: float, cfg: FactorGraphConfig) -> np.ndarray:
    """The loop edge's covariance (module notes): ICP's own, ``rmse^2 H^-1``, plus the floor of its local maps'
    placement."""
    floor = np.repeat([cfg.loop_floor_rotation_rad, cfg.loop_floor_translation_m], 3) ** 2
    return rmse_m**2 * np.linalg.inv(H) + np.diag(floor)


def verify_loops(
    candidates: list[LoopCandidate], scans: dict[int, np.ndarray], world_from_base: np.ndarray, cfg: FactorGraphConfig
) -> list[LoopCheck]:
    """:func:`verify_loop` for every candidate, in order."""
    return [verify_loop(c, scans, world_from_base, cfg) for c in candidates]


__all__ = [
    "LoopCandidate",
    "LoopCheck",
    "LoopReason",
    "horizontal_drift_sigma_m",
    "local_map",
    "loop_closures",
    "propose_loops",
    "read_scans",
    "register_local_maps",
    "scans_needed",
    "support",
    "translation_constraint",
    "verify_loop",
    "verify_loops",
]
