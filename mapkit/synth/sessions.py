"""Sessions: routes on the road graph (or an external trajectory), vehicle motion, and the logs.

Every planned route drives the town's anchor road (so that all sessions share one place), and
extends from it by random walks that prefer going straight and never repeat a road, so routes
overlap in part. The vehicle keeps to the right-hand lane with a per-session lateral offset and a
slow wander, turns on fillets at junctions, and follows a speed profile limited by lateral
acceleration in curves. Body roll and pitch follow lateral and longitudinal acceleration.

Ground truth is sampled at ``motion.ground_truth_rate_hz``; every sensor pose is interpolated
from these samples (linear position, slerp rotation, ``mapkit.core.geometry.interpolate_poses``), so
that the ``.gt.tum`` file reproduces every sensor pose exactly.
"""

from __future__ import annotations

import csv
import datetime as dt
import time
from dataclasses import dataclass
from pathlib import Path
from zoneinfo import ZoneInfo, ZoneInfoNotFoundError

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.spatial.transform import Rotation

from mapkit.core.errors import ConfigError, InputError
from mapkit.core.geometry import interpolate_poses, make_pose
from mapkit.core.runio import progress_bar
from mapkit.core.types import (
    CameraFrame,
    CameraInfo,
    FrameTransform,
    GpsFix,
    GpsStatus,
    ImuSample,
    LidarScan,
    PoseSample,
)
from mapkit.io.mcap_log import Rosbag2Writer
from mapkit.io.trajectory import read_kitti_poses, read_tum, write_tum
from mapkit.synth import moving_cars_path, session_log_relpath
from mapkit.synth.appearance import Conditions, make_conditions
from mapkit.synth.config import SessionConfig, SynthConfig
from mapkit.synth.sensors import (
    FRAME_BASE,
    FRAME_CAMERA,
    FRAME_GPS,
    FRAME_IMU,
    FRAME_LIDAR,
    FRAME_WORLD,
    GpsErrorModel,
    extrinsics,
    imu_from_poses,
    intrinsics,
)
from mapkit.synth.traffic import oncoming_traffic, write_dynamic_truth
from mapkit.synth.world import DRIVE_LANE_CENTER_M, Mat, RoadGraph, Town, parked_cars, write_ply

TOPIC_IMAGE = "/camera/front/image"
TOPIC_CAMERA_INFO = "/camera/front/camera_info"
TOPIC_LIDAR = "/lidar/points"
TOPIC_GPS = "/gps/fix"
TOPIC_IMU = "/imu/data"
TOPIC_TF_STATIC = "/tf_static"
TOPIC_GROUND_TRUTH = "/ground_truth/odom"

MAX_TURN_RAD = np.radians(125.0)
ROUTE_MARGIN_M = 150.0  # planned beyond the session's window, so that followers can shift along it


# --- routes ----------------------------------------------------------------------------------------


def _heading_at(g: RoadGraph, road_id: int, start: int, at_start: bool, lookahead: float = 8.0) -> np.ndarray:
    road = g.roads[road_id]
    poly = g.oriented(road, start)
    S = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(poly, axis=0), axis=1))])
    s = min(lookahead, S[-1] / 2)
    if at_start:
        a, b = poly[0], np.array([np.interp(s, S, poly[:, 0]), np.interp(s, S, poly[:, 1])])
    else:
        a, b = np.array([np.interp(S[-1] - s, S, poly[:, 0]), np.interp(S[-1] - s, S, poly[:, 1])]), poly[-1]
    d = b - a
    return d / max(np.linalg.norm(d), 1e-9)


def _walk(
    g: RoadGraph,
    in_road: int,
    came_from: int,
    node: int,
    target_m: float,
    rng: np.random.Generator,
    used: set[int],
    driven: dict[int, int] | None = None,
    new_road_weight: float = 0.0,
) -> tuple[list[int], list[int]]:
    """Nodes and roads of a random walk from ``node`` (arrived on ``in_road``), about ``target_m`` long.
    A road earlier sessions drove ``n`` times (``driven``) is ``exp(-new_road_weight * n)`` times
    less likely to be taken."""
    deg = g.degree()
    nodes, roads = [], []
    total = 0.0
    while total < target_m:
        arrive = _heading_at(g, in_road, came_from, at_start=False)
        cands, weights = [], []
        for road, other in g.incident(node):
            if road.id == in_road or road.id in used:
                continue
            dep = _heading_at(g, road.id, node, at_start=True)
            turn = abs(float(np.arctan2(arrive[0] * dep[1] - arrive[1] * dep[0], arrive @ dep)))
            if turn > MAX_TURN_RAD:
                continue
            if deg[other] == 1 and total + road.length_m < target_m:
                continue  # a dead end only as the last leg
            cands.append((road, other))
            weights.append(np.exp(-turn / 0.8 - new_road_weight * (driven or {}).get(road.id, 0)))
        if not cands:
            break
        w = np.array(weights) / np.sum(weights)
        road, other = cands[int(rng.choice(len(cands), p=w))]
        used.add(road.id)
        nodes.append(other)
        roads.append(road.id)
        total += road.length_m
        came_from, node, in_road = node, other, road.id
    return nodes, roads


