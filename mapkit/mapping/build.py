"""``mapkit build``: one drive log to a georeferenced session map, stage by stage.

Stages (each a folder under ``WORKSPACE/sessions/<name>/`` with a ``.done`` marker holding the
hash of the config that made it, the log's fingerprint, the digests of the upstream stages it read
and the SHA-256 of its outputs; re-running skips finished stages and redoes half-written ones, those
whose log or upstream stage changed, and those whose outputs were changed or truncated since):

1. ``trajectory/``  vehicle poses (kiss-icp, a pose stream, ...), TUM and KITTI files
2. ``georef/``      GPS alignment: ``enu_from_map``, residuals, rejected fixes, aligned trajectory,
                    a PNG of the trajectory over the fixes
3. ``map/``         the semi-dense map in the workspace's local ENU frame (PLY + observations)
4. ``imagedb/``     the georeferenced image database (COLMAP reconstruction + images.csv)

The image stages (3 and 4) are skipped, with the reason in the session's ``metrics.json`` and a
warning, when the log has no image stream; stage 3 also when ``map: false`` or when a camera-only
trajectory could not be georeferenced (its scale is arbitrary, the mapper's parameters are in
metres), stage 4 when ``imagedb: false``. Lengths and poses of a camera-only session that is not
georeferenced are in the reconstruction's arbitrary units and say so (``length_sfm_units``,
``pose_units``).

Before any stage writes, every log is checked: one still being written (a copy in progress) is
refused, topics the config names must exist, and a camera the config names (``camera``,
``topics.images``) must have frames and intrinsics when a map or image database is asked for
(it is not found missing after the trajectory has been estimated).

Every session of a workspace shares one local ENU origin and UTM zone (``WORKSPACE/origin.json``,
set by the first session with GPS), so maps of different sessions are in one frame from the start.
"""

from __future__ import annotations

import json
import logging
import time
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import replace
from fnmatch import fnmatchcase
from functools import partial
from pathlib import Path
from types import SimpleNamespace
from typing import Literal

import numpy as np
from pydantic import Field, ValidationError, field_validator, model_validator
from scipy.spatial.transform import Rotation

from mapkit.core.config import MapkitConfig, TopicConfig, deep_merge, dump_config, load_config, resolve_topics
from mapkit.core.errors import InputError, InputWarning, MapkitError
from mapkit.core.executor import Executor, TaskError, get_executor
from mapkit.core.fingerprint import describe_change, log_fingerprint
from mapkit.core.geodesy import LocalFrame
from mapkit.core.geometry import interpolate_poses, transform_points, transform_poses
from mapkit.core.runio import (
    atomic_path,
    atomic_write_text,
    config_hash,
    is_done,
    mark_done,
    read_timings,
    reset_stage,
    stage_digest,
    write_json,
    write_timings,
)
from mapkit.core.types import CameraFrame, CameraInfo, GpsFix, StreamKind
from mapkit.core.workspace import SessionDirs, Workspace
from mapkit.io import open_log
from mapkit.io.base import DriveLog
from mapkit.io.plots import map_top_view, trajectory_over_gps
from mapkit.mapping.factor_graph import (
    FactorGraphConfig,
    FusedTrajectory,
    GpsObservations,
    ImuObservations,
    fuse_session,
    loop_counts,
)
from mapkit.mapping.gps_align import Mode as AlignMode
from mapkit.mapping.gps_align import align_to_gps, associate_fixes
from mapkit.mapping.gps_screen import GpsScreen, screen_fixes
from mapkit.mapping.imagedb import ImageDbConfig, ImageDbWriter
from mapkit.mapping.loop_closure import loop_closures, propose_loops, read_scans, scans_needed, verify_loops
from mapkit.mapping.semidense import SemiDenseConfig, SemiDenseMap, build_semidense_map
from mapkit.mapping.trajectory import SensorMounts, Trajectory, TrajectoryConfig, camera_up_hint, estimate_trajectory

logger = logging.getLogger(__name__)


