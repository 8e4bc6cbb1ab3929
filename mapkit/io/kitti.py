"""KITTI odometry sequences and KITTI raw drives (Geiger, Lenz, Stiller, Urtasun, IJRR 2013).

Frames. Camera frames follow KITTI's camera convention (x right, y down, z forward); ``camera_i``
is camera i of the rig (0/1 grayscale left/right, 2/3 colour left/right). The rectified cameras
share one orientation and differ by a translation read from their projection matrices
``P_i = K_i [I | t_i]``: ``t_i = K_i^-1 P_i[:, 3]`` is the position of the rectified camera-0 origin
in camera i, so ``camera_0_from_camera_i = [I | t_0 - t_i]`` (for KITTI's P matrices this reduces
to a baseline ``-P_i[0, 3] / fx`` along x, plus the few millimetres KITTI stores in P[1:, 3]).
``velodyne`` is the scanner (x forward, y left, z up) and ``imu`` the OXTS unit (x forward, y left,
z up). Extrinsics come out as static ``FrameTransform`` records on ``/kitti/tf_static``, as a tree
``imu -> velodyne -> camera_0 -> camera_i`` (each ``parent_from_child``).

Velodyne point times. KITTI triggers the cameras when the scanner faces forward, and the HDL-64E
turns clockwise seen from above, so a sweep runs from the rear (azimuth +pi) through the front
(azimuth 0) to the rear again (-pi). Each point's time is interpolated from its azimuth across the
sweep: in raw drives between ``timestamps_start.txt`` and ``timestamps_end.txt``; in odometry
sequences, which keep no sweep times, over the nominal 0.1 s centred on the frame stamp.
"""

from __future__ import annotations

import calendar
import warnings
from dataclasses import dataclass
from datetime import datetime
from functools import partial
from pathlib import Path
from typing import Iterator, Optional, Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from mapkit.core.errors import InputError, InputWarning
from mapkit.core.geometry import invert_pose, make_pose, matrix_to_quat_wxyz
from mapkit.core.types import CameraInfo, FrameTransform, GpsFix, GpsStatus, ImuSample, LidarScan, Message, PoseSample, StreamKind
from mapkit.io.folder import (
    FolderLayoutLog,
    ImageLayout,
    Wanted,
    probe_image,
    read_stamp_lines,
    seconds_to_ns,
    stream_info,
)
from mapkit.io.trajectory import read_kitti_poses

#: KITTI recorded every sensor at 10 Hz (Geiger et al., IJRR 2013, Sec. 2)
NOMINAL_PERIOD_NS = 100_000_000

#: odometry camera folders by camera index; the first that exists is used
ODOMETRY_CAMERA_FOLDERS: dict[int, tuple[str, ...]] = {
    0: ("image_0", "image_l"),
    1: ("image_1", "image_r"),
    2: ("image_2",),
    3: ("image_3",),
}

#: the names KITTI's devkit gives the lines of an odometry calib.txt, in file order
ODOMETRY_CALIB_ORDER = ("P0", "P1", "P2", "P3", "Tr")

#: columns of a KITTI raw OXTS record (devkit readme, ``dataformat.txt``)
OXTS_FIELDS = (
    "lat lon alt roll pitch yaw vn ve vf vl vu ax ay az af al au wx wy wz wf wl wu "
    "pos_accuracy vel_accuracy navstat numsats posmode velmode orimode"
).split()
_OXTS = {name: i for i, name in enumerate(OXTS_FIELDS)}

#: IMU axes of an OXTS record: the vehicle body (rotates with roll and pitch) or the level frame
#: (heading only, parallel to the earth's surface), as the devkit's dataformat.txt defines them
IMU_AXES = {
    "body": (("wx", "wy", "wz"), ("ax", "ay", "az"), "imu"),
    "level": (("wf", "wl", "wu"), ("af", "al", "au"), "imu_level"),
}


# --- shared parsing ------------------------------------------------------------------------------

