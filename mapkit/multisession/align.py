"""``mapkit align``: every session of a workspace in one consistent georeferenced frame.

The semi-dense paper (section 4.1) aligns each session's trajectory to GPS and then refines local
point clouds of different sessions against each other with ICP, rejecting pairs whose RMSE after
ICP exceeds lambda_ICP. mapkit does this for a whole workspace:

1. Each georeferenced session (``mapkit build`` output) is brought into the workspace's ENU frame
   (one UTM zone, one origin); its map is cut into submaps of ``submap_length_m`` of driving.
2. Submaps of different sessions whose trajectory centres are close are registered with open3d
   point-to-plane ICP (normals estimated from neighbourhoods, coarse to fine). Pairs with too low
   a fitness, an RMSE above lambda_ICP or an implausibly large correction are rejected, each with
   its reason. Registrations are cached: adding a session registers only its pairs.
3. A pose graph over all submaps (odometry edges inside a session, ICP edges between sessions,
   weak GPS priors) is solved with scipy's robust least squares; ICP edges that disagree with the
   rest after the solve are rejected and it is solved again.
4. Corrections are interpolated along each session (no tearing) and applied to its trajectory and
   map. Submaps that overlap other sessions but have no accepted registration are *unverified* and
   left out of the merged map (never silently merged).

Outputs under ``WORKSPACE/align/``: refined trajectories and maps per session, every submap's
correction, the merged map tiled by UTM, and a QA report (JSON, Markdown, PNGs).
"""

from __future__ import annotations

import copy
import json
import sys
import time
import warnings
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Optional

import numpy as np
from pydantic import Field
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation, Slerp

from mapkit.core.config import MapkitConfig, dump_config, load_config
from mapkit.core.errors import InputError, InputWarning
from mapkit.core.executor import Executor, get_executor
from mapkit.core.geodesy import LocalFrame
from mapkit.core.runio import atomic_path, atomic_write_ply, atomic_write_text, config_hash, is_done, mark_done, sha256_file, write_json
from mapkit.mapping.trajectory import Trajectory

ALIGN_FORMAT_VERSION = 1


class IcpConfig(MapkitConfig):
    voxel_sizes_m: list[float] = Field([1.0, 0.5, 0.25], description="Voxel size of each coarse-to-fine ICP level (m).")
    max_correspondence_m: list[float] = Field([4.0, 1.5, 0.6], description="Largest correspondence distance of each level (m); the first bounds the misalignment ICP can pull in.")
    max_iterations: int = Field(40, ge=1, description="ICP iterations per level.")
    normal_radius_factor: float = Field(3.0, gt=0, description="Normals from neighbours within this many voxels (the semi-dense clouds carry no reliable normals).")
    normal_max_nn: int = Field(30, ge=5, description="At most this many neighbours per normal.")
    lambda_icp_m: float = Field(
        0.40, gt=0,
        description="lambda_ICP: reject a pair whose point-to-plane RMSE after ICP (over correspondences within eval_distance_m; "
        "overall and for the structure alone) exceeds this (semi-dense paper, section 4.1; the paper gives no value: "
        "0.40 m sits above the demo maps' own noise, whose accepted pairs reach 0.35 m).",
    )
    eval_distance_m: float = Field(1.0, gt=0, description="Correspondence distance for the RMSE and fitness that decide acceptance (m).")
    min_fitness: float = Field(0.25, ge=0, le=1, description="Reject a pair when fewer than this fraction of source points have a target point within eval_distance_m.")
    min_structure_fitness: float = Field(0.25, ge=0, le=1, description="... and the same for the structure alone (points whose normal is not vertical): the ground fits any horizontal shift.")
    structure_max_normal_z: float = Field(0.7, gt=0, le=1, description="A point is structure when |normal z| is below this.")
    max_correction_m: float = Field(12.0, gt=0, description="Reject a pair whose correction moves the pair centre more than this (m): more than GPS can be off.")
    max_rotation_deg: float = Field(5.0, gt=0, description="Reject a pair whose correction rotates more than this (deg).")


class GraphConfig(MapkitConfig):
    prior_sigma_m: list[float] = Field([3.0, 3.0, 3.0], description="GPS prior on each submap's correction, east/north/up (m): weak, GPS drifts by metres.")
    prior_sigma_deg: float = Field(3.0, gt=0, description="Prior on each submap's rotation correction (deg).")
    odometry_sigma_m: float = Field(0.10, gt=0, description="How much two consecutive submaps of a session may disagree at their boundary (m).")
    icp_sigma_m: float = Field(0.10, gt=0, description="Uncertainty of an accepted ICP registration at its support points (m).")
    lever_m: float = Field(10.0, gt=0, description="Support points of an edge lie this far from its centre, so rotations are constrained too (m).")
    robust_scale: float = Field(3.0, gt=0, description="Cauchy loss scale, in sigmas, of the robust solve (applied to every whitened residual).")
    reject_sigmas: float = Field(6.0, gt=0, description="After the solve, an ICP edge whose RMS residual exceeds this many sigmas is rejected and the graph solved again.")
    max_rounds: int = Field(3, ge=1, description="Solve / reject rounds.")


class AlignConfig(MapkitConfig):
    submap_length_m: float = Field(50.0, gt=0, description="Submaps are cut every this much driving (m); the issue's example, 50 m.")
    overlap_radius_m: float = Field(35.0, gt=0, description="Submaps of different sessions whose trajectory centres lie within this distance (m) are registered.")
    crop_radius_m: float = Field(40.0, gt=0, description="Both clouds of a pair are cropped to this horizontal radius around the pair centre (m).")
    target_neighbours: int = Field(1, ge=0, description="The target cloud also includes this many neighbouring submaps on each side, so the source is fully covered.")
    min_points: int = Field(1000, ge=10, description="A submap with fewer points (after cropping) is not registered: a few hundred points "
                            "fit a wall in many places (on the demo, such a pair was accepted 1.8 m off).")
    icp: IcpConfig = IcpConfig()
    graph: GraphConfig = GraphConfig()
    freeze_existing: bool = Field(True, description="When sessions are added, keep the corrections of sessions aligned before fixed (their outputs do not change); false re-solves all.")
    merge_unverified: bool = Field(False, description="Put submaps that overlap other sessions but have no accepted registration into the merged map.")
    tile_size_m: float = Field(100.0, gt=0, description="Side of the UTM tiles of the merged map (m).")


# --- session data ----------------------------------------------------------------------------------


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
    submap_of_point: np.ndarray = field(default=None)  # (N,) int
    centres: np.ndarray = field(default=None)  # (S, 3) trajectory position at each submap's middle
    boundaries: np.ndarray = field(default=None)  # (S-1, 3) positions where consecutive submaps meet
    directions: np.ndarray = field(default=None)  # (S, 3) unit driving direction at each centre
    submap_edges_m: np.ndarray = field(default=None)  # (S+1,) distance driven where submaps start and end
    smap: object = field(default=None, repr=False)  # the SemiDenseMap as built (session frame)
    ws_from_session: np.ndarray = field(default_factory=lambda: np.eye(4))

    @property
    def n_submaps(self) -> int:
        return len(self.centres)