def plan_route(
    g: RoadGraph,
    anchor: dict,
    before_m: float,
    after_m: float,
    rng: np.random.Generator,
    driven: dict[int, int] | None = None,
    new_road_weight: float = 0.0,
) -> tuple[list[int], list[int]]:
    """(nodes, roads) of a route through the anchor road (a -> b), about ``before_m``/``after_m``
    of road before and after it; ``driven``/``new_road_weight``: see :func:`_walk`."""
    a, b, rid = anchor["from_node"], anchor["to_node"], anchor["road"]
    used = {rid}
    bwd_nodes, bwd_roads = _walk(g, rid, b, a, before_m, rng, used, driven, new_road_weight)
    fwd_nodes, fwd_roads = _walk(g, rid, a, b, after_m, rng, used, driven, new_road_weight)
    nodes = bwd_nodes[::-1] + [a, b] + fwd_nodes
    roads = bwd_roads[::-1] + [rid] + fwd_roads
    return nodes, roads


def _bezier(p0: np.ndarray, c: np.ndarray, p2: np.ndarray, step: float = 0.5) -> np.ndarray:
    L = np.linalg.norm(c - p0) + np.linalg.norm(p2 - c)
    t = np.linspace(0, 1, max(3, int(L / step) + 1))[:, None]
    return (1 - t) ** 2 * p0 + 2 * t * (1 - t) * c + t**2 * p2


def _trim(poly: np.ndarray, s0: float, s1: float, step: float = 0.5) -> np.ndarray:
    S = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(poly, axis=0), axis=1))])
    s = np.linspace(s0, s1, max(2, int((s1 - s0) / step) + 1))
    return np.stack([np.interp(s, S, poly[:, 0]), np.interp(s, S, poly[:, 1])], 1)


def route_centerline(g: RoadGraph, nodes: list[int], roads: list[int]) -> np.ndarray:
    """Dense centreline (M, 2) along the route's roads, with fillets through the junctions."""
    polys = [g.oriented(g.roads[r], n) for r, n in zip(roads, nodes[:-1], strict=True)]
    lengths = [g.roads[r].length_m for r in roads]
    fil = [0.0] * (len(nodes))
    for i in range(1, len(nodes) - 1):
        fil[i] = min(max(g.junction_radius_m[nodes[i]] + 3.0, 10.0), 0.45 * lengths[i - 1], 0.45 * lengths[i])
    out = []
    for i, poly in enumerate(polys):
        s0 = fil[i]
        s1 = lengths[i] - fil[i + 1]
        if i > 0:
            prev_end = _trim(polys[i - 1], lengths[i - 1] - fil[i], lengths[i - 1] - fil[i])[0]
            start = _trim(poly, s0, s0)[0]
            out.append(_bezier(prev_end, g.nodes_xy[nodes[i]], start)[1:-1])
        out.append(_trim(poly, s0, s1))
    pts = np.concatenate(out)
    keep = np.concatenate([[True], np.linalg.norm(np.diff(pts, axis=0), axis=1) > 1e-6])
    return pts[keep]


def _resample_uniform(pts: np.ndarray, ds: float) -> tuple[np.ndarray, np.ndarray]:
    S = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    s = np.arange(0.0, S[-1], ds)
    return np.stack([np.interp(s, S, pts[:, 0]), np.interp(s, S, pts[:, 1])], 1), s


# --- motion ----------------------------------------------------------------------------------------


@dataclass
class Drive:
    """Ground-truth motion of a session: base_link in the world frame at the GT rate."""

    stamps_ns: np.ndarray  # (N,) int64
    world_from_base: np.ndarray  # (N, 4, 4)
    path_xy: np.ndarray  # (M, 2) the driven path (for maps)
    length_m: float
    route_nodes: list[int]
    route_roads: list[int]
    source: str
    plan: tuple | None = None  # (route nodes, roads, split) a following session reuses

    @property
    def duration_s(self) -> float:
        return float((self.stamps_ns[-1] - self.stamps_ns[0]) * 1e-9)

    def poses_at(self, query_ns: np.ndarray) -> np.ndarray:
        """Interpolated ``world_from_base`` at ``query_ns`` (clamped to the drive's time span)."""
        q = np.clip(np.asarray(query_ns, np.int64), self.stamps_ns[0], self.stamps_ns[-1])
        i0 = max(0, int(np.searchsorted(self.stamps_ns, q.min(), side="right")) - 2)
        i1 = min(len(self.stamps_ns), int(np.searchsorted(self.stamps_ns, q.max(), side="left")) + 2)
        poses, mask = interpolate_poses(self.stamps_ns[i0:i1], self.world_from_base[i0:i1], q)
        assert mask.all()
        return poses


def poses_from_profile(
    xy: np.ndarray,
    heading: np.ndarray,
    s: np.ndarray,
    v: np.ndarray,
    kappa: np.ndarray,
    start_ns: int,
    cfg: SynthConfig,
    max_duration_s: float | None,
) -> tuple[np.ndarray, np.ndarray]:
    """Sample a path with a speed profile at the GT rate: (stamps_ns, world_from_base)."""
    ds = np.diff(s)
    v_mid = np.maximum((v[1:] + v[:-1]) / 2, 1e-3)
    t = np.concatenate([[0.0], np.cumsum(ds / v_mid)])
    T = t[-1] if max_duration_s is None else min(t[-1], max_duration_s)
    step_ns = int(round(1e9 / cfg.motion.ground_truth_rate_hz))
    k = np.arange(int(np.floor(T * 1e9 / step_ns)) + 1)
    tk = k * step_ns * 1e-9
    sk = np.interp(tk, t, s)
    x, y = np.interp(sk, s, xy[:, 0]), np.interp(sk, s, xy[:, 1])
    yaw = np.interp(sk, s, heading)
    vk = np.interp(sk, s, v)
    a_lat = vk**2 * np.interp(sk, s, kappa)
    a_long = np.interp(sk, s, np.gradient(v, s) * v) if len(s) > 1 else np.zeros_like(sk)
    roll = np.radians(cfg.motion.roll_per_lateral_accel_deg) * a_lat
    pitch = -np.radians(cfg.motion.pitch_per_accel_deg) * a_long
    R = Rotation.from_euler("ZYX", np.stack([yaw, pitch, roll], 1)).as_matrix()
    poses = make_pose(R, np.stack([x, y, np.zeros_like(x)], 1))
    return start_ns + k.astype(np.int64) * step_ns, poses


