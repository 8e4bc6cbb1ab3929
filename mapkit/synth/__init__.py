"""Synthetic town: georeferenced multi-session drive logs with exact ground truth (``mapkit synth``).

A procedural town (road graph with 3- to 5-way junctions, curves, straight avenues and dead ends;
buildings with textured facades in repeated styles; trees, lamps, signs, fences, parked cars) is
generated from a seed at a WGS84 origin, and vehicles drive routes through it under different
times of day and weathers. Camera images are ray cast on the CPU with open3d's RaycastingScene
and shaded from what the rays hit; a spinning LiDAR, GPS with a realistic error process and an
IMU are simulated alongside. Presets (``configs/synth/*.yaml``): ``tiny`` (three 250 m drives, every
stage of ``mapkit demo`` in a few minutes on 2 cores), ``demo`` (the main job's default: five drives,
every stage within ten minutes on 2 cores), ``places`` (eight drives; the papers' claims are measured
on it) and ``benchmark`` (MCVL Sec. IV-B scale, hours).

Public API::

    synthesize(preset="tiny", out=..., seed=None, config=None, trajectory=None, overwrite=False) -> Path
    load_world(out) -> World           # mesh (open3d), road graph, LocalFrame, manifest, config
    gt_poses(out, session) -> (stamps_ns (N,), world_from_base (N, 4, 4))
    camera_poses(out, session) -> (stamps_ns (M,), world_from_camera (M, 4, 4))   # optical frame
    load_config(preset, config, seed) -> SynthConfig
    session_log(out, session) -> Path; session_logs(out) -> [Path]   # the sessions' logs (rosbag2 folders)
    GpsErrorModel(cfg.gps).simulate(n, rng); extrinsics(cfg); intrinsics(cfg.camera)
    World.renderer(session) -> Renderer  # re-render any pose; returns image, range and depth

Output layout (``out``)::

    world/mesh.ply            static surfaces (world ENU, metres; binary PLY, per-face material and object id)
    world/roads.json          road graph: nodes (ENU xy, degree), edges (polylines, widths), the anchor place
    world/origin.json         LocalFrame.to_dict(): WGS84 origin and UTM EPSG code
    world/manifest.json       format version, seed, preset, config hash, sessions (route, time, weather, rates,
                              GPS noise)
    world/config.yaml         the resolved configuration
    sessions/<name>/          the session's log, a rosbag2 folder as ``ros2 bag record -s mcap`` writes it:
                              metadata.yaml and <name>_0.mcap with ROS 2 messages: /camera/front/image
                              (+ camera_info), /lidar/points, /gps/fix, /imu/data, /tf_static, /ground_truth/odom
                              (``session_log(out, name)``, ``session_logs(out)``; mapkit reads the folder or the .mcap)
    sessions/<name>.gt.tum    ground-truth base_link poses in the world frame (GT rate)
    sessions/<name>.camera.tum  ground-truth camera (optical frame) poses at the image stamps
    sessions/<name>.parked_cars.ply  this session's parked cars (not in world/mesh.ply: they move)
    metrics.json              world statistics, per-session counts, what was rendered, street coverage
    timings.json              wall-clock figures: seconds per step, camera frames and LiDAR scans
                              rendered per second, per-session render seconds
    pictures/map.png          bird's-eye map of roads, buildings and routes
    pictures/contact_sheet.png  the anchor place seen by every session

Frames: ``world`` is ENU at the origin (x east, y north, z up; the road surface is z = 0);
``base_link`` is x forward, y left, z up (REP-103) on the road surface under the centre of the
rear axle; ``camera_front`` is an optical frame (x right, y down, z forward); ``lidar``, ``gps`` and
``imu`` are x forward, y left, z up. Stamps are integer nanoseconds since the Unix epoch, on the
scenario's date at the session's local time of day. A LiDAR point's ``time`` is seconds after its
message stamp (the start of the sweep); points are in the sensor frame at their own firing time.

Finished outputs are marked with ``runio.mark_done``; re-running skips finished sessions (the
markers live in ``sessions/.markers/<name>/``) unless ``overwrite``; files are written atomically.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from mapkit.core.errors import ConfigError, MapkitError
from mapkit.core.geodesy import LocalFrame
from mapkit.core.runio import (
    atomic_write_text,
    config_hash,
    is_done,
    mark_done,
    sha256_file,
    stage_hash,
    write_json,
    write_timings,
)
from mapkit.core.threads import single_thread_blas
from mapkit.io.mcap_log import ROSBAG2_METADATA, is_rosbag2
from mapkit.io.trajectory import read_tum
from mapkit.synth.config import FORMAT_VERSION, PRESETS, SynthConfig, dump_yaml, load_config
from mapkit.synth.sensors import GpsErrorModel, extrinsics, intrinsics
from mapkit.synth.world import RoadGraph, read_ply, read_roads

if TYPE_CHECKING:
    from mapkit.synth.sessions import ExternalPath

__all__ = [
    "synthesize",
    "load_world",
    "gt_poses",
    "camera_poses",
    "World",
    "load_config",
    "SynthConfig",
    "PRESETS",
    "GpsErrorModel",
    "extrinsics",
    "intrinsics",
    "session_log",
    "session_logs",
    "street_coverage",
]

#: how a session's log is written; part of the output hashes, so that a town written with bare
#: ``sessions/<name>.mcap`` logs is rewritten with rosbag2 folders (and a manifest naming them)
SESSION_LOG_LAYOUT = "rosbag2-mcap"
#: the versions of the town's and the sessions' algorithms, each bumped whenever its output for the same inputs
#: changes (it reruns; a new town version renders the sessions again too)
TOWN_STAGE_VERSION = 1
SESSIONS_STAGE_VERSION = 1


def session_log_relpath(session: str) -> str:
    """Where a session's log is written, relative to the town: the rosbag2 folder ``sessions/<name>``."""
    return f"sessions/{session}"