def _arc_length(positions: np.ndarray) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(positions, axis=0), axis=1))])


def _position_at_arc(arc: np.ndarray, positions: np.ndarray, s: np.ndarray) -> np.ndarray:
    return np.stack([np.interp(s, arc, positions[:, k]) for k in range(3)], axis=-1)


def load_session(sdir: Path, ws_frame: LocalFrame, length_m: float) -> Optional[SessionData]:
    """A built session in the workspace frame, or None (with a warning) if it cannot be aligned."""
    from mapkit.mapping.semidense import SemiDenseMap

    name = sdir.name
    ga_path = sdir / "georef" / "gps_alignment.json"
    map_dir = sdir / "map"
    if not (sdir / "georef" / ".done").is_file() or not (map_dir / ".done").is_file():
        warnings.warn(f"{sdir}: session is not fully built (georef and map stages); skipped", InputWarning, stacklevel=2)
        return None
    ga = json.loads(ga_path.read_text())
    if not ga.get("georeferenced"):
        warnings.warn(f"{ga_path}: session is not georeferenced ({ga.get('reason', 'no reason given')}); skipped", InputWarning, stacklevel=2)
        return None
    traj = Trajectory.load(sdir / "georef" / "trajectory_enu")
    smap = SemiDenseMap.load(map_dir)
    ws_from_session = LocalFrame.from_dict(ga).to_frame(ws_frame)
    poses = ws_from_session @ traj.world_from_base
    pts = smap.points_world @ ws_from_session[:3, :3].T + ws_from_session[:3, 3]
    arc = _arc_length(poses[:, :3, 3])
    kf_stamp = dict(zip(smap.keyframe_ids.tolist(), smap.keyframe_stamps_ns.tolist()))
    src_stamp = np.array([kf_stamp[int(k)] for k in smap.source_keyframe], np.float64) if len(pts) else np.zeros(0)
    point_arc = np.interp(src_stamp, traj.stamps_ns.astype(np.float64), arc)
    done = json.loads((map_dir / ".done").read_text())
    s = SessionData(name, traj.stamps_ns, poses, arc, pts, point_arc, map_dir, done.get("config_hash", ""),
                    smap=smap, ws_from_session=ws_from_session)
    cut_submaps(s, length_m)
    return s


def cut_submaps(s: SessionData, length_m: float) -> None:
    """Submap k holds the points whose source keyframe was taken in [k L, (k+1) L) of driving;
    the last piece joins the one before it when it is shorter than half a submap."""
    total = float(s.arc_m[-1])
    n = max(1, int(np.floor(total / length_m)))
    if total - n * length_m >= 0.5 * length_m:
        n += 1
    edges = np.linspace(0.0, total, n + 1) if n * length_m > total else np.concatenate([np.arange(n) * length_m, [total]])
    s.submap_of_point = np.clip(np.searchsorted(edges, s.point_arc_m, side="right") - 1, 0, n - 1)
    mids = 0.5 * (edges[:-1] + edges[1:])
    P = s.poses[:, :3, 3]
    s.centres = _position_at_arc(s.arc_m, P, mids)
    s.boundaries = _position_at_arc(s.arc_m, P, edges[1:-1])
    ahead = _position_at_arc(s.arc_m, P, np.minimum(mids + 1.0, total))
    behind = _position_at_arc(s.arc_m, P, np.maximum(mids - 1.0, 0.0))
    d = ahead - behind
    s.directions = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
    s.submap_edges_m = edges


# --- pairwise registration -----------------------------------------------------------------------


@dataclass
class PairResult:
    source: tuple[str, int]
    target: tuple[str, int]
    centre: np.ndarray  # (3,) ENU, where the pair's support points lie
    target_from_source: np.ndarray  # (4, 4): maps source points onto the target's
    accepted: bool
    reason: str
    fitness: float
    rmse_m: float
    source_points: int
    target_points: int
    correction_m: float
    seconds: float
    structure_fitness: float = 0.0
    structure_rmse_m: float = float("nan")
    key: str = ""

    def metrics(self) -> dict:
        return {"target_from_source": self.target_from_source, "fitness": self.fitness, "rmse_m": self.rmse_m,
                "structure_fitness": self.structure_fitness, "structure_rmse_m": self.structure_rmse_m}

    def to_dict(self) -> dict:
        return {
            "source": list(self.source), "target": list(self.target), "centre": self.centre.tolist(),
            "target_from_source": self.target_from_source.tolist(), "accepted": self.accepted, "reason": self.reason,
            "fitness": self.fitness, "structure_fitness": self.structure_fitness, "rmse_m": self.rmse_m,
            "structure_rmse_m": self.structure_rmse_m, "source_points": self.source_points,
            "target_points": self.target_points, "correction_m": self.correction_m, "seconds": self.seconds, "key": self.key,
        }

    @classmethod
    def from_dict(cls, d: dict) -> "PairResult":
        return cls(tuple(d["source"]), tuple(d["target"]), np.asarray(d["centre"]), np.asarray(d["target_from_source"]),
                   bool(d["accepted"]), d["reason"], float(d["fitness"]), float(d["rmse_m"]), int(d["source_points"]),
                   int(d["target_points"]), float(d["correction_m"]), float(d["seconds"]), float(d.get("structure_fitness", 0.0)),
                   float(d.get("structure_rmse_m", float("nan"))), d.get("key", ""))


def _cloud(points: np.ndarray, origin: np.ndarray):
    import open3d as o3d

    pc = o3d.geometry.PointCloud()
    pc.points = o3d.utility.Vector3dVector(np.asarray(points, np.float64) - origin)
    return pc


