"""``mapkit build``: one drive log to a georeferenced session map, stage by stage.

Stages (each a folder under ``WORKSPACE/sessions/<name>/`` with a ``.done`` marker holding the
hash of the config sections and the version of the code that made it, the log's fingerprint, the
digests of the upstream stages it read and the SHA-256 of its outputs; re-running skips finished
stages and redoes half-written ones, those whose config, code, log or upstream stage changed, and
those whose outputs were changed or truncated since):

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
from collections.abc import Callable, Sequence
from fnmatch import fnmatchcase
from pathlib import Path

import numpy as np
from pydantic import Field, ValidationError, field_validator, model_validator

from mapkit.core.config import MapkitConfig, TopicConfig, deep_merge, dump_config, load_config, resolve_topics
from mapkit.core.errors import InputError, InputWarning, MapkitError
from mapkit.core.executor import Executor, TaskError, get_executor
from mapkit.core.fingerprint import describe_change, log_fingerprint
from mapkit.core.geodesy import LocalFrame
from mapkit.core.lock import adopted_lock, lock_token, workspace_lock
from mapkit.core.runio import (
    atomic_write_text,
    config_hash,
    is_done,
    mark_done,
    read_timings,
    reset_stage,
    stage_digest,
    stage_hash,
    write_json,
    write_timings,
)
from mapkit.core.types import StreamKind
from mapkit.core.workspace import SessionDirs, Workspace
from mapkit.core.writers import lock_wait, writes_workspace
from mapkit.io import open_log
from mapkit.io.base import DriveLog
from mapkit.mapping.lidar_map import LidarMapConfig
from mapkit.mapping.semidense import SemiDenseConfig
from mapkit.mapping.stages import georef as georef_stage
from mapkit.mapping.stages import imagedb as imagedb_stage
from mapkit.mapping.stages import lidar_map as lidar_map_stage
from mapkit.mapping.stages import map as map_stage
from mapkit.mapping.stages import trajectory as trajectory_stage
from mapkit.mapping.stages.common import camera_only
from mapkit.mapping.stages.frames import MappingCamera, PosedFrames, choose_camera
from mapkit.mapping.stages.georef import (
    GeorefConfig,
    Georeference,
    ScreenedFixes,
    proposed_frame,
    screened_fixes,
    workspace_frame,
)
from mapkit.mapping.stages.imagedb import ImageDbStageConfig, write_imagedb
from mapkit.mapping.stages.lidar_map import write_lidar_map
from mapkit.mapping.stages.map import write_map
from mapkit.mapping.stages.trajectory import write_trajectory
from mapkit.mapping.trajectory import SensorMounts, Trajectory, TrajectoryConfig

logger = logging.getLogger(__name__)


class ExtrinsicsConfig(MapkitConfig):
    assume_identity: list[str] = Field(
        default_factory=list,
        description="Sensor frames (a NavSatFix's, a PointCloud2's, a camera's frame_id) that the log's tf may leave "
        "unlinked to the trajectory's frame: each is then taken as mounted at it (the identity), with one warning. Any "
        "other unlinked sensor is an error: a guessed mount moves the map by the lever arm, or turns it.",
    )


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
    lidar_map: LidarMapConfig = Field(
        default_factory=LidarMapConfig,
        description="The LiDAR map (lidar_map/): the deskewed scans in voxels on the session's final trajectory. "
        "false: none; true: required (a log without a LiDAR is an error); auto (the default): when the log has one.",
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

    @field_validator("lidar_map", mode="before")
    @classmethod
    def _lidar_map_switch(cls, v):
        return {"enabled": v} if isinstance(v, bool) or v == "auto" else v

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


# each stage: its module (whose STAGE_VERSION is read when hashing, so a bumped version counts at once) and the
# config sections its output depends on
_STAGES = {
    "trajectory": (trajectory_stage, ("topics", "trajectory")),
    "georef": (georef_stage, ("topics", "trajectory", "georef")),
    "lidar_map": (lidar_map_stage, ("topics", "trajectory", "georef", "lidar_map")),
    "map": (map_stage, ("topics", "trajectory", "georef", "semidense", "camera")),
    "imagedb": (imagedb_stage, ("topics", "trajectory", "georef", "semidense", "camera", "imagedb", "map")),
}


def _stage_config(d: dict, parts: tuple[str, ...]) -> dict:
    """Of a config dumped as JSON, the sections ``parts`` a stage depends on, as far as they change its output."""
    d = json.loads(json.dumps(d))
    # the image database's and the LiDAR map's switches decide whether they run, not what they hold
    d["imagedb"].pop("enabled", None)
    d["lidar_map"].pop("enabled", None)
    # the factor graph's section counts only when fusion is on
    if not d["georef"]["fuse"]:
        d["georef"].pop("fuse")
        d["georef"].pop("factor_graph")
    # the assumed mounts count only when one is assumed: then every stage depends on them
    if d["extrinsics"]["assume_identity"]:
        parts = (*parts, "extrinsics")
    return {p: d.get(p) for p in parts}


def _stage_version(stage: str) -> int:
    """The version of a build stage's algorithm (its module's ``STAGE_VERSION``)."""
    return int(_STAGES[stage][0].STAGE_VERSION)


def _stage_hash(cfg: BuildConfig, stage: str) -> str:
    """The hash a build stage's marker holds (:func:`mapkit.core.runio.stage_hash`): of its version and the
    resolved config sections it depends on, every field with its default."""
    return stage_hash(stage, _stage_version(stage), _stage_config(cfg.model_dump(mode="json"), _STAGES[stage][1]))


# defaults that the older rule (:func:`_legacy_stage_hash`) left out of the hash
_LEGACY_IMAGEDB_DEFAULTS = {"min_interval_s": 0.0, "training_frames": False, "training_interval_s": 0.0}


def _legacy_stage_hash(cfg: BuildConfig, stage: str) -> str:
    """The hash markers without a stage version hold (only to migrate them, :func:`mapkit.core.runio.is_done`):
    no version, the semi-dense section as the overrides it was given and the image database's time
    sub-sampling and training frames only when set."""
    d = cfg.model_dump(mode="json")
    d["semidense"] = cfg.semidense.model_dump(mode="json", exclude_unset=True)
    for key, default in _LEGACY_IMAGEDB_DEFAULTS.items():
        if d["imagedb"].get(key) == default:
            d["imagedb"].pop(key)
    return config_hash(_stage_config(d, _STAGES[stage][1]))


def session_name(log_path: str | Path) -> str:
    """The session a log builds: its file or folder name up to the first dot."""
    return Path(log_path).stem.split(".")[0]


class SessionBuilder:
    """Builds one session: runs its stages (:mod:`mapkit.mapping.stages`) in order, each method returning
    its stage folder, and reuses a stage that finished with this config from these inputs.

    The builder owns what the stages share: the log (opened once), the session's sensor mounts, its GPS
    fixes and mapping camera (read once), the markers and stage hashes that decide what runs again, why
    a stage is skipped, and the session's metrics and timings."""

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
        self._camera_choice: MappingCamera | None = None
        self._mounts: dict[str, np.ndarray] = {}  # trajectory body frame -> base_from_camera
        self._sensor_mounts: SensorMounts | None = None
        self._enu_trajectory: Trajectory | None = None
        self._fixes: ScreenedFixes | None = None
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

    def _is_finished(self, out: Path, stage: str, inputs: dict) -> bool:
        """The stage ``stage`` at ``out`` finished with this config, this version of its code and these inputs, its
        outputs unchanged (checked once per run); a marker of an older mapkit that still matches is migrated."""
        if out in self._finished:
            return True
        if is_done(
            out,
            _stage_hash(self.cfg, stage),
            inputs=inputs,
            verify=True,
            legacy_hash=_legacy_stage_hash(self.cfg, stage),
            version=_stage_version(stage),
        ):
            self._finished.add(out)
            return True
        return False

    def _mark(self, out: Path, stage: str, inputs: dict) -> None:
        """Mark a stage finished, unless its log changed while the stage read it (then nothing is marked)."""
        now = log_fingerprint(self.log_path, watch=False)
        if now != inputs["log"]:
            raise InputError(
                self.log_path,
                f"changed while the {out.name} stage read it ({describe_change(inputs['log'], now)}); "
                "the stage is not marked finished: build again once the log is complete",
                field="mtime",
            )
        mark_done(out, _stage_hash(self.cfg, stage), version=_stage_version(stage), inputs=inputs, outputs=True)
        self._finished.add(out)

    def _run_stage(self, out: Path, stage: str, inputs: dict, write: Callable[[], Path]) -> Path:
        """The stage folder ``out`` of stage ``stage``: reused when it finished with this config and version from
        ``inputs``, else emptied, written by ``write``, timed (its ``timings.json``) and marked finished."""
        if self._is_finished(out, stage, inputs):
            return out
        with workspace_lock(self.ws.root, wait_s=lock_wait()):  # emptied and re-made only under the lock
            t0 = time.perf_counter()
            reset_stage(out)
            write()
            write_timings(out, seconds=time.perf_counter() - t0)
            self._mark(out, stage, inputs)
        return out

    def preflight(self) -> None:
        """Checks that need the log but write nothing: the log is not still being written, the topics
        the config names exist, and, when the config asks for a map or an image database, that the
        mapping camera has frames and intrinsics: a camera the config names (``camera``, or
        ``topics.images``) must exist, and a log with images must have intrinsics for the camera
        chosen. A log without images skips the image stages instead (see :meth:`skip_reason`)."""
        self.log_fingerprint()
        topics = resolve_topics(self.log, self.cfg.topics)
        if self.cfg.lidar_map.enabled is True and not topics.get(StreamKind.LIDAR):
            raise InputError(
                self.log_path,
                f"has no LiDAR stream{'' if self.cfg.topics.lidar is None else ' on topics.lidar'}, but the config "
                "asks for a LiDAR map (lidar_map.enabled: true)",
                field="lidar_map.enabled",
            )
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

    # --- the stages, in order -------------------------------------------------------------------
    def trajectory(self) -> Path:
        """Stage 1 (:mod:`mapkit.mapping.stages.trajectory`)."""
        return self._run_stage(
            self.dirs.trajectory,
            "trajectory",
            self._inputs(),
            lambda: write_trajectory(
                self.dirs, self.log, self.cfg.trajectory, self.cfg.topics, self.mounts, progress=self.progress
            ),
        )

    def georef(self) -> Path:
        """Stage 2 (:mod:`mapkit.mapping.stages.georef`)."""
        trajectory = self.trajectory()
        return self._run_stage(
            self.dirs.georef,
            "georef",
            self._inputs(trajectory),
            lambda: self._georeference(trajectory),
        )

    def _georeference(self, trajectory: Path) -> Path:
        """Run the georef stage on the trajectory stage's folder (the ENU trajectory read before is dropped)."""
        self._enu_trajectory = None
        stage = Georeference(
            self.ws,
            self.dirs,
            self.cfg.georef,
            log=self.log,
            log_path=self.log_path,
            topics=self.cfg.topics,
            mounts=self.mounts,
            gps=self._screened_fixes,
        )
        return stage.run(trajectory)

    def lidar_map(self) -> Path:
        """The LiDAR map (:mod:`mapkit.mapping.stages.lidar_map`), on the trajectory the semi-dense map uses."""
        return self._run_stage(
            self.dirs.lidar_map,
            "lidar_map",
            self._inputs(self.georef()),
            lambda: write_lidar_map(
                self.dirs,
                self.log,
                resolve_topics(self.log, self.cfg.topics)[StreamKind.LIDAR][0],
                self.enu_trajectory(),
                self.mounts,
                self.cfg.lidar_map,
                self.frame(),
                progress=self.progress,
            ),
        )

    def semidense(self) -> Path:
        """Stage 3 (:mod:`mapkit.mapping.stages.map`)."""
        return self._run_stage(
            self.dirs.map,
            "map",
            self._inputs(self.georef()),
            lambda: write_map(self.dirs, self.posed_frames(), self.cfg.semidense, self.frame(), progress=self.progress),
        )

    def imagedb(self) -> Path:
        """Stage 4 (:mod:`mapkit.mapping.stages.imagedb`), with the map's points when stage 3 runs."""
        with_map = self.skip_reason("semidense") is None
        map_dir = self.semidense() if with_map else None
        return self._run_stage(
            self.dirs.imagedb,
            "imagedb",
            self._inputs(self.georef(), *([map_dir] if map_dir is not None else [])),
            lambda: write_imagedb(
                self.dirs, self.posed_frames(decode=False), self.cfg.imagedb, self.frame(), self.metric(), map_dir
            ),
        )

    # --- what the stages share --------------------------------------------------------------------
    def _screened_fixes(self) -> ScreenedFixes:
        """The log's GPS fixes that pass screening (:func:`mapkit.mapping.stages.georef.screened_fixes`), read once."""
        if self._fixes is None:
            self._fixes = screened_fixes(self.log, self.cfg.topics, self.log_path)
        return self._fixes

    def proposed_frame(self) -> LocalFrame | None:
        """The workspace frame this session would set if it were the first one georeferenced
        (:func:`mapkit.mapping.stages.georef.proposed_frame`)."""
        return proposed_frame(self.cfg.georef, self._screened_fixes)

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

    def _camera(self) -> MappingCamera:
        """The mapping camera (:func:`mapkit.mapping.stages.frames.choose_camera`), chosen once."""
        if self._camera_choice is None:
            self._camera_choice = choose_camera(self.log, self.cfg.camera, self.cfg.topics, self.log_path)
        return self._camera_choice

    def base_from_camera(self, body_frame: str) -> np.ndarray:
        """The mapping camera's mount: the pose of the camera in the trajectory's body frame
        (looked up in the log's transforms once per body frame)."""
        if body_frame not in self._mounts:
            self._mounts[body_frame] = self.mounts.base_from(body_frame, self._camera().name, "camera")
        return self._mounts[body_frame]

    def posed_frames(self, decode: bool = True) -> PosedFrames:
        """The mapping camera's frames with their poses on the session's ENU trajectory."""
        camera = self._camera()
        traj = self.enu_trajectory()
        return PosedFrames(self.log, camera, traj, self.base_from_camera(traj.body_frame), decode=decode)

    # --- which stages run -----------------------------------------------------------------------
    def metric(self) -> bool:
        """Whether the session's poses are in metres: georeferenced, or a metric source (LiDAR, poses)."""
        return not camera_only(self.enu_trajectory()) or self.frame() is not None

    def skip_reason(self, stage: str) -> str | None:
        """Why an image stage (``semidense``, ``imagedb``) or the LiDAR map does not run for this session, or None."""
        if stage == "lidar_map":
            return self._lidar_map_skip()
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

    def _lidar_map_skip(self) -> str | None:
        """Why the LiDAR map does not run: switched off, no LiDAR (quietly, with ``enabled: auto``; ``true`` failed
        at :meth:`preflight`), or a camera-only trajectory of arbitrary scale."""
        if self.cfg.lidar_map.enabled is False:
            return SKIPPED_BY_CONFIG["lidar_map"]
        if not resolve_topics(self.log, self.cfg.topics).get(StreamKind.LIDAR):
            return NO_LIDAR
        if not self.metric():
            return "the camera-only trajectory is not georeferenced: its scale is arbitrary and the scans are in metres"
        return None

    def run(self) -> dict:
        """Every stage of the session in order (the image stages unless skipped, with the reason in the metrics);
        writes the session's config, metrics and timings; returns the metrics."""
        t0 = time.perf_counter()
        self.preflight()
        self.dir.mkdir(parents=True, exist_ok=True)
        atomic_write_text(self.dirs.config, dump_config(self.cfg))
        for stage in (self.trajectory, self.georef, self.lidar_map, self.semidense, self.imagedb):
            s0 = time.perf_counter()
            reason = self.skip_reason(stage.__name__) if stage.__name__ in SKIPPED_BY_CONFIG else None
            if reason is not None:
                if reason not in SKIPPED_BY_CONFIG.values() and reason != NO_LIDAR:
                    warnings.warn(f"{self.log_path}: {stage.__name__} skipped: {reason}", InputWarning, stacklevel=2)
                self.metrics["stages"][stage.__name__] = {"skipped": reason}
                continue
            stage_metrics = self._stage_metrics(stage())
            self.timings[stage.__name__] = time.perf_counter() - s0
            self.metrics["stages"][stage.__name__] = stage_metrics
        self.timings["total"] = time.perf_counter() - t0
        write_json(self.dirs.metrics, self.metrics)
        write_timings(self.dir, wall_s_this_run=self.timings)
        self.close()
        return self.metrics

    def _stage_metrics(self, folder: Path) -> dict:
        """A stage's entry in the session's metrics: its ``metrics.json``; for the georef stage the headline of
        ``gps_alignment.json`` (whether and how the session is georeferenced, its length, the alignment)."""
        if folder == self.dirs.georef:
            ga = json.loads(self.dirs.gps_alignment.read_text())
            return {
                "georeferenced": ga["georeferenced"],
                **{k: ga[k] for k in ("reason", "units") if k in ga},
                **{k: v for k, v in ga.items() if k.startswith("length_")},
                **ga.get("alignment", {}),
            }
        m_path = folder / "metrics.json"
        return json.loads(m_path.read_text()) if m_path.is_file() else {}