@dataclass(frozen=True)
class CalibFile:
    """A KITTI calibration file of ``name: values`` lines, read on demand by entry."""

    path: Path
    entries: dict[str, tuple[int, str]]  # name -> (line number, value text)

    @classmethod
    def read(cls, path: Path, unlabelled: Sequence[str] = ()) -> "CalibFile":
        """Lines without a ``name:`` take the names in ``unlabelled`` in order (odometry calib.txt
        files are sometimes stored without labels)."""
        entries: dict[str, tuple[int, str]] = {}
        next_unlabelled = 0
        with open(path) as f:
            for lineno, line in enumerate(f, start=1):
                text = line.strip()
                if not text:
                    continue
                name, sep, values = text.partition(":")
                if sep:
                    entries[name.strip()] = (lineno, values.strip())
                    continue
                if next_unlabelled >= len(unlabelled):
                    raise InputError(path, f"line {lineno} has no 'name:' label", field=f"line {lineno}")
                entries[unlabelled[next_unlabelled]] = (lineno, text)
                next_unlabelled += 1
        return cls(Path(path), entries)

    def __contains__(self, name: str) -> bool:
        return name in self.entries

    def numbers(self, name: str, count: int) -> np.ndarray:
        """The ``count`` numbers of entry ``name``; an error names the file and line otherwise."""
        if name not in self.entries:
            raise InputError(self.path, f"missing calibration entry {name!r}", field=name)
        lineno, text = self.entries[name]
        try:
            values = np.array([float(p) for p in text.split()], dtype=np.float64)
        except ValueError:
            raise InputError(self.path, f"line {lineno} ({name}): a value is not a number: {text[:80]!r}", field=f"line {lineno}") from None
        if len(values) != count:
            raise InputError(self.path, f"line {lineno} ({name}) has {len(values)} numbers, expected {count}", field=f"line {lineno}")
        if not np.all(np.isfinite(values)):
            raise InputError(self.path, f"line {lineno} ({name}) has a non-finite value", field=f"line {lineno}")
        return values

    def matrix(self, name: str, rows: int, cols: int) -> np.ndarray:
        return self.numbers(name, rows * cols).reshape(rows, cols)

    def rigid(self, rotation: str, translation: str) -> np.ndarray:
        """4x4 ``[R | T]`` from a 9-number rotation entry and a 3-number translation entry."""
        return make_pose(self.matrix(rotation, 3, 3), self.numbers(translation, 3))


def kitti_datetime_ns(text: str) -> int:
    """``2011-09-26 13:02:25.964389445`` to integer ns since the Unix epoch, exactly.

    The wall-clock time is read as UTC: KITTI does not state a zone, and only differences between
    stamps matter for mapping.
    """
    s = text.strip()
    whole, _, frac = s.partition(".")
    try:
        dt = datetime.strptime(whole, "%Y-%m-%d %H:%M:%S")
    except ValueError:
        raise ValueError(f"{s!r} is not a time like '2011-09-26 13:02:25.964389445'") from None
    if len(frac) > 9 or not (frac.isascii() and frac.isdigit() or frac == ""):
        raise ValueError(f"{s!r} has a fraction of a second that is not 0-9 digits")
    return calendar.timegm(dt.timetuple()) * 1_000_000_000 + int(frac.ljust(9, "0"))