def register_clouds(source: np.ndarray, target: np.ndarray, centre: np.ndarray, cfg: IcpConfig, structure: bool = True) -> dict:
    """Coarse-to-fine point-to-plane ICP of ``source`` onto ``target`` (both ENU, N x 3).

    Works next to ``centre`` (float32 inside open3d). Returns ``target_from_source`` (4x4, ENU),
    and the fitness and point-to-plane RMSE at ``cfg.eval_distance_m`` (see
    :func:`evaluate_alignment`; ``structure=False`` skips the structure-only figures).
    """
    import open3d as o3d

    reg = o3d.pipelines.registration
    src0, tgt0 = _cloud(source, centre), _cloud(target, centre)
    T = np.eye(4)
    src = tgt = None
    for voxel, max_d in zip(cfg.voxel_sizes_m, cfg.max_correspondence_m):
        src = src0.voxel_down_sample(voxel)
        tgt = tgt0.voxel_down_sample(voxel)
        if len(src.points) < 10 or len(tgt.points) < 10:
            src = tgt = None
            break
        tgt.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=cfg.normal_radius_factor * voxel, max_nn=cfg.normal_max_nn))
        res = reg.registration_icp(src, tgt, max_d, T, reg.TransformationEstimationPointToPlane(),
                                   reg.ICPConvergenceCriteria(max_iteration=cfg.max_iterations))
        T = np.asarray(res.transformation)
    fine = cfg.voxel_sizes_m[-1]
    if tgt is None:  # stopped early: evaluate at the fine level from scratch
        src, tgt = src0.voxel_down_sample(fine), tgt0.voxel_down_sample(fine)
        target_normals = None
    else:  # the last level is the fine one: its target normals are already there
        target_normals = np.asarray(tgt.normals)
    ev = evaluate_alignment(np.asarray(src.points), np.asarray(tgt.points), T, fine, cfg, target_normals, structure)
    C = np.eye(4)  # back to ENU from centre-relative coordinates x' = x - c
    C[:3, 3] = centre
    return {"target_from_source": C @ T @ np.linalg.inv(C), **ev}


def evaluate_alignment(source: np.ndarray, target: np.ndarray, T: np.ndarray, voxel: float, cfg: IcpConfig,
                       target_normals: Optional[np.ndarray] = None, structure: bool = True) -> dict:
    """Fitness and point-to-plane RMSE of ``T @ source`` against ``target``, overall and for the
    structure alone.

    Point-to-plane, because two semi-dense maps sample a surface at different points: the
    point-to-point distance measures their sampling, not their alignment. Structure (points whose
    normal is not vertical) is scored on its own because the ground fits any horizontal shift.
    """
    import open3d as o3d

    def normals(pts):
        pc = _cloud(pts, np.zeros(3))
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=cfg.normal_radius_factor * voxel, max_nn=cfg.normal_max_nn))
        return np.asarray(pc.normals)

    rms = lambda v: float(np.sqrt(np.mean(v**2))) if len(v) else float("nan")  # noqa: E731
    if len(source) == 0 or len(target) == 0:
        return {"fitness": 0.0, "rmse_m": float("nan"), "structure_fitness": 0.0, "structure_rmse_m": float("nan"), "structure_points": 0}
    moved = source @ T[:3, :3].T + T[:3, 3]
    d, k = cKDTree(target).query(moved, distance_upper_bound=cfg.eval_distance_m)
    inlier = np.isfinite(d)
    n_t = normals(target) if target_normals is None else target_normals
    r = np.abs(np.einsum("ij,ij->i", moved[inlier] - target[k[inlier]], n_t[k[inlier]]))
    out = {"fitness": float(inlier.mean()), "rmse_m": rms(r)}
    if not structure:
        return {**out, "structure_fitness": out["fitness"], "structure_rmse_m": out["rmse_m"], "structure_points": 0}
    upright = np.abs(normals(source) @ T[:3, :3].T[:, 2]) < cfg.structure_max_normal_z
    r_s = np.abs(np.einsum("ij,ij->i", moved[inlier & upright] - target[k[inlier & upright]], n_t[k[inlier & upright]]))
    return {**out, "structure_fitness": float((inlier & upright).sum() / max(1, upright.sum())), "structure_rmse_m": rms(r_s),
            "structure_points": int(upright.sum())}


def _decide(r: dict, cfg: IcpConfig, centre: np.ndarray) -> tuple[bool, str, float]:
    T = r["target_from_source"]
    moved = float(np.linalg.norm(T[:3, :3] @ centre + T[:3, 3] - centre))
    angle = float(np.degrees(Rotation.from_matrix(T[:3, :3]).magnitude()))
    if r["fitness"] < cfg.min_fitness:
        return False, f"fitness {r['fitness']:.2f} < {cfg.min_fitness}", moved
    if r["structure_fitness"] < cfg.min_structure_fitness:
        return False, f"structure fitness {r['structure_fitness']:.2f} < {cfg.min_structure_fitness}", moved
    if not r["rmse_m"] <= cfg.lambda_icp_m:  # NaN (no correspondence) fails too
        return False, f"RMSE {r['rmse_m']:.3f} m > lambda_ICP {cfg.lambda_icp_m} m", moved
    if not r["structure_rmse_m"] <= cfg.lambda_icp_m:
        return False, f"structure RMSE {r['structure_rmse_m']:.3f} m > lambda_ICP {cfg.lambda_icp_m} m", moved
    if moved > cfg.max_correction_m:
        return False, f"correction {moved:.1f} m > {cfg.max_correction_m} m", moved
    if angle > cfg.max_rotation_deg:
        return False, f"rotation {angle:.1f} deg > {cfg.max_rotation_deg} deg", moved
    return True, "accepted", moved


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


def _submap_points(s: SessionData, idx: int, neighbours: int = 0) -> np.ndarray:
    lo, hi = idx - neighbours, idx + neighbours
    return s.points[(s.submap_of_point >= lo) & (s.submap_of_point <= hi)]


def register_pair(a: SessionData | _SubmapClouds, i: int, b: SessionData | _SubmapClouds, j: int, cfg: AlignConfig) -> PairResult:
    t0 = time.perf_counter()
    centre = 0.5 * (a.centres[i] + b.centres[j])
    src = _submap_points(a, i)
    tgt = _submap_points(b, j, cfg.target_neighbours)
    r2 = cfg.crop_radius_m**2
    src = src[np.sum((src[:, :2] - centre[:2]) ** 2, axis=1) < r2]
    tgt = tgt[np.sum((tgt[:, :2] - centre[:2]) ** 2, axis=1) < r2]
    base = dict(source=(a.name, i), target=(b.name, j), centre=centre, source_points=len(src), target_points=len(tgt))
    if len(src) < cfg.min_points or len(tgt) < cfg.min_points:
        return PairResult(**base, target_from_source=np.eye(4), accepted=False, reason="not registered",
                          fitness=0.0, rmse_m=float("nan"), correction_m=0.0, seconds=time.perf_counter() - t0)
    r = register_clouds(src, tgt, centre, cfg.icp)
    ok, reason, moved = _decide(r, cfg.icp, centre)
    return PairResult(**base, target_from_source=r["target_from_source"], accepted=ok, reason=reason, fitness=r["fitness"],
                      rmse_m=r["rmse_m"], correction_m=moved, seconds=time.perf_counter() - t0, structure_fitness=r["structure_fitness"],
                      structure_rmse_m=r["structure_rmse_m"])


@dataclass
class _SubmapClouds:
    """What registering a session's submaps needs (``register_pair`` reads these fields only):
    shipped to workers once, without the rest of the session."""

    name: str
    points: np.ndarray
    submap_of_point: np.ndarray
    centres: np.ndarray