def speed_profile(
    s: np.ndarray, kappa: np.ndarray, v_max: float, cfg: SynthConfig, rng: np.random.Generator
) -> np.ndarray:
    m = cfg.motion
    wobble = 1.0 - 0.08 * (1 + np.sin(2 * np.pi * s / rng.uniform(150, 400) + rng.uniform(0, 2 * np.pi))) / 2
    v = np.minimum(v_max * wobble, np.sqrt(m.max_lateral_accel_m_s2 / np.maximum(np.abs(kappa), 1e-6)))
    if m.start_from_rest:
        v[0] = v[-1] = 0.0
    ds = np.diff(s)
    for i in range(1, len(v)):  # acceleration limit forward, deceleration backward
        v[i] = min(v[i], np.sqrt(v[i - 1] ** 2 + 2 * m.max_accel_m_s2 * ds[i - 1]))
    for i in range(len(v) - 2, -1, -1):
        v[i] = min(v[i], np.sqrt(v[i + 1] ** 2 + 2 * m.max_decel_m_s2 * ds[i]))
    return v


def drive_route(
    town: Town,
    sc: SessionConfig,
    cfg: SynthConfig,
    start_ns: int,
    rng: np.random.Generator,
    follow: tuple[list[int], list[int], float] | None = None,
    driven: dict[int, int] | None = None,
) -> Drive:
    """A route through the anchor (or along another session's route: ``follow`` = its nodes, roads
    and split), driven in the right-hand lane and cropped to the session's length; ``driven``:
    how often earlier sessions planned each road (``session_plan.new_road_weight`` steers away)."""
    g = town.roads
    anchor = town.anchor
    split = float(rng.uniform(0.3, 0.6))
    if follow is not None:
        nodes, roads, split0 = follow
        # the same roads, the window shifted along them: overlap in part
        split = split0 - sc.follow_shift_m / sc.length_m
    else:
        before = split * sc.length_m + ROUTE_MARGIN_M
        after = (1 - split) * sc.length_m + ROUTE_MARGIN_M
        nodes, roads = plan_route(g, anchor, before, after, rng, driven, cfg.session_plan.new_road_weight)
    centre = route_centerline(g, nodes, roads)
    centre = np.stack([gaussian_filter1d(centre[:, k], 3.0, mode="nearest") for k in range(2)], 1)
    pts, s = _resample_uniform(centre, 0.5)
    tg = np.gradient(pts, axis=0)
    tg /= np.maximum(np.linalg.norm(tg, axis=1, keepdims=True), 1e-9)
    nl = np.stack([-tg[:, 1], tg[:, 0]], 1)
    wander = cfg.motion.lane_wander_m * np.sin(2 * np.pi * s / rng.uniform(80, 200) + rng.uniform(0, 2 * np.pi))
    lat = DRIVE_LANE_CENTER_M + sc.lane_offset_m + wander
    path = pts - nl * lat[:, None]
    path = np.stack([gaussian_filter1d(path[:, k], 2.0, mode="nearest") for k in range(2)], 1)
    xy, s = _resample_uniform(path, 0.25)
    # crop around the anchor: the anchor point sits at ``split`` of the session's length
    a_xy = (
        np.array(anchor["xy"])
        - np.array([-np.sin(anchor["heading_rad"]), np.cos(anchor["heading_rad"])]) * DRIVE_LANE_CENTER_M
    )
    s_anchor = s[int(np.argmin(np.linalg.norm(xy - a_xy, axis=1)))]
    s0 = max(0.0, s_anchor - split * sc.length_m)
    s1 = min(s[-1], s0 + sc.length_m)
    keep = (s >= s0) & (s <= s1)
    xy, s = xy[keep], s[keep] - s0
    drive = _drive_from_path(xy, s, sc, cfg, start_ns, rng, nodes, roads, g, "route")
    drive.plan = (nodes, roads, split)
    return drive


def _drive_from_path(xy, s, sc, cfg, start_ns, rng, nodes, roads, g, source) -> Drive:
    d = np.gradient(xy, axis=0)
    heading = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
    kappa = gaussian_filter1d(np.gradient(heading, s), 8.0, mode="nearest")
    v = speed_profile(s, kappa, sc.speed_mps, cfg, rng)
    stamps, poses = poses_from_profile(xy, heading, s, v, kappa, start_ns, cfg, sc.max_duration_s)
    driven = poses[:, :2, 3]
    touched = [
        n for n in nodes if np.min(np.linalg.norm(driven - g.nodes_xy[n], axis=1)) < g.junction_radius_m[n] + 8.0
    ]
    length = float(np.linalg.norm(np.diff(driven, axis=0), axis=1).sum())
    return Drive(stamps, poses, driven, length, touched, roads, source)


