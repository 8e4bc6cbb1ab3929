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
3. A factor graph over all submaps (GTSAM, iSAM2; odometry edges inside a session, ICP edges
   between sessions, both robust, and one GPS bias state per session) is solved, sessions entering
   one update at a time; ICP edges that disagree with the rest after the solve are rejected and
   removed from the graph. Every submap's correction gets its marginal covariance, every session
   its GPS bias with its covariance.
4. Corrections are interpolated along each session (no tearing) and applied to its trajectory and
   maps (the semi-dense map and, where the build made one, the LiDAR map). Submaps that overlap
   other sessions but have no accepted registration are *unverified* and left out of the merged
   map (never silently merged).

Outputs under ``WORKSPACE/align/``: refined trajectories and maps per session, every submap's
correction, the merged map tiled by UTM, and a QA report (JSON, Markdown, PNGs).

Which maps are registered (``map_source``): the semi-dense maps (the default), the LiDAR maps
(every session must have one), or ``auto``: the LiDAR maps of a pair whose two sessions both have
one, the semi-dense maps of the others. Every pair records the maps it was registered on
(``map_source`` in pairs.json); metrics.json and qa.md count them.

The stage lives here (:func:`align_workspace`, its registration cache and outputs); its parts are
modules of their own: :mod:`~mapkit.multisession.submaps` (sessions and submap pairs),
:mod:`~mapkit.multisession.registration` (ICP and the accept/reject decision),
:mod:`~mapkit.multisession.posegraph`, :mod:`~mapkit.multisession.corrections` and
:mod:`~mapkit.multisession.tiles` (the merged map).
"""

from __future__ import annotations

import copy
import json
import logging
import time
import warnings
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field, field_validator
from scipy.spatial.transform import Rotation

from mapkit.core.config import MapkitConfig, dump_config, load_config
from mapkit.core.errors import InputError, InputWarning
from mapkit.core.executor import Executor, get_executor
from mapkit.core.fingerprint import check_file
from mapkit.core.geodesy import LocalFrame
from mapkit.core.geometry import interpolate_poses
from mapkit.core.runio import (
    atomic_path,
    atomic_write_text,
    config_hash,
    is_done,
    mark_done,
    read_marker,
    stage_digest,
    stage_hash,
    verify_file,
    write_json,
    write_timings,
)
from mapkit.core.workspace import AlignedDirs, MapKind, SessionDirs, Workspace
from mapkit.core.writers import writes_workspace
from mapkit.io.plots import align_histograms, align_pairs_map
from mapkit.mapping.icp import open3d_one_thread
from mapkit.mapping.imagedb import images_world_from_cam, read_images_csv, write_images_csv
from mapkit.mapping.lidar_map import save_voxel_map
from mapkit.mapping.trajectory import Trajectory
from mapkit.multisession.corrections import (
    apply_correction_points,
    apply_correction_poses,
    apply_correction_voxels,
    correction_at,
)
from mapkit.multisession.posegraph import Edge, GraphConfig, PoseGraph, session_offsets, support_points
from mapkit.multisession.registration import (
    IcpConfig,
    PairResult,
    Reason,
    Verdict,
    decide,
    enough_points,
    pair_points,
    register_pair,
)
from mapkit.multisession.submaps import SessionData, SubmapClouds, candidate_pairs, load_session
from mapkit.multisession.tiles import ALIGN_FORMAT_VERSION, write_tiles

log = logging.getLogger(__name__)

#: the version of this stage's algorithm, bumped whenever its output for the same inputs changes (it reruns)
STAGE_VERSION = 1

__all__ = [
    "AlignConfig",
    "align_workspace",
    "check_levels",
    "config_identity",
    "format_align_qa",
    "pair_sources",
]


class AlignConfig(MapkitConfig):
    submap_length_m: float = Field(
        50.0,
        gt=0,
        description="Submaps are cut every this much driving (m). mapkit choice: each submap gets one rigid "
        "correction, so shorter submaps follow the GPS error more closely and longer ones hold more points to "
        "register.",
    )
    overlap_radius_m: float = Field(
        35.0,
        gt=0,
        description="Submaps of different sessions whose trajectory centres lie within this distance (m) are "
        "registered.",
    )
    crop_radius_m: float = Field(
        40.0,
        gt=0,
        description="Both clouds of a pair are cropped to this horizontal radius around the pair centre (m).",
    )
    target_neighbours: int = Field(
        1,
        ge=0,
        description="The target cloud also includes this many neighbouring submaps on each side, so the source is "
        "fully covered.",
    )
    min_points: int = Field(
        1000,
        ge=10,
        description="A submap with fewer points (after cropping) is not registered: a few hundred points "
        "fit a wall in many places, and such a pair can be accepted metres off.",
    )
    icp: IcpConfig = IcpConfig()
    graph: GraphConfig = GraphConfig()
    freeze_existing: bool = Field(
        True,
        description="When sessions are added, keep the corrections of sessions aligned before fixed (their outputs do "
        "not change); false re-solves all.",
    )
    merge_unverified: bool = Field(
        False,
        description="Put submaps that overlap other sessions but have no accepted registration into the merged map.",
    )
    tile_size_m: float = Field(100.0, gt=0, description="Side of the UTM tiles of the merged map (m).")
    map_source: Literal["semidense", "lidar", "auto", "semidense+lidar"] = Field(
        "semidense+lidar",
        description="Maps the submap pairs are registered on: semidense, lidar (every session needs a LiDAR map), "
        "auto (lidar for a pair whose two sessions have a LiDAR map, semidense for the others), or semidense+lidar: "
        "semidense, and lidar for a pair whose semi-dense maps hold fewer than min_points about it (a drive in fog "
        "or at dusk, whose camera saw little) where both sessions have a LiDAR map. Each pair records which. The "
        "corrections move both maps either way. mapkit's default: aligning every pair on the LiDAR maps takes about "
        "four times as long (bench/align_map_sources.py on the demo town), and only where the semi-dense maps cannot "
        "register at all does a session otherwise stay where its GPS put it, metres off.",
    )

    @field_validator("icp")
    @classmethod
    def _icp_levels(cls, icp: IcpConfig) -> IcpConfig:
        """ICP's levels, checked before anything is loaded (open3d fails on a voxel <= 0 deep inside the
        registration)."""
        check_levels(icp.voxel_sizes_m, "voxel_sizes_m")
        check_levels(icp.max_correspondence_m, "max_correspondence_m")
        if len(icp.voxel_sizes_m) != len(icp.max_correspondence_m):
            raise ValueError(
                f"{len(icp.voxel_sizes_m)} voxel_sizes_m but {len(icp.max_correspondence_m)} max_correspondence_m "
                "(one per level)"
            )
        return icp


def config_identity(cfg: AlignConfig) -> dict:
    """What the alignment's hashes know of its config: ``map_source`` enters only when it is not ``semidense`` (the
    default before the option existed), so that alignments made before it stay valid."""
    return cfg.model_dump(mode="json", exclude={"map_source"} if cfg.map_source == "semidense" else set())


def check_levels(values: list[float], name: str) -> None:
    """ICP levels (voxel sizes, distances in m): at least one, each finite and > 0 (a ``ValueError`` naming
    ``name`` otherwise)."""
    if not values:
        raise ValueError(f"{name}: at least one ICP level is needed")
    bad = [v for v in values if not np.isfinite(v) or v <= 0]
    if bad:
        raise ValueError(f"{name}: every level must be a finite length > 0 m, not {bad[0]}")


# --- registering pairs on an executor -------------------------------------------------------------


def _register_task(
    shared: tuple[dict[MapKind, list[SubmapClouds | None]], AlignConfig], pair: tuple[int, int, int, int, MapKind]
) -> PairResult:
    """One submap pair on an executor's worker (open3d on one thread, so results do not depend on the executor),
    registered on the maps ``pair`` names."""
    clouds, cfg = shared
    ia, i, ib, j, source = pair
    a, b = clouds[source][ia], clouds[source][ib]
    assert a is not None and b is not None  # pair_sources chose lidar only where both sessions have a LiDAR map
    with open3d_one_thread():
        r = register_pair(a, i, b, j, cfg.icp, cfg.crop_radius_m, cfg.target_neighbours, cfg.min_points)
    r.map_source = source
    return r


def pair_sources(data: list[SessionData], cands: list[tuple[int, int, int, int]], cfg: AlignConfig) -> list[MapKind]:
    """The maps each candidate pair is registered on, under ``cfg.map_source`` (see :class:`AlignConfig`); ``lidar``
    with a session that has no LiDAR map is one error naming them."""
    if cfg.map_source == "lidar":
        lacking = [s.name for s in data if s.lidar is None]
        if lacking:
            raise InputError(
                None,
                f"map_source lidar, but session(s) {lacking} have no LiDAR map (lidar_map/ of mapkit build); "
                "use map_source auto (semi-dense maps for their pairs) or semidense",
                field="map_source",
            )
    if cfg.map_source == "semidense":
        return ["semidense"] * len(cands)
    both = [data[ia].lidar is not None and data[ib].lidar is not None for ia, _, ib, _ in cands]
    if cfg.map_source == "semidense+lidar":
        both = [b and _too_sparse(data[ia], i, data[ib], j, cfg) for b, (ia, i, ib, j) in zip(both, cands, strict=True)]
    return ["lidar" if b else "semidense" for b in both]


def _too_sparse(a: SessionData, i: int, b: SessionData, j: int, cfg: AlignConfig) -> bool:
    """Whether the semi-dense maps hold too few points about the pair to register it (either side under
    ``min_points`` once cropped as the registration crops them)."""
    src, tgt, _ = pair_points(a, i, b, j, cfg.crop_radius_m, cfg.target_neighbours)
    return not enough_points(len(src), len(tgt), cfg.min_points)


# --- the registration cache ------------------------------------------------------------------------


_DECISION_FIELDS = {"lambda_icp_m", "min_fitness", "min_structure_fitness", "max_correction_m", "max_rotation_deg"}


def _pair_key(a: SessionData, i: int, b: SessionData, j: int, cfg: AlignConfig, source: MapKind = "semidense") -> str:
    """What a registration depends on; the acceptance thresholds are not part of it (a cached
    registration is judged again under the current thresholds). A registration on the LiDAR maps
    is keyed by them as well (and a semi-dense one as it always was)."""
    icp = {k: v for k, v in cfg.icp.model_dump().items() if k not in _DECISION_FIELDS}
    key = {
        "a": [a.name, a.map_hash, i],
        "b": [b.name, b.map_hash, j],
        "len": cfg.submap_length_m,
        "crop": cfg.crop_radius_m,
        "nb": cfg.target_neighbours,
        "icp": icp,
    }
    if source == "lidar":
        assert a.lidar is not None and b.lidar is not None  # pair_sources chose lidar
        key["lidar"] = [a.lidar.map_hash, b.lidar.map_hash]
    return config_hash(key)


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


# --- the stage -------------------------------------------------------------------------------------


@writes_workspace("workspace")
def align_workspace(
    workspace: str | Path,
    config: str | Path | None = None,
    overrides: dict | None = None,
    progress: bool = True,
    sessions: list[str] | None = None,
    executor: Executor | None = None,
) -> Path:
    """Align every built session of ``workspace``; returns ``WORKSPACE/align``.

    Submap pairs are registered on ``executor`` (default: :func:`mapkit.core.executor.get_executor`),
    each with open3d on one thread, so that the registrations are the same bit for bit on any
    executor (open3d's multi-threaded ICP sums in a varying order).
    """
    ws = Workspace(workspace)
    cfg = load_config(AlignConfig, config, overrides)
    if not ws.origin.is_file():
        raise InputError(
            ws.origin, "no such file: the workspace has no georeferenced session to align (run mapkit build first)"
        )
    ws_frame = ws.frame()
    assert ws_frame is not None  # origin.json exists (checked above)
    out = ws.align_dir
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "config.yaml", dump_config(cfg))
    t0 = time.perf_counter()

    names = ws.session_names() if sessions is None else sessions
    for n in names:
        _verify_built(ws.session(n))
    ident = config_identity(cfg)
    data = [s for s in (load_session(ws.session(n), ws_frame, cfg.submap_length_m) for n in names) if s is not None]
    for s in data:
        _identify_map(s, ws.session(s.name))
    if len(data) < 2:
        raise InputError(
            ws.root,
            f"{len(data)} alignable session(s); multi-session alignment needs at least two built, "
            "georeferenced sessions with a semi-dense map (the warnings above say why each was skipped)",
        )
    run_config = {
        "cfg": ident,
        "sessions": [[s.name, s.map_hash] + ([s.lidar.map_hash] if s.lidar else []) for s in data],
    }
    run_hash = stage_hash("align", STAGE_VERSION, run_config)
    inputs = {
        s.name: {
            stage: stage_digest(ws.session(s.name).stage(stage))
            for stage in ("georef", "map", *(("lidar_map",) if s.lidar else ()))
        }
        for s in data
    }
    if is_done(out, run_hash, inputs=inputs, legacy_hash=config_hash(run_config), version=STAGE_VERSION):
        return out
    finished = (read_marker(out) or {}).get(
        "outputs"
    ) or {}  # what the last finished run wrote (frozen sessions keep theirs)
    ws.align_done.unlink(missing_ok=True)

    regs = _register_pairs(out / "registrations.json", data, cfg, executor, progress)  # 1. registrations
    nodes = _Nodes.of(data)
    sol = _solve_graph(ws, data, nodes, regs.results, cfg)  # 2. pose graph
    status, n_cand, n_acc = _submap_status(nodes, regs.results)  # 3. which submaps are verified
    _require_a_verified_pair(ws, regs.results)

    # 4. outputs
    qa = _write_outputs(ws, data, sol, nodes.offsets, status, n_cand, n_acc, regs.results, cfg, ws_frame, finished)
    qa["graph"] = {"isam2_updates": sol.updates, "sessions_solved": sol.solved}
    qa["registration"] = {"pairs": len(regs.results), "registered_this_run": regs.fresh}
    write_json(out / "metrics.json", qa)
    write_timings(
        out,
        seconds=time.perf_counter() - t0,
        graph_seconds=sol.seconds,
        seconds_registering=regs.seconds,
        pairs_per_s=regs.fresh / regs.seconds if regs.seconds > 0 else None,
    )
    atomic_write_text(out / "qa.md", format_align_qa(qa))
    mark_done(
        out,
        run_hash,
        version=STAGE_VERSION,
        inputs=inputs,
        outputs=["sessions", "tiles", "pairs.json"],
        sessions=[s.name for s in data],
    )
    return out


def _verify_built(dirs: SessionDirs) -> None:
    """Refuse a built session whose map or aligned trajectory changed since ``mapkit build`` wrote
    it (a truncated ``points.ply`` would load with its missing points as zeros): one error naming
    the file. Sessions that are not fully built are left to :func:`load_session`'s warning."""
    if not (dirs.has("georef") and dirs.has("map")):
        return
    lidar = (dirs.lidar_map / "points.ply", dirs.lidar_map / "voxels.npz") if dirs.has("lidar_map") else ()
    for path in (
        dirs.map / "points.ply",
        dirs.map / "observations.npz",
        *lidar,
        dirs.gps_alignment,
        *sorted(dirs.enu_trajectory.glob("*.npz")),
    ):
        verify_file(path, f"mapkit build (session {dirs.name})")


def _identify_map(s: SessionData, dirs: SessionDirs) -> None:
    """Make the session's map hash (the key of cached registrations and corrections) cover the
    map's content where its build recorded it, not only its config: a map rebuilt from a changed
    log is registered again. A map whose marker records no outputs keeps its config hash, and its cache."""
    outputs = (read_marker(dirs.map) or {}).get("outputs")
    if outputs:
        s.map_hash = config_hash([s.map_hash, outputs])


@dataclass
class _Registrations:
    results: list[PairResult]  # every candidate pair, judged under today's config
    fresh: int  # pairs registered by this run (the others came from the cache)
    seconds: float  # time spent registering them (summed over workers)


def _register_pairs(
    cache_path: Path, data: list[SessionData], cfg: AlignConfig, executor: Executor | None, progress: bool
) -> _Registrations:
    """Every candidate pair registered (cached by content: a new session only registers its own
    pairs) and judged under the current gates; the cache keeps the registrations."""
    cache = _load_pair_cache(cache_path)
    cands = candidate_pairs(data, cfg.overlap_radius_m)
    sources = pair_sources(data, cands, cfg)
    keys = [_pair_key(data[ia], i, data[ib], j, cfg, src) for (ia, i, ib, j), src in zip(cands, sources, strict=True)]
    cached: list[PairResult | None] = []
    for key in keys:
        r = cache.get(key)
        if (
            r is not None
            and r.verdict.reason is Reason.NOT_REGISTERED
            and enough_points(r.source_points, r.target_points, cfg.min_points)
        ):
            r = None  # skipped under a stricter min_points than today's
        cached.append(r)
    todo = [n for n, r in enumerate(cached) if r is None]
    if todo:
        log.info("registering %d new submap pairs (%d in all)", len(todo), len(cands))
    fresh, seconds = 0, 0.0
    clouds: dict[MapKind, list[SubmapClouds | None]] = {
        "semidense": [SubmapClouds(s.name, s.points, s.submap_of_point, s.centres) for s in data],
        "lidar": [
            None if s.lidar is None else SubmapClouds(s.name, s.lidar.points, s.lidar.submap_of_point, s.centres)
            for s in data
        ],
    }
    registered = (executor or get_executor()).map(
        _register_task,
        [(*cands[n], sources[n]) for n in todo],
        shared=(clouds, cfg),
        progress=progress,
        desc="ICP of submap pairs",
        unit="pair",
        label=lambda c: f"{data[c[0]].name} submap {c[1]} onto {data[c[2]].name} submap {c[3]}",
    )
    for n, r in zip(todo, registered, strict=True):  # in candidate order, whichever executor ran them
        r.key = keys[n]
        cache[keys[n]] = cached[n] = r
        fresh += 1
        seconds += r.seconds
        if fresh % 25 == 0:
            _save_pair_cache(cache_path, cache)  # an interrupted run keeps what it registered
    # copies: the graph may reject them, the cache keeps the registration
    results = []
    for r in cached:
        assert r is not None  # registered above when not cached
        results.append(_judge(copy.deepcopy(r), cfg))
    _save_pair_cache(cache_path, cache)
    return _Registrations(results, fresh, seconds)


def _judge(r: PairResult, cfg: AlignConfig) -> PairResult:
    """``r`` with its verdict under the current gates (a cached registration was judged under the gates of the run
    that cached it)."""
    if (
        enough_points(r.source_points, r.target_points, cfg.min_points)
        and r.verdict.reason is not Reason.NOT_REGISTERED
    ):
        r.verdict, _ = decide(r.registration(), cfg.icp, r.centre)
    else:
        r.verdict = Verdict.of(
            Reason.TOO_FEW_POINTS, f"{r.source_points} source, {r.target_points} target; need {cfg.min_points}"
        )
    return r


@dataclass(frozen=True)
class _Nodes:
    """Every session's submaps as the nodes of one pose graph."""

    offsets: np.ndarray  # (S + 1,) first node of each session, then the number of nodes
    node_of: dict[tuple[str, int], int]  # (session, submap) -> node
    centres: np.ndarray  # (n, 3)

    @classmethod
    def of(cls, data: list[SessionData]) -> _Nodes:
        offsets = np.cumsum([0] + [s.n_submaps for s in data])
        node_of = {(s.name, k): offsets[si] + k for si, s in enumerate(data) for k in range(s.n_submaps)}
        return cls(offsets, node_of, np.concatenate([s.centres for s in data]))


@dataclass
class _Solution:
    x: np.ndarray  # (n, 6) corrections [rotation vector, translation at the centre]
    covariance: np.ndarray  # (n, 6, 6) their marginal covariances (rotation rad, translation m; ENU axes)
    biases: dict[str, tuple[np.ndarray, np.ndarray]]  # session -> GPS bias estimate (ENU m) and its covariance
    seconds: float
    updates: int  # iSAM2 updates
    solved: int  # sessions whose submaps were variables (the others were frozen by an earlier run)
    frozen: frozenset[str] = frozenset()  # those others: their corrections are the earlier run's


def _solve_graph(
    ws: Workspace, data: list[SessionData], nodes: _Nodes, results: list[PairResult], cfg: AlignConfig
) -> _Solution:
    """Corrections of all submaps and their covariances; ICP edges that disagree with the rest after
    a solve are rejected (their pairs' verdicts say so) and removed from the graph."""
    t0 = time.perf_counter()
    offsets = nodes.offsets
    prev = _previous_corrections(ws, data, cfg) if cfg.freeze_existing else {}
    fixed = np.zeros(len(nodes.centres), bool)
    x0 = np.zeros((len(nodes.centres), 6))
    cov0 = np.zeros((len(nodes.centres), 6, 6))
    for si, s in enumerate(data):
        if s.name in prev:
            fixed[offsets[si] : offsets[si + 1]] = True
            x0[offsets[si] : offsets[si + 1]], cov0[offsets[si] : offsets[si + 1]] = (
                prev[s.name].x,
                prev[s.name].covariance,
            )
    # start every free session at its robust session-level offset, so that the Cauchy kernel below
    # judges ICP edges from inside the right basin (a session 8 m off would otherwise see all of its
    # correct registrations as outliers against its prior)
    init = session_offsets(
        [r for r in results if r.accepted],
        [s.name for s in data],
        {s.name: prev[s.name].x[:, 3:].mean(axis=0) for s in data if s.name in prev},
    )
    for si, s in enumerate(data):
        if s.name not in prev:
            x0[offsets[si] : offsets[si + 1], 3:] = init[s.name]
    session_of = np.repeat(np.arange(len(data)), np.diff(offsets))
    graph = PoseGraph(nodes.centres, cfg.graph, fixed=fixed, initial=x0, session_of=session_of)
    for si, s in enumerate(data):
        for k in range(s.n_submaps - 1):
            a, b = offsets[si] + k, offsets[si] + k + 1
            sup = support_points(s.boundaries[k], s.directions[k], cfg.graph.lever_m)
            sigma = cfg.graph.odometry_sigma_fused_m if s.fused else cfg.graph.odometry_sigma_m
            graph.add(Edge("odometry", a, b, sup, np.eye(4), sigma))
    session_index = {s.name: si for si, s in enumerate(data)}
    for pi, r in enumerate(results):
        if not r.accepted:
            continue
        a, b = nodes.node_of[r.source], nodes.node_of[r.target]
        direction = data[session_index[r.source[0]]].directions[r.source[1]]
        graph.add(
            Edge(
                "icp",
                a,
                b,
                support_points(r.centre, direction, cfg.graph.lever_m),
                r.target_from_source,
                cfg.graph.icp_sigma_m,
                pi,
            )
        )
    active = [e for e in graph.edges if e.kind == "icp"]
    x = graph.solve()
    for _ in range(cfg.graph.max_rounds - 1):
        rms = graph.edge_rms_sigmas(x, active)
        bad = rms > cfg.graph.reject_sigmas
        if not bad.any():
            break
        for e, rr, is_bad in zip(active, rms, bad, strict=True):
            if is_bad:
                assert e.pair is not None  # an ICP edge names its pair
                results[e.pair].verdict = Verdict.of(Reason.INCONSISTENT, f"{rr:.1f} sigma after the pose graph")
        x = graph.remove([e for e, is_bad in zip(active, bad, strict=True) if is_bad])
        active = [e for e, is_bad in zip(active, bad, strict=True) if not is_bad]
    # frozen sessions enter as known: what the graph gives the new ones is relative to their frame,
    # so the frame's own uncertainty (the frozen anchors' covariance, nearly all common to them) is added
    frame = _frame_covariance(fixed, cov0, graph.edges, active)
    cov = np.where(fixed[:, None, None], cov0, graph.covariances() + frame)
    biases = {n: p.bias for n, p in prev.items() if p.bias is not None}
    biases.update({data[si].name: (b, c + frame[3:, 3:]) for si, (b, c) in graph.biases().items()})
    return _Solution(x, cov, biases, time.perf_counter() - t0, graph.updates, len(data) - len(prev), frozenset(prev))


def _frame_covariance(fixed: np.ndarray, cov0: np.ndarray, edges: list[Edge], active: list[Edge]) -> np.ndarray:
    """(6, 6) covariance of the frozen sessions' frame as the new ones see it: the mean covariance
    of the frozen nodes that an edge in the graph ties to a free node (zeros if none)."""
    kept = {id(e) for e in active}
    anchors = {
        e.a if fixed[e.a] else e.b for e in edges if fixed[e.a] != fixed[e.b] and (e.kind != "icp" or id(e) in kept)
    }
    return cov0[sorted(anchors)].mean(axis=0) if anchors else np.zeros((6, 6))


def _submap_status(nodes: _Nodes, results: list[PairResult]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per node: "verified", "unverified" (overlaps another session, no accepted registration) or
    "no overlap"; and its candidate and accepted pair counts."""
    n_cand = np.zeros(len(nodes.centres), int)
    n_acc = np.zeros(len(nodes.centres), int)
    for r in results:
        for end in (r.source, r.target):
            n_cand[nodes.node_of[end]] += 1
            n_acc[nodes.node_of[end]] += r.accepted
    status = np.where(n_cand == 0, "no overlap", np.where(n_acc > 0, "verified", "unverified"))
    return status, n_cand, n_acc


def _require_a_verified_pair(ws: Workspace, results: list[PairResult]) -> None:
    """Nothing ties the sessions together without an accepted pair: fail before any output or marker."""
    if any(r.accepted for r in results):
        return
    why = Counter(r.verdict.headline for r in results)
    raise InputError(
        ws.root,
        f"0 of {len(results)} candidate submap pairs verified by ICP"
        + (f" ({', '.join(f'{k}: {v}' for k, v in sorted(why.items()))})" if why else "")
        + "; the sessions share no mapped surface that registers: drive the same streets in at least two "
        "sessions (more overlap, longer drives), or relax the icp gates of the align config",
    )


# --- outputs ---------------------------------------------------------------------------------------


@dataclass
class _Previous:
    """A session aligned by an earlier run: its corrections, their covariances and its GPS bias (if recorded)."""

    x: np.ndarray
    covariance: np.ndarray
    bias: tuple[np.ndarray, np.ndarray] | None


def _previous_corrections(ws: Workspace, data: list[SessionData], cfg: AlignConfig) -> dict[str, _Previous]:
    """Sessions aligned by an earlier run with the same config and maps."""
    prev: dict[str, _Previous] = {}
    for s in data:
        p = ws.aligned(s.name).submaps
        if not p.is_file():
            continue
        d = json.loads(p.read_text())
        if (
            d.get("map_hash") != s.map_hash
            or d.get("config_hash") != config_hash(config_identity(cfg))
            or len(d["submaps"]) != s.n_submaps
            or (cfg.map_source != "semidense" and d.get("lidar_map_hash") != (s.lidar.map_hash if s.lidar else None))
        ):
            continue
        if not any(sm["status"] == "verified" for sm in d["submaps"]):
            continue  # nothing confirmed it then: align it afresh with the new company
        bias = d.get("gps_bias")
        prev[s.name] = _Previous(
            np.array([sm["correction"] for sm in d["submaps"]], np.float64),
            np.array([sm.get("covariance", np.zeros((6, 6)).tolist()) for sm in d["submaps"]], np.float64),
            (np.asarray(bias["enu_m"]), np.asarray(bias["covariance_m2"])) if bias else None,
        )
    if len(prev) == len(data):
        return {}  # no new session (a changed threshold, say): solve everything again
    return prev


def _write_outputs(
    ws: Workspace,
    data: list[SessionData],
    sol: _Solution,
    offsets: np.ndarray,
    status: np.ndarray,
    n_cand: np.ndarray,
    n_acc: np.ndarray,
    results: list[PairResult],
    cfg: AlignConfig,
    ws_frame: LocalFrame,
    finished: dict,
) -> dict:
    """Every session's refined outputs, pairs.json, the merged map's tiles and the QA pictures; returns the QA summary.
    ``finished``: the output records of the last finished run (its marker's), by which a frozen session's
    trajectory, map and image table are kept instead of written again when they are still those files."""
    out = ws.align_dir
    qa: dict = {"format_version": ALIGN_FORMAT_VERSION, "frame": ws_frame.to_dict(), "sessions": {}, "pairs": {}}
    merged_pts, merged_sid, merged_idx = [], [], []
    for si, s in enumerate(data):
        nodes = slice(offsets[si], offsets[si + 1])
        bias = sol.biases.get(s.name)
        keep_files = s.name in sol.frozen and _outputs_intact(ws, s.name, finished, s.lidar is not None)
        pts, keep, qa["sessions"][s.name] = _write_session(
            ws,
            s,
            sol.x[nodes],
            sol.covariance[nodes],
            bias,
            status[nodes],
            n_cand[nodes],
            n_acc[nodes],
            cfg,
            ws_frame,
            keep_files,
        )
        merged_pts.append(pts[keep])
        merged_sid.append(np.full(int(keep.sum()), si, np.int16))
        merged_idx.append(np.flatnonzero(keep).astype(np.int64))
    qa["pairs"] = _pair_summary(results)
    qa["map_source"] = {
        "config": cfg.map_source,
        "pairs": dict(sorted(Counter(r.map_source for r in results).items())),
        "sessions_without_lidar_map": [s.name for s in data if s.lidar is None],
    }
    write_json(out / "pairs.json", {"format_version": ALIGN_FORMAT_VERSION, "pairs": [r.to_dict() for r in results]})
    qa["tiles"] = write_tiles(
        ws.tiles_dir,
        np.concatenate(merged_pts),
        np.concatenate(merged_sid),
        np.concatenate(merged_idx),
        [s.name for s in data],
        ws_frame,
        cfg.tile_size_m,
    )

    align_pairs_map(out / "pairs_map.png", data, results)
    align_histograms(out / "icp_histograms.png", results, cfg.icp.lambda_icp_m, cfg.icp.min_fitness)
    return qa


def _outputs_intact(ws: Workspace, name: str, finished: dict, lidar: bool = False) -> bool:
    """Whether session ``name``'s trajectory, map(s) and image table under ``align/sessions`` are still the
    files the last finished run recorded (size and SHA-256 in ``finished``), its map (and with ``lidar`` its
    LiDAR map) among them."""
    prefix = f"sessions/{name}/"
    recorded = {rel: rec for rel, rec in finished.items() if rel.startswith(prefix) and rel != prefix + "submaps.json"}
    needed = {prefix + "map/points.ply", prefix + "map/observations.npz"}
    if lidar:
        needed |= {prefix + "lidar_map/points.ply", prefix + "lidar_map/voxels.npz"}
    if not needed <= set(recorded):
        return False
    return all(check_file(ws.align_dir / rel, rec) is None for rel, rec in recorded.items())


def _write_session(
    ws: Workspace,
    s: SessionData,
    xs: np.ndarray,
    cov: np.ndarray,
    bias: tuple[np.ndarray, np.ndarray] | None,
    st: np.ndarray,
    n_cand: np.ndarray,
    n_acc: np.ndarray,
    cfg: AlignConfig,
    ws_frame: LocalFrame,
    keep_files: bool = False,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """Session ``s`` under its submaps' corrections ``xs`` (covariances ``cov``, GPS bias ``bias``):
    trajectory, map, image table and submaps.json in ``align/sessions/<name>``. Returns its
    corrected points, those that go into the merged map (not unverified, unless merge_unverified)
    and its QA summary. ``keep_files``: the trajectory, map and image table on disk were made from
    these same corrections (a frozen session, checked against the last run's records): only
    submaps.json, whose statuses and pair counts the new pairs change, is written."""
    dirs = ws.aligned(s.name)
    poses = apply_correction_poses(s, xs)
    pts = apply_correction_points(s, xs, s.points, s.point_arc_m)
    if not keep_files:
        Trajectory(s.stamps_ns, poses, "align", frame="enu").save(dirs.trajectory)
        assert s.smap is not None  # load_session keeps the map as built
        smap = copy.copy(s.smap)
        smap.points_world = pts
        # keyframe poses follow their trajectory's correction
        kf_arc = np.interp(smap.keyframe_stamps_ns.astype(np.float64), s.stamps_ns.astype(np.float64), s.arc_m)
        R, c, t = correction_at(s, xs, kf_arc)
        kf = s.ws_from_session @ smap.keyframe_world_from_cam
        kf[:, :3, :3] = R @ kf[:, :3, :3]
        kf[:, :3, 3] = np.einsum("mij,mj->mi", R, kf[:, :3, 3] - c) + c + t
        smap.keyframe_world_from_cam = kf
        smap.save(dirs.map, frame=ws_frame)
        if s.lidar is not None:
            _write_lidar_map(dirs.lidar_map, s, xs, st, cfg, ws_frame)
        _write_refined_images(s, poses, ws.session(s.name).images_csv, dirs, ws_frame)
    move = np.linalg.norm(poses[:, :3, 3] - s.poses[:, :3, 3], axis=1)
    sigma = np.sqrt(np.maximum(np.diagonal(cov, axis1=1, axis2=2)[:, 3:], 0))  # (K, 3) position sigmas, ENU m
    submaps = []
    for k in range(s.n_submaps):
        Rk = Rotation.from_rotvec(xs[k, :3]).as_matrix()
        T = np.eye(4)
        T[:3, :3] = Rk
        T[:3, 3] = s.centres[k] + xs[k, 3:] - Rk @ s.centres[k]
        submaps.append(
            {
                "index": k,
                "arc_m": [float(s.submap_edges_m[k]), float(s.submap_edges_m[k + 1])],
                "centre_enu": s.centres[k].tolist(),
                "correction": xs[k].tolist(),
                "corrected_from_built": T.tolist(),
                "covariance": cov[k].tolist(),
                "position_sigma_enu_m": sigma[k].tolist(),
                "status": str(st[k]),
                "pairs": int(n_cand[k]),
                "pairs_accepted": int(n_acc[k]),
                "points": int((s.submap_of_point == k).sum()),
            }
        )
    doc = {
        "session": s.name,
        "map_hash": s.map_hash,
        **({"lidar_map_hash": s.lidar.map_hash} if s.lidar else {}),
        "config_hash": config_hash(config_identity(cfg)),
        "frame": ws_frame.to_dict(),
        "submaps": submaps,
        "covariance_axes": "rotation (rad) about east, north, up; translation (m) east, north, up; at each submap's "
        "centre",
    }
    if bias is not None:
        doc["gps_bias"] = {
            "enu_m": bias[0].tolist(),
            "covariance_m2": bias[1].tolist(),
            "sigma_enu_m": np.sqrt(np.diag(bias[1])).tolist(),
        }
    write_json(dirs.submaps, doc)
    keep = np.isin(s.submap_of_point, np.flatnonzero((st != "unverified") | cfg.merge_unverified))
    summary = {
        "submaps": s.n_submaps,
        "verified": int((st == "verified").sum()),
        "unverified": int((st == "unverified").sum()),
        "no_overlap": int((st == "no overlap").sum()),
        "points": len(pts),
        "points_merged": int(keep.sum()),
        "correction_median_m": float(np.median(move)),
        "correction_max_m": float(move.max()),
        "position_sigma_median_m": np.median(sigma, axis=0).tolist(),
        "merged": bool(keep.any()),
        "outputs_kept": keep_files,
        **({"lidar_voxels": len(s.lidar.points)} if s.lidar else {}),
    }
    return pts, keep, summary


def _write_lidar_map(
    folder: Path, s: SessionData, xs: np.ndarray, st: np.ndarray, cfg: AlignConfig, ws_frame: LocalFrame
) -> None:
    """Session ``s``'s LiDAR map under its corrections ``xs`` into ``folder`` (``points.ply`` with the frame in its
    header, ``voxels.npz`` as the build writes them), and ``voxel_submaps.npz``: each voxel's submap and whether it
    belongs to the merged map (its submap is not unverified, unless merge_unverified), as the tiles say of the
    semi-dense points."""
    assert s.lidar is not None
    save_voxel_map(folder, apply_correction_voxels(s, xs, s.lidar), ws_frame)
    sub = s.lidar.submap_of_point
    merged = np.isin(sub, np.flatnonzero((st != "unverified") | cfg.merge_unverified))
    with atomic_path(folder / "voxel_submaps.npz") as tmp, open(tmp, "wb") as f:
        np.savez(f, submap=sub.astype(np.int32), merged=merged)


def _pair_summary(results: list[PairResult]) -> dict:
    """Pair counts, rejections by reason and the accepted pairs' medians (qa.json's ``pairs``)."""
    acc = [r for r in results if r.accepted]
    rej = [r for r in results if not r.accepted]
    reasons: dict[str, int] = {}
    for r in rej:
        reasons[r.verdict.reason.tally] = reasons.get(r.verdict.reason.tally, 0) + 1
    return {
        "candidates": len(results),
        "accepted": len(acc),
        "rejected": len(rej),
        "rejected_by_reason": reasons,
        "rmse_accepted_median_m": float(np.median([r.rmse_m for r in acc])) if acc else None,
        "fitness_accepted_median": float(np.median([r.fitness for r in acc])) if acc else None,
        "correction_accepted_median_m": float(np.median([r.correction_m for r in acc])) if acc else None,
    }


def _write_refined_images(
    s: SessionData, refined_poses: np.ndarray, src: Path, dirs: AlignedDirs, ws_frame: LocalFrame
) -> None:
    """The session's image database table ``src`` with refined camera poses (``images.csv`` of
    ``dirs``, paths relative to it): each image moves with the correction of the trajectory at its stamp."""
    import os

    if not src.is_file():
        return
    tab = read_images_csv(src)
    cams = s.ws_from_session @ images_world_from_cam(tab)
    before, ok = interpolate_poses(s.stamps_ns, s.poses, tab["stamp_ns"])
    after, _ = interpolate_poses(s.stamps_ns, refined_poses, tab["stamp_ns"])  # same stamps, same mask
    keep = np.flatnonzero(ok)
    if len(keep) < len(tab["stamp_ns"]):
        warnings.warn(
            f"{src}: {len(tab['stamp_ns']) - len(keep)} images outside the trajectory's time span left out of the "
            "refined table",
            InputWarning,
            stacklevel=4,
        )
    refined = after @ np.linalg.inv(before) @ cams[ok]
    rel = [os.path.relpath(src.parent / p, dirs.root) for p in tab["image"][keep]]
    write_images_csv(
        dirs.images_csv, tab["image_id"][keep], tab["stamp_ns"][keep], list(tab["camera"][keep]), rel, refined, ws_frame
    )


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
        lines.append(
            f"| {name} | {s['submaps']} | {s['verified']} | {s['unverified']} | {s['no_overlap']} | "
            f"{s['points_merged']}/{s['points']} | {s['correction_median_m']:.2f} | {s['correction_max_m']:.2f} |"
        )
    ms = qa.get("map_source")
    if ms and ms["config"] != "semidense":
        counts = ", ".join(f"{n} on {k} maps" for k, n in ms["pairs"].items()) or "none"
        lacking = ms["sessions_without_lidar_map"]
        lines += [
            "",
            f"Registered on (map_source {ms['config']}): {counts}"
            + (f"; the semi-dense maps where a session has no LiDAR map ({', '.join(lacking)})" if lacking else "")
            + ".",
        ]
    return "\n".join(lines) + "\n"