@contextmanager
def _open3d_one_thread() -> Iterator[None]:
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


def _register_task(shared: tuple[list[_SubmapClouds], "AlignConfig"], pair: tuple[int, int, int, int]) -> PairResult:
    clouds, cfg = shared
    ia, i, ib, j = pair
    with _open3d_one_thread():
        return register_pair(clouds[ia], i, clouds[ib], j, cfg)


# --- pose graph ------------------------------------------------------------------------------------


@dataclass
class Edge:
    kind: str  # "odometry" | "icp"
    a: int  # node whose (current) frame the measurement starts from
    b: int
    support: np.ndarray  # (P, 3) support points in a's current frame
    target_from_source: np.ndarray  # (4, 4): a's current frame -> b's current frame
    sigma_m: float
    pair: Optional[int] = None  # index into the pair list (ICP edges)


def _support_points(centre: np.ndarray, direction: np.ndarray, lever: float) -> np.ndarray:
    d = np.array([direction[0], direction[1], 0.0])
    d = d / max(np.linalg.norm(d), 1e-9)
    lateral = np.array([-d[1], d[0], 0.0])
    up = np.array([0.0, 0.0, 1.0])
    return np.stack([centre, centre + lever * d, centre - lever * d, centre + lever * lateral, centre - lever * lateral, centre + 0.5 * lever * up])


