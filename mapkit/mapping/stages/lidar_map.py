"""The LiDAR map of a session, ``lidar_map/``: the LiDAR's scans deskewed, placed by the session's final
trajectory (stage 2's, the factor graph's with ``georef.fuse``) and accumulated into voxels
(:mod:`mapkit.mapping.lidar_map`), in the workspace's local ENU frame like the semi-dense map (the
trajectory's own frame when the session is not georeferenced).

Files: ``points.ply`` (one point per voxel, its centroid, grey by mean intensity; the frame in the header),
``voxels.npz`` (per voxel: centroid, count, mean intensity, normal, planarity, first and last stamp seen),
``dynamic.ply`` (the points removed as moving objects, one per voxel, when ``dynamic`` is on),
``top_view.png`` (coloured by height, the removed points in magenta) and ``metrics.json`` (points, voxels,
scans used and skipped, deskew, points removed).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mapkit.core.errors import InputError
from mapkit.core.geodesy import LocalFrame
from mapkit.core.runio import atomic_write_ply, write_json
from mapkit.core.types import StreamKind
from mapkit.core.workspace import SessionDirs
from mapkit.core.writers import writes_workspace
from mapkit.io.base import DriveLog
from mapkit.io.plots import raster_top_view
from mapkit.mapping.lidar_map import LidarMapConfig, build_lidar_map, save_voxel_map
from mapkit.mapping.stages.common import plot_axes
from mapkit.mapping.trajectory import SensorMounts, Trajectory

#: the version of this stage's algorithm, bumped whenever its output for the same inputs changes (it reruns)
STAGE_VERSION = 3


def lidar_frame(log: DriveLog, topic: str) -> str | None:
    """The frame of the first scan on ``topic`` (None when it has none)."""
    scans = log.records(StreamKind.LIDAR, topic=topic)
    try:
        first = next(scans, None)
    finally:
        scans.close()
    return None if first is None else first.frame_id


@writes_workspace("dirs", within=True)
def write_lidar_map(
    dirs: SessionDirs,
    log: DriveLog,
    topic: str,
    trajectory: Trajectory,
    mounts: SensorMounts,
    cfg: LidarMapConfig,
    frame: LocalFrame | None,
    progress: bool = True,
) -> Path:
    """Map the scans of ``topic`` into ``dirs.lidar_map`` on ``trajectory`` (ENU from the trajectory's body frame);
    the LiDAR's mount is looked up in ``mounts`` (its frame taken as the body's, with a warning, when the log holds
    no tf at all, as the trajectory stage does). Returns the folder."""
    out = dirs.lidar_map
    sensor = lidar_frame(log, topic) or ""
    base_from_lidar = mounts.base_from(trajectory.body_frame, sensor, "LiDAR", without_tf_ok=True)
    total = next((s.count for s in log.streams() if s.topic == topic), None)
    scans = log.records(StreamKind.LIDAR, topic=topic)
    result = build_lidar_map(scans, trajectory, base_from_lidar, cfg, source=log.path, total=total, progress=progress)
    m = result.metrics(cfg)
    if m["voxels"] == 0:  # an empty map would pass for a finished one; open3d cannot even read it
        raise InputError(
            log.path,
            f"session {dirs.name}: the LiDAR map has 0 points from {result.scans_used + m['scans_skipped']} scans of "
            f"{topic} ({m.get('skipped') or 'no point in any scan'}); set `lidar_map: false` to build the session "
            "without it",
            field="lidar_map",
        )
    stats = result.voxels.stats()
    save_voxel_map(out, stats, frame)
    removed = None
    if result.removed is not None and len(result.removed):  # an empty PLY is one open3d cannot read
        removed = result.removed.stats().centroid
        atomic_write_ply(out / "dynamic.ply", removed, np.tile([0.9, 0.0, 0.8], (len(removed), 1)), frame=frame)
    else:
        (out / "dynamic.ply").unlink(missing_ok=True)  # from an earlier build that removed points
    raster_top_view(
        out / "top_view.png",
        stats.centroid,
        trajectory.world_from_base[:, :3, 3],
        f"{dirs.name}: LiDAR map, {len(stats)} voxels of {cfg.voxel_size_m:g} m",
        axes=plot_axes(frame),
        marked=removed,
        marked_label=f"removed as moving ({m['dynamic'].get('points_removed', 0)} points)",
    )
    m["crs"] = None if frame is None else frame.to_dict()
    m["topic"] = topic
    write_json(out / "metrics.json", m)
    return out
