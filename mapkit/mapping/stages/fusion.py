"""The georef stage's factor graph (``georef.fuse``): one session's odometry, the GPS fixes the rigid
alignment kept and the IMU fused by :func:`mapkit.mapping.factor_graph.fuse_session`, with loop closures
(:mod:`mapkit.mapping.loop_closure`) verified on the LiDAR scans where the drive comes back.

Writes ``georef/trajectory_fused/`` and its per-pose covariances; the graph's wall-clock figures go into
the stage's run record (``timings.json``), its other statistics back to the caller for
``gps_alignment.json``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from functools import partial
from pathlib import Path

import numpy as np

from mapkit.core.config import TopicConfig, resolve_topics
from mapkit.core.runio import atomic_path, write_timings
from mapkit.core.types import StreamKind
from mapkit.core.workspace import SessionDirs
from mapkit.core.writers import writes_workspace
from mapkit.io.base import DriveLog
from mapkit.mapping.factor_graph import (
    FactorGraphConfig,
    FusedTrajectory,
    GpsObservations,
    ImuObservations,
    fuse_session,
    loop_counts,
)
from mapkit.mapping.loop_closure import loop_closures, propose_loops, read_scans, scans_needed, verify_loops
from mapkit.mapping.trajectory import SensorMounts, Trajectory

#: the factor graph's wall-clock figures: the stage's run record holds them (as ``fused_<name>``), not its results
FUSED_TIMINGS = ("seconds", "solve_s", "loop_seconds")


@writes_workspace("dirs", within=True)
def fuse_georeferenced(
    traj: Trajectory,
    enu_from_map: np.ndarray,
    dirs: SessionDirs,
    cfg: FactorGraphConfig,
    *,
    log: DriveLog,
    log_path: Path,
    topics: TopicConfig,
    mounts: SensorMounts,
    gps_frame_id: str,
) -> dict:
    """The factor graph over the odometry ``traj``, the fixes the georef stage kept (``dirs.gps_fixes``, from the
    antenna at ``gps_frame_id``) and the IMU (odometry and GPS alone without one), started at ``enu_from_map``:
    writes the fused trajectory and its covariances, returns the graph's stats (its timings written to the run
    record)."""
    with np.load(dirs.gps_fixes) as f:
        fixes = {k: f[k] for k in ("stamps_ns", "enu", "sigma_m")}
    gps = GpsObservations(
        fixes["stamps_ns"],
        fixes["enu"],
        fixes["sigma_m"],
        mounts.base_from(traj.body_frame, gps_frame_id, "GPS antenna", without_tf_ok=True),
    )
    imu = _imu(log, topics, mounts, traj.body_frame)
    fuse = partial(
        fuse_session,
        traj.stamps_ns,
        traj.world_from_base,
        gps,
        None,
        cfg,
        enu_from_odom=enu_from_map,
        source=str(log_path),
        imu=imu,
    )
    fused = fuse()
    loop_stats: dict = {}
    if cfg.loop_closures:
        fused, loop_stats = _close_loops(
            traj, fused, fuse, cfg, log=log, log_path=log_path, topics=topics, mounts=mounts
        )
    Trajectory(fused.stamps_ns, fused.enu_from_base, traj.source, frame="enu", body_frame=traj.body_frame).save(
        dirs.fused_trajectory
    )
    with atomic_path(dirs.fused_covariances) as tmp, open(tmp, "wb") as f:
        np.savez(f, stamps_ns=fused.stamps_ns, covariances=fused.covariances, georef_covariance=fused.georef_covariance)
    stats = {**fused.stats, **loop_stats, "imu": "preintegrated" if imu is not None else "no IMU stream"}
    timings = {f"fused_{k}": stats.pop(k) for k in FUSED_TIMINGS if k in stats}
    write_timings(dirs.georef, **timings)
    return stats


def _imu(log: DriveLog, topics: TopicConfig, mounts: SensorMounts, body_frame: str) -> ImuObservations | None:
    """The samples of the log's first IMU topic, mounted on the trajectory's body frame (None without two of them)."""
    imu_topics = resolve_topics(log, topics).get(StreamKind.IMU, [])
    if not imu_topics:
        return None
    samples = list(log.records(StreamKind.IMU, topic=imu_topics[0]))
    if len(samples) < 2:
        return None
    return ImuObservations.from_samples(samples, mounts.base_from(body_frame, samples[0].frame_id, "IMU"))


def _close_loops(
    traj: Trajectory,
    fused: FusedTrajectory,
    fuse: Callable[..., FusedTrajectory],
    cfg: FactorGraphConfig,
    *,
    log: DriveLog,
    log_path: Path,
    topics: TopicConfig,
    mounts: SensorMounts,
) -> tuple[FusedTrajectory, dict]:
    """Loop closures (mapping/loop_closure.py) proposed on the fused trajectory and verified by ICP of local maps of
    the LiDAR scans (read once, up to the last one needed), placed with it; with any accepted, the graph solved
    again with them (``fuse``), from the solution without. Returns the trajectory and the loop step's stats."""
    lidar_topics = resolve_topics(log, topics).get(StreamKind.LIDAR, [])
    if not lidar_topics:
        return fused, {"loops": "not used: no LiDAR stream"}
    t0 = time.perf_counter()
    candidates = propose_loops(fused.enu_from_base, fused.keyframes, cfg)
    scans = read_scans(
        log.records(StreamKind.LIDAR, topic=lidar_topics[0]),
        traj.stamps_ns,
        fused.enu_from_base,
        scans_needed(candidates, len(traj.stamps_ns), cfg),
        partial(mounts.base_from, traj.body_frame, what="LiDAR", without_tf_ok=True),
        cfg,
        source=f"{log_path} {lidar_topics[0]}",
    )
    checks = verify_loops(candidates, scans, fused.enu_from_base, cfg)
    loops = loop_closures(checks, traj.stamps_ns)
    stats = loop_counts(loops)
    if loops.edges:
        fused = fuse(loops=loops, start=fused)
    stats.update(loop_checks=[c.to_dict(traj.stamps_ns) for c in checks], loop_seconds=time.perf_counter() - t0)
    return fused, stats
