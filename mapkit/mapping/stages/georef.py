"""Stage 2 of a session, ``georef/``: the trajectory placed in the workspace's local ENU frame.

The transform ``enu_from_map`` comes from the log's GPS (:func:`mapkit.mapping.gps_align.align_to_gps`
on the screened fixes, :func:`mapkit.mapping.gps_screen.screen_fixes`), or from the pose stream itself
(``georef.mode: given``). The stage writes ``gps_alignment.json`` (the transform, its residuals, the
rejected fixes, or why the session is not georeferenced), the aligned trajectory, the fixes it used and
a PNG of the trajectory over them; with ``georef.fuse`` also the factor graph's trajectory
(:mod:`mapkit.mapping.stages.fusion`).

A drive without usable GPS is still built, in its own frame, and says why it is not georeferenced;
``georef.strict`` makes GPS that cannot place it an error instead.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field
from scipy.spatial.transform import Rotation

from mapkit.core.config import MapkitConfig, TopicConfig, resolve_topics
from mapkit.core.errors import InputError, InputWarning
from mapkit.core.geodesy import LocalFrame
from mapkit.core.geometry import transform_points, transform_poses
from mapkit.core.lock import workspace_lock
from mapkit.core.runio import atomic_path, write_json
from mapkit.core.types import GpsFix, StreamKind
from mapkit.core.workspace import SessionDirs, Workspace
from mapkit.core.writers import lock_wait, writes_workspace
from mapkit.io.base import DriveLog
from mapkit.io.plots import map_top_view, trajectory_over_gps
from mapkit.mapping.factor_graph import FactorGraphConfig
from mapkit.mapping.gps_align import GpsAlignment, align_to_gps, associate_fixes
from mapkit.mapping.gps_align import Mode as AlignMode
from mapkit.mapping.gps_screen import GpsScreen, screen_fixes
from mapkit.mapping.stages.common import camera_only, path_length, plot_axes
from mapkit.mapping.stages.fusion import fuse_georeferenced
from mapkit.mapping.trajectory import SensorMounts, Trajectory, camera_up_hint

#: the version of this stage's algorithm, bumped whenever its output for the same inputs changes (it reruns)
STAGE_VERSION = 1


class GeorefConfig(MapkitConfig):
    mode: Literal["auto", "yaw_scale", "sim3", "yaw", "given"] = Field(
        "auto",
        description="'auto' (default): 'yaw' for metric trajectories (LiDAR odometry, INS poses), 'sim3' for "
        "camera-only ones. 'yaw': gravity-aware yaw + translation, the trajectory keeps its own scale. 'yaw_scale': "
        "also a scale from GPS (for a trajectory whose own scale is off, such as KITTI's OXTS projection; on a metric "
        "LiDAR trajectory GPS noise makes the scale worse than the odometry's own). 'sim3': all 7 parameters. "
        "'given': the trajectory (a pose "
        "stream) is already in the ENU frame at `origin`, GPS is not used.",
    )
    origin: tuple[float, float, float] | None = Field(
        None, description="(lat deg, lon deg, alt m) of the pose stream's ENU frame; only with mode 'given'."
    )
    inlier_sigmas: float = Field(
        3.37, gt=0, allow_inf_nan=False, description="Gate on the sigma-normalised residual (chi-square 3 dof, 99%)."
    )
    vertical_sigma_factor: float = Field(
        2.0, gt=0, allow_inf_nan=False, description="GPS height sigma as a multiple of its horizontal sigma."
    )
    min_inlier_threshold_m: float = Field(
        2.0, ge=0, allow_inf_nan=False, description="The horizontal gate is never tighter than this."
    )
    max_pose_gap_s: float = Field(
        1.0,
        gt=0,
        allow_inf_nan=False,
        description="A fix between trajectory poses further apart than this is not used.",
    )
    strict: bool = Field(
        False,
        description="Fail instead of building the session unreferenced when GPS cannot place it, "
        "and when a camera-only drive is too straight for GPS to fix its roll and the cameras give no up hint.",
    )
    fuse: bool = Field(
        False,
        description="Also fuse the odometry, GPS and the IMU on a factor graph (mapping/factor_graph.py, "
        "GPS with its bias state, the IMU preintegrated): georef/trajectory_fused/ and its per-pose covariances beside "
        "trajectory_enu/; the map and image database then use it. Metric trajectories only. Off by default: it needs "
        "an IMU stream to keep its height, and the rigid GPS fit needs none.",
    )
    factor_graph: FactorGraphConfig = FactorGraphConfig()


@dataclass(frozen=True)
class ScreenedFixes:
    """A log's GPS as the georef stage uses it."""

    topics: list[str]  # the log's GPS topics
    fixes: list[GpsFix]  # the fixes of the first topic that passed screening, a missing altitude filled in
    screen: GpsScreen | None  # the screening (None without a GPS topic)