class GeorefConfig(MapkitConfig):
    mode: Literal["auto", "yaw_scale", "sim3", "yaw", "given"] = Field(
        "auto",
        description="'auto' (default): 'yaw' for metric trajectories (LiDAR odometry, INS poses), 'sim3' for "
        "camera-only ones. 'yaw': gravity-aware yaw + translation, the trajectory keeps its own scale. 'yaw_scale': "
        "also a scale from GPS (the issue's model; on the demo sessions GPS chose scales 0.9961-1.0046 where "
        "kiss-icp's own is 1.0003-1.0010 against truth). 'sim3': all 7 parameters. 'given': the trajectory (a pose "
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


class ExtrinsicsConfig(MapkitConfig):
    assume_identity: list[str] = Field(
        default_factory=list,
        description="Sensor frames (a NavSatFix's, a PointCloud2's, a camera's frame_id) that the log's tf may leave "
        "unlinked to the trajectory's frame: each is then taken as mounted at it (the identity), with one warning. Any "
        "other unlinked sensor is an error: a guessed mount moves the map by the lever arm, or turns it.",
    )


class ImageDbStageConfig(ImageDbConfig):
    enabled: bool = Field(
        True, description="Write the image database (stage 4); `imagedb: false` is short for `enabled: false`."
    )

    @field_validator("min_spacing_m")
    @classmethod
    def _spacing(cls, v: float) -> float:
        if not np.isfinite(v) or v < 0:
            raise ValueError(f"must be a finite distance >= 0 m, not {v}")
        return v


class BuildConfig(MapkitConfig):
    topics: TopicConfig = TopicConfig()
    trajectory: TrajectoryConfig = TrajectoryConfig()
    georef: GeorefConfig = GeorefConfig()
    imagedb: ImageDbStageConfig = ImageDbStageConfig()
    extrinsics: ExtrinsicsConfig = ExtrinsicsConfig()
    semidense: SemiDenseConfig = Field(
        default_factory=SemiDenseConfig,
        description="Semi-dense mapping (stage 3), checked with the rest of the config before any stage runs.",
    )
    map: bool = Field(
        True,
        description="Build the semi-dense map (stage 3). False: trajectory, georeferencing and an image "
        "database without triangulated points, all that image retrieval and MCVL need.",
    )
    camera: str | None = Field(
        None,
        description="Camera (frame id) to map with; if unset, the first one (by name) with "
        "intrinsics, of those on topics.images when that is set.",
    )

    sessions: dict[str, dict] = Field(
        default_factory=dict,
        description="Per-session overrides: a glob of session names -> settings of this config for the sessions it "
        "matches, applied in order. MCVL's database is its training drives at 2 Hz while its queries stay at 4 Hz "
        "(Sec. IV-B): {'train-*': {imagedb: {min_interval_s: 0.5}}}.",
    )

    @field_validator("imagedb", mode="before")
    @classmethod
    def _imagedb_switch(cls, v):
        return {"enabled": v} if isinstance(v, bool) else v

    @model_validator(mode="after")
    def _session_overrides_are_valid(self):
        for pattern, override in self.sessions.items():
            if "sessions" in override:
                raise ValueError(f"sessions.{pattern}: a session's overrides cannot hold per-session overrides")
            try:
                self._merged(override)
            except ValidationError as exc:
                err = exc.errors()[0]
                raise ValueError(f"sessions.{pattern}.{'.'.join(str(p) for p in err['loc'])}: {err['msg']}") from None
        return self

    def _merged(self, override: dict) -> BuildConfig:
        return BuildConfig.model_validate(
            deep_merge(self.model_dump(mode="json", exclude_unset=True, exclude={"sessions"}), override)
        )

    def for_session(self, name: str) -> BuildConfig:
        """The config session ``name`` is built with: this one with the overrides of every pattern of
        ``sessions`` that matches the name, in order (itself when none does)."""
        matching = [o for pattern, o in self.sessions.items() if fnmatchcase(name, pattern)]
        if not matching:
            return self
        cfg = self
        for override in matching:
            cfg = cfg._merged(override)
        return cfg


_IMAGEDB_LATER_DEFAULTS = {"min_interval_s": 0.0, "training_frames": False, "training_interval_s": 0.0}


def _stage_hash(cfg: BuildConfig, *parts: str) -> str:
    d = cfg.model_dump(mode="json")
    # semi-dense hashes as the overrides it was given, as when it was a plain dict of them: stages
    # finished before it was typed stay finished
    d["semidense"] = cfg.semidense.model_dump(mode="json", exclude_unset=True)
    # the image database's switch decides whether it runs, not what it holds: stages finished before
    # the switch existed stay finished
    d["imagedb"].pop("enabled")
    # ... and so do those finished before the image database could sub-sample by time or keep training frames
    for key, default in _IMAGEDB_LATER_DEFAULTS.items():
        if d["imagedb"].get(key) == default:
            d["imagedb"].pop(key)
    # ... and those georeferenced before the factor graph could fuse them, while it does not
    if not d["georef"]["fuse"]:
        d["georef"].pop("fuse")
        d["georef"].pop("factor_graph")
    # ... and those built before a mount could be assumed, while none is: where one is, every stage depends on it
    if d["extrinsics"]["assume_identity"]:
        parts = (*parts, "extrinsics")
    return config_hash({p: d.get(p) for p in parts})


def session_name(log_path: str | Path) -> str:
    """The session a log builds: its file or folder name up to the first dot."""
    return Path(log_path).stem.split(".")[0]


class SessionBuilder:
    """Runs the stages of one session; each stage method returns its output folder."""

    def __init__(
        self,
        log_path: str | Path,
        workspace: str | Path | Workspace,
        cfg: BuildConfig,
        progress: bool = True,
        name: str | None = None,
    ):
        self.log_path = Path(log_path)
        self.ws = Workspace(workspace)
        self.workspace = self.ws.root
        self.progress = progress
        self.name = name or session_name(self.log_path)
        self.cfg = cfg.for_session(self.name)
        self.dirs: SessionDirs = self.ws.session(self.name)
        self.dir = self.dirs.root
        self.metrics: dict = {"session": self.name, "log": str(self.log_path), "stages": {}}
        self.timings: dict[str, float] = {}  # wall seconds of each stage in this run (the session's timings.json)
        self._log: DriveLog | None = None
        self._camera_choice: tuple[str, list[str], CameraInfo] | None = None
        self._mounts: dict[str, np.ndarray] = {}  # trajectory body frame -> base_from_camera
        self._sensor_mounts: SensorMounts | None = None
        self._enu_trajectory: Trajectory | None = None
        self._fixes: tuple[list[str], list[GpsFix], GpsScreen | None] | None = None
        self._undecodable = 0  # frames whose image did not decode, in the current pass over the log
        self._log_fp: dict | None = None
        self._finished: set[Path] = set()  # stage folders found finished (outputs verified) in this run

    @property
    def log(self) -> DriveLog:
        if self._log is None:
            self._log = open_log(self.log_path)
        return self._log

    @property
    def mounts(self) -> SensorMounts:
        """The log's sensor mounts (its static tf, with ``extrinsics.assume_identity``), read once per builder."""
        if self._sensor_mounts is None:
            self._sensor_mounts = SensorMounts.of(self.log, self.cfg.extrinsics.assume_identity)
        return self._sensor_mounts

    def close(self) -> None:
        if self._log is not None:
            self._log.close()
            self._log = None

    # --- what the stages consumed -----------------------------------------------------------------
    def log_fingerprint(self) -> dict:
        """The log's fingerprint (:func:`mapkit.core.fingerprint.log_fingerprint`), taken once: a log
        still being written is refused here, before any stage reads it."""
        if self._log_fp is None:
            self._log_fp = log_fingerprint(self.log_path)
        return self._log_fp

    def _inputs(self, *upstream: Path) -> dict:
        """A stage's input record: the log's fingerprint and the digests of the upstream stages it reads."""
        return {"log": self.log_fingerprint(), **{folder.name: stage_digest(folder) for folder in upstream}}

    def _is_finished(self, out: Path, h: str, inputs: dict) -> bool:
        """The stage at ``out`` finished with this config and these inputs, its outputs unchanged (checked once per
        run)."""
        if out in self._finished:
            return True
        if is_done(out, h, inputs=inputs, verify=True):
            self._finished.add(out)
            return True
        return False

    def _mark(self, out: Path, h: str, inputs: dict) -> None:
        """Mark a stage finished, unless its log changed while the stage read it (then nothing is marked)."""
        now = log_fingerprint(self.log_path, watch=False)
        if now != inputs["log"]:
            raise InputError(
                self.log_path,
                f"changed while the {out.name} stage read it ({describe_change(inputs['log'], now)}); "
                "the stage is not marked finished: build again once the log is complete",
                field="mtime",
            )
        mark_done(out, h, inputs=inputs, outputs=True)
        self._finished.add(out)

    def preflight(self) -> None:
        """Checks that need the log but write nothing: the log is not still being written, the topics
        the config names exist, and, when the config asks for a map or an image database, that the
        mapping camera has frames and intrinsics: a camera the config names (``camera``, or
        ``topics.images``) must exist, and a log with images must have intrinsics for the camera
        chosen. A log without images skips the image stages instead (see :meth:`skip_reason`)."""
        self.log_fingerprint()
        topics = resolve_topics(self.log, self.cfg.topics)
        if not (self.cfg.map or self.cfg.imagedb.enabled):
            return
        named = self.cfg.camera is not None or self.cfg.topics.images is not None
        if named and not topics.get(StreamKind.IMAGE):
            asked = (
                f"camera {self.cfg.camera!r}"
                if self.cfg.camera is not None
                else f"topics.images {self.cfg.topics.images}"
            )
            raise InputError(
                self.log_path,
                f"has no image stream, but the config asks for {asked} to map with",
                field="camera" if self.cfg.camera is not None else "topics.images",
            )
        if topics.get(StreamKind.IMAGE):
            self._camera()

    # --- stage 1 --------------------------------------------------------------------------------
    def trajectory(self) -> Path:
        out = self.dirs.trajectory
        h = _stage_hash(self.cfg, "topics", "trajectory")
        inputs = self._inputs()
        if self._is_finished(out, h, inputs):
            return out
        t0 = time.perf_counter()
        reset_stage(out)
        traj = estimate_trajectory(
            self.log, self.cfg.trajectory, self.cfg.topics, progress=self.progress, mounts=self.mounts
        )
        traj.save(out)
        m = {
            "source": traj.source,
            "poses": len(traj),
            "duration_s": (int(traj.stamps_ns[-1]) - int(traj.stamps_ns[0])) * 1e-9,
            **_length(traj),
        }
        write_json(out / "metrics.json", m)
        write_timings(out, seconds=time.perf_counter() - t0)
        self._mark(out, h, inputs)
        return out

    # --- stage 2 --------------------------------------------------------------------------------
    def georef(self) -> Path:
        out = self.dirs.georef
        h = _stage_hash(self.cfg, "topics", "trajectory", "georef")
        inputs = self._inputs(self.trajectory())
        if self._is_finished(out, h, inputs):
            return out
        t0 = time.perf_counter()
        reset_stage(out)
        self._enu_trajectory = None
        traj = Trajectory.load(self.trajectory())
        result: dict = {"session": self.name, "georeferenced": False}
        al, frame = self._align(traj, out, result)
        enu_from_map = np.eye(4) if al is None else al.enu_from_map
        result["enu_from_map"] = enu_from_map
        # the aligned trajectory: rigid poses in ENU (the similarity's scale goes into positions)
        aligned = Trajectory(
            traj.stamps_ns,
            transform_poses(enu_from_map, traj.world_from_base),
            traj.source,
            frame="enu" if al is not None else traj.frame,
            body_frame=traj.body_frame,
        )
        aligned.save(self.dirs.georef_trajectory)
        result.update(_length(aligned, georeferenced=al is not None))
        fused_timings: dict = {}
        if self.cfg.georef.fuse and al is not None and not _camera_only(traj):
            result["fused"] = self._fuse(traj, al.enu_from_map)
            fused_timings = {f"fused_{k}": result["fused"].pop(k) for k in FUSED_TIMINGS if k in result["fused"]}
        if al is None:  # a picture of what there is, in the trajectory's own frame and units
            xyz, axes = _top_view_positions(traj)
            map_top_view(
                out / "trajectory_top_view.png",
                np.zeros((0, 3)),
                xyz,
                f"{self.name}: trajectory, NOT georeferenced",
                axes=axes,
                units="m" if result["units"] == "m" else "arbitrary units",
            )
        write_json(self.dirs.gps_alignment, result)
        write_timings(out, seconds=time.perf_counter() - t0, **fused_timings)
        self._mark(out, h, inputs)
        return out

    def _align(self, traj: Trajectory, out: Path, result: dict):
        """(alignment, workspace frame), or (None, None) with the reason in ``result`` and a warning.

        No GPS, or GPS that cannot fix the transform (a short or stationary drive): the session is
        still mapped, in its own frame, and says why it is not georeferenced. ``georef.strict``
        makes the second case an error instead.
        """
        if self.cfg.georef.mode == "given":
            return self._given(traj, result)
        gps_topics, fixes, screen = self._screened_fixes()
        if screen is not None:
            result["gps_screen"] = screen.summary()
            screen.warn(str(self.log_path))
        if len(fixes) < 3:
            result["reason"] = "no GPS stream" if not gps_topics else f"{len(fixes)} valid GPS fixes"
            warnings.warn(
                f"{self.log_path}: {result['reason']}; the map is built in the trajectory's local frame "
                "and is NOT georeferenced",
                InputWarning,
                stacklevel=3,
            )
            return None, None
        frame = self._workspace_frame(LocalFrame(fixes[0].lat_deg, fixes[0].lon_deg, fixes[0].alt_m))
        stamps = np.array([f.stamp_ns for f in fixes], np.int64)
        gps_enu = frame.geodetic_to_enu(
            [f.lat_deg for f in fixes], [f.lon_deg for f in fixes], [f.alt_m for f in fixes]
        )
        sigma = np.array([f.horizontal_sigma_m for f in fixes])
        base_from_gps = self.mounts.base_from(traj.body_frame, fixes[0].frame_id, "GPS antenna", without_tf_ok=True)
        g = self.cfg.georef
        antenna, ok = associate_fixes(
            traj.stamps_ns, traj.world_from_base, stamps, base_from_gps, int(g.max_pose_gap_s * 1e9)
        )
        # structure from motion has no gravity and no scale: only a full Sim3 can place it. A metric
        # trajectory keeps its scale under 'auto': GPS over a drive of a few hundred metres, with a
        # bias that drifts over minutes, estimates scale worse than LiDAR odometry measures it.
        # Its gravity comes from GPS where the path bends enough; on a straight path the cameras'
        # mean up fixes the roll about it (see gps_align's module notes).
        up_map = None
        mode: AlignMode
        if _camera_only(traj):
            mode = "sim3"
            up_map = camera_up_hint(traj.world_from_base)
        else:
            assert g.mode != "given"  # handled at the top, by _given
            mode = "yaw" if g.mode == "auto" else g.mode
        try:
            al = align_to_gps(
                antenna,
                gps_enu[ok],
                sigma[ok],
                stamps[ok],
                mode=mode,
                inlier_sigmas=g.inlier_sigmas,
                vertical_sigma_factor=g.vertical_sigma_factor,
                min_inlier_threshold_m=g.min_inlier_threshold_m,
                up_map=up_map,
                strict=g.strict,
                source=str(self.log_path),
            )
        except InputError as exc:
            if g.strict:
                raise
            result["reason"] = exc.what
            warnings.warn(f"{exc}; the session is NOT georeferenced", InputWarning, stacklevel=3)
            return None, None
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
            out / "trajectory_over_gps.png",
            traj_enu,
            gps_enu[ok],
            al.inliers,
            f"{self.name}: trajectory over GPS ({al.mode}, RMSE {al.stats()['residual_rmse_m']:.2f} m)",
        )
        return al, frame

    def _fuse(self, traj: Trajectory, enu_from_map: np.ndarray) -> dict:
        """The factor graph over the odometry, the fixes this stage kept and the IMU (odometry and GPS alone without
        one): writes the fused trajectory and its covariances, returns the graph's stats."""
        with np.load(self.dirs.gps_fixes) as f:
            fixes = {k: f[k] for k in ("stamps_ns", "enu", "sigma_m")}
        _, kept, _ = self._screened_fixes()
        gps = GpsObservations(
            fixes["stamps_ns"],
            fixes["enu"],
            fixes["sigma_m"],
            self.mounts.base_from(traj.body_frame, kept[0].frame_id, "GPS antenna", without_tf_ok=True),
        )
        imu = None
        imu_topics = resolve_topics(self.log, self.cfg.topics).get(StreamKind.IMU, [])
        if imu_topics:
            samples = list(self.log.records(StreamKind.IMU, topic=imu_topics[0]))
            if len(samples) >= 2:
                imu = ImuObservations.from_samples(
                    samples, self.mounts.base_from(traj.body_frame, samples[0].frame_id, "IMU")
                )
        fuse = partial(
            fuse_session,
            traj.stamps_ns,
            traj.world_from_base,
            gps,
            None,
            self.cfg.georef.factor_graph,
            enu_from_odom=enu_from_map,
            source=str(self.log_path),
            imu=imu,
        )
        fused = fuse()
        loop_stats: dict = {}
        if self.cfg.georef.factor_graph.loop_closures:
            fused, loop_stats = self._close_loops(traj, fused, fuse)
        Trajectory(fused.stamps_ns, fused.enu_from_base, traj.source, frame="enu", body_frame=traj.body_frame).save(
            self.dirs.fused_trajectory
        )
        with atomic_path(self.dirs.fused_covariances) as tmp, open(tmp, "wb") as f:
            np.savez(
                f, stamps_ns=fused.stamps_ns, covariances=fused.covariances, georef_covariance=fused.georef_covariance
            )
        return {**fused.stats, **loop_stats, "imu": "preintegrated" if imu is not None else "no IMU stream"}

    def _close_loops(self, traj: Trajectory, fused: FusedTrajectory, fuse) -> tuple[FusedTrajectory, dict]:
        """Loop closures (mapping/loop_closure.py) proposed on the fused trajectory and verified by ICP of local maps of
        the LiDAR scans (read once, up to the last one needed), placed with it; with any accepted, the graph solved
        again with them, from the solution without. Returns the trajectory and the loop step's stats."""
        topics = resolve_topics(self.log, self.cfg.topics).get(StreamKind.LIDAR, [])
        if not topics:
            return fused, {"loops": "not used: no LiDAR stream"}
        t0 = time.perf_counter()
        cfg = self.cfg.georef.factor_graph
        candidates = propose_loops(fused.enu_from_base, fused.keyframes, cfg)
        scans = read_scans(
            self.log.records(StreamKind.LIDAR, topic=topics[0]),
            traj.stamps_ns,
            fused.enu_from_base,
            scans_needed(candidates, len(traj.stamps_ns), cfg),
            partial(self.mounts.base_from, traj.body_frame, what="LiDAR", without_tf_ok=True),
            cfg,
            source=f"{self.log_path} {topics[0]}",
        )
        checks = verify_loops(candidates, scans, fused.enu_from_base, cfg)
        loops = loop_closures(checks, traj.stamps_ns)
        stats = loop_counts(loops)
        if loops.edges:
            fused = fuse(loops=loops, start=fused)
        stats.update(loop_checks=[c.to_dict(traj.stamps_ns) for c in checks], loop_seconds=time.perf_counter() - t0)
        return fused, stats

    def _given(self, traj: Trajectory, result: dict):
        """Georeferencing that the pose stream already carries (an INS, or a simulator's truth):
        its frame is ENU at ``georef.origin``; placed exactly (through ECEF) in the workspace frame."""
        g = self.cfg.georef
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
        frame = self._workspace_frame(given)
        al = SimpleNamespace(enu_from_map=given.to_frame(frame))
        result.update(
            georeferenced=True,
            **frame.to_dict(),
            alignment={"mode": "given", "origin": list(g.origin)},
            rejected_fixes=[],
            fixes_total=0,
            fixes_outside_trajectory=0,
        )
        return al, frame

    def proposed_frame(self) -> LocalFrame | None:
        """The workspace frame this session would set if it were the first one georeferenced: at its
        first fix that passed screening (a wild fix never becomes the origin)."""
        g = self.cfg.georef
        if g.mode == "given":
            return None if g.origin is None else LocalFrame(*g.origin)
        _, fixes, _ = self._screened_fixes()
        return None if not fixes else LocalFrame(fixes[0].lat_deg, fixes[0].lon_deg, fixes[0].alt_m)

    def _screened_fixes(self) -> tuple[list[str], list[GpsFix], GpsScreen | None]:
        """(GPS topics, the fixes of the first that pass :func:`screen_fixes`, the screening), read once.

        A fix without altitude (NaN: a frame table without ``alt``, a photo without GPSAltitude) takes
        the median altitude of the others, or 0 m when none has one; the georef record says how many."""
        if self._fixes is None:
            gps_topics = resolve_topics(self.log, self.cfg.topics).get(StreamKind.GPS, [])
            if not gps_topics:
                self._fixes = (gps_topics, [], None)
            else:
                screen = screen_fixes([f for f in self.log.records(StreamKind.GPS, topic=gps_topics[0]) if f.has_fix])
                fixes = screen.kept
                alt = np.array([f.alt_m for f in fixes], np.float64)
                missing = ~np.isfinite(alt)
                if missing.any():
                    fill = float(np.median(alt[~missing])) if (~missing).any() else 0.0
                    fixes = [replace(f, alt_m=fill) if m else f for f, m in zip(fixes, missing, strict=True)]
                    screen.altitude_filled = int(missing.sum())
                    warnings.warn(
                        f"{self.log_path}: {int(missing.sum())} of {len(fixes)} GPS fixes have no altitude; "
                        f"{fill:.2f} m ({'the median of the others' if (~missing).any() else 'none has one'}) is used",
                        InputWarning,
                        stacklevel=3,
                    )
                self._fixes = (gps_topics, fixes, screen)
        return self._fixes

    def _workspace_frame(self, proposed: LocalFrame) -> LocalFrame:
        """The workspace's frame: the one already set, else ``proposed``, which becomes it."""
        frame = self.ws.frame()
        if frame is not None:
            return frame
        write_json(self.ws.origin, proposed.to_dict())
        return proposed

    def frame(self) -> LocalFrame | None:
        """The session's local frame (the workspace's), None when it is not georeferenced."""
        self.georef()
        d = json.loads(self.dirs.gps_alignment.read_text())
        return LocalFrame.from_dict(d) if d.get("georeferenced") else None

    def enu_trajectory(self) -> Trajectory:
        """The GPS-aligned trajectory (stage 2's output, the stage run first if need be; the fused one with
        ``georef.fuse``), read once."""
        if self._enu_trajectory is None:
            self.georef()
            self._enu_trajectory = Trajectory.load(self.dirs.enu_trajectory)
        return self._enu_trajectory

    # --- camera frames with poses ---------------------------------------------------------------
    def _camera(self) -> tuple[str, list[str], CameraInfo]:
        """(name, image topics, intrinsics) of the mapping camera and the topics its frames are read
        from (``topics.images``, every image stream if unset). The camera is ``camera``, else the
        first one (by name) with intrinsics; with ``topics.images`` set, the first of those that the
        named topics carry, so that naming a topic is enough to map from it."""
        if self._camera_choice is not None:
            return self._camera_choice
        topics = resolve_topics(self.log, self.cfg.topics)
        image_topics = topics.get(StreamKind.IMAGE, [])
        infos = self.log.camera_infos()
        if not image_topics:
            raise InputError(self.log_path, "has no image stream to map from", field="topics.images")
        if not infos:
            raise InputError(
                self.log_path,
                "has no camera intrinsics (CameraInfo / calibration); a map cannot be built",
                field="camera_info",
            )
        name = self.cfg.camera
        if name is None:
            on_topics = self._cameras_on(image_topics) if self.cfg.topics.images is not None else set(infos)
            name = next((c for c in sorted(infos) if c in on_topics), sorted(infos)[0])
        if name not in infos:
            raise InputError(
                self.log_path,
                f"camera {name!r} has no intrinsics; cameras with intrinsics: {sorted(infos)}",
                field="camera",
            )
        self._camera_choice = (name, image_topics, infos[name])
        return self._camera_choice

    def _cameras_on(self, image_topics: list[str]) -> set[str]:
        """The cameras of the first frame of each topic (a frame's pixels are not decoded to read it)."""
        cameras = set()
        for topic in image_topics:
            frames = self.log.records(StreamKind.IMAGE, topic=topic)
            try:
                first = next(frames, None)
            finally:
                frames.close()
            if first is not None:
                cameras.add(first.camera)
        return cameras

    def base_from_camera(self, body_frame: str) -> np.ndarray:
        """The mapping camera's mount: the pose of the camera in the trajectory's body frame
        (looked up in the log's transforms once per body frame)."""
        if body_frame not in self._mounts:
            self._mounts[body_frame] = self.mounts.base_from(body_frame, self._camera()[0], "camera")
        return self._mounts[body_frame]

    def posed_frames(self, decode: bool = True) -> Iterator[tuple[int, CameraFrame, np.ndarray]]:
        """(frame index, CameraFrame, enu_from_camera) of the mapping camera on the chosen image
        topics (``topics.images``), inside the trajectory; with ``decode``, decoded first. A frame
        whose image cannot be decoded (a corrupt PNG or JPEG: the reader's ``InputError`` names the
        file) is skipped with a warning: it costs that frame, not the build. Without ``decode`` the
        caller decodes the frames it keeps through :meth:`decodes`."""
        name, image_topics, info = self._camera()
        traj = self.enu_trajectory()
        base_from_cam = self.base_from_camera(traj.body_frame)
        index = 0
        self._undecodable = 0
        for msg in self.log.messages(topics=image_topics):
            frame = msg.record
            assert isinstance(frame, CameraFrame)  # the records of image topics
            if frame.camera != name:
                continue
            poses, ok = interpolate_poses(traj.stamps_ns, traj.world_from_base, np.array([frame.stamp_ns], np.int64))
            if ok[0] and (not decode or self.decodes(frame, index)):
                yield index, frame, poses[0] @ base_from_cam
            index += 1
        if self._undecodable > 5:
            warnings.warn(
                f"{self.log.path}: {self._undecodable} frames of {name} could not be decoded and were skipped "
                "(the first 5 are named above)",
                InputWarning,
                stacklevel=2,
            )

    def decodes(self, frame: CameraFrame, index: int) -> bool:
        """Whether the frame's image decodes (it is then cached on the frame); a warning names the
        first five that do not."""
        try:
            _ = frame.image  # decodes the image and caches it on the frame
        except InputError as exc:
            self._undecodable += 1
            if self._undecodable <= 5:
                warnings.warn(f"{exc}; frame {index} of {frame.camera} skipped", InputWarning, stacklevel=3)
            return False
        return True

    # --- stage 3 --------------------------------------------------------------------------------
    def semidense(self) -> Path:
        out = self.dirs.map
        h = _stage_hash(self.cfg, "topics", "trajectory", "georef", "semidense", "camera")
        inputs = self._inputs(self.georef())
        if self._is_finished(out, h, inputs):
            return out
        t0 = time.perf_counter()
        reset_stage(out)
        _, _, info = self._camera()
        frames = ((i, f.stamp_ns, f.gray(), T) for i, f, T in self.posed_frames())
        smap = build_semidense_map(frames, info.K, self.cfg.semidense, progress=self.progress)
        frame = self.frame()
        smap.save(out, frame=frame)
        traj = self.enu_trajectory()

        map_top_view(
            out / "top_view.png",
            smap.points_world,
            traj.world_from_base[:, :3, 3],
            f"{self.name}: semi-dense map, {len(smap.points_world)} points",
            axes=_plot_axes(frame),
        )
        m = {"points": int(len(smap.points_world)), "crs": None if frame is None else frame.to_dict()}
        m.update(smap.stats())
        write_json(out / "metrics.json", m)
        write_timings(out, seconds=time.perf_counter() - t0)
        self._mark(out, h, inputs)
        return out

    # --- stage 4 --------------------------------------------------------------------------------
    def imagedb(self) -> Path:
        out = self.dirs.imagedb
        h = _stage_hash(self.cfg, "topics", "trajectory", "georef", "semidense", "camera", "imagedb", "map")
        with_map = self.skip_reason("semidense") is None
        inputs = self._inputs(self.georef(), *([self.semidense()] if with_map else []))
        if self._is_finished(out, h, inputs):
            return out
        t0 = time.perf_counter()
        reset_stage(out)
        name, _, info = self._camera()
        body = self.enu_trajectory().body_frame
        write_json(
            self.dirs.camera_mount,
            {"camera": name, "base_frame": body, "base_from_camera": self.base_from_camera(body).tolist()},
        )
        writer = ImageDbWriter(out, self.cfg.imagedb, {name: info})
        metric = self.metric()
        # a spacing in metres means nothing at a reconstruction's arbitrary scale: every registered frame is kept
        dbc = self.cfg.imagedb
        min_spacing = dbc.min_spacing_m if metric else 0.0
        # a tenth of an interval's slack for the jitter of real camera stamps
        # (2 Hz from a 4 Hz camera is every other frame)
        min_interval_ns, training_interval_ns = dbc.min_interval_s * 0.9e9, dbc.training_interval_s * 0.9e9
        last: np.ndarray | None = None  # position of the last database image
        last_ns = last_stored_ns = 0  # stamps of the last database image and the last stored one: read once last is set
        db_id_of_frame: dict[int, int] = {}
        for i, frame, T in self.posed_frames(decode=False):  # only the frames kept are decoded
            in_db = last is None or (
                np.linalg.norm(T[:3, 3] - last) >= min_spacing and frame.stamp_ns - last_ns >= min_interval_ns
            )
            if not in_db and not (dbc.training_frames and frame.stamp_ns - last_stored_ns >= training_interval_ns):
                continue
            if not self.decodes(frame, i):
                continue
            im = writer.add(frame.stamp_ns, name, frame.image, T, frame.encoding, training=not in_db)
            last_stored_ns = frame.stamp_ns
            if in_db:
                last, last_ns = T[:3, 3], frame.stamp_ns
                db_id_of_frame[i] = im.image_id
        m: dict = {"images": len(writer.images), "pose_units": "m" if metric else ARBITRARY_UNITS}
        if dbc.training_frames:
            m["training_frames"] = len(writer.training)
        if not metric:
            m["note"] = (
                "not georeferenced: poses (images.csv x_m/y_m/z_m, colmap/) are in the reconstruction's arbitrary "
                "units, and imagedb.min_spacing_m was not applied"
            )
        if not with_map:
            writer.close(self.frame())
            write_json(out / "metrics.json", {**m, "map": False})
            write_timings(out, seconds=time.perf_counter() - t0)
            self._mark(out, h, inputs)
            return out
        smap = SemiDenseMap.load(self.semidense())
        # observations by map frame index -> by database image id (frames not kept are dropped)
        point_of = np.repeat(np.arange(len(smap.points_world)), np.diff(smap.obs_indptr))
        ids = np.array([db_id_of_frame.get(int(f), 0) for f in smap.obs_frame_ids], np.int64)
        keep = ids > 0
        counts = np.bincount(point_of[keep], minlength=len(smap.points_world))
        indptr = np.concatenate([[0], np.cumsum(counts)])
        writer.close(self.frame(), smap.points_world, (indptr, ids[keep]))
        write_json(out / "metrics.json", m)
        write_timings(out, seconds=time.perf_counter() - t0)
        self._mark(out, h, inputs)
        return out

    # --- which stages run -----------------------------------------------------------------------
    def metric(self) -> bool:
        """Whether the session's poses are in metres: georeferenced, or a metric source (LiDAR, poses)."""
        return not _camera_only(self.enu_trajectory()) or self.frame() is not None

    def skip_reason(self, stage: str) -> str | None:
        """Why an image stage (``semidense``, ``imagedb``) does not run for this session, or None."""
        if stage in SKIPPED_BY_CONFIG and not (self.cfg.map if stage == "semidense" else self.cfg.imagedb.enabled):
            return SKIPPED_BY_CONFIG[stage]
        if not resolve_topics(self.log, self.cfg.topics).get(StreamKind.IMAGE):
            return "the log has no image stream" + ("" if self.cfg.topics.images is None else " on topics.images")
        if stage == "semidense" and not self.metric():
            return (
                "the camera-only trajectory is not georeferenced: its scale is arbitrary and the mapper's parameters "
                "are in metres"
            )
        return None

    def run(self) -> dict:
        t0 = time.perf_counter()
        self.preflight()
        self.dir.mkdir(parents=True, exist_ok=True)
        atomic_write_text(self.dirs.config, dump_config(self.cfg))
        for stage in (self.trajectory, self.georef, self.semidense, self.imagedb):
            s0 = time.perf_counter()
            reason = self.skip_reason(stage.__name__) if stage.__name__ in SKIPPED_BY_CONFIG else None
            if reason is not None:
                if reason not in SKIPPED_BY_CONFIG.values():
                    warnings.warn(f"{self.log_path}: {stage.__name__} skipped: {reason}", InputWarning, stacklevel=2)
                self.metrics["stages"][stage.__name__] = {"skipped": reason}
                continue
            folder = stage()
            m_path = folder / "metrics.json"
            stage_metrics = json.loads(m_path.read_text()) if m_path.is_file() else {}
            if folder == self.dirs.georef:
                ga = json.loads(self.dirs.gps_alignment.read_text())
                stage_metrics = {
                    "georeferenced": ga["georeferenced"],
                    **{k: ga[k] for k in ("reason", "units") if k in ga},
                    **{k: v for k, v in ga.items() if k.startswith("length_")},
                    **ga.get("alignment", {}),
                }
            self.timings[stage.__name__] = time.perf_counter() - s0
            self.metrics["stages"][stage.__name__] = stage_metrics
        self.timings["total"] = time.perf_counter() - t0
        write_json(self.dirs.metrics, self.metrics)
        write_timings(self.dir, wall_s_this_run=self.timings)
        self.close()
        return self.metrics


