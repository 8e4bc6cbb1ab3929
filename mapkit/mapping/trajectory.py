"""Stage 1 of map construction: the vehicle trajectory of one session.

Sources, chosen by ``TrajectoryConfig.source``:
- ``lidar``: kiss-icp (the library, with its own deskewing from per-point times) on the LiDAR
  stream; poses are of the base frame, in the frame of the base at the first scan.
- ``poses``: a pose stream of the log (INS, or ground truth when the log has nothing better).
- ``camera``: pycolmap incremental mapping with the log's intrinsics (scale and orientation are
  arbitrary until GPS alignment, which then must estimate a full Sim3).
``auto`` takes LiDAR when the log has it, else a pose stream, else the camera.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from mapkit.core.config import MapkitConfig, TopicConfig, resolve_topics
from mapkit.core.errors import InputError, InputWarning
from mapkit.core.frames import FrameTree
from mapkit.core.geometry import interpolate_poses, invert_pose
from mapkit.core.runio import atomic_path, atomic_write_text, progress_bar
from mapkit.core.types import FrameTransform, StreamKind
from mapkit.io.base import DriveLog
from mapkit.io.benchmark import colmap_camera_params
from mapkit.io.trajectory import read_tum, write_kitti_poses, write_tum

WARM_START_LEAD_S = 1.0  # the scans after the warm start whose map it registers against (see _warm_start)


class KissIcpOptions(MapkitConfig):
    """kiss-icp's parameters, checked here: kiss-icp itself fails on a zero voxel or a negative range
    with a traceback from its C++ core, after the log has been opened."""

    max_range_m: float = Field(
        100.0,
        gt=0,
        allow_inf_nan=False,
        description="kiss-icp data.max_range; its voxel size is max_range/100 unless set.",
    )
    min_range_m: float = Field(
        2.0, ge=0, allow_inf_nan=False, description="kiss-icp data.min_range: drops returns from the vehicle body."
    )
    deskew: bool = Field(True, description="Motion compensation from per-point times (kiss-icp's own).")
    voxel_size_m: float | None = Field(
        None,
        gt=0,
        allow_inf_nan=False,
        description="kiss-icp mapping.voxel_size; None = max_range/100 (kiss-icp's rule).",
    )
    max_points_per_voxel: int = Field(
        20, ge=1, description="kiss-icp mapping.max_points_per_voxel: points kept per voxel of its local map."
    )
    max_threads: int = Field(
        1,
        ge=0,
        description="kiss-icp registration.max_num_threads; 0 = all cores. With one thread kiss-icp gives the same "
        "poses to the bit on every run; with more, its correspondences are summed in a varying order. kiss-icp fixes "
        "the count once per process (a TBB global control): the first kiss-icp of a process decides.",
    )
    warm_start_s: float = Field(
        2.0,
        ge=0,
        allow_inf_nan=False,
        description="kiss-icp starts from standstill (its motion model's first guess is no motion, and against a map "
        "of one or two sweeps the ground rings pull towards none), so a log that begins in motion has its first "
        "second or so under-estimated. The drive's first this-many seconds are registered again, backwards in time, "
        "against the map the next second's sweeps made, and take those poses. 0: off, the poses are kiss-icp's own "
        "forward run's, as its kiss_icp_pipeline gives them. 2 s: kiss-icp needed 0.8 s to reach the speed of a "
        "synthetic drive begun at 8 m/s (tests/test_rosbag2.py's).",
    )

    @model_validator(mode="after")
    def _ranges(self) -> KissIcpOptions:
        if self.min_range_m >= self.max_range_m:
            raise ValueError(f"min_range_m ({self.min_range_m}) must be below max_range_m ({self.max_range_m})")
        return self


class CameraSfmOptions(MapkitConfig):
    max_images: int = Field(400, description="Images given to pycolmap (evenly sub-sampled in time beyond this).")
    max_image_size: int = Field(1024, description="pycolmap SIFT extraction's max_image_size (px).")
    sequential_overlap: int = Field(
        10, description="pycolmap sequential matching: each image is matched with this many next ones."
    )
    max_threads: int = Field(-1, description="pycolmap threads; -1 = all cores.")
    init_min_tri_angle_deg: float = Field(
        4.0,
        description="Initial pair's triangulation angle (COLMAP's 16 suits photo collections; a forward-moving car "
        "sees less).",
    )
    init_max_forward_motion: float = Field(
        1.0,
        description="COLMAP rejects initial pairs moving along the view axis above this (0.95): a front camera only "
        "does that.",
    )


class TrajectoryConfig(MapkitConfig):
    source: Literal["auto", "lidar", "poses", "camera"] = Field(
        "auto", description="Where the trajectory comes from; auto = lidar, else a pose stream, else camera."
    )
    base_frame: str = Field("base_link", description="The vehicle frame whose poses the trajectory holds.")
    kiss_icp: KissIcpOptions = KissIcpOptions()
    camera: CameraSfmOptions = CameraSfmOptions()


@dataclass
class Trajectory:
    """Poses of the vehicle base frame: ``world_from_base[i]`` at ``stamps_ns[i]``."""

    stamps_ns: np.ndarray
    world_from_base: np.ndarray
    source: str
    frame: str = "odom"
    body_frame: str = "base_link"  # whose poses these are: the base, or the sensor a pose stream gives

    def __len__(self) -> int:
        return len(self.stamps_ns)

    def save(self, folder: str | Path) -> Path:
        """TUM and KITTI (+ times.txt) files and an exact npz (int64 stamps, float64 poses)."""
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        write_tum(folder / "poses_tum.txt", self.stamps_ns, self.world_from_base)
        write_kitti_poses(folder / "poses_kitti.txt", self.world_from_base)
        t0 = int(self.stamps_ns[0])
        atomic_write_text(folder / "times.txt", "".join(f"{(s - t0) * 1e-9:.9f}\n" for s in self.stamps_ns))
        with atomic_path(folder / "trajectory.npz") as tmp, open(tmp, "wb") as f:
            np.savez(
                f,
                stamps_ns=self.stamps_ns,
                world_from_base=self.world_from_base,
                source=self.source,
                frame=self.frame,
                body_frame=self.body_frame,
            )
        return folder

    @classmethod
    def load(cls, folder: str | Path) -> Trajectory:
        folder = Path(folder)
        npz = folder / "trajectory.npz"
        if npz.is_file():
            d = np.load(npz)
            body = str(d["body_frame"]) if "body_frame" in d else "base_link"
            return cls(d["stamps_ns"], d["world_from_base"], str(d["source"]), str(d["frame"]), body)
        stamps, poses = read_tum(folder / "poses_tum.txt")
        return cls(stamps, poses, "tum")


class SensorMounts:
    """Where a log's sensors sit on the vehicle: ``base``-from-``frame``, looked up in the log's static tf.

    A sensor whose frame is the base (or empty) is at the identity. One that tf does not link to the base is an
    :class:`InputError` naming the log, the two frames and what the tree holds, unless ``assume_identity`` (the build
    config's ``extrinsics.assume_identity``) lists its frame: the two frames are then taken as one, and one
    :class:`InputWarning` per pair says so. A log that holds no transform at all (a bag recorded without
    ``/tf_static``, frame tables, photos, RobotCar) has nothing that could place its GPS antenna or LiDAR: lookups
    that pass ``without_tf_ok`` take those at the base too, with the same warning; a camera or an IMU, whose
    orientation matters, still needs its extrinsic or the config's word.
    """

    def __init__(
        self, transforms: Iterable[FrameTransform], source: str | Path | None, assume_identity: Iterable[str] = ()
    ):
        self.tree = FrameTree(list(transforms))
        self.source = source
        self.assume_identity = frozenset(assume_identity)
        self._assumed: set[tuple[str, str]] = set()  # (base, frame) pairs already taken as one, and said so

    @classmethod
    def of(cls, log: DriveLog, assume_identity: Iterable[str] = ()) -> SensorMounts:
        return cls(log.transforms(), log.path, assume_identity)

    def base_from(self, base: str, frame: str, what: str, *, without_tf_ok: bool = False) -> np.ndarray:
        """``base``-from-``frame`` of the ``what`` sensor (``"camera"``, ``"GPS antenna"``, ...)."""
        if frame in ("", base):
            return np.eye(4)
        try:
            return self.tree.lookup(base, frame)
        except InputError:
            pass
        allowed = frame in self.assume_identity
        if not allowed and not (without_tf_ok and not self.tree.frames):
            raise InputError(
                self.source,
                f"tf does not link the {what} frame {frame!r} to {base!r} "
                f"({self._holds(base, frame)}): record that transform in /tf_static, or list {frame!r} in "
                f"the build config's extrinsics.assume_identity to take the {what} as mounted at {base!r}",
                field="tf",
            )
        if (base, frame) not in self._assumed:
            self._assumed.add((base, frame))
            why = (
                "as extrinsics.assume_identity allows: tf does not link them"
                if allowed
                else "the log holds no extrinsics (tf) at all"
            )
            warnings.warn(
                f"{self.source}: the {what} frame {frame!r} is taken as {base!r} (identity {base}_from_{frame}), {why}",
                InputWarning,
                stacklevel=3,
            )
        return np.eye(4)

    def _holds(self, base: str, frame: str) -> str:
        """What the tree holds of the two frames, for the error."""
        frames = sorted(self.tree.frames)
        if not frames:
            return "the log's tf holds no transform"
        said = []
        for f in (base, frame):
            if f not in self.tree.frames:
                said.append(f"{f!r} is not in it")
                continue
            linked = [g for g in frames if g != f and self._linked(f, g)]
            said.append(
                f"{f!r} is linked to {', '.join(map(repr, linked))}" if linked else f"{f!r} is linked to nothing"
            )
        return f"the log's tf holds {', '.join(map(repr, frames))}; " + ", ".join(said)

    def _linked(self, a: str, b: str) -> bool:
        try:
            self.tree.lookup(a, b)
            return True
        except InputError:
            return False


def trajectory_from_poses(log: DriveLog, topic: str, base_frame: str, mounts: SensorMounts | None = None) -> Trajectory:
    """A pose stream as the trajectory; a stream of another body frame is moved to the base (``mounts``: the log's
    sensor mounts with the build's policy, else its tf alone)."""
    stamps, poses = [], []
    child = None
    for p in log.records(StreamKind.POSE, topic=topic):
        stamps.append(p.stamp_ns)
        poses.append(p.parent_from_child)
        child = p.child_frame
    if len(stamps) < 2:
        raise InputError(
            log.path, f"pose topic {topic} has {len(stamps)} poses; a trajectory needs at least 2", field=topic
        )
    child = child or base_frame
    mounts = mounts or SensorMounts.of(log)
    tree = mounts.tree
    if child == base_frame or (base_frame in tree.frames and child in tree.frames):
        world_from_base = np.stack(poses) @ invert_pose(mounts.base_from(base_frame, child, "pose stream"))
        body = base_frame
    else:
        # no calibration ties the pose's frame to the base (KITTI odometry: poses are camera_0's);
        # the trajectory is then of that frame, and later lookups start from it
        world_from_base, body = np.stack(poses), child
    return Trajectory(
        np.asarray(stamps, np.int64), world_from_base, source=f"poses:{topic}", frame="world", body_frame=body
    )


def _scans(log: DriveLog, topic: str) -> Iterator:
    yield from log.records(StreamKind.LIDAR, topic=topic)


def trajectory_from_lidar(
    log: DriveLog, topic: str, cfg: TrajectoryConfig, progress: bool = False, mounts: SensorMounts | None = None
) -> Trajectory:
    """kiss-icp odometry on one LiDAR stream, reported for the base frame (placed by ``mounts``, else by the log's tf).

    kiss-icp deskews each sweep to the time of its last point (``exp((t_norm - 1) * omega)``),
    so the pose it returns belongs to the stamp of that point, not to the header stamp.
    """
    from kiss_icp.config import KISSConfig
    from kiss_icp.kiss_icp import KissICP

    o = cfg.kiss_icp
    kcfg = KISSConfig()
    kcfg.data.max_range = o.max_range_m
    kcfg.data.min_range = o.min_range_m
    kcfg.data.deskew = o.deskew
    kcfg.mapping.voxel_size = o.voxel_size_m if o.voxel_size_m is not None else o.max_range_m / 100.0
    kcfg.mapping.max_points_per_voxel = o.max_points_per_voxel
    kcfg.registration.max_num_threads = o.max_threads
    odometry = KissICP(kcfg)
    stamps, lidar0_from_lidar = [], []
    held: list[tuple[np.ndarray, np.ndarray, int]] = []  # the first warm_start_s: points, times, first point's stamp
    first_ns: int | None = None
    lidar_frame = None
    bar = _progress(log, topic, progress)
    for scan in _scans(log, topic):
        lidar_frame = scan.frame_id
        pts = np.asarray(scan.points_xyz, np.float64)
        if scan.point_time_s is not None and o.deskew:
            t = np.asarray(scan.point_time_s, np.float64)
            end_ns = scan.stamp_ns + int(round(float(t.max()) * 1e9)) if len(t) else scan.stamp_ns
        else:
            t = np.zeros(0)
            end_ns = scan.stamp_ns
        if len(pts) < 100:
            warnings.warn(
                f"{log.path}: {topic} scan at {scan.stamp_ns} has {len(pts)} points; skipped",
                InputWarning,
                stacklevel=2,
            )
            continue
        odometry.register_frame(pts, t)
        stamps.append(end_ns)
        lidar0_from_lidar.append(odometry.last_pose.copy())
        first_ns = scan.stamp_ns if first_ns is None else first_ns
        if o.warm_start_s > 0 and scan.stamp_ns - first_ns <= (o.warm_start_s + WARM_START_LEAD_S) * 1e9:
            start_ns = scan.stamp_ns + int(round(float(t.min()) * 1e9)) if len(t) else scan.stamp_ns
            held.append((pts, t, start_ns))
        bar.update(1)
    bar.close()
    replaced = sum(h[2] - held[0][2] < o.warm_start_s * 1e9 for h in held)
    if 1 < replaced < len(held) < len(stamps):
        stamps, lidar0_from_lidar = _warm_start(KissICP(kcfg), odometry, held, replaced, stamps, lidar0_from_lidar)
    if len(stamps) < 2:
        raise InputError(
            log.path, f"LiDAR topic {topic} gave {len(stamps)} usable scans; a trajectory needs at least 2", field=topic
        )
    mounts = mounts or SensorMounts.of(log)
    tree = mounts.tree
    body = cfg.base_frame
    if lidar_frame and body not in tree.frames and lidar_frame in tree.frames:
        # the calibration names no base (KITTI raw: imu, velodyne, cameras): the trajectory is the
        # scanner's, so that later lookups (the GPS antenna, the cameras) start from a frame it knows
        body, base_from_lidar = lidar_frame, np.eye(4)
    else:
        base_from_lidar = mounts.base_from(body, lidar_frame or "", "LiDAR", without_tf_ok=True)
    # world := the base frame at the first scan
    world_from_base = base_from_lidar @ np.stack(lidar0_from_lidar) @ invert_pose(base_from_lidar)
    order = np.argsort(stamps, kind="stable")
    return Trajectory(
        np.asarray(stamps, np.int64)[order],
        world_from_base[order],
        source=f"lidar:{topic}",
        frame="odom",
        body_frame=body,
    )


def _warm_start(
    backward,
    forward,
    held: list[tuple[np.ndarray, np.ndarray, int]],
    m: int,
    stamps: list[int],
    poses: list[np.ndarray],
) -> tuple[list[int], list[np.ndarray]]:
    """The forward run's ``stamps`` and ``poses`` with those of its first ``m`` scans replaced by registering them
    again, backwards in time, against the map the ``held`` scans after them made on the forward run's poses.

    ``backward`` is a fresh kiss-icp: its local map is filled with the later held scans (deskewed and placed as the
    forward run placed them), its threshold is the forward run's (``forward``) at its end, and its motion model
    starts from the forward run's motion at scan ``m``, reversed. Backwards in time a sweep runs from its last point
    to its first: each scan's times are negated (kiss-icp normalises them to the sweep), and the pose kiss-icp gives
    is that of the sweep's first point, stamped so. Each scan thus meets a map of many sweeps, whose ground rings lie
    at other places than its own: against one or two sweeps they pull the motion towards none, which is why the
    forward run lags where a drive begins in motion. The poses are re-expressed so that the first is the identity."""
    if np.any(np.diff(stamps) <= 0):  # scans out of order: kept as they are
        return stamps, poses
    at_start, ok = interpolate_poses(np.asarray(stamps, np.int64), np.stack(poses), np.array([held[m][2]]))
    if not ok.all():  # scan m's first point before the forward run's first pose: nothing to start from
        return stamps, poses
    for j in range(len(held) - 1, m - 1, -1):  # the map of the later scans, last to first: trimmed around scan m
        pts, t, _ = held[j]
        frame = backward.preprocessor.preprocess(pts, t, invert_pose(poses[j - 1]) @ poses[j])
        backward.local_map.update(backward.voxelize(frame)[1], poses[j])
    backward.adaptive_threshold = forward.adaptive_threshold
    backward.last_pose = at_start[0]
    backward.last_delta = invert_pose(poses[m]) @ poses[m - 1]
    back = []
    for pts, t, _ in reversed(held[:m]):
        backward.register_frame(pts, -t)
        back.append(backward.last_pose.copy())
    new = back[::-1] + poses[m:]
    first = invert_pose(new[0])
    return [h[2] for h in held[:m]] + stamps[m:], [first @ p for p in new]


def _progress(log: DriveLog, topic: str, enabled: bool):
    total = next((s.count for s in log.streams() if s.topic == topic), None)
    return progress_bar(total, enabled, desc="kiss-icp", unit="scan", leave=False)


def choose_source(log: DriveLog, cfg: TrajectoryConfig, topics: dict[StreamKind, list[str]]) -> str:
    if cfg.source != "auto":
        return cfg.source
    if topics.get(StreamKind.LIDAR):
        return "lidar"
    if topics.get(StreamKind.POSE):
        return "poses"
    if topics.get(StreamKind.IMAGE):
        return "camera"
    raise InputError(log.path, "has no LiDAR, pose or image stream to make a trajectory from", field="topics")


def estimate_trajectory(
    log: DriveLog,
    cfg: TrajectoryConfig,
    topic_cfg: TopicConfig | None = None,
    progress: bool = False,
    mounts: SensorMounts | None = None,
) -> Trajectory:
    topics = resolve_topics(log, topic_cfg or TopicConfig())
    source = choose_source(log, cfg, topics)
    if source == "lidar":
        if not topics.get(StreamKind.LIDAR):
            raise InputError(
                log.path, "trajectory.source is lidar but the log has no LiDAR stream", field="trajectory.source"
            )
        return trajectory_from_lidar(log, topics[StreamKind.LIDAR][0], cfg, progress, mounts)
    if source == "poses":
        if not topics.get(StreamKind.POSE):
            raise InputError(
                log.path, "trajectory.source is poses but the log has no pose stream", field="trajectory.source"
            )
        return trajectory_from_poses(log, topics[StreamKind.POSE][0], cfg.base_frame, mounts)
    if not topics.get(StreamKind.IMAGE):
        raise InputError(
            log.path, "trajectory.source is camera but the log has no image stream", field="trajectory.source"
        )
    return trajectory_from_camera(log, topics[StreamKind.IMAGE][0], cfg, progress)


def camera_up_hint(world_from_cam: np.ndarray, min_agreement: float = 0.5) -> np.ndarray | None:
    """The cameras' mean up (-y of the optical frame: x right, y down, z forward) in the trajectory's
    frame, as a unit vector: roughly the world's up when the cameras are mounted (or held) roughly
    level. None when the cameras disagree (the mean of their unit up vectors is shorter than
    ``min_agreement``), as in a collection of photos taken in every direction."""
    up = -np.asarray(world_from_cam, np.float64)[:, :3, 1].mean(axis=0)
    n = float(np.linalg.norm(up))
    return up / n if n >= min_agreement else None


def trajectory_from_camera(log: DriveLog, topic: str, cfg: TrajectoryConfig, progress: bool = False) -> Trajectory:
    """pycolmap structure from motion (SIFT, sequential matching, incremental mapping) with the
    log's intrinsics fixed. The result has an arbitrary orientation and scale: GPS alignment must
    then estimate a full Sim3 (``georef.mode: sim3``).
    """
    import tempfile

    import cv2
    import pycolmap

    infos = log.camera_infos()
    o = cfg.camera
    counts = next((s.count for s in log.streams() if s.topic == topic), None)
    step = max(1, -(-counts // o.max_images)) if counts else 1
    with tempfile.TemporaryDirectory(prefix="mapkit-sfm-") as tmp_name:
        tmp = Path(tmp_name)
        (tmp / "images").mkdir()
        stamps: dict[str, int] = {}
        camera = None
        for i, frame in enumerate(log.records(StreamKind.IMAGE, topic=topic)):
            if i % step:
                continue
            camera = camera or frame.camera
            if frame.camera != camera:
                continue
            name = f"{frame.stamp_ns}.png"
            cv2.imwrite(str(tmp / "images" / name), frame.gray())
            stamps[name] = frame.stamp_ns
        if camera not in infos:
            raise InputError(
                log.path,
                f"camera {camera!r} has no intrinsics; camera-only trajectories need them",
                field="camera_info",
            )
        info = infos[camera]
        if len(stamps) < 3:
            raise InputError(
                log.path, f"{len(stamps)} images on {topic}: too few for structure from motion", field=topic
            )
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model, params = colmap_camera_params(info)
        reader.camera_params = ",".join(repr(float(v)) for v in params)
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.max_image_size = o.max_image_size
        extraction.num_threads = o.max_threads
        db = tmp / "database.db"
        pycolmap.extract_features(
            db,
            tmp / "images",
            camera_mode=pycolmap.CameraMode.SINGLE,
            reader_options=reader,
            extraction_options=extraction,
            device=pycolmap.Device.cpu,
        )
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = o.sequential_overlap
        pycolmap.match_sequential(db, pairing_options=pairing, device=pycolmap.Device.cpu)
        options = pycolmap.IncrementalPipelineOptions()
        options.ba_refine_focal_length = False
        options.ba_refine_principal_point = False
        options.ba_refine_extra_params = False
        options.num_threads = o.max_threads
        options.mapper.init_min_tri_angle = o.init_min_tri_angle_deg
        options.mapper.init_max_forward_motion = o.init_max_forward_motion
        (tmp / "sparse").mkdir()
        recs = pycolmap.incremental_mapping(db, tmp / "images", tmp / "sparse", options=options)
    if not recs:
        raise InputError(log.path, f"pycolmap could not reconstruct the camera path from {topic}", field=topic)
    rec = max(recs.values(), key=lambda r: r.num_reg_images())
    regs = sorted(
        (stamps[im.name], np.linalg.inv(np.vstack([im.cam_from_world().matrix(), [0, 0, 0, 1]])))
        for im in rec.images.values()
        if im.has_pose
    )
    if len(regs) < 0.5 * len(stamps):
        warnings.warn(
            f"{log.path}: pycolmap registered {len(regs)} of {len(stamps)} images; the trajectory has gaps",
            InputWarning,
            stacklevel=2,
        )
    world_from_cam = np.stack([T for _, T in regs])
    return Trajectory(
        np.array([s for s, _ in regs], np.int64),
        world_from_cam,
        source=f"camera:{topic}",
        frame="sfm",
        body_frame=camera,
    )