def screened_fixes(log: DriveLog, topics: TopicConfig, log_path: Path) -> ScreenedFixes:
    """The fixes of the log's first GPS topic that pass :func:`screen_fixes`, with the screening.

    A fix without altitude (NaN: a frame table without ``alt``, a photo without GPSAltitude) takes
    the median altitude of the others, or 0 m when none has one; the screening's record says how many."""
    gps_topics = resolve_topics(log, topics).get(StreamKind.GPS, [])
    if not gps_topics:
        return ScreenedFixes(gps_topics, [], None)
    screen = screen_fixes([f for f in log.records(StreamKind.GPS, topic=gps_topics[0]) if f.has_fix])
    fixes = screen.kept
    alt = np.array([f.alt_m for f in fixes], np.float64)
    missing = ~np.isfinite(alt)
    if missing.any():
        fill = float(np.median(alt[~missing])) if (~missing).any() else 0.0
        fixes = [replace(f, alt_m=fill) if m else f for f, m in zip(fixes, missing, strict=True)]
        screen.altitude_filled = int(missing.sum())
        warnings.warn(
            f"{log_path}: {int(missing.sum())} of {len(fixes)} GPS fixes have no altitude; "
            f"{fill:.2f} m ({'the median of the others' if (~missing).any() else 'none has one'}) is used",
            InputWarning,
            stacklevel=3,
        )
    return ScreenedFixes(gps_topics, fixes, screen)


def proposed_frame(cfg: GeorefConfig, gps: Callable[[], ScreenedFixes]) -> LocalFrame | None:
    """The workspace frame a session would set if it were the first one georeferenced: at its first fix
    that passed screening (a wild fix never becomes the origin), or the origin of a ``given`` pose stream.
    ``gps`` gives the session's screened fixes (read only when the mode needs them)."""
    if cfg.mode == "given":
        return None if cfg.origin is None else LocalFrame(*cfg.origin)
    fixes = gps().fixes
    return None if not fixes else LocalFrame(fixes[0].lat_deg, fixes[0].lon_deg, fixes[0].alt_m)


@writes_workspace("ws")
def workspace_frame(ws: Workspace, proposed: LocalFrame) -> LocalFrame:
    """The workspace's frame: the one already set, else ``proposed``, which becomes it (``origin.json``)."""
    frame = ws.frame()
    if frame is not None:
        return frame
    write_json(ws.origin, proposed.to_dict())
    return proposed