def session_log(path: str | Path, session: str) -> Path:
    """A session's log: its rosbag2 folder ``sessions/<name>/`` (``metadata.yaml``, ``<name>_0.mcap``),
    or else a bare ``sessions/<name>.mcap`` (a log written as one MCAP file)."""
    folder = Path(path) / session_log_relpath(session)
    if is_rosbag2(folder):
        return folder
    bare = Path(path) / "sessions" / f"{session}.mcap"
    if bare.is_file():
        return bare
    raise MapkitError(f"{path}: no log for session {session!r} ({folder}{os.sep}{ROSBAG2_METADATA} missing)")


def session_logs(path: str | Path) -> list[Path]:
    """Every finished session log of a town, by session name (what ``mapkit build`` takes)."""
    sdir = Path(path) / "sessions"
    if not sdir.is_dir():
        raise MapkitError(f"{path}: not a synthesized town (no sessions/ folder)")
    found: dict[str, Path] = {}
    for p in sdir.iterdir():
        if p.name.startswith("."):
            continue  # .markers, and .<name>.partial folders of a run still writing (or killed)
        if p.is_dir() and is_rosbag2(p):
            found[p.name] = p
        elif p.is_file() and p.suffix == ".mcap" and "." not in p.stem:
            found.setdefault(p.stem, p)  # a bare .mcap log; the session's folder wins when both exist
    return [found[k] for k in sorted(found)]


def _world_hash(cfg: SynthConfig, trajectory_digest: str | None) -> str:
    return config_hash(
        {
            "format_version": FORMAT_VERSION,
            "seed": cfg.seed,
            "origin": cfg.origin,
            "town": cfg.town,
            "trajectory": trajectory_digest,
        }
    )


def _town_identity(cfg: SynthConfig, trajectory_digest: str | None) -> dict:
    """What the town's outputs depend on (its marker's and manifest's hash is of this): the resolved config but its
    worker count, which only says how many processes render the same files, the external trajectory's digest and
    the log layout."""
    return {
        "config": cfg.model_dump(mode="json", exclude={"workers"}),
        "trajectory": trajectory_digest,
        "log": SESSION_LOG_LAYOUT,
    }


