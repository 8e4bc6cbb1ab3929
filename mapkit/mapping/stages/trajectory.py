"""Stage 1 of a session, ``trajectory/``: the vehicle's poses from the log (kiss-icp, a pose stream,
structure from motion, ...), as :func:`mapkit.mapping.trajectory.estimate_trajectory` chooses, with
TUM and KITTI files and the stage's metrics."""

from __future__ import annotations

from pathlib import Path

from mapkit.core.config import TopicConfig
from mapkit.core.runio import write_json
from mapkit.core.workspace import SessionDirs
from mapkit.core.writers import writes_workspace
from mapkit.io.base import DriveLog
from mapkit.mapping.stages.common import path_length
from mapkit.mapping.trajectory import SensorMounts, TrajectoryConfig, estimate_trajectory

#: the version of this stage's algorithm, bumped whenever its output for the same inputs changes (it reruns)
STAGE_VERSION = 2


@writes_workspace("dirs", within=True)
def write_trajectory(
    dirs: SessionDirs,
    log: DriveLog,
    cfg: TrajectoryConfig,
    topics: TopicConfig,
    mounts: SensorMounts,
    progress: bool = True,
) -> Path:
    """Estimate the session's trajectory from ``log`` and write it into ``dirs.trajectory`` with its metrics
    (source, poses, duration, length with its units); returns the folder."""
    out = dirs.trajectory
    traj = estimate_trajectory(log, cfg, topics, progress=progress, mounts=mounts)
    traj.save(out)
    m = {
        "source": traj.source,
        "poses": len(traj),
        "duration_s": (int(traj.stamps_ns[-1]) - int(traj.stamps_ns[0])) * 1e-9,
        **path_length(traj),
    }
    write_json(out / "metrics.json", m)
    return out
