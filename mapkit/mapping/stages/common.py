"""What several stages of a session state alike: whether a trajectory is metric, its length with its units,
and the axes of a top view."""

from __future__ import annotations

import numpy as np

from mapkit.core.geodesy import LocalFrame
from mapkit.mapping.trajectory import Trajectory

ARBITRARY_UNITS = "arbitrary units (structure from motion, not georeferenced)"


def camera_only(traj: Trajectory) -> bool:
    """Structure from motion: no scale, no gravity until GPS alignment."""
    return traj.source.startswith("camera")


def path_length(traj: Trajectory, georeferenced: bool = False) -> dict:
    """The path length with its units: metres, or the arbitrary units of an unreferenced reconstruction."""
    length = float(np.linalg.norm(np.diff(traj.world_from_base[:, :3, 3], axis=0), axis=1).sum())
    if georeferenced or not camera_only(traj):
        return {"units": "m", "length_m": length}
    return {"units": ARBITRARY_UNITS, "length_sfm_units": length}


def plot_axes(frame: LocalFrame | None) -> tuple[str, str]:
    """Axis names of a top view: east/north in a georeferenced session, the odometry's x/y otherwise."""
    return ("east", "north") if frame is not None else ("x (trajectory frame)", "y (trajectory frame)")
