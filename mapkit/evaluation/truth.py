"""The synthetic town's ground truth, moved into a workspace's frame: the one place evaluations read it.

The truth lives in the town's ENU frame (``TOWN/world/origin.json``); every transform to a
workspace goes exactly through ECEF.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import numpy as np

from mapkit.core.geodesy import LocalFrame
from mapkit.core.geometry import interpolate_poses
from mapkit.synth import camera_poses, gt_poses, parked_cars_path, town_frame


def ws_from_town(truth: Path, ws_frame: LocalFrame) -> np.ndarray:
    """The exact rigid transform from a synthetic town's ENU frame to a workspace's (via ECEF)."""

    return town_frame(truth).to_frame(ws_frame)


def town_sessions(truth: Optional[Path]) -> dict[str, dict]:
    """The town manifest's entry of every session (role, condition, ...), by name; {} without one."""
    if truth is None:
        return {}
    p = Path(truth) / "world" / "manifest.json"
    if not p.is_file():
        return {}
    return {s["name"]: s for s in json.loads(p.read_text()).get("sessions", [])}


def truth_camera_poses(truth: Path, name: str, ws_frame: Optional[LocalFrame]) -> tuple[np.ndarray, np.ndarray]:
    """(stamps_ns, world_from_camera) of a town session's true camera, in the workspace's frame
    (the town's own when ``ws_frame`` is None)."""

    stamps, world_from_cam = camera_poses(truth, name)
    if ws_frame is not None:
        world_from_cam = ws_from_town(truth, ws_frame) @ world_from_cam
    return np.asarray(stamps, np.int64), world_from_cam


def session_truth(truth: Path, name: str):
    return gt_poses(truth, name)


def session_truth_mesh(town_mesh, truth: Path, name: str, town_to_ws: np.ndarray):
    """The surfaces session ``name`` saw: a copy of the town's mesh (already in the workspace frame)
    with the cars parked during that session, if the town has them."""
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh(town_mesh)

    cars = parked_cars_path(truth, name)
    if cars.is_file():
        car_mesh = o3d.io.read_triangle_mesh(str(cars))
        car_mesh.transform(town_to_ws)
        mesh += car_mesh
    return mesh


def error_transforms(est_stamps, est_poses, gt_stamps, gt_ws) -> tuple[np.ndarray, np.ndarray]:
    """Per estimated pose (inside the truth's time span): position and E = T_est T_gt^-1, the
    transform that takes a true point to where this session's map puts it."""
    gt, ok = interpolate_poses(gt_stamps, gt_ws, est_stamps)
    est = est_poses[ok]
    E = est @ np.linalg.inv(gt)
    return est[:, :3, 3], E


def truth_camera_poses_at(truth: Path, name: str, ws_frame: Optional[LocalFrame], stamps_ns: np.ndarray):
    """True camera poses (world_from_camera, workspace ENU) at ``stamps_ns`` and their validity mask."""
    from mapkit.core.geometry import interpolate_poses

    return interpolate_poses(*truth_camera_poses(truth, name, ws_frame), stamps_ns)