def _session_identity(cfg: SynthConfig, world_hash: str, index: int, session) -> dict:
    """What a session's render depends on (its marker's hash is of this, the town's and the sessions' versions)."""
    return {
        "world": world_hash,
        "index": index,
        "session": session,
        "camera": cfg.camera,
        "lidar": cfg.lidar,
        "gps": cfg.gps,
        "imu": cfg.imu,
        "motion": cfg.motion,
        "log": SESSION_LOG_LAYOUT,
    }


def synthesize(
    preset: str = "tiny",
    out: Path = Path("synth"),
    seed: int | None = None,
    config: Path | None = None,
    trajectory: Path | None = None,
    overwrite: bool = False,
    *,
    progress: bool | None = None,
    overrides: dict | None = None,
) -> Path:
    """Generate a town and its sessions into ``out``; returns ``out``.

    ``trajectory`` (TUM, KITTI poses or RobotCar INS CSV) makes the first session follow it, with
    the town generated around it; RobotCar files with latitude/longitude also move the origin there.
    ``overrides`` is a mapping merged over the preset and ``config`` (as a YAML file would be).
    """
    from mapkit.synth.sessions import plan_sessions
    from mapkit.synth.world import build_town

    t_start = time.perf_counter()
    cfg, external, digest = _config_and_trajectory(preset, config, seed, overrides, trajectory)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    town_identity = _town_identity(cfg, digest)
    full_hash = stage_hash("town", TOWN_STAGE_VERSION, town_identity)
    w_hash = _world_hash(cfg, digest)
    timing: dict[str, float] = {}
    with single_thread_blas():
        t = time.perf_counter()
        town = build_town(cfg, None if external is None else _external_xy(external))
        timing["world_generation_s"] = time.perf_counter() - t
        t = time.perf_counter()
        plans = plan_sessions(cfg, town, external)
        timing["session_planning_s"] = time.perf_counter() - t
        world_dir = out / "world"
        manifest = _manifest(cfg, town, plans, full_hash, w_hash, None if external is None else str(trajectory))
        if overwrite or not is_done(
            world_dir, full_hash, legacy_hash=config_hash(town_identity), version=TOWN_STAGE_VERSION
        ):
            t = time.perf_counter()
            _write_world(world_dir, town, cfg, manifest, full_hash, w_hash)
            timing["world_write_s"] = time.perf_counter() - t
        session_metrics, todo = _sessions_to_render(cfg, plans, w_hash, out, overwrite)
        t = time.perf_counter()
        session_timings = _render_sessions(cfg, town, trajectory, out, todo, session_metrics, progress)
        timing["render_s"] = time.perf_counter() - t
        t = time.perf_counter()
        _pictures(out, town, plans)
        timing["pictures_s"] = time.perf_counter() - t
    timing["total_s"] = time.perf_counter() - t_start
    metrics = _town_metrics(cfg, town, plans, full_hash, session_metrics)
    write_json(out / "metrics.json", metrics)
    cam, lid = metrics["rendered"]["camera_frames"], metrics["rendered"]["lidar_scans"]
    cam_s = sum(t["camera_render_s"] for t in session_timings.values())
    lid_s = sum(t["lidar_render_s"] for t in session_timings.values())
    write_timings(
        out,
        **{k: round(v, 3) for k, v in timing.items()},
        camera_frames_per_s=round(cam / cam_s, 3) if cam_s else None,
        lidar_scans_per_s=round(lid / lid_s, 3) if lid_s else None,
        sessions=session_timings,
    )
    mark_done(out, full_hash, version=TOWN_STAGE_VERSION)
    return out