# --- external trajectories --------------------------------------------------------------------------


@dataclass
class ExternalPath:
    stamps_ns: np.ndarray  # relative to the first pose
    xy: np.ndarray  # (N, 2) metres, x east, y north (or the file's planar axes)
    origin_latlon: tuple[float, float] | None
    source: str


def read_external_trajectory(path: Path) -> ExternalPath:
    """TUM (z up), KITTI poses (camera frame: x right, y down, z forward; ``times.txt`` beside it or
    10 Hz) or an Oxford RobotCar INS/GPS-style CSV with a header (timestamp in microseconds;
    northing, easting; latitude/longitude if present georeference the town)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "no such trajectory file")
    first = path.read_text().lstrip().splitlines()[0] if path.stat().st_size else ""
    if path.suffix.lower() == ".csv" or (
        first and not first[0].isdigit() and not first.startswith("#") and "," in first
    ):
        return _read_robotcar(path)
    ncols = len(
        next((ln for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#")), "")
        .replace(",", " ")
        .split()
    )
    if ncols == 8:
        stamps, T = read_tum(path)
        return ExternalPath(stamps - stamps[0], T[:, :2, 3], None, f"tum:{path.name}")
    if ncols == 12:
        T = read_kitti_poses(path)
        times = path.with_name("times.txt")
        if times.is_file():
            t = np.array([float(x) for x in times.read_text().split()])
            if len(t) != len(T):
                raise InputError(times, f"has {len(t)} times for {len(T)} poses")
            stamps = np.round(t * 1e9).astype(np.int64)
        else:
            stamps = np.arange(len(T), dtype=np.int64) * 100_000_000
        p = T[:, :3, 3]
        return ExternalPath(stamps - stamps[0], np.stack([p[:, 2], -p[:, 0]], 1), None, f"kitti:{path.name}")
    raise InputError(
        path, f"not a TUM (8 values), KITTI (12 values) or RobotCar CSV trajectory ({ncols} values a line)"
    )


def _read_robotcar(path: Path) -> ExternalPath:
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows:
        raise InputError(path, "holds no rows")
    cols = {k.strip().lower(): k for k in rows[0]}
    for need in ("timestamp", "northing", "easting"):
        if need not in cols:
            raise InputError(path, f"has no {need!r} column (columns: {sorted(cols)})", field=need)
    try:
        t = np.array([int(float(r[cols["timestamp"]])) for r in rows], np.int64)
        north = np.array([float(r[cols["northing"]]) for r in rows])
        east = np.array([float(r[cols["easting"]]) for r in rows])
    except ValueError as exc:
        raise InputError(path, f"a value is not a number ({exc})") from None
    scale = 1 if t[0] > 10**17 else (1000 if t[0] > 10**14 else 10**9)  # ns, us (RobotCar) or s
    stamps = t * scale
    if np.any(np.diff(stamps) <= 0):
        raise InputError(path, "timestamps do not increase")
    origin = None
    if "latitude" in cols and "longitude" in cols:
        origin = (float(rows[0][cols["latitude"]]), float(rows[0][cols["longitude"]]))
    xy = np.stack([east - east[0], north - north[0]], 1)
    return ExternalPath(stamps - stamps[0], xy, origin, f"robotcar:{path.name}")


def drive_external(ext: ExternalPath, sc: SessionConfig, cfg: SynthConfig, start_ns: int, town: Town) -> Drive:
    """The external path at the GT rate: planar position and heading of motion (flat town)."""
    step_ns = int(round(1e9 / cfg.motion.ground_truth_rate_hz))
    end = int(ext.stamps_ns[-1])
    if sc.max_duration_s is not None:
        end = min(end, int(sc.max_duration_s * 1e9))
    k = np.arange(end // step_ns + 1, dtype=np.int64)
    tq = k * step_ns
    x = np.interp(tq, ext.stamps_ns, ext.xy[:, 0])
    y = np.interp(tq, ext.stamps_ns, ext.xy[:, 1])
    d = np.diff(ext.xy, axis=0)
    moving = np.linalg.norm(d, axis=1) > 0.01
    if not moving.any():
        raise InputError(None, f"{ext.source}: the trajectory does not move")
    hd = np.arctan2(d[:, 1], d[:, 0])
    idx = np.where(moving, np.arange(len(hd)), 0)
    np.maximum.accumulate(idx, out=idx)
    first = int(np.argmax(moving))
    idx[:first] = first
    heading = np.unwrap(hd[idx])
    heading = np.concatenate([heading, heading[-1:]])
    yaw = np.interp(tq, ext.stamps_ns, heading)
    poses = make_pose(Rotation.from_euler("z", yaw[:, None]).as_matrix(), np.stack([x, y, np.zeros_like(x)], 1))
    xy = np.stack([x, y], 1)
    track = [r for r in town.roads.roads if r.kind == "track"]
    nodes = [track[0].a, track[0].b] if track else []
    length = float(np.linalg.norm(np.diff(xy, axis=0), axis=1).sum())
    return Drive(start_ns + tq, poses, xy, length, nodes, [track[0].id] if track else [], ext.source)


# --- plans ------------------------------------------------------------------------------------------


@dataclass
class SessionPlan:
    index: int
    config: SessionConfig
    local_start: dt.datetime
    start_ns: int
    conditions: Conditions
    drive: Drive
    camera_rate_hz: float  # the rate the camera records at
    seed: int
    image_rate_hz: float  # the session's own rate (lower than camera_rate_hz when camera.record_rate_hz records video)

    @property
    def name(self) -> str:
        return self.config.name

    def manifest_entry(self, cfg: SynthConfig) -> dict:
        sc = self.config
        g = cfg.gps
        return {
            "name": sc.name,
            "file": session_log_relpath(sc.name),  # a rosbag2 folder (metadata.yaml, <name>_0.mcap)
            "ground_truth": f"sessions/{sc.name}.gt.tum",
            "camera_ground_truth": f"sessions/{sc.name}.camera.tum",
            "parked_cars": f"sessions/{sc.name}.parked_cars.ply",
            "role": sc.role,
            "route_node_ids": [int(n) for n in self.drive.route_nodes],
            "route_road_ids": [int(r) for r in self.drive.route_roads],
            "trajectory_source": self.drive.source,
            "follows": sc.follow,
            "length_m": round(self.drive.length_m, 3),
            "duration_s": round(self.drive.duration_s, 3),
            "start_time_ns": int(self.start_ns),
            "start_time_local": self.local_start.isoformat(),
            "date": self.local_start.date().isoformat(),
            "time_of_day": self.local_start.strftime("%H:%M"),
            "weather": sc.weather,
            "condition": self.conditions.label,
            "season": self.conditions.season,
            "sun_elevation_deg": round(self.conditions.sun_elevation_deg, 2),
            "sun_azimuth_deg": round(self.conditions.sun_azimuth_deg, 2),
            "exposure_ev": sc.exposure_ev,
            "white_balance_k": sc.white_balance_k,
            "speed_mps": sc.speed_mps,
            "lane_offset_m": sc.lane_offset_m,
            "camera_rate_hz": self.camera_rate_hz,
            "image_rate_hz": self.image_rate_hz,
            "lidar_rate_hz": cfg.lidar.rate_hz if cfg.lidar.enabled else None,
            "gps_rate_hz": g.rate_hz,
            "imu_rate_hz": cfg.imu.rate_hz if cfg.imu.enabled else None,
            "ground_truth_rate_hz": cfg.motion.ground_truth_rate_hz,
            "gps_noise": {
                "white_sigma_m": g.white_sigma_m,
                "vertical_factor": g.vertical_factor,
                "bias_sigma_m": g.bias_sigma_m,
                "bias_tau_s": g.bias_tau_s,
                "multipath_rate_hz": g.multipath_rate_hz,
                "multipath_duration_s": g.multipath_duration_s,
                "multipath_sigma_m": g.multipath_sigma_m,
                "dropout_rate_hz": g.dropout_rate_hz,
                "dropout_duration_s": g.dropout_duration_s,
            },
            "seed": self.seed,
        }


def auto_sessions(cfg: SynthConfig, rng: np.random.Generator) -> list[SessionConfig]:
    """Training sessions spread uniformly over times of day and weathers (MCVL Sec. IV-B)."""
    p = cfg.session_plan
    n = p.n_train
    if n == 0:
        return []
    hours = p.hours[0] + (np.arange(n) + rng.uniform(0, 1, n)) / n * (p.hours[1] - p.hours[0])
    hours = rng.permutation(hours)
    weathers = [p.weathers[k % len(p.weathers)] for k in rng.permutation(n)]
    dates = list(p.dates) or [cfg.origin.date]
    out = []
    for k in range(n):
        hh = int(hours[k])
        mm = int((hours[k] - hh) * 60)
        date = dates[k % len(dates)]
        lt = _local_datetime(date, f"{hh:02d}:{mm:02d}", cfg.origin.timezone)
        from mapkit.synth.appearance import sun_position

        _, el = sun_position(lt.astimezone(dt.timezone.utc), cfg.origin.lat_deg, cfg.origin.lon_deg)
        out.append(
            SessionConfig(
                name=f"train-{k + 1:03d}",
                role="train",
                date=date,
                time=f"{hh:02d}:{mm:02d}",
                weather=weathers[k],
                length_m=float(rng.uniform(*p.length_m)),
                speed_mps=float(rng.uniform(*p.speed_mps)),
                lane_offset_m=float(rng.uniform(*p.lane_offset_m)),
                exposure_ev=p.night_exposure_ev if el < -6 else 0.0,
                camera_rate_hz=p.camera_rate_hz,
            )
        )
    return out


def _local_datetime(date: dt.date, hhmm: str, tz: str) -> dt.datetime:
    try:
        zone = ZoneInfo(tz)
    except (ZoneInfoNotFoundError, ValueError):
        raise ConfigError(
            f"field `origin.timezone`: unknown time zone {tz!r} (an IANA name such as Europe/London)"
        ) from None
    hh, mm = (int(x) for x in hhmm.split(":"))
    return dt.datetime(date.year, date.month, date.day, hh, mm, tzinfo=zone)


def plan_sessions(cfg: SynthConfig, town: Town, external: ExternalPath | None = None) -> list[SessionPlan]:
    rng_auto = np.random.default_rng(np.random.SeedSequence([cfg.seed, 0x5E55]))
    sessions = list(cfg.sessions) + auto_sessions(cfg, rng_auto)
    plans: list[SessionPlan] = []
    driven: dict[int, int] = {}  # road id -> sessions whose planned route takes it
    for i, sc in enumerate(sessions):
        seed = int(np.random.SeedSequence([cfg.seed, 0xD21, i]).generate_state(1)[0])
        rng = np.random.default_rng(seed)
        local = _local_datetime(sc.date or cfg.origin.date, sc.time, cfg.origin.timezone)
        start_ns = int(local.timestamp()) * 1_000_000_000 + int(rng.integers(0, 1_000_000_000))
        cond = make_conditions(
            sc.weather,
            local,
            cfg.origin.lat_deg,
            cfg.origin.lon_deg,
            exposure_ev=sc.exposure_ev,
            white_balance_k=sc.white_balance_k,
            season=sc.season,
            seed=seed,
        )
        if (sc.trajectory is not None) or (external is not None and i == 0):
            ext = external if sc.trajectory is None else read_external_trajectory(sc.trajectory)
            assert ext is not None  # by the condition: the session's own trajectory, or the external one
            drive = drive_external(ext, sc, cfg, start_ns, town)
        else:
            follow = None
            if sc.follow is not None:
                leader = next(p for p in plans if p.name == sc.follow)
                if leader.drive.plan is None:
                    raise ConfigError(
                        f"session {sc.name!r} cannot follow {sc.follow!r}: it drives an external trajectory"
                    )
                follow = leader.drive.plan
            drive = drive_route(town, sc, cfg, start_ns, rng, follow, driven)
            for r in set(drive.route_roads):
                driven[r] = driven.get(r, 0) + 1
        if len(drive.stamps_ns) < 2:
            raise ConfigError(f"session {sc.name!r}: its drive is shorter than one ground-truth step")
        own_rate = sc.camera_rate_hz or cfg.camera.rate_hz
        plans.append(
            SessionPlan(i, sc, local, start_ns, cond, drive, cfg.camera.record_rate_hz or own_rate, seed, own_rate)
        )
    return plans


# --- writing a session -------------------------------------------------------------------------------


def _stamps(start_ns: int, end_ns: int, rate_hz: float, margin_ns: int = 0) -> np.ndarray:
    step = 1e9 / rate_hz
    n = int(np.floor((end_ns - margin_ns - start_ns) / step)) + 1
    return start_ns + np.round(np.arange(max(n, 0)) * step).astype(np.int64)


def anchor_frame(world_from_camera: np.ndarray, anchor: dict, max_heading_deg: float = 60.0) -> int:
    """Index of the camera pose nearest to the anchor place that looks along the anchor road."""
    pos = world_from_camera[:, :2, 3]
    fwd = world_from_camera[:, :2, 2]  # optical z in the world
    hd = np.array([np.cos(anchor["heading_rad"]), np.sin(anchor["heading_rad"])])
    ok = (fwd @ hd) / np.maximum(np.linalg.norm(fwd, axis=1), 1e-9) > np.cos(np.radians(max_heading_deg))
    target = np.array(anchor["xy"]) - hd * 12.0  # a few metres before the place: it is in view
    dist = np.linalg.norm(pos - target, axis=1) + np.where(ok, 0.0, 1e6)
    return int(np.argmin(dist))


def session_rngs(seed: int) -> tuple[np.random.Generator, np.random.Generator, np.random.Generator]:
    """The random streams of a session: parked cars, GPS errors, IMU noise."""
    return tuple(np.random.default_rng(s) for s in np.random.SeedSequence([seed, 7]).spawn(3))  # type: ignore[return-value]


def session_parked_cars(town: Town, seed: int):
    return parked_cars(town, session_rngs(seed)[0])


@dataclass
class _SessionStreams:
    """What a session's log holds besides the rendered sensors: the stamps (ns) of every stream,
    the camera poses at the image stamps, the GPS fixes and the IMU samples."""

    camera_ns: np.ndarray
    lidar_ns: np.ndarray
    gps_ns: np.ndarray
    imu_ns: np.ndarray
    world_from_camera: np.ndarray  # (len(camera_ns), 4, 4), optical frame
    gps_valid: np.ndarray  # (len(gps_ns),) bool: a fix, else NO_FIX
    gps_lat_lon_alt: tuple  # three arrays (or empty lists without GPS stamps), WGS84
    gps_covariance_enu_m2: np.ndarray
    imu_gyro: np.ndarray  # (len(imu_ns), 3)
    imu_accel: np.ndarray  # (len(imu_ns), 3)


def _session_streams(
    town: Town,
    plan: SessionPlan,
    cfg: SynthConfig,
    ex: dict,
    rng_gps: np.random.Generator,
    rng_imu: np.random.Generator,
) -> _SessionStreams:
    """Every stream's stamps over the drive, the camera poses, the GPS fixes (antenna position plus
    the error process, to WGS84; draws from ``rng_gps``) and the IMU samples (from ``rng_imu``)."""
    drive = plan.drive
    start, end = int(drive.stamps_ns[0]), int(drive.stamps_ns[-1])
    lidar_period_ns = int(round(1e9 / cfg.lidar.rate_hz))
    cam_ns = _stamps(start, end, plan.camera_rate_hz)
    lidar_ns = (
        _stamps(start, end, cfg.lidar.rate_hz, margin_ns=lidar_period_ns)
        if cfg.lidar.enabled
        else np.zeros(0, np.int64)
    )
    gps_ns = _stamps(start, end, cfg.gps.rate_hz)
    imu_ns = _stamps(start, end, cfg.imu.rate_hz) if cfg.imu.enabled else np.zeros(0, np.int64)
    world_from_cam = drive.poses_at(cam_ns) @ ex[FRAME_CAMERA] if len(cam_ns) else np.zeros((0, 4, 4))
    model = GpsErrorModel(cfg.gps)
    err = model.simulate(len(gps_ns), rng_gps)
    antenna = (drive.poses_at(gps_ns) @ ex[FRAME_GPS])[:, :3, 3] if len(gps_ns) else np.zeros((0, 3))
    lat_lon_alt = town.frame.enu_to_geodetic(antenna + err.total_enu) if len(gps_ns) else ([], [], [])
    gyro, accel = (np.zeros((0, 3)), np.zeros((0, 3)))
    if len(imu_ns):
        gyro, accel = imu_from_poses(imu_ns, drive.poses_at(imu_ns) @ ex[FRAME_IMU], cfg.imu, rng_imu)
    return _SessionStreams(
        cam_ns, lidar_ns, gps_ns, imu_ns, world_from_cam, err.valid, lat_lon_alt, model.covariance_enu_m2, gyro, accel
    )


def _messages_in_time_order(drive: Drive, st: _SessionStreams) -> list[tuple[int, int, int]]:
    """(stamp, kind, index in its stream) of every message in time order; kinds 1 to 5 are ground
    truth, IMU, GPS, LiDAR and camera, which is also the order at equal stamps (then by index)."""
    kinds = [(drive.stamps_ns, 1), (st.imu_ns, 2), (st.gps_ns, 3), (st.lidar_ns, 4), (st.camera_ns, 5)]
    stamps = np.concatenate([k[0] for k in kinds])
    order_kind = np.concatenate([np.full(len(k[0]), k[1]) for k in kinds])
    index = np.concatenate([np.arange(len(k[0])) for k in kinds])
    order = np.lexsort((index, order_kind, stamps))
    return [(int(stamps[j]), int(order_kind[j]), int(index[j])) for j in order]


def _gps_message(st: _SessionStreams, i: int, stamp: int) -> GpsFix:
    """GPS fix ``i`` of the session: its position and covariance, or NaN and NO_FIX where the
    error process has no fix."""
    ok = bool(st.gps_valid[i])
    lat, lon, alt = st.gps_lat_lon_alt
    return GpsFix(
        stamp,
        float(lat[i]) if ok else float("nan"),
        float(lon[i]) if ok else float("nan"),
        float(alt[i]) if ok else float("nan"),
        GpsStatus.FIX if ok else GpsStatus.NO_FIX,
        st.gps_covariance_enu_m2 if ok else None,
        FRAME_GPS,
    )


def _log_metadata(plan: SessionPlan) -> dict:
    """The session's description in its log's metadata."""
    return {
        "session": plan.name,
        "condition": plan.conditions.label,
        "weather": plan.config.weather,
        "start_time_local": plan.local_start.isoformat(),
        "seed": plan.seed,
        "world_frame": "ENU at the origin in world/origin.json",
    }


def _write_png(path: Path, rgb: np.ndarray) -> None:
    """An RGB image (h, w, 3) as a PNG file, written atomically."""
    import cv2

    from mapkit.core.runio import atomic_path

    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        ok_png, buf = cv2.imencode(".png", rgb[..., ::-1])
        tmp.write_bytes(buf.tobytes())


def _write_log(
    log_dir: Path,
    plan: SessionPlan,
    cfg: SynthConfig,
    renderer,
    ex: dict,
    st: _SessionStreams,
    picture_frame: int,
    picture: Path,
    progress: bool | None,
    moving_hits: list[tuple[int, np.ndarray]] | None = None,
) -> dict[str, float]:
    """Render the session's LiDAR sweeps and camera frames and write them with every other
    message into the rosbag2 folder ``log_dir``; camera frame ``picture_frame`` is also saved as
    the PNG ``picture``. Returns the seconds spent rendering camera and LiDAR; each sweep's stamp and the indices
    of its points that hit a moving car are appended to ``moving_hits`` when given.
    Each sweep and frame draws from its own generator, seeded by the session's seed and its index."""
    drive = plan.drive
    K = intrinsics(cfg.camera)
    compress = None if cfg.camera.compression == "raw" else cfg.camera.compression
    info = CameraInfo(FRAME_CAMERA, cfg.camera.width, cfg.camera.height, K, "plumb_bob", np.zeros(5))
    render_s = {"camera": 0.0, "lidar": 0.0}
    label = f"{plan.name} ({plan.conditions.label})"
    bar = progress_bar(len(st.camera_ns) + len(st.lidar_ns), progress, label, "frame", leave=False)
    with Rosbag2Writer(log_dir) as w:
        w.add_metadata("mapkit.synth", _log_metadata(plan))
        w.write_transforms(
            TOPIC_TF_STATIC, [FrameTransform(int(drive.stamps_ns[0]), FRAME_BASE, k, v) for k, v in ex.items()]
        )
        for stamp, kind, i in _messages_in_time_order(drive, st):
            if kind == 1:
                w.write(
                    TOPIC_GROUND_TRUTH,
                    PoseSample(stamp, FRAME_WORLD, FRAME_BASE, drive.world_from_base[i], source="ground_truth"),
                )
            elif kind == 2:
                w.write(TOPIC_IMU, ImuSample(stamp, FRAME_IMU, st.imu_gyro[i], st.imu_accel[i], None))
            elif kind == 3:
                w.write(TOPIC_GPS, _gps_message(st, i, stamp))
            elif kind == 4:
                tt = time.perf_counter()
                col_ns = stamp + np.round(renderer.lidar_col_time_s * 1e9).astype(np.int64)
                sweep = renderer.scan_lidar(
                    drive.poses_at(col_ns) @ ex[FRAME_LIDAR],
                    np.random.default_rng([plan.seed, 4, i]),
                    stamp + int(round(0.5e9 / cfg.lidar.rate_hz)),
                )
                if moving_hits is not None:
                    moving_hits.append((stamp, np.flatnonzero(sweep.moving)))
                render_s["lidar"] += time.perf_counter() - tt
                w.write(
                    TOPIC_LIDAR,
                    LidarScan(stamp, FRAME_LIDAR, sweep.points_xyz, sweep.intensity, sweep.time_s, sweep.ring),
                )
                bar.update(1)
            else:
                tt = time.perf_counter()
                wfb = drive.poses_at(np.array([stamp]))[0]
                frame = renderer.render_camera(
                    st.world_from_camera[i], plan.conditions, np.random.default_rng([plan.seed, 5, i]), wfb, stamp
                )
                render_s["camera"] += time.perf_counter() - tt
                w.write(
                    TOPIC_CAMERA_INFO,
                    CameraInfo(info.camera, info.width, info.height, K, info.distortion_model, info.D, stamp),
                )
                w.write(TOPIC_IMAGE, CameraFrame(stamp, FRAME_CAMERA, frame.rgb, encoding="rgb8"), compress=compress)
                if i == picture_frame:
                    _write_png(picture, frame.rgb)
                bar.update(1)
    bar.close()
    return render_s