#: the factor graph's wall-clock figures, moved from its stats to the georef stage's run record
FUSED_TIMINGS = ("seconds", "solve_s", "loop_seconds")
ARBITRARY_UNITS = "arbitrary units (structure from motion, not georeferenced)"
SKIPPED_BY_CONFIG = {"semidense": "map: false in the config", "imagedb": "imagedb: false in the config"}


def _camera_only(traj: Trajectory) -> bool:
    """Structure from motion: no scale, no gravity until GPS alignment."""
    return traj.source.startswith("camera")


def _length(traj: Trajectory, georeferenced: bool = False) -> dict:
    """The path length with its units: metres, or the arbitrary units of an unreferenced reconstruction."""
    length = float(np.linalg.norm(np.diff(traj.world_from_base[:, :3, 3], axis=0), axis=1).sum())
    if georeferenced or not _camera_only(traj):
        return {"units": "m", "length_m": length}
    return {"units": ARBITRARY_UNITS, "length_sfm_units": length}


def _top_view_positions(traj: Trajectory) -> tuple[np.ndarray, tuple[str, str]]:
    """Positions to draw from above, and their axis names: a camera-only trajectory turned so that
    the cameras' mean up is +z (its own frame has no gravity), any other as it is."""
    xyz = traj.world_from_base[:, :3, 3]
    up = camera_up_hint(traj.world_from_base) if _camera_only(traj) else None
    if up is None:
        return xyz, _plot_axes(None)
    axis = np.cross(up, [0.0, 0.0, 1.0])
    n = float(np.linalg.norm(axis))
    rotvec = (axis / n if n > 1e-12 else np.array([1.0, 0.0, 0.0])) * float(np.arctan2(n, up[2]))  # up onto +z
    return xyz @ Rotation.from_rotvec(rotvec).as_matrix().T, ("x (levelled by the cameras' up)", "y")