def _config_and_trajectory(
    preset: str, config: Path | None, seed: int | None, overrides: dict | None, trajectory: Path | None
) -> tuple[SynthConfig, ExternalPath | None, str | None]:
    """(resolved config, external trajectory or None, its file's sha256 or None). An external
    trajectory with latitude/longitude moves the config's origin there."""
    from mapkit.synth.sessions import read_external_trajectory

    cfg = load_config(preset, config, seed, overrides)
    if trajectory is None:
        return cfg, None, None
    external = read_external_trajectory(Path(trajectory))
    digest = sha256_file(trajectory)
    if not cfg.sessions:
        raise ConfigError(
            f"--trajectory needs at least one session in `sessions` to drive it (preset {preset!r} has none)"
        )
    if external.origin_latlon is not None:
        lat, lon = external.origin_latlon
        cfg = cfg.model_copy(update={"origin": cfg.origin.model_copy(update={"lat_deg": lat, "lon_deg": lon})})
    return cfg, external, digest


def _manifest(
    cfg: SynthConfig, town, plans: list, full_hash: str, w_hash: str, trajectory_file: str | None
) -> dict[str, Any]:
    """What ``world/manifest.json`` holds: format, seed, hashes, frames, anchor, world summary,
    sessions (the first naming ``trajectory_file``, the external trajectory it drives, if any)."""
    manifest: dict[str, Any] = {
        "format_version": FORMAT_VERSION,
        "generator": "mapkit.synth",
        "preset": cfg.preset,
        "seed": cfg.seed,
        "config_hash": full_hash,
        "world_hash": w_hash,
        "frame": "world = ENU at the origin (origin.json)",
        "base_link": "x forward, y left, z up; on the road surface under the rear axle centre",
        "anchor": town.anchor,
        "world": town.summary(),
        "sessions": [p.manifest_entry(cfg) for p in plans],
    }
    if trajectory_file is not None:
        manifest["sessions"][0]["trajectory_file"] = trajectory_file
    return manifest


def _write_world(world_dir: Path, town, cfg: SynthConfig, manifest: dict, full_hash: str, w_hash: str) -> None:
    """The ``world/`` folder: mesh, road graph, origin, resolved config and manifest, then its marker."""
    from mapkit.synth.world import write_ply, write_roads

    world_dir.mkdir(parents=True, exist_ok=True)
    write_ply(world_dir / "mesh.ply", town.geometry)
    write_roads(world_dir / "roads.json", town.roads, town.anchor)
    write_json(world_dir / "origin.json", town.frame.to_dict())
    atomic_write_text(world_dir / "config.yaml", dump_yaml(cfg))
    write_json(world_dir / "manifest.json", manifest)
    mark_done(world_dir, full_hash, version=TOWN_STAGE_VERSION, world_hash=w_hash)


def _sessions_to_render(
    cfg: SynthConfig, plans: list, w_hash: str, out: Path, overwrite: bool
) -> tuple[list[dict], list[tuple]]:
    """(metrics of the sessions already finished with these settings, marked ``skipped``;
    ``(plan, session hash, marker folder)`` of those still to render)."""
    session_metrics = []
    todo = []
    for p in plans:
        identity = _session_identity(cfg, w_hash, p.index, p.config)
        h = stage_hash("sessions", SESSIONS_STAGE_VERSION, {**identity, "town_version": TOWN_STAGE_VERSION})
        marker = out / "sessions" / ".markers" / p.name
        if not overwrite and is_done(marker, h, legacy_hash=config_hash(identity), version=SESSIONS_STAGE_VERSION):
            done = json.loads((marker / ".done").read_text()).get("metrics", {})
            done.pop("timings_s", None)  # a marker may hold the session's timings: a run record, not a result
            session_metrics.append(done | {"skipped": True})
        else:
            todo.append((p, h, marker))
    return session_metrics, todo


def _render_sessions(
    cfg: SynthConfig, town, trajectory, out: Path, todo: list, session_metrics: list[dict], progress
) -> dict[str, dict]:
    """Render the sessions of ``todo`` (in this process, or in ``cfg.workers`` processes), appending
    their metrics to ``session_metrics``; returns their timings by session name."""
    from mapkit.synth.sessions import write_session

    session_timings: dict[str, dict] = {}
    workers = min(cfg.workers, len(todo))
    if workers <= 1:
        for p, h, marker in todo:
            m = write_session(town, p, cfg, out, progress)
            session_timings[p.name] = m.pop("timings_s")
            mark_done(marker, h, version=SESSIONS_STAGE_VERSION, metrics=m)
            session_metrics.append(m)
    else:
        for m in _render_parallel(cfg, trajectory, out, todo, workers, progress):
            session_timings[m["name"]] = m.pop("timings_s")
            session_metrics.append(m)
    return session_timings