def camera_0_from_rectified_cameras(projections: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
    """``camera_0_from_camera_i`` of rectified cameras from their 3x4 projection matrices."""
    t = {i: np.linalg.solve(P[:, :3], P[:, 3]) for i, P in projections.items()}
    t0 = t.get(0, np.zeros(3))
    return {i: make_pose(np.eye(3), t0 - ti) for i, ti in t.items()}


def read_velodyne_bin(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(xyz (N, 3) float32, reflectance (N,)) of a KITTI scan; non-finite points are dropped."""
    raw = np.fromfile(path, dtype="<f4")
    if raw.size % 4:
        raise InputError(path, f"{raw.size * 4} bytes is not a whole number of 16-byte points (x, y, z, reflectance as float32)")
    points = raw.reshape(-1, 4)
    valid = np.isfinite(points).all(axis=1)
    if not valid.all():
        points = points[valid]
    return np.ascontiguousarray(points[:, :3]), np.ascontiguousarray(points[:, 3])


def sweep_point_times_s(xyz: np.ndarray, sweep_start_s: float, sweep_duration_s: float) -> np.ndarray:
    """Per-point times (s, relative to the scan stamp) of a clockwise sweep starting behind the sensor."""
    azimuth = np.arctan2(xyz[:, 1], xyz[:, 0])
    fraction = (np.pi - azimuth) / (2.0 * np.pi)
    return (sweep_start_s + fraction * sweep_duration_s).astype(np.float32)


def _require_same_count(path: Path, what: str, n: int, other: str, m: int) -> None:
    if n != m:
        raise InputError(path, f"{n} {what} but {m} {other}; the counts must agree")


# --- odometry -------------------------------------------------------------------------------------

class KittiOdometry(FolderLayoutLog):
    """A KITTI odometry sequence folder (``image_0/`` or ``image_l/``, ``calib.txt``, ...).

    Topics (prefix ``/kitti``): ``/camera_i/image`` and ``/camera_i/camera_info`` per camera folder,
    ``/ground_truth`` (when ``poses.txt`` exists: ``world_from_camera_0``, where world is camera 0 at
    the first frame), ``/velodyne/points`` (with ``velodyne/``) and ``/tf_static``. Stamps come from
    ``times.txt``; without it, frames are 0.1 s apart from 0, with one ``InputWarning`` saying so.
    """

    format_name = "kitti-odometry"

    def __init__(self, path: str | Path, *, lidar: bool = True, topic_prefix: str = "/kitti"):
        super().__init__(path)
        prefix = topic_prefix.rstrip("/")
        self.image_dirs = self._camera_folders()
        image_paths = {i: sorted(p for p in d.iterdir() if p.suffix == ".png") for i, d in self.image_dirs.items()}
        n = len(image_paths[0])
        if n == 0:
            raise InputError(self.image_dirs[0], "holds no .png images")
        first_folder = self.image_dirs[0].name
        for i, paths in image_paths.items():
            folder = self.image_dirs[i]
            _require_same_count(folder, f"images in {folder.name}/", len(paths), f"in {first_folder}/", n)

        self.calib = self._read_calib()
        self.projections = self._projections()
        self.stamps_ns = self._read_stamps(n)
        self.world_from_camera_0 = self._read_poses(n)
        self.velodyne_paths = self._velodyne_paths(n) if lidar else []

        first = int(self.stamps_ns[0])
        transforms = [
            FrameTransform(first, "camera_0", f"camera_{i}", T)
            for i, T in sorted(camera_0_from_rectified_cameras(self.projections).items())
            if i != 0 and i in self.image_dirs
        ]
        if "Tr" in self.calib:
            Tr = self.calib.matrix("Tr", 3, 4)
            transforms.append(FrameTransform(first, "camera_0", "velodyne", make_pose(Tr[:, :3], Tr[:, 3])))
        self._add_static_transforms(f"{prefix}/tf_static", transforms)

        stamps = self.stamps_ns.tolist()
        for i, folder in sorted(self.image_dirs.items()):
            camera = f"camera_{i}"
            layout = probe_image(image_paths[i][0])
            P = self.projections[i]
            info = CameraInfo(camera, layout.width, layout.height, P[:, :3].copy(), "plumb_bob", np.zeros(5), first)
            self._add_camera(
                camera,
                f"{prefix}/{camera}/image",
                partial(zip, stamps, image_paths[i]),
                layout,
                info=info,
                info_topic=f"{prefix}/{camera}/camera_info",
                count=n,
            )
        if self.world_from_camera_0 is not None:
            self._add_records(f"{prefix}/ground_truth", StreamKind.POSE, self._ground_truth, count=n)
        if self.velodyne_paths:
            self._add_records(f"{prefix}/velodyne/points", StreamKind.LIDAR, self._scans, count=n)

    @classmethod
    def detect(cls, path: Path) -> bool:
        path = Path(path)
        for name in ODOMETRY_CAMERA_FOLDERS[0]:
            folder = path / name
            if folder.is_dir() and any(p.suffix == ".png" and p.stem.isdigit() for p in folder.iterdir()):
                return True
        return False

    @property
    def calib_path(self) -> Path:
        return self.path / "calib.txt"

    def _camera_folders(self) -> dict[int, Path]:
        found: dict[int, Path] = {}
        for i, names in ODOMETRY_CAMERA_FOLDERS.items():
            folder = next((self.path / n for n in names if (self.path / n).is_dir()), None)
            if folder is not None:
                found[i] = folder
        if 0 not in found:
            raise InputError(self.path, "no image_0/ or image_l/ folder: not a KITTI odometry sequence")
        return found

    def _read_calib(self) -> CalibFile:
        path = self.calib_path
        if not path.is_file():
            raise InputError(path, "missing calibration: a KITTI odometry sequence needs calib.txt (P0 ... P3)")
        calib = CalibFile.read(path, ODOMETRY_CALIB_ORDER)
        # every entry of an odometry calib.txt is a 3x4 matrix: check them all, used or not
        for name in calib.entries:
            calib.matrix(name, 3, 4)
        return calib

    def _projections(self) -> dict[int, np.ndarray]:
        projections = {}
        for i, folder in self.image_dirs.items():
            if f"P{i}" not in self.calib:
                raise InputError(self.calib.path, f"missing calibration: no P{i} for the images in {folder.name}/", field=f"P{i}")
            projections[i] = self.calib.matrix(f"P{i}", 3, 4)
        return projections

    def _read_stamps(self, n: int) -> np.ndarray:
        path = self.path / "times.txt"
        if not path.is_file():
            warnings.warn(
                f"{self.path}: no times.txt; frames are given stamps 0.1 s apart from 0 (KITTI's nominal 10 Hz)",
                InputWarning,
                stacklevel=3,
            )
            return np.arange(n, dtype=np.int64) * NOMINAL_PERIOD_NS
        stamps = read_stamp_lines(path, seconds_to_ns, "frame times")
        _require_same_count(path, "times", len(stamps), f"images in {self.image_dirs[0].name}/", n)
        return stamps

    def _read_poses(self, n: int) -> Optional[np.ndarray]:
        path = self.path / "poses.txt"
        if not path.is_file():
            return None
        poses = read_kitti_poses(path)
        _require_same_count(path, "poses", len(poses), f"images in {self.image_dirs[0].name}/", n)
        return poses

    def _velodyne_paths(self, n: int) -> list[Path]:
        folder = self.path / "velodyne"
        if not folder.is_dir():
            return []
        paths = sorted(folder.glob("*.bin"))
        _require_same_count(folder, "scans", len(paths), f"images in {self.image_dirs[0].name}/", n)
        return paths

    def _ground_truth(self) -> Iterator[PoseSample]:
        assert self.world_from_camera_0 is not None
        for stamp, T in zip(self.stamps_ns.tolist(), self.world_from_camera_0):
            yield PoseSample(stamp, "world", "camera_0", T, source="ground_truth")

    def _scans(self) -> Iterator[LidarScan]:
        half_sweep_s = 0.5 * NOMINAL_PERIOD_NS * 1e-9
        for stamp, path in zip(self.stamps_ns.tolist(), self.velodyne_paths):
            xyz, reflectance = read_velodyne_bin(path)
            times = sweep_point_times_s(xyz, -half_sweep_s, 2 * half_sweep_s)
            yield LidarScan(stamp, "velodyne", xyz, intensity=reflectance, point_time_s=times)


# --- raw ------------------------------------------------------------------------------------------

class KittiRaw(FolderLayoutLog):
    """A KITTI raw drive folder (``2011_09_26_drive_0001_sync/``: image_0X/, oxts/, velodyne_points/).

    Calibration files (calib_cam_to_cam.txt, calib_velo_to_cam.txt, calib_imu_to_velo.txt) are
    looked up in the drive folder, then in its parent (the date folder, where KITTI puts them).

    Topics (prefix ``/kitti``): ``/camera_i/image`` and ``/camera_i/camera_info`` per image_0i/,
    ``/oxts/gps`` (``GpsFix``), ``/oxts/imu`` (``ImuSample``), ``/velodyne/points`` and ``/tf_static``.

    Options:
    - ``rectified``: whether images are rectified (``_sync``: intrinsics from ``P_rect_0i``, no
      distortion) or not (``_extract``: ``K_0i``, ``D_0i``); by default from the folder name.
    - ``imu_axes``: ``"body"`` (default) gives the OXTS rates ``wx wy wz`` and accelerations
      ``ax ay az``, measured in the vehicle body frame (x forward, y left, z up, turning with roll
      and pitch) -- the frame ``imu`` that calib_imu_to_velo.txt relates to the scanner, and what
      a strapdown IMU measures. ``"level"`` gives ``wf wl wu`` / ``af al au`` instead, which the
      devkit defines in the level frame (forward, left, up, rotated by heading only, parallel to
      the earth's surface); their ``frame_id`` is ``imu_level``.
    The orientation of each ``ImuSample`` is ``enu_from_imu = Rz(yaw) Ry(pitch) Rx(roll)`` (yaw 0 =
    east, counter-clockwise; pitch positive = front down; roll positive = left side up), or
    ``Rz(yaw)`` for the level frame. A GPS fix has covariance ``pos_accuracy^2`` on east, north, up.
    """

    format_name = "kitti-raw"

    def __init__(
        self,
        path: str | Path,
        *,
        lidar: bool = True,
        imu_axes: str = "body",
        rectified: Optional[bool] = None,
        topic_prefix: str = "/kitti",
    ):
        super().__init__(path)
        if imu_axes not in IMU_AXES:
            raise ValueError(f"imu_axes must be one of {sorted(IMU_AXES)}, not {imu_axes!r}")
        self.imu_axes = imu_axes
        self.rectified = (not self.path.name.endswith("_extract")) if rectified is None else rectified
        prefix = topic_prefix.rstrip("/")

        cameras = {i: self.path / f"image_{i:02d}" for i in range(4) if (self.path / f"image_{i:02d}" / "data").is_dir()}
        camera_files = {i: self._stamped_files(folder, ".png") for i, folder in cameras.items()}
        oxts = self._stamped_files(self.path / "oxts", ".txt") if (self.path / "oxts" / "data").is_dir() else None
        velodyne_dir = self.path / "velodyne_points"
        velodyne = self._stamped_files(velodyne_dir, ".bin") if lidar and (velodyne_dir / "data").is_dir() else None
        if not camera_files and oxts is None and velodyne is None:
            raise InputError(self.path, "no image_0X/data, oxts/data or velodyne_points/data folder: not a KITTI raw drive")

        stamp_arrays = [s for s, _ in camera_files.values()] + [f[0] for f in (oxts, velodyne) if f is not None]
        first = min((int(s[0]) for s in stamp_arrays if len(s)), default=0)

        cam_to_cam = self._calib("calib_cam_to_cam.txt")
        if camera_files and cam_to_cam is None:
            warnings.warn(
                f"{self.path}: no calib_cam_to_cam.txt here or in {self.path.parent}: images have no camera_info",
                InputWarning,
                stacklevel=2,
            )
        self._add_static_transforms(f"{prefix}/tf_static", self._extrinsics(first, sorted(cameras), cam_to_cam))

        for i, (stamps, paths) in sorted(camera_files.items()):
            if not paths:
                continue
            camera = f"camera_{i}"
            layout = probe_image(paths[0])
            info = self._camera_info(camera, i, layout, cam_to_cam, first) if cam_to_cam is not None else None
            self._add_camera(
                camera,
                f"{prefix}/{camera}/image",
                partial(zip, stamps.tolist(), paths),
                layout,
                info=info,
                info_topic=f"{prefix}/{camera}/camera_info",
                count=len(paths),
            )
        if oxts is not None:
            self._add_oxts(prefix, *oxts)
        if velodyne is not None:
            self._add_velodyne(prefix, *velodyne)

    @classmethod
    def detect(cls, path: Path) -> bool:
        path = Path(path)
        folders = [f"image_{i:02d}" for i in range(4)] + ["oxts", "velodyne_points"]
        return any((path / f / "timestamps.txt").is_file() and (path / f / "data").is_dir() for f in folders)

    # --- files and calibration ---------------------------------------------------------------------
    def _stamped_files(self, folder: Path, suffix: str) -> tuple[np.ndarray, list[Path]]:
        stamps_path = folder / "timestamps.txt"
        stamps = read_stamp_lines(stamps_path, kitti_datetime_ns, "timestamps")
        paths = sorted(p for p in (folder / "data").iterdir() if p.suffix == suffix)
        _require_same_count(stamps_path, "timestamps", len(stamps), f"{suffix} files in {folder.name}/data/", len(paths))
        return stamps, paths

    def _calib(self, name: str) -> Optional[CalibFile]:
        for folder in (self.path, self.path.parent):
            if (folder / name).is_file():
                return CalibFile.read(folder / name)
        return None

    def _camera_info(self, camera: str, i: int, layout: ImageLayout, cam_to_cam: CalibFile, stamp_ns: int) -> CameraInfo:
        if self.rectified:
            K = cam_to_cam.matrix(f"P_rect_{i:02d}", 3, 4)[:, :3]
            D = np.zeros(5)
        else:
            K = cam_to_cam.matrix(f"K_{i:02d}", 3, 3)
            D = cam_to_cam.numbers(f"D_{i:02d}", 5)
        return CameraInfo(camera, layout.width, layout.height, K, "plumb_bob", D, stamp_ns)

    def _extrinsics(self, stamp_ns: int, cameras: list[int], cam_to_cam: Optional[CalibFile]) -> list[FrameTransform]:
        """The tree imu -> velodyne -> camera_0 -> camera_i, as far as the calibration files go."""
        out: list[FrameTransform] = []
        imu_to_velo = self._calib("calib_imu_to_velo.txt")
        if imu_to_velo is not None:
            velodyne_from_imu = imu_to_velo.rigid("R", "T")
            out.append(FrameTransform(stamp_ns, "imu", "velodyne", invert_pose(velodyne_from_imu)))
        velo_to_cam = self._calib("calib_velo_to_cam.txt")
        if cam_to_cam is None:
            if velo_to_cam is not None and not self.rectified:
                out.append(FrameTransform(stamp_ns, "velodyne", "camera_0", invert_pose(velo_to_cam.rigid("R", "T"))))
            return out
        if self.rectified:
            # the rectified camera 0 is the unrectified one turned by R_rect_00
            rect_0_from_camera_0 = make_pose(cam_to_cam.matrix("R_rect_00", 3, 3), np.zeros(3))
            projections = {i: cam_to_cam.matrix(f"P_rect_{i:02d}", 3, 4) for i in sorted({0, *cameras})}
            camera_0_from_camera_i = camera_0_from_rectified_cameras(projections)
        else:
            rect_0_from_camera_0 = np.eye(4)
            camera_0_from_camera_i = {i: invert_pose(cam_to_cam.rigid(f"R_{i:02d}", f"T_{i:02d}")) for i in sorted({0, *cameras})}
        if velo_to_cam is not None:
            camera_0_from_velodyne = rect_0_from_camera_0 @ velo_to_cam.rigid("R", "T")
            out.append(FrameTransform(stamp_ns, "velodyne", "camera_0", invert_pose(camera_0_from_velodyne)))
        for i in cameras:
            if i != 0:
                out.append(FrameTransform(stamp_ns, "camera_0", f"camera_{i}", camera_0_from_camera_i[i]))
        return out

    # --- OXTS and Velodyne ---------------------------------------------------------------------------
    def _add_oxts(self, prefix: str, stamps: np.ndarray, paths: list[Path]) -> None:
        gps_topic, imu_topic = f"{prefix}/oxts/gps", f"{prefix}/oxts/imu"
        rate_names, accel_names, imu_frame = IMU_AXES[self.imu_axes]
        rate_idx = [_OXTS[c] for c in rate_names]
        accel_idx = [_OXTS[c] for c in accel_names]
        level = self.imu_axes == "level"

        def iterate(wanted: Wanted) -> Iterator[Message]:
            want_gps, want_imu = wanted(gps_topic), wanted(imu_topic)
            for i, (stamp, path) in enumerate(zip(stamps.tolist(), paths)):
                v = read_oxts_record(path)
                if want_gps:
                    cov = np.eye(3) * v[_OXTS["pos_accuracy"]] ** 2
                    fix = GpsFix(stamp, v[_OXTS["lat"]], v[_OXTS["lon"]], v[_OXTS["alt"]], GpsStatus.FIX, cov, frame_id="imu")
                    yield Message(gps_topic, StreamKind.GPS, i, fix)
                if want_imu:
                    # the level frame turns with heading only
                    roll, pitch = (0.0, 0.0) if level else (v[_OXTS["roll"]], v[_OXTS["pitch"]])
                    q_wxyz = matrix_to_quat_wxyz(enu_from_rpy(roll, pitch, v[_OXTS["yaw"]]))
                    yield Message(imu_topic, StreamKind.IMU, i, ImuSample(stamp, imu_frame, v[rate_idx], v[accel_idx], q_wxyz))

        n = len(paths)
        self._add([stream_info(gps_topic, StreamKind.GPS, n), stream_info(imu_topic, StreamKind.IMU, n)], iterate)

    def _add_velodyne(self, prefix: str, stamps: np.ndarray, paths: list[Path]) -> None:
        folder = self.path / "velodyne_points"
        starts = ends = None
        if (folder / "timestamps_start.txt").is_file() and (folder / "timestamps_end.txt").is_file():
            starts = read_stamp_lines(folder / "timestamps_start.txt", kitti_datetime_ns, "sweep start times")
            ends = read_stamp_lines(folder / "timestamps_end.txt", kitti_datetime_ns, "sweep end times")
            _require_same_count(folder / "timestamps_start.txt", "start times", len(starts), "scans", len(paths))
            _require_same_count(folder / "timestamps_end.txt", "end times", len(ends), "scans", len(paths))

        def scans() -> Iterator[LidarScan]:
            for i, (stamp, path) in enumerate(zip(stamps.tolist(), paths)):
                xyz, reflectance = read_velodyne_bin(path)
                times = None
                if starts is not None and ends is not None:
                    start, end = int(starts[i]), int(ends[i])
                    times = sweep_point_times_s(xyz, (start - stamp) * 1e-9, (end - start) * 1e-9)
                yield LidarScan(stamp, "velodyne", xyz, intensity=reflectance, point_time_s=times)

        self._add_records(f"{prefix}/velodyne/points", StreamKind.LIDAR, scans, count=len(paths))


def enu_from_rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """``Rz(yaw) Ry(pitch) Rx(roll)``: the OXTS orientation of a forward-left-up body in ENU."""
    return Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_matrix()


def read_oxts_record(path: Path) -> np.ndarray:
    """The 30 values of one OXTS file (one line); anything else is an error naming file and line."""
    lines = [(n, line) for n, line in enumerate(path.read_text().splitlines(), start=1) if line.strip()]
    if len(lines) != 1:
        raise InputError(path, f"holds {len(lines)} non-empty lines, expected one OXTS record", field="line 1")
    lineno, line = lines[0]
    parts = line.split()
    if len(parts) != len(OXTS_FIELDS):
        raise InputError(path, f"line {lineno} has {len(parts)} values, expected {len(OXTS_FIELDS)}", field=f"line {lineno}")
    try:
        values = np.array([float(p) for p in parts])
    except ValueError:
        raise InputError(path, f"line {lineno} has a value that is not a number: {line[:80]!r}", field=f"line {lineno}") from None
    bad = np.nonzero(~np.isfinite(values))[0]
    if len(bad):
        raise InputError(path, f"line {lineno}: {OXTS_FIELDS[bad[0]]} is not finite", field=f"line {lineno}, {OXTS_FIELDS[bad[0]]}")
    return values