def _apply_node(x: np.ndarray, centres: np.ndarray, node: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Corrected positions of ``pts`` (E, P, 3) under nodes ``node`` (E,): p' = R (p - c) + c + t."""
    rv, t = x[node, :3], x[node, 3:]
    R = Rotation.from_rotvec(rv).as_matrix()  # (E, 3, 3)
    c = centres[node][:, None, :]
    return np.einsum("eij,epj->epi", R, pts - c) + c + t[:, None, :]


class PoseGraph:
    """Corrections of submaps: node k moves its submap's points by p' = R_k (p - c_k) + c_k + t_k.

    Residuals are distances at support points (so rotation and translation share one unit):
    odometry edges ask consecutive submaps of a session to move their common boundary alike,
    ICP edges ask T_a(p) = T_b(T_ab p), priors keep every correction near zero (GPS).
    """

    def __init__(self, centres: np.ndarray, cfg: GraphConfig, fixed: Optional[np.ndarray] = None, initial: Optional[np.ndarray] = None):
        self.centres = np.asarray(centres, np.float64)
        self.cfg = cfg
        n = len(self.centres)
        self.fixed = np.zeros(n, bool) if fixed is None else np.asarray(fixed, bool)
        self.x0 = np.zeros((n, 6)) if initial is None else np.asarray(initial, np.float64).copy()
        self.edges: list[Edge] = []

    def add(self, edge: Edge) -> None:
        self.edges.append(edge)

    @staticmethod
    def _stack(edges: list[Edge]) -> Optional[tuple]:
        """Node indices, support points in both frames and sigmas of ``edges``, as arrays (built
        once per solve, not at every evaluation of the residuals)."""
        if not edges:
            return None
        a = np.array([e.a for e in edges])
        b = np.array([e.b for e in edges])
        P = np.stack([e.support for e in edges])  # (E, P, 3), in a's current frame
        Tab = np.stack([e.target_from_source for e in edges])
        Pb = np.einsum("eij,epj->epi", Tab[:, :3, :3], P) + Tab[:, None, :3, 3]  # the same points in b's frame
        return a, b, P, Pb, np.array([e.sigma_m for e in edges])

    def _edge_displacements(self, x: np.ndarray, stacked: tuple) -> np.ndarray:
        """(E, P, 3) disagreement T_a(p) - T_b(T_ab p) at every support point, in metres."""
        a, b, P, Pb, _ = stacked
        return _apply_node(x, self.centres, a, P) - _apply_node(x, self.centres, b, Pb)

    def _residuals(self, x_free: np.ndarray, stacked: Optional[tuple]) -> np.ndarray:
        x = self.x0.copy()
        x[~self.fixed] = x_free.reshape(-1, 6)
        free = np.flatnonzero(~self.fixed)
        out = [(x[free, 3:] / np.asarray(self.cfg.prior_sigma_m)).ravel(), (x[free, :3] / np.radians(self.cfg.prior_sigma_deg)).ravel()]
        if stacked is not None:
            out.append((self._edge_displacements(x, stacked) / stacked[4][:, None, None]).ravel())
        return np.concatenate(out)

    def solve(self, edges: Optional[list[Edge]] = None) -> np.ndarray:
        """Corrections (n, 6) = [rotation vector, translation at the centre]."""
        from scipy.optimize import least_squares
        from scipy.sparse import lil_matrix

        edges = self.edges if edges is None else edges
        free = np.flatnonzero(~self.fixed)
        if len(free) == 0:
            return self.x0.copy()
        col = -np.ones(len(self.centres), np.int64)
        col[free] = np.arange(len(free))
        stacked = self._stack(edges)
        n_res = len(self._residuals(self.x0[free].ravel(), stacked))
        S = lil_matrix((n_res, 6 * len(free)), dtype=np.int8)
        row = 0
        for k in range(len(free)):  # translation priors, then rotation priors
            S[row + 3 * k : row + 3 * k + 3, 6 * k + 3 : 6 * k + 6] = 1
        row += 3 * len(free)
        for k in range(len(free)):
            S[row + 3 * k : row + 3 * k + 3, 6 * k : 6 * k + 3] = 1
        row += 3 * len(free)
        for e in edges:
            m = 3 * len(e.support)
            for node in (e.a, e.b):
                if col[node] >= 0:
                    S[row : row + m, 6 * col[node] : 6 * col[node] + 6] = 1
            row += m
        # one Cauchy loss on every whitened row (scipy applies it to all residuals): rows within
        # a few sigmas stay nearly quadratic, a wrong ICP edge far out loses its pull
        res = least_squares(self._residuals, self.x0[free].ravel(), jac_sparsity=S.tocsr(), args=(stacked,),
                            loss="cauchy", f_scale=self.cfg.robust_scale, method="trf", x_scale="jac", max_nfev=200)
        x = self.x0.copy()
        x[free] = res.x.reshape(-1, 6)
        return x

    def edge_rms_sigmas(self, x: np.ndarray, edges: list[Edge]) -> np.ndarray:
        """RMS residual of each edge, in its sigmas."""
        stacked = self._stack(edges)
        if stacked is None:
            return np.zeros(0)
        d = np.linalg.norm(self._edge_displacements(x, stacked), axis=2)
        return np.sqrt(np.mean(d**2, axis=1)) / stacked[4]


# --- applying corrections ----------------------------------------------------------------------------


def session_offsets(pairs: list[PairResult], names: list[str], fixed: Optional[dict[str, np.ndarray]] = None,
                    iterations: int = 10, huber_m: float = 0.5) -> dict[str, np.ndarray]:
    """One translation per session from the accepted registrations: o_a - o_b = d_ab, where d_ab
    moves source a onto target b at the pair centre; iteratively reweighted (Huber) least squares,
    sessions in ``fixed`` held, otherwise the mean offset is zero (the GPS frame on average)."""
    fixed = fixed or {}
    idx = {n: k for k, n in enumerate(names)}
    rows = [(idx[p.source[0]], idx[p.target[0]], p.target_from_source[:3, :3] @ p.centre + p.target_from_source[:3, 3] - p.centre)
            for p in pairs if p.source[0] in idx and p.target[0] in idx]
    out = {n: np.asarray(fixed.get(n, np.zeros(3)), np.float64) for n in names}
    if not rows:
        return out
    n = len(names)
    free = [k for k in range(n) if names[k] not in fixed]
    w = np.ones(len(rows))
    o = np.array([out[nm] for nm in names])
    for _ in range(iterations):
        A = np.zeros((len(rows) + 1, n))
        b = np.zeros((len(rows) + 1, 3))
        for r, (ia, ib, d) in enumerate(rows):
            A[r, ia], A[r, ib], b[r] = w[r], -w[r], w[r] * d
        if fixed:  # fixed sessions: move their terms to the right-hand side
            for k in range(n):
                if k not in free:
                    b -= np.outer(A[:, k], o[k])
                    A[:, k] = 0
        else:
            A[-1, :] = 1.0  # gauge: zero mean
        sol, *_ = np.linalg.lstsq(A[:, free], b, rcond=None)
        o[free] = sol
        res = np.linalg.norm(np.array([o[ia] - o[ib] - d for ia, ib, d in rows]), axis=1)
        w = np.where(res <= huber_m, 1.0, huber_m / np.maximum(res, 1e-12)) ** 0.5
    return {nm: o[k] for k, nm in enumerate(names)}


def correction_at(s: SessionData, x_session: np.ndarray, arc_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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
    c = _position_at_arc(mids, s.centres, arc_m)
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


# --- the stage -------------------------------------------------------------------------------------


_DECISION_FIELDS = {"lambda_icp_m", "min_fitness", "min_structure_fitness", "max_correction_m", "max_rotation_deg"}


def _pair_key(a: SessionData, i: int, b: SessionData, j: int, cfg: AlignConfig) -> str:
    """What a registration depends on; the acceptance thresholds are not part of it (a cached
    registration is judged again under the current thresholds)."""
    icp = {k: v for k, v in cfg.icp.model_dump().items() if k not in _DECISION_FIELDS}
    return config_hash({"a": [a.name, a.map_hash, i], "b": [b.name, b.map_hash, j], "len": cfg.submap_length_m,
                        "crop": cfg.crop_radius_m, "nb": cfg.target_neighbours, "icp": icp})


def _load_pair_cache(path: Path) -> dict[str, PairResult]:
    if not path.is_file():
        return {}
    try:
        d = json.loads(path.read_text())
    except json.JSONDecodeError:
        warnings.warn(f"{path}: unreadable registration cache; registering again", InputWarning, stacklevel=2)
        return {}
    return {k: PairResult.from_dict(v) for k, v in d.get("pairs", {}).items()}


def _save_pair_cache(path: Path, cache: dict[str, PairResult]) -> None:
    write_json(path, {"format_version": ALIGN_FORMAT_VERSION, "pairs": {k: v.to_dict() for k, v in cache.items()}})


def align_workspace(workspace: str | Path, config: str | Path | None = None, overrides: Optional[dict] = None,
                    progress: bool = True, sessions: Optional[list[str]] = None, executor: Optional[Executor] = None) -> Path:
    """Align every built session of ``workspace``; returns ``WORKSPACE/align``.

    Submap pairs are registered on ``executor`` (default: :func:`mapkit.core.executor.get_executor`),
    each with open3d on one thread, so that the registrations are the same bit for bit on any
    executor (open3d's multi-threaded ICP sums in a varying order).
    """
    workspace = Path(workspace)
    cfg = load_config(AlignConfig, config, overrides)
    origin = workspace / "origin.json"
    if not origin.is_file():
        raise InputError(origin, "no such file: the workspace has no georeferenced session to align (run mapkit build first)")
    ws_frame = LocalFrame.from_dict(json.loads(origin.read_text()))
    out = workspace / "align"
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "config.yaml", dump_config(cfg))
    t0 = time.perf_counter()

    if sessions is None:
        sdir = workspace / "sessions"
        sessions = sorted(p.name for p in sdir.iterdir() if p.is_dir()) if sdir.is_dir() else []
    names = sessions
    data = [s for s in (load_session(workspace / "sessions" / n, ws_frame, cfg.submap_length_m) for n in names) if s is not None]
    if len(data) < 2:
        raise InputError(workspace, f"{len(data)} alignable session(s); multi-session alignment needs at least two built, georeferenced sessions")
    run_hash = config_hash({"cfg": cfg, "sessions": [[s.name, s.map_hash] for s in data]})
    if is_done(out, run_hash):
        return out
    (out / ".done").unlink(missing_ok=True)

    # 1. registrations (cached by content: a new session only registers its own pairs)
    cache_path = out / "registrations.json"
    cache = _load_pair_cache(cache_path)
    cands = candidate_pairs(data, cfg.overlap_radius_m)
    keys = [_pair_key(data[ia], i, data[ib], j, cfg) for ia, i, ib, j in cands]
    cached: list[Optional[PairResult]] = []
    for key in keys:
        r = cache.get(key)
        if r is not None and r.reason == "not registered" and min(r.source_points, r.target_points) >= cfg.min_points:
            r = None  # skipped under a stricter min_points than today's
        cached.append(r)
    todo = [n for n, r in enumerate(cached) if r is None]
    fresh = 0
    t_reg = 0.0
    clouds = [_SubmapClouds(s.name, s.points, s.submap_of_point, s.centres) for s in data]
    registered = (executor or get_executor()).map(
        _register_task, [cands[n] for n in todo], shared=(clouds, cfg), desc="ICP of submap pairs",
        label=lambda c: f"{data[c[0]].name} submap {c[1]} onto {data[c[2]].name} submap {c[3]}")
    for n, r in zip(todo, registered):  # in candidate order, whichever executor ran them
        r.key = keys[n]
        cache[keys[n]] = cached[n] = r
        fresh += 1
        t_reg += r.seconds
        if fresh % 25 == 0:
            _save_pair_cache(cache_path, cache)  # an interrupted run keeps what it registered
        if progress:
            print(f"\r[align] registered {fresh}/{len(todo)} new submap pairs ({len(cands)} in all)", end="", file=sys.stderr, flush=True)
    if progress and todo:
        print(file=sys.stderr)
    results: list[PairResult] = []
    for r in cached:
        r = copy.deepcopy(r)  # the graph may reject it below; the cache keeps the registration
        if r.source_points >= cfg.min_points and r.target_points >= cfg.min_points and r.reason != "not registered":
            r.accepted, r.reason, _ = _decide(r.metrics(), cfg.icp, r.centre)
        else:
            r.accepted = False
            r.reason = f"too few points ({r.source_points} source, {r.target_points} target; need {cfg.min_points})"
        results.append(r)
    _save_pair_cache(cache_path, cache)

    # 2. pose graph
    offsets = np.cumsum([0] + [s.n_submaps for s in data])
    node_of = {(s.name, k): offsets[si] + k for si, s in enumerate(data) for k in range(s.n_submaps)}
    centres = np.concatenate([s.centres for s in data])
    prev = _previous_corrections(out, data, cfg) if cfg.freeze_existing else {}
    fixed = np.zeros(len(centres), bool)
    x0 = np.zeros((len(centres), 6))
    for si, s in enumerate(data):
        if s.name in prev:
            fixed[offsets[si] : offsets[si + 1]] = True
            x0[offsets[si] : offsets[si + 1]] = prev[s.name]
    # start every free session at its robust session-level offset, so that the Cauchy loss below
    # judges ICP edges from inside the right basin (a session 8 m off would otherwise see all of its
    # correct registrations as outliers against its prior)
    init = session_offsets([r for r in results if r.accepted], [s.name for s in data],
                           {s.name: prev[s.name][:, 3:].mean(axis=0) for s in data if s.name in prev})
    for si, s in enumerate(data):
        if s.name not in prev:
            x0[offsets[si] : offsets[si + 1], 3:] = init[s.name]
    graph = PoseGraph(centres, cfg.graph, fixed=fixed, initial=x0)
    for si, s in enumerate(data):
        for k in range(s.n_submaps - 1):
            a, b = offsets[si] + k, offsets[si] + k + 1
            sup = _support_points(s.boundaries[k], s.directions[k], cfg.graph.lever_m)
            graph.add(Edge("odometry", a, b, sup, np.eye(4), cfg.graph.odometry_sigma_m))
    icp_edges = []
    session_index = {s.name: si for si, s in enumerate(data)}
    for pi, r in enumerate(results):
        if not r.accepted:
            continue
        a, b = node_of[tuple(r.source)], node_of[tuple(r.target)]
        direction = data[session_index[r.source[0]]].directions[r.source[1]]
        icp_edges.append(Edge("icp", a, b, _support_points(r.centre, direction, cfg.graph.lever_m), r.target_from_source, cfg.graph.icp_sigma_m, pi))
    odo_edges = list(graph.edges)
    active = list(icp_edges)
    x = graph.solve(odo_edges + active)
    for _ in range(cfg.graph.max_rounds - 1):
        rms = graph.edge_rms_sigmas(x, active)
        bad = rms > cfg.graph.reject_sigmas
        if not bad.any():
            break
        for e, rr, is_bad in zip(active, rms, bad):
            if is_bad:
                r = results[e.pair]
                r.accepted = False
                r.reason = f"inconsistent with the other registrations ({rr:.1f} sigma after the pose graph)"
        active = [e for e, is_bad in zip(active, bad) if not is_bad]
        x = graph.solve(odo_edges + active)

    # 3. per submap status: an overlapping submap without an accepted registration is unverified
    n_cand = np.zeros(len(centres), int)
    n_acc = np.zeros(len(centres), int)
    for r in results:
        for end in (r.source, r.target):
            n_cand[node_of[tuple(end)]] += 1
            n_acc[node_of[tuple(end)]] += r.accepted
    status = np.where(n_cand == 0, "no overlap", np.where(n_acc > 0, "verified", "unverified"))
    if not any(r.accepted for r in results):  # nothing ties the sessions together: fail before any output or marker
        from collections import Counter

        why = Counter(r.reason.split(" (")[0] for r in results)
        raise InputError(workspace, f"0 of {len(results)} candidate submap pairs verified by ICP"
                         + (f" ({', '.join(f'{k}: {v}' for k, v in sorted(why.items()))})" if why else "")
                         + "; the sessions share no mapped surface that registers: drive the same streets in at least two "
                         "sessions (more overlap, longer drives), or relax the icp gates of the align config")

    # 4. outputs
    qa = _write_outputs(out, data, x, offsets, status, n_cand, n_acc, results, cfg, ws_frame)
    qa["seconds"] = time.perf_counter() - t0
    qa["registration"] = {"pairs": len(results), "registered_this_run": fresh, "seconds_registering": t_reg,
                          "pairs_per_s": fresh / t_reg if t_reg > 0 else None}
    write_json(out / "metrics.json", qa)
    atomic_write_text(out / "qa.md", format_align_qa(qa))
    mark_done(out, run_hash, sessions=[s.name for s in data])
    return out


def aligned_sessions(workspace: str | Path) -> list[str]:
    """Sessions that a finished ``mapkit align`` holds (listed in ``WORKSPACE/align/.done``)."""
    done = Path(workspace) / "align" / ".done"
    if not done.is_file():
        return []
    try:
        return list(json.loads(done.read_text()).get("sessions", []))
    except (json.JSONDecodeError, AttributeError):
        return []


def _previous_corrections(out: Path, data: list[SessionData], cfg: AlignConfig) -> dict[str, np.ndarray]:
    """Corrections of sessions aligned by an earlier run with the same config and maps."""
    prev: dict[str, np.ndarray] = {}
    for s in data:
        p = out / "sessions" / s.name / "submaps.json"
        if not p.is_file():
            continue
        d = json.loads(p.read_text())
        if d.get("map_hash") != s.map_hash or d.get("config_hash") != config_hash(cfg) or len(d["submaps"]) != s.n_submaps:
            continue
        if not any(sm["status"] == "verified" for sm in d["submaps"]):
            continue  # nothing confirmed it then: align it afresh with the new company
        prev[s.name] = np.array([sm["correction"] for sm in d["submaps"]], np.float64)
    if len(prev) == len(data):
        return {}  # no new session (a changed threshold, say): solve everything again
    return prev


def _write_outputs(out: Path, data: list[SessionData], x: np.ndarray, offsets: np.ndarray, status: np.ndarray,
                   n_cand: np.ndarray, n_acc: np.ndarray, results: list[PairResult], cfg: AlignConfig, ws_frame: LocalFrame) -> dict:
    qa: dict = {"format_version": ALIGN_FORMAT_VERSION, "frame": ws_frame.to_dict(), "sessions": {}, "pairs": {}}
    merged_pts, merged_sid, merged_idx = [], [], []
    for si, s in enumerate(data):
        xs = x[offsets[si] : offsets[si + 1]]
        st = status[offsets[si] : offsets[si + 1]]
        sdir = out / "sessions" / s.name
        poses = apply_correction_poses(s, xs)
        traj = Trajectory(s.stamps_ns, poses, "align", frame="enu")
        traj.save(sdir / "trajectory")
        pts = apply_correction_points(s, xs, s.points, s.point_arc_m)
        smap = copy.copy(s.smap)
        smap.points_world = pts
        # keyframe poses follow their trajectory's correction
        kf_arc = np.interp(smap.keyframe_stamps_ns.astype(np.float64), s.stamps_ns.astype(np.float64), s.arc_m)
        R, c, t = correction_at(s, xs, kf_arc)
        kf = s.ws_from_session @ smap.keyframe_world_from_cam
        kf[:, :3, :3] = R @ kf[:, :3, :3]
        kf[:, :3, 3] = np.einsum("mij,mj->mi", R, kf[:, :3, 3] - c) + c + t
        smap.keyframe_world_from_cam = kf
        smap.save(sdir / "map", frame=ws_frame)
        _write_refined_images(s, poses, sdir, ws_frame)
        move = np.linalg.norm(poses[:, :3, 3] - s.poses[:, :3, 3], axis=1)
        submaps = []
        for k in range(s.n_submaps):
            Rk = Rotation.from_rotvec(xs[k, :3]).as_matrix()
            T = np.eye(4)
            T[:3, :3] = Rk
            T[:3, 3] = s.centres[k] + xs[k, 3:] - Rk @ s.centres[k]
            submaps.append({"index": k, "arc_m": [float(s.submap_edges_m[k]), float(s.submap_edges_m[k + 1])],
                            "centre_enu": s.centres[k].tolist(), "correction": xs[k].tolist(), "corrected_from_built": T.tolist(),
                            "status": str(st[k]), "pairs": int(n_cand[offsets[si] + k]), "pairs_accepted": int(n_acc[offsets[si] + k]),
                            "points": int((s.submap_of_point == k).sum())})
        write_json(sdir / "submaps.json", {"session": s.name, "map_hash": s.map_hash, "config_hash": config_hash(cfg),
                                           "frame": ws_frame.to_dict(), "submaps": submaps})
        keep = np.isin(s.submap_of_point, np.flatnonzero((st != "unverified") | cfg.merge_unverified))
        merged_pts.append(pts[keep])
        merged_sid.append(np.full(int(keep.sum()), si, np.int16))
        merged_idx.append(np.flatnonzero(keep).astype(np.int64))
        qa["sessions"][s.name] = {
            "submaps": s.n_submaps, "verified": int((st == "verified").sum()), "unverified": int((st == "unverified").sum()),
            "no_overlap": int((st == "no overlap").sum()), "points": len(pts), "points_merged": int(keep.sum()),
            "correction_median_m": float(np.median(move)), "correction_max_m": float(move.max()),
            "merged": bool(keep.any()),
        }
    acc = [r for r in results if r.accepted]
    rej = [r for r in results if not r.accepted]
    reasons: dict[str, int] = {}
    for r in rej:
        k = r.reason.split(" (")[0] if r.reason.startswith("inconsistent") or r.reason.startswith("too few") else r.reason.split(" ")[0]
        reasons[k] = reasons.get(k, 0) + 1
    qa["pairs"] = {"candidates": len(results), "accepted": len(acc), "rejected": len(rej), "rejected_by_reason": reasons,
                   "rmse_accepted_median_m": float(np.median([r.rmse_m for r in acc])) if acc else None,
                   "fitness_accepted_median": float(np.median([r.fitness for r in acc])) if acc else None,
                   "correction_accepted_median_m": float(np.median([r.correction_m for r in acc])) if acc else None}
    write_json(out / "pairs.json", {"format_version": ALIGN_FORMAT_VERSION, "pairs": [r.to_dict() for r in results]})
    qa["tiles"] = write_tiles(out / "tiles", np.concatenate(merged_pts), np.concatenate(merged_sid), np.concatenate(merged_idx),
                              [s.name for s in data], ws_frame, cfg.tile_size_m)
    from mapkit.io.plots import align_pairs_map, align_histograms

    align_pairs_map(out / "pairs_map.png", data, results)
    align_histograms(out / "icp_histograms.png", results, cfg.icp.lambda_icp_m, cfg.icp.min_fitness)
    return qa


def _write_refined_images(s: SessionData, refined_poses: np.ndarray, sdir: Path, ws_frame: LocalFrame) -> None:
    """The session's image database table with refined camera poses (``images.csv``, paths
    relative to it): each image moves with the correction of the trajectory at its stamp."""
    import os

    from mapkit.core.geometry import interpolate_poses
    from mapkit.mapping.imagedb import images_world_from_cam, read_images_csv, write_images_csv

    src = s.map_dir.parent / "imagedb" / "images.csv"
    if not src.is_file():
        return
    tab = read_images_csv(src)
    cams = s.ws_from_session @ images_world_from_cam(tab)
    before, ok = interpolate_poses(s.stamps_ns, s.poses, tab["stamp_ns"])
    after, _ = interpolate_poses(s.stamps_ns, refined_poses, tab["stamp_ns"])  # same stamps, same mask
    keep = np.flatnonzero(ok)
    if len(keep) < len(tab["stamp_ns"]):
        warnings.warn(f"{src}: {len(tab['stamp_ns']) - len(keep)} images outside the trajectory's time span left out of the refined table",
                      InputWarning, stacklevel=3)
    refined = after @ np.linalg.inv(before) @ cams[ok]
    rel = [os.path.relpath(src.parent / p, sdir) for p in tab["image"][keep]]
    write_images_csv(sdir / "images.csv", tab["image_id"][keep], tab["stamp_ns"][keep], list(tab["camera"][keep]), rel, refined, ws_frame)


def write_tiles(folder: Path, points_enu: np.ndarray, session_id: np.ndarray, point_index: np.ndarray, names: list[str],
                frame: LocalFrame, tile_m: float) -> dict:
    """The merged map as UTM tiles: ``E{easting}_N{northing}.ply`` holding UTM coordinates of the
    workspace's zone (float64 easting, northing, WGS84 ellipsoidal height; the EPSG code and the
    workspace origin in the PLY header), ``.npz`` (session and point index of every point, so
    observations stay reachable), and ``tiles.json`` with each tile's UTM bounds, count and
    checksums, and ``points_crs_epsg``: the CRS of the tiles' points."""
    folder.mkdir(parents=True, exist_ok=True)
    for old in folder.glob("E*_N*.*"):
        old.unlink()
    manifest = {"format_version": ALIGN_FORMAT_VERSION, "tile_size_m": tile_m, "utm_crs_epsg": frame.utm_epsg,
                "frame": frame.to_dict(), "points_frame": "utm", "points_crs_epsg": int(frame.utm_epsg),
                "points_z": "WGS84 ellipsoidal height (m)", "sessions": names, "tiles": []}
    if len(points_enu) == 0:
        write_json(folder / "tiles.json", manifest)
        return {"tiles": 0, "points": 0}
    utm = frame.enu_to_utm(points_enu)
    key = np.floor(utm[:, :2] / tile_m).astype(np.int64)
    order = np.lexsort((key[:, 1], key[:, 0]))
    key_sorted = key[order]
    starts = np.flatnonzero(np.r_[True, np.any(np.diff(key_sorted, axis=0) != 0, axis=1)])
    ends = np.r_[starts[1:], len(order)]
    tiles = []
    for s0, s1 in zip(starts, ends):
        sel = order[s0:s1]
        e, n = (int(v) for v in key_sorted[s0])
        stem = f"E{e * int(tile_m)}_N{n * int(tile_m)}"
        atomic_write_ply(folder / f"{stem}.ply", utm[sel], frame=frame, crs_epsg=int(frame.utm_epsg))
        with atomic_path(folder / f"{stem}.npz") as tmp:
            with open(tmp, "wb") as f:
                np.savez_compressed(f, session_id=session_id[sel], point_index=point_index[sel])
        tiles.append({"name": stem, "utm_min": [e * tile_m, n * tile_m], "utm_max": [(e + 1) * tile_m, (n + 1) * tile_m],
                      "points": int(len(sel)), "ply_sha256": sha256_file(folder / f"{stem}.ply"),
                      "npz_sha256": sha256_file(folder / f"{stem}.npz")})
    manifest["tiles"] = tiles
    write_json(folder / "tiles.json", manifest)
    return {"tiles": len(tiles), "points": int(len(points_enu))}


def load_tiles(folder: str | Path, bounds_utm: Optional[tuple[float, float, float, float]] = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """Points (workspace ENU), session ids, point indices and session names of the merged map,
    optionally only of the tiles meeting ``bounds_utm`` = (e_min, n_min, e_max, n_max). Tiles in
    UTM (``points_crs_epsg`` in tiles.json) are converted back to ENU; tiles written before mapkit
    stored UTM in them (``points_frame`` "workspace ENU") are read as they are."""
    import open3d as o3d

    folder = Path(folder)
    manifest_path = folder / "tiles.json"
    if not manifest_path.is_file():
        raise InputError(manifest_path, "no such file (not a merged map folder?)")
    m = json.loads(manifest_path.read_text())
    if m.get("format_version") != ALIGN_FORMAT_VERSION:
        raise InputError(manifest_path, f"format version {m.get('format_version')!r}; this mapkit reads {ALIGN_FORMAT_VERSION}", field="format_version")
    crs = m.get("points_crs_epsg")
    if crs is not None and "frame" not in m:
        raise InputError(manifest_path, f"tiles in EPSG:{crs} but no workspace frame to bring them back to ENU", field="frame")
    pts, sid, idx = [], [], []
    for t in m["tiles"]:
        if bounds_utm is not None:
            e0, n0, e1, n1 = bounds_utm
            if t["utm_max"][0] < e0 or t["utm_min"][0] > e1 or t["utm_max"][1] < n0 or t["utm_min"][1] > n1:
                continue
        pts.append(np.asarray(o3d.io.read_point_cloud(str(folder / f"{t['name']}.ply"), format="ply").points))
        with np.load(folder / f"{t['name']}.npz") as z:
            sid.append(z["session_id"])
            idx.append(z["point_index"])
    if not pts:
        return np.zeros((0, 3)), np.zeros(0, np.int16), np.zeros(0, np.int64), m.get("sessions", [])
    xyz = np.concatenate(pts)
    if crs is not None:
        xyz = LocalFrame.from_dict(m["frame"]).crs_to_enu(xyz, int(crs))
    return xyz, np.concatenate(sid), np.concatenate(idx), m["sessions"]


def format_align_qa(qa: dict) -> str:
    p = qa["pairs"]
    lines = [
        "# Multi-session alignment",
        "",
        f"Submap pairs: {p['candidates']} candidates, {p['accepted']} accepted, {p['rejected']} rejected "
        f"({', '.join(f'{k}: {v}' for k, v in p['rejected_by_reason'].items()) or 'none'}).",
        "",
        "| session | submaps | verified | unverified | no overlap | points merged | correction median m | max m |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, s in qa["sessions"].items():
        lines.append(f"| {name} | {s['submaps']} | {s['verified']} | {s['unverified']} | {s['no_overlap']} | "
                     f"{s['points_merged']}/{s['points']} | {s['correction_median_m']:.2f} | {s['correction_max_m']:.2f} |")
    if "truth" in qa:
        lines += ["", "## Against the synthetic truth", "", format_align_truth(qa["truth"])]
    return "\n".join(lines) + "\n"


def format_align_truth(t: dict) -> str:
    lines = ["| session pair | overlap points | misalignment median m, GPS alone | after refinement |", "|---|---|---|---|"]
    for k, v in t["pairs"].items():
        lines.append(f"| {k} | {v['points']} | {v['before_median_m']:.3f} | {v['after_median_m']:.3f} |")
    lines.append("")
    lines.append(f"Overall median: {t['before_median_m']:.3f} m -> {t['after_median_m']:.3f} m. "
                 f"Accepted ICP pairs with a true error above 1 m: {t['accepted_pairs_true_error_above_1m']} of {t['accepted_pairs']} "
                 f"(max {t['accepted_pair_true_error_max_m']:.2f} m).")
    if t.get("trajectories"):
        lines += ["", "Absolute trajectory error in the workspace frame (3D / horizontal RMSE, mean offset east, north, up), "
                  "and with that offset removed by a rigid yaw-only fit to truth (3D / horizontal / vertical RMSE):", "",
                  "| session | GPS alignment alone | after mapkit align | offset removed, GPS alone | offset removed, after align |",
                  "|---|---|---|---|---|"]
        for name, e in t["trajectories"].items():
            cells = [f"{e[w]['ate_rmse_m']:.2f} / {e[w]['horizontal_rmse_m']:.2f} m, ({', '.join(f'{x:.1f}' for x in e[w]['mean_offset_enu_m'])})"
                     for w in ("gps", "aligned")]
            cells += [f"{o['ate_rmse_m']:.2f} / {o['horizontal_rmse_m']:.2f} / {o['vertical_rmse_m']:.2f} m"
                      for o in (e[w].get("offset_removed") for w in ("gps", "aligned")) if o]
            lines.append("| " + " | ".join([name, *cells]) + " |")
    return "\n".join(lines)