def _town_metrics(cfg: SynthConfig, town, plans: list, full_hash: str, session_metrics: list[dict]) -> dict:
    """What ``metrics.json`` holds: the world's statistics, what was rendered, per-session counts
    (in plan order) and street coverage."""
    rendered = [m for m in session_metrics if not m.get("skipped")]
    order = {p.name: k for k, p in enumerate(plans)}
    return {
        "format_version": FORMAT_VERSION,
        "preset": cfg.preset,
        "seed": cfg.seed,
        "config_hash": full_hash,
        "world": town.summary(),
        "rendered": {
            "sessions": len(rendered),
            "camera_frames": sum(m["camera_frames"] for m in rendered),
            "lidar_scans": sum(m["lidar_scans"] for m in rendered),
            "image_size": [cfg.camera.width, cfg.camera.height],
            "lidar_rays_per_scan": cfg.lidar.beams * cfg.lidar.azimuth_steps,
        },
        "sessions": sorted(session_metrics, key=lambda m: order.get(m.get("name"), 0)),
        "streets": street_coverage(plans),
    }


_WORKER: dict = {}


def _worker_init(cfg_json: str, trajectory: str | None, progress: bool | None, nthreads: int) -> None:
    from mapkit.core.executor import exit_with_parent
    from mapkit.synth.sessions import plan_sessions, read_external_trajectory
    from mapkit.synth.world import build_town

    exit_with_parent()

    cfg = SynthConfig.model_validate_json(cfg_json)
    ext = read_external_trajectory(Path(trajectory)) if trajectory else None
    town = build_town(cfg, None if ext is None else _external_xy(ext))
    _WORKER.update(cfg=cfg, town=town, plans=plan_sessions(cfg, town, ext), progress=progress, nthreads=nthreads)


def _worker_render(index: int, out: str, cfg_hash: str, marker: str) -> dict:
    from mapkit.synth.sessions import write_session

    with single_thread_blas():
        m = write_session(
            _WORKER["town"],
            _WORKER["plans"][index],
            _WORKER["cfg"],
            Path(out),
            _WORKER["progress"],
            nthreads=_WORKER["nthreads"],
        )
    mark_done(
        Path(marker), cfg_hash, version=SESSIONS_STAGE_VERSION, metrics={k: v for k, v in m.items() if k != "timings_s"}
    )
    return m


def street_coverage(plans: list, radius_m: float = 15.0) -> dict:
    """Metres of street the drives cover: all drives, and the distinct ones (1 m samples of each
    drive's path farther than ``radius_m`` from every earlier drive's), in all and of the training
    drives: where held-out places can lie."""
    from scipy.spatial import cKDTree

    from mapkit.synth.sessions import _resample_uniform

    seen: list[np.ndarray] = []
    driven = distinct = distinct_train = 0
    for p in plans:
        r = _resample_uniform(p.drive.path_xy, 1.0)[0]
        new = int((cKDTree(np.vstack(seen)).query(r)[0] > radius_m).sum()) if seen else len(r)
        driven, distinct = driven + len(r), distinct + new
        distinct_train += new if p.config.role == "train" else 0
        seen.append(r)
    return {"driven_m": driven, "distinct_m": distinct, "distinct_train_m": distinct_train, "radius_m": radius_m}