def _plot_axes(frame: LocalFrame | None) -> tuple[str, str]:
    """Axis names of a top view: east/north in a georeferenced session, the odometry's x/y otherwise."""
    return ("east", "north") if frame is not None else ("x (trajectory frame)", "y (trajectory frame)")


def _log_bytes(log: Path) -> int:
    """Size of a log: a file's, or the sum of the files in a log folder (rosbag2, KITTI)."""
    if log.is_file():
        return log.stat().st_size
    return sum(p.stat().st_size for p in log.rglob("*") if p.is_file()) if log.is_dir() else 0


def build(
    logs: Sequence[str | Path],
    workspace: str | Path | Workspace,
    config: str | Path | None = None,
    progress: bool = True,
    executor: Executor | None = None,
) -> Path:
    """Build every log into a session of ``workspace``; returns the workspace.

    With an executor of several workers (``executor``, else :func:`mapkit.core.executor.get_executor`)
    and several logs, whole sessions are built in parallel, the largest logs first, each one
    serially inside its worker: a session's own stages leave a core idle for a third of the time
    (kiss-icp's registration is mostly sequential). The workspace frame is then fixed before
    they start, from the first log's first GPS fix (or its given origin), which is where a serial
    build puts it too."""
    log_paths = [Path(p) for p in logs]
    names: dict[str, Path] = {}
    for log in log_paths:
        name = session_name(log)
        if name in names:
            raise InputError(
                log, f"gives the same session name {name!r} as {names[name]}: rename one of the logs", field="session"
            )
        names[name] = log
    cfg = load_config(BuildConfig, config)
    for pattern in cfg.sessions:
        if not any(fnmatchcase(name, pattern) for name in names):
            warnings.warn(
                f"{config}: sessions.{pattern} matches none of this build's sessions {sorted(names)}; its settings "
                "are not used",
                InputWarning,
                stacklevel=2,
            )
    builders = [SessionBuilder(log, workspace, cfg, progress=progress) for log in log_paths]
    for b in builders:  # nothing is written before every log passed its checks
        try:
            b.preflight()
        finally:
            b.close()
    ws = Workspace(workspace)
    ws.root.mkdir(parents=True, exist_ok=True)
    atomic_write_text(ws.build_config, dump_config(cfg))
    ex = executor or get_executor()
    if ex.workers > 1 and len(log_paths) > 1:
        summary = _build_parallel(log_paths, ws, cfg, ex, progress)
    else:
        summary = {b.name: b.run() for b in builders}
    write_json(ws.metrics, {"sessions": summary})
    return ws.root