def write_session(
    town: Town,
    plan: SessionPlan,
    cfg: SynthConfig,
    out_dir: Path,
    progress: bool | None = None,
    nthreads: int | None = None,
) -> dict:
    """Render and write one session: its log (a rosbag2 folder with MCAP storage), ground-truth files,
    parked cars and anchor picture."""
    from mapkit.synth.render import Renderer

    sess_dir = out_dir / "sessions"
    sess_dir.mkdir(parents=True, exist_ok=True)
    name = plan.name
    rng_cars, rng_gps, rng_imu = session_rngs(plan.seed)
    parked = parked_cars(town, rng_cars)
    write_ply(sess_dir / f"{name}.parked_cars.ply", parked)
    t0 = time.perf_counter()
    drive = plan.drive
    traffic = oncoming_traffic(
        drive.stamps_ns, drive.world_from_base, plan.config.moving_cars, np.random.default_rng([plan.seed, 8])
    )
    renderer = Renderer(town, parked, cfg.camera, cfg.lidar, nthreads=nthreads, traffic=traffic)
    ex = extrinsics(cfg)
    st = _session_streams(town, plan, cfg, ex, rng_gps, rng_imu)
    write_tum(sess_dir / f"{name}.gt.tum", drive.stamps_ns, drive.world_from_base)
    write_tum(sess_dir / f"{name}.camera.tum", st.camera_ns, st.world_from_camera)
    keep_frame = anchor_frame(st.world_from_camera, town.anchor) if len(st.camera_ns) else -1
    log_dir = out_dir / session_log_relpath(name)
    picture = out_dir / "pictures" / "frames" / f"{name}.png"
    moving_hits: list[tuple[int, np.ndarray]] | None = [] if traffic is not None else None
    render_s = _write_log(log_dir, plan, cfg, renderer, ex, st, keep_frame, picture, progress, moving_hits)
    if traffic is not None and moving_hits is not None:
        write_dynamic_truth(
            moving_cars_path(out_dir, name), traffic, [t for t, _ in moving_hits], [h for _, h in moving_hits]
        )
    (sess_dir / f"{name}.mcap").unlink(missing_ok=True)  # the bare log of a town written before rosbag2 folders
    wall = time.perf_counter() - t0
    return {
        "name": name,
        "camera_frames": int(len(st.camera_ns)),
        "lidar_scans": int(len(st.lidar_ns)),
        "gps_fixes": int(len(st.gps_ns)),
        "gps_fixes_without_fix": int((~st.gps_valid).sum()),
        "imu_samples": int(len(st.imu_ns)),
        "ground_truth_poses": int(len(drive.stamps_ns)),
        "parked_cars": int(len(np.unique(parked.object_id[parked.material == Mat.CAR_BODY]))),
        **(
            {}
            if traffic is None or moving_hits is None
            else {"moving_cars": len(traffic), "lidar_moving_car_points": int(sum(len(h) for _, h in moving_hits))}
        ),
        "anchor_frame": keep_frame,
        "mcap_bytes": int(sum(f.stat().st_size for f in log_dir.glob("*.mcap"))),
        # how long it took: a run record (the caller moves it to the town's timings.json)
        "timings_s": {
            "wall_s": round(wall, 3),
            "camera_render_s": round(render_s["camera"], 3),
            "lidar_render_s": round(render_s["lidar"], 3),
        },
    }


def camera_poses(out_dir: Path, name: str) -> tuple[np.ndarray, np.ndarray]:
    """(stamps_ns, world_from_camera) of a written session's images."""
    return read_tum(Path(out_dir) / "sessions" / f"{name}.camera.tum")


__all__ = ["plan_sessions", "write_session", "read_external_trajectory", "Drive", "SessionPlan", "session_parked_cars"]