SKIPPED_BY_CONFIG = {
    "semidense": "map: false in the config",
    "imagedb": "imagedb: false in the config",
    "lidar_map": "lidar_map: false in the config",
}
NO_LIDAR = "the log has no LiDAR stream"  # with lidar_map.enabled: auto, no warning


def _log_bytes(log: Path) -> int:
    """Size of a log: a file's, or the sum of the files in a log folder (rosbag2, KITTI)."""
    if log.is_file():
        return log.stat().st_size
    return sum(p.stat().st_size for p in log.rglob("*") if p.is_file()) if log.is_dir() else 0


@writes_workspace("workspace", creates=True)
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
            ex.map(
                _build_task,
                [logs[i] for i in order],
                shared=(ws, cfg, lock_token(ws.root)),
                desc="build",
                label=lambda p: str(p),
            ),
            order,
            strict=True,
        ):
            done[i] = m
            if progress:
                logger.info("built %s: %.1f s", m["session"], _session_seconds(ws, m["session"]))
    except TaskError as exc:
        raise (exc.cause if isinstance(exc.cause, MapkitError) else exc) from exc
    return {done[i]["session"]: done[i] for i in range(len(logs))}


def _build_task(shared: tuple[Workspace, BuildConfig, str | None], log: Path) -> dict:
    ws, cfg, token = shared
    with adopted_lock(ws.root, token):  # a worker writes under the lock build() holds in the parent
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
            workspace_frame(ws, frame)
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