def _build_parallel(logs: list[Path], ws: Workspace, cfg: BuildConfig, ex: Executor, progress: bool) -> dict[str, dict]:
    """Whole sessions on the executor's workers, the largest logs first; their metrics by session, in ``logs`` order."""
    _fix_workspace_frame(logs, ws, cfg)
    order = sorted(range(len(logs)), key=lambda i: -_log_bytes(logs[i]))  # the largest log first
    done: dict[int, dict] = {}
    try:
        for m, i in zip(
            ex.map(_build_task, [logs[i] for i in order], shared=(ws, cfg), desc="build", label=lambda p: str(p)),
            order,
            strict=True,
        ):
            done[i] = m
            if progress:
                logger.info("built %s: %.1f s", m["session"], _session_seconds(ws, m["session"]))
    except TaskError as exc:
        raise (exc.cause if isinstance(exc.cause, MapkitError) else exc) from exc
    return {done[i]["session"]: done[i] for i in range(len(logs))}


def _build_task(shared: tuple[Workspace, BuildConfig], log: Path) -> dict:
    ws, cfg = shared
    return SessionBuilder(log, ws, cfg, progress=False).run()


def _fix_workspace_frame(logs: list[Path], ws: Workspace, cfg: BuildConfig) -> None:
    """Write ``origin.json`` before sessions are built concurrently (each would otherwise write its own)."""
    if ws.frame() is not None:
        return
    for log in logs:
        b = SessionBuilder(log, ws, cfg, progress=False)
        try:
            frame = b.proposed_frame()
        finally:
            b.close()
        if frame is not None:
            b._workspace_frame(frame)
            return