class Georeference:
    """The georef stage of one session: :meth:`run` aligns the trajectory stage's output and writes
    ``georef/``.

    ``gps`` gives the session's screened fixes (:func:`screened_fixes`, read once by the caller); ``log``
    and ``topics`` are read for the IMU and LiDAR streams only when ``cfg.fuse`` runs the factor graph.
    ``log_path`` names the log in messages.
    """

    def __init__(
        self,
        ws: Workspace,
        dirs: SessionDirs,
        cfg: GeorefConfig,
        *,
        log: DriveLog,
        log_path: Path,
        topics: TopicConfig,
        mounts: SensorMounts,
        gps: Callable[[], ScreenedFixes],
    ):
        self.ws = ws
        self.dirs = dirs
        self.cfg = cfg
        self.log = log
        self.log_path = log_path
        self.topics = topics
        self.mounts = mounts
        self.gps = gps

    def run(self, trajectory_dir: Path) -> Path:
        """Georeference the trajectory in ``trajectory_dir``; returns the stage folder (under the workspace's lock)."""
        with workspace_lock(self.ws.root, wait_s=lock_wait()):
            return self._run(trajectory_dir)

    def _run(self, trajectory_dir: Path) -> Path:
        out = self.dirs.georef
        traj = Trajectory.load(trajectory_dir)
        result: dict = {"session": self.dirs.name, "georeferenced": False}
        placed = self._align(traj, result)
        enu_from_map = np.eye(4) if placed is None else placed
        result["enu_from_map"] = enu_from_map
        # the aligned trajectory: rigid poses in ENU (the similarity's scale goes into positions)
        aligned = Trajectory(
            traj.stamps_ns,
            transform_poses(enu_from_map, traj.world_from_base),
            traj.source,
            frame="enu" if placed is not None else traj.frame,
            body_frame=traj.body_frame,
        )
        aligned.save(self.dirs.georef_trajectory)
        result.update(path_length(aligned, georeferenced=placed is not None))
        if self.cfg.fuse and placed is not None and not camera_only(traj):
            result["fused"] = fuse_georeferenced(
                traj,
                placed,
                self.dirs,
                self.cfg.factor_graph,
                log=self.log,
                log_path=self.log_path,
                topics=self.topics,
                mounts=self.mounts,
                gps_frame_id=self.gps().fixes[0].frame_id,
            )
        if placed is None:  # a picture of what there is, in the trajectory's own frame and units
            xyz, axes = _top_view_positions(traj)
            map_top_view(
                out / "trajectory_top_view.png",
                np.zeros((0, 3)),
                xyz,
                f"{self.dirs.name}: trajectory, NOT georeferenced",
                axes=axes,
                units="m" if result["units"] == "m" else "arbitrary units",
            )
        write_json(self.dirs.gps_alignment, result)
        return out

    def _align(self, traj: Trajectory, result: dict) -> np.ndarray | None:
        """``enu_from_map``, or None with the reason in ``result`` and a warning.

        No GPS, or GPS that cannot fix the transform (a short or stationary drive): the session is
        still mapped, in its own frame, and says why it is not georeferenced. ``georef.strict``
        makes the second case an error instead.
        """
        if self.cfg.mode == "given":
            return self._given(traj, result)
        gps = self.gps()
        if gps.screen is not None:
            result["gps_screen"] = gps.screen.summary()
            gps.screen.warn(str(self.log_path))
        fixes = gps.fixes
        if len(fixes) < 3:
            result["reason"] = "no GPS stream" if not gps.topics else f"{len(fixes)} valid GPS fixes"
            warnings.warn(
                f"{self.log_path}: {result['reason']}; the map is built in the trajectory's local frame "
                "and is NOT georeferenced",
                InputWarning,
                stacklevel=3,
            )
            return None
        frame = workspace_frame(self.ws, LocalFrame(fixes[0].lat_deg, fixes[0].lon_deg, fixes[0].alt_m))
        stamps = np.array([f.stamp_ns for f in fixes], np.int64)
        gps_enu = frame.geodetic_to_enu(
            [f.lat_deg for f in fixes], [f.lon_deg for f in fixes], [f.alt_m for f in fixes]
        )
        sigma = np.array([f.horizontal_sigma_m for f in fixes])
        base_from_gps = self.mounts.base_from(traj.body_frame, fixes[0].frame_id, "GPS antenna", without_tf_ok=True)
        g = self.cfg
        antenna, ok = associate_fixes(
            traj.stamps_ns, traj.world_from_base, stamps, base_from_gps, int(g.max_pose_gap_s * 1e9)
        )
        try:
            al = self._fit(traj, antenna, gps_enu[ok], sigma[ok], stamps[ok])
        except InputError as exc:
            if g.strict:
                raise
            result["reason"] = exc.what
            warnings.warn(f"{exc}; the session is NOT georeferenced", InputWarning, stacklevel=3)
            return None
        result.update(
            georeferenced=True,
            **frame.to_dict(),
            alignment=al.stats(),
            rejected_fixes=al.rejected,
            fixes_total=len(fixes),
            fixes_outside_trajectory=int((~ok).sum()),
        )
        inlier = np.zeros(len(fixes), bool)
        inlier[np.nonzero(ok)[0][al.inliers]] = True
        with atomic_path(self.dirs.gps_fixes) as tmp, open(tmp, "wb") as f:
            np.savez(f, stamps_ns=stamps, enu=gps_enu, sigma_m=sigma, associated=ok, inlier=inlier)

        traj_enu = transform_points(al.enu_from_map, traj.world_from_base[:, :3, 3])
        trajectory_over_gps(
            self.dirs.georef / "trajectory_over_gps.png",
            traj_enu,
            gps_enu[ok],
            al.inliers,
            f"{self.dirs.name}: trajectory over GPS ({al.mode}, RMSE {al.stats()['residual_rmse_m']:.2f} m)",
        )
        return al.enu_from_map

    def _fit(
        self, traj: Trajectory, antenna: np.ndarray, gps_enu: np.ndarray, sigma: np.ndarray, stamps: np.ndarray
    ) -> GpsAlignment:
        """The alignment of the antenna positions (trajectory frame) onto the fixes associated with them.

        Structure from motion has no gravity and no scale: only a full Sim3 can place it. A metric
        trajectory keeps its scale under 'auto': GPS over a drive of a few hundred metres, with a
        bias that drifts over minutes, estimates scale worse than LiDAR odometry measures it.
        Its gravity comes from GPS where the path bends enough; on a straight path the cameras'
        mean up fixes the roll about it (see gps_align's module notes)."""
        g = self.cfg
        up_map = None
        mode: AlignMode
        if camera_only(traj):
            mode = "sim3"
            up_map = camera_up_hint(traj.world_from_base)
        else:
            assert g.mode != "given"  # handled by _given
            mode = "yaw" if g.mode == "auto" else g.mode
        return align_to_gps(
            antenna,
            gps_enu,
            sigma,
            stamps,
            mode=mode,
            inlier_sigmas=g.inlier_sigmas,
            vertical_sigma_factor=g.vertical_sigma_factor,
            min_inlier_threshold_m=g.min_inlier_threshold_m,
            up_map=up_map,
            strict=g.strict,
            source=str(self.log_path),
        )

    def _given(self, traj: Trajectory, result: dict) -> np.ndarray:
        """Georeferencing that the pose stream already carries (an INS, or a simulator's truth):
        its frame is ENU at ``georef.origin``; placed exactly (through ECEF) in the workspace frame."""
        g = self.cfg
        if g.origin is None:
            raise InputError(
                self.ws.build_config, "georef mode 'given' needs the pose stream's ENU origin", field="georef.origin"
            )
        if not traj.source.startswith("poses"):
            raise InputError(
                self.log_path,
                f"georef mode 'given' needs a pose-stream trajectory, not {traj.source!r}",
                field="trajectory.source",
            )
        given = LocalFrame(*g.origin)
        frame = workspace_frame(self.ws, given)
        result.update(
            georeferenced=True,
            **frame.to_dict(),
            alignment={"mode": "given", "origin": list(g.origin)},
            rejected_fixes=[],
            fixes_total=0,
            fixes_outside_trajectory=0,
        )
        return given.to_frame(frame)


def _top_view_positions(traj: Trajectory) -> tuple[np.ndarray, tuple[str, str]]:
    """Positions to draw from above, and their axis names: a camera-only trajectory turned so that
    the cameras' mean up is +z (its own frame has no gravity), any other as it is."""
    xyz = traj.world_from_base[:, :3, 3]
    up = camera_up_hint(traj.world_from_base) if camera_only(traj) else None
    if up is None:
        return xyz, plot_axes(None)
    axis = np.cross(up, [0.0, 0.0, 1.0])
    n = float(np.linalg.norm(axis))
    rotvec = (axis / n if n > 1e-12 else np.array([1.0, 0.0, 0.0])) * float(np.arctan2(n, up[2]))  # up onto +z
    return xyz @ Rotation.from_rotvec(rotvec).as_matrix().T, ("x (levelled by the cameras' up)", "y")