def _render_parallel(cfg: SynthConfig, trajectory, out: Path, todo: list, workers: int, progress) -> list[dict]:
    """Sessions rendered by ``workers`` spawned processes (each regenerates the same town once)."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    from mapkit.synth.render import available_cores

    nthreads = max(1, available_cores() // workers)
    ctx = mp.get_context("spawn")
    # most work first, so that the pool finishes together (longest-processing-time order): per
    # second of driving, a camera frame costs ~0.17 s, a LiDAR sweep ~0.02 s, the rest ~0.1 s
    # (demo preset, the sessions' render seconds in timings.json); a test drive's 4 Hz camera doubles its cost
    lidar_rate = cfg.lidar.rate_hz if cfg.lidar.enabled else 0.0
    todo = sorted(todo, key=lambda x: -x[0].drive.duration_s * (0.17 * x[0].camera_rate_hz + 0.02 * lidar_rate + 0.1))
    with ProcessPoolExecutor(
        workers,
        mp_context=ctx,
        initializer=_worker_init,
        initargs=(cfg.model_dump_json(), None if trajectory is None else str(trajectory), progress, nthreads),
    ) as ex:
        futures = [ex.submit(_worker_render, p.index, str(out), h, str(marker)) for p, h, marker in todo]
        return [f.result() for f in futures]


def _external_xy(ext) -> np.ndarray:
    """The external path's planar positions, decimated to about a metre apart."""
    xy = ext.xy
    step = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    keep = np.concatenate([[True], np.cumsum(step) // 1.0 != np.concatenate([[0], np.cumsum(step)[:-1]]) // 1.0])
    keep[-1] = True
    return xy[keep]


def _pictures(out: Path, town, plans) -> None:
    import cv2

    from mapkit.synth.pictures import draw_contact_sheet, draw_map

    routes = [
        {
            "name": p.name,
            "role": p.config.role,
            "condition": p.conditions.label,
            "time": p.local_start.strftime("%H:%M"),
            "xy": p.drive.world_from_base[::10, :2, 3],
        }
        for p in plans
    ]
    draw_map(town, routes, out / "pictures" / "map.png")
    frames = []
    for p in plans:
        f = out / "pictures" / "frames" / f"{p.name}.png"
        if f.is_file():
            img = cv2.imread(str(f), cv2.IMREAD_COLOR)
            if img is not None:
                caption = (
                    f"{p.name} ({p.config.role}) {p.local_start:%Y-%m-%d %H:%M}\n{p.conditions.label}, "
                    f"{p.conditions.season}"
                )
                frames.append((caption, img[..., ::-1]))
    if frames:
        draw_contact_sheet(
            frames,
            out / "pictures" / "contact_sheet.png",
            f"The same place (star on the map) seen by {len(frames)} sessions",
        )


# --- reading back ----------------------------------------------------------------------------------


@dataclass
class World:
    """A synthesized town read back from its folder."""

    path: Path
    frame: LocalFrame
    roads: RoadGraph
    manifest: dict
    config: SynthConfig

    @cached_property
    def mesh_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(vertices, triangles, material, object_id) of world/mesh.ply."""
        return read_ply(self.path / "world" / "mesh.ply")

    @cached_property
    def mesh(self):
        """world/mesh.ply as an open3d legacy TriangleMesh."""
        import open3d as o3d

        V, T, _, _ = self.mesh_arrays
        return o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(V), o3d.utility.Vector3iVector(T))

    @property
    def sessions(self) -> list[dict]:
        return self.manifest["sessions"]

    def session(self, name: str) -> dict:
        for s in self.sessions:
            if s["name"] == name:
                return s
        raise MapkitError(f"{self.path}: no session {name!r} (sessions: {', '.join(s['name'] for s in self.sessions)})")

    def session_mesh_arrays(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """Vertices and triangles of the static world plus this session's parked cars."""
        V, T, _, _ = self.mesh_arrays
        Vc, Tc, _, _ = read_ply(self.path / self.session(name)["parked_cars"])
        return np.concatenate([V, Vc]), np.concatenate([T, Tc + len(V)]).astype(np.int32)

    def session_mesh(self, name: str):
        import open3d as o3d

        V, T = self.session_mesh_arrays(name)
        return o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(V), o3d.utility.Vector3iVector(T))

    def town(self):
        """The generator's Town (with texture attributes), regenerated from the config and checked."""
        from mapkit.synth.sessions import read_external_trajectory
        from mapkit.synth.world import build_town

        ext_xy = None
        src = self.sessions[0]["trajectory_source"] if self.sessions else "route"
        if src != "route" and self.sessions[0].get("trajectory_file"):
            ext_xy = _external_xy(read_external_trajectory(Path(self.sessions[0]["trajectory_file"])))
        town = build_town(self.config, ext_xy)
        if town.geometry.n_triangles != len(self.mesh_arrays[1]):
            raise MapkitError(
                f"{self.path}: regenerating the town gave {town.geometry.n_triangles} triangles, "
                f"mesh.ply has {len(self.mesh_arrays[1])} (another mapkit version?)"
            )
        return town

    def renderer(self, session: str, town=None):
        """A Renderer of this world with ``session``'s parked cars (to re-render any pose)."""
        from mapkit.synth.render import Renderer
        from mapkit.synth.sessions import session_parked_cars

        town = town or self.town()
        parked = session_parked_cars(town, int(self.session(session)["seed"]))
        return Renderer(town, parked, self.config.camera, self.config.lidar)

    def conditions(self, session: str):
        """The session's appearance conditions (sun, weather, exposure...)."""
        import datetime as dt

        from mapkit.synth.appearance import make_conditions

        s = self.session(session)
        sc = (
            next(x for x in self.config.sessions if x.name == session)
            if any(x.name == session for x in self.config.sessions)
            else None
        )
        local = dt.datetime.fromisoformat(s["start_time_local"])
        return make_conditions(
            s["weather"],
            local,
            self.frame.lat0_deg,
            self.frame.lon0_deg,
            exposure_ev=s["exposure_ev"],
            white_balance_k=s["white_balance_k"],
            season=sc.season if sc else None,
            seed=int(s["seed"]),
        )


def load_world(path: str | Path) -> World:
    """Read a synthesized town's world folder (raises MapkitError when it is incomplete)."""
    import yaml

    from mapkit.synth.config import validate

    path = Path(path)
    world = path / "world"
    for f in ("mesh.ply", "roads.json", "origin.json", "manifest.json", "config.yaml"):
        if not (world / f).is_file():
            raise MapkitError(f"{path}: not a synthesized town (missing world/{f})")
    frame = LocalFrame.from_dict(json.loads((world / "origin.json").read_text()))
    manifest = json.loads((world / "manifest.json").read_text())
    cfg = validate(yaml.safe_load((world / "config.yaml").read_text()), str(world / "config.yaml"))
    return World(path, frame, read_roads(world / "roads.json"), manifest, cfg)


def town_frame(path: str | Path) -> LocalFrame:
    """The town's ENU frame (``world/origin.json``), without reading the rest of the world."""
    f = Path(path) / "world" / "origin.json"
    if not f.is_file():
        raise MapkitError(f"{path}: not a synthesized town (missing world/origin.json)")
    return LocalFrame.from_dict(json.loads(f.read_text()))


def parked_cars_path(path: str | Path, session: str) -> Path:
    """The mesh of the cars parked during ``session`` (absent in towns made without them)."""
    return Path(path) / "sessions" / f"{session}.parked_cars.ply"


def moving_cars_path(path: str | Path, session: str) -> Path:
    """Which LiDAR returns of ``session`` hit a moving car (:mod:`mapkit.synth.traffic`; absent without them)."""
    return Path(path) / "sessions" / f"{session}.moving_cars.npz"


def gt_poses(path: str | Path, session: str) -> tuple[np.ndarray, np.ndarray]:
    """Ground truth of a session: (stamps_ns (N,) int64, world_from_base (N, 4, 4))."""
    f = Path(path) / "sessions" / f"{session}.gt.tum"
    if not f.is_file():
        raise MapkitError(f"{path}: no ground truth for session {session!r} ({f} missing)")
    return read_tum(f)


def camera_poses(path: str | Path, session: str) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth camera poses at the image stamps: (stamps_ns, world_from_camera (optical frame))."""
    f = Path(path) / "sessions" / f"{session}.camera.tum"
    if not f.is_file():
        raise MapkitError(f"{path}: no camera ground truth for session {session!r} ({f} missing)")
    return read_tum(f)