def _session_seconds(ws: Workspace, name: str) -> float:
    """Wall seconds of a session's last build run, from its run record (0 when it has none)."""
    return float(read_timings(ws.session(name).root).get("wall_s_this_run", {}).get("total", 0.0))


def format_build_summary(workspace: str | Path | Workspace) -> str:
    """A table of every session of a workspace: trajectory, georeferencing, map and database, and
    under a session the stages it skipped and why. Lengths are in metres except those marked
    ``au`` (a camera-only session that is not georeferenced: the reconstruction's arbitrary units)."""
    ws = Workspace(workspace)
    m = json.loads(ws.metrics.read_text())
    rows = [
        f"workspace {ws.root}",
        f"  {'session':<24} {'traj src':<22} {'length m':>11} {'georef':>7} {'GPS rmse m':>10} {'rejected':>8} "
        f"{'points':>9} {'images':>7} {'time s':>7}",
    ]
    for name, s in m["sessions"].items():
        st = s["stages"]
        tr, ge, mp, db = st.get("trajectory", {}), st.get("georef", {}), st.get("semidense", {}), st.get("imagedb", {})
        rmse = ge.get("residual_rmse_m")
        length = ge.get("length_m", tr.get("length_m"))
        length_cell = f"{length:.1f}" if length is not None else f"{tr.get('length_sfm_units', 0):.1f} au"
        rows.append(
            f"  {name:<24} {str(tr.get('source', ''))[:22]:<22} {length_cell:>11} "
            f"{'yes' if ge.get('georeferenced') else 'NO':>7} {'' if rmse is None else f'{rmse:.2f}':>10} "
            f"{ge.get('fixes_rejected', ''):>8} {mp.get('points', 0):>9} {db.get('images', 0):>7} "
            f"{_session_seconds(ws, name):>7.1f}"
        )
        if ge.get("reason"):
            rows.append(f"    not georeferenced: {ge['reason']}")
        rows.extend(
            f"    {stage} skipped: {st[stage]['skipped']}"
            for stage in ("semidense", "imagedb")
            if "skipped" in st.get(stage, {})
        )
        if db.get("pose_units", "m") != "m":
            rows.append(f"    imagedb poses in {db['pose_units']}")
    return "\n".join(rows)
