"""Scoring the LiDAR map's removal of moving objects against a synthetic town's truth.

A session rendered with ``moving_cars`` knows which LiDAR returns hit a moving car
(:mod:`mapkit.synth.traffic`). Its scans are placed as the LiDAR map places them (on the true poses by default,
or on a given trajectory: the build's own) and given their keep masks as the map gives them
(:func:`~mapkit.mapping.lidar_map.keep_masks`); each point is then a car point kept or removed, or a static point
kept or removed. The figures are shares of points, before the map's voxels merge them.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from mapkit.core.errors import InputError
from mapkit.core.types import LidarScan, StreamKind
from mapkit.io import open_log
from mapkit.mapping.lidar_dynamic import PlacedScan
from mapkit.mapping.lidar_map import LidarMapConfig, keep_masks, place_scan, scan_times, within_range
from mapkit.mapping.trajectory import Trajectory
from mapkit.synth import extrinsics, gt_poses, load_world, moving_cars_path, session_log
from mapkit.synth.traffic import read_dynamic_truth


def score_dynamic_removal(
    town: str | Path, session: str, cfg: LidarMapConfig | None = None, trajectory: Trajectory | None = None
) -> dict:
    """Car points kept and static points removed by ``cfg.dynamic`` on ``session`` of ``town``, its scans placed
    by ``trajectory`` (world_from_base; the session's true poses by default)."""
    town = Path(town)
    cfg = cfg or LidarMapConfig()
    truth_file = moving_cars_path(town, session)
    if not truth_file.is_file():
        raise InputError(truth_file, f"session {session!r} was rendered without moving cars", field="moving_cars")
    truth = read_dynamic_truth(truth_file)
    if trajectory is None:
        trajectory = Trajectory(*gt_poses(town, session), "truth")
    base_from_lidar = extrinsics(load_world(town).config)["lidar"]
    labels: dict[int, np.ndarray] = {}

    def placed_scans() -> Iterator[tuple[LidarScan, PlacedScan]]:
        for scan in open_log(session_log(town, session)).records(StreamKind.LIDAR):
            placed = place_scan(scan, trajectory, base_from_lidar, cfg, scan_times(scan, cfg)[0])
            if placed is None or not len(placed.points):
                continue
            car = np.zeros(len(scan), bool)
            car[truth[scan.stamp_ns]] = True
            labels[scan.stamp_ns] = car[within_range(np.asarray(scan.points_xyz, np.float64), cfg)]
            yield scan, placed

    per_scan = []  # stamp, car points, car points kept, static points, static points removed
    for placed, keep in keep_masks(placed_scans(), cfg):
        stamp, car = placed.stamp_ns, labels.pop(placed.stamp_ns)
        per_scan.append([stamp, int(car.sum()), int((keep & car).sum()), int((~car).sum()), int((~keep & ~car).sum())])
    car_n, car_kept, static_n, static_removed = (int(sum(row[k] for row in per_scan)) for k in (1, 2, 3, 4))
    return {
        "session": session,
        "poses": trajectory.source,
        "scans": len(per_scan),
        "car_points": car_n,
        "car_points_kept": car_kept,
        "car_kept_fraction": car_kept / max(car_n, 1),
        "static_points": static_n,
        "static_points_removed": static_removed,
        "static_removed_fraction": static_removed / max(static_n, 1),
        "per_scan": per_scan,
    }


__all__ = ["score_dynamic_removal"]
