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

OXTS poses. A raw drive's OXTS records also give the INS pose of ``imu`` on ``/oxts/pose``, made
as the KITTI devkit makes it (``convertOxtsToPose.m``): position by a Mercator projection on a
sphere of radius 6378137 m whose scale is cos(latitude of the first record), so x is east and y
north in metres near the drive, z the altitude; orientation ``Rz(yaw) Ry(pitch) Rx(roll)`` of the
forward-left-up body in that east-north-up frame. By default (``oxts_origin="first_position"``)
only the translation is moved to the first record, as pykitti does: the stream's frame stays
levelled with x east and y north, so gravity and heading need no estimating, and a pose and the
GPS fix of its record share one point (the fixes' ``frame_id`` is ``imu`` too). With
``oxts_origin="first_pose"`` the first pose is the identity, as the devkit's own output.

The projection is the devkit's, not an exact tangent frame: a sphere of the equatorial radius
stands in for the WGS84 ellipsoid, so near latitude 49 deg its east scale is 0.19 % short and its
north scale 0.10 % long (a/N and a/M, N and M the ellipsoid's radii of curvature). On the real
107 m drive in ../shared/data this puts the last pose 0.19 m from the fix's exact local ENU
position; a rigid yaw fit to the fixes leaves 4.6 cm RMSE, a yaw + scale fit 2 mm.
"""

from __future__ import annotations

import calendar
import warnings
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime
from functools import partial
from pathlib import Path
from typing import Literal

import numpy as np
from scipy.spatial.transform import Rotation

from mapkit.core.errors import InputError, InputWarning
from mapkit.core.geometry import invert_pose, make_pose, matrix_to_quat_wxyz
from mapkit.core.types import (
    CameraInfo,
    FrameTransform,
    GpsFix,
    GpsStatus,
    ImuSample,
    LidarScan,
    Message,
    PoseSample,
    StreamKind,
)
from mapkit.io.folder import (
    FolderLayoutLog,
    ImageLayout,
    Wanted,
    probe_images,
    read_stamp_lines,
    seconds_to_ns,
    stream_info,
    undecodable,
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
OXTS_FIELDS = [
    "lat",
    "lon",
    "alt",
    "roll",
    "pitch",
    "yaw",
    "vn",
    "ve",
    "vf",
    "vl",
    "vu",
    "ax",
    "ay",
    "az",
    "af",
    "al",
    "au",
    "wx",
    "wy",
    "wz",
    "wf",
    "wl",
    "wu",
    "pos_accuracy",
    "vel_accuracy",
    "navstat",
    "numsats",
    "posmode",
    "velmode",
    "orimode",
]
_OXTS = {name: i for i, name in enumerate(OXTS_FIELDS)}

#: IMU axes of an OXTS record: the vehicle body (rotates with roll and pitch) or the level frame
#: (heading only, parallel to the earth's surface), as the devkit's dataformat.txt defines them
IMU_AXES = {
    "body": (("wx", "wy", "wz"), ("ax", "ay", "az"), "imu"),
    "level": (("wf", "wl", "wu"), ("af", "al", "au"), "imu_level"),
}

#: radius of the sphere the devkit's Mercator projection uses (``latlonToMercator.m``)
MERCATOR_EARTH_RADIUS_M = 6378137.0

#: origin of the OXTS pose stream, and the name of its parent frame (module docstring)
OxtsOrigin = Literal["first_position", "first_pose"]
OXTS_POSE_FRAME: dict[str, str] = {"first_position": "oxts_enu", "first_pose": "oxts_first_pose"}

#: largest departure of ``R^T R`` from the identity (max abs entry) a rotation may show. KITTI prints poses and
#: calibration with 6-7 significant digits, which leaves about 1e-7 (1.5e-7 on the real clip in ../shared/data);
#: a rotation scaled x5 departs by 24, a zero one by 1
ORTHONORMAL_TOL = 1e-3
#: fastest a pose or OXTS fix may move from the previous accepted one: 100 m/s (360 km/h) is far above what the
#: car of a drive log reaches (KITTI's poses move at most 1.2 m per 0.1 s frame on the real clip) and still
#: 100 times below a 1 km jump within 0.1 s, so one bad record is rejected, a fast drive never
MAX_SPEED_MPS = 100.0
#: how many rejected lines a warning lists by name
_LISTED = 5


# --- shared parsing ------------------------------------------------------------------------------


def _undecodable(path: Path) -> InputError:
    return undecodable(path, "KITTI writes ASCII")


def read_text(path: Path) -> str:
    """A KITTI text file's content; a byte that is not UTF-8 is an ``InputError`` naming its line."""
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise _undecodable(path) from None


@contextmanager
def decode_errors_named(path: Path) -> Iterator[None]:
    """Turns a ``UnicodeDecodeError`` raised while reading ``path`` into an ``InputError`` naming its line."""
    try:
        yield
    except UnicodeDecodeError:
        raise _undecodable(path) from None


@dataclass(frozen=True)
class CalibFile:
    """A KITTI calibration file of ``name: values`` lines, read on demand by entry."""

    path: Path
    entries: dict[str, tuple[int, str]]  # name -> (line number, value text)

    @classmethod
    def read(cls, path: Path, unlabelled: Sequence[str] = ()) -> CalibFile:
        """Lines without a ``name:`` take the names in ``unlabelled`` in order (odometry calib.txt
        files are sometimes stored without labels)."""
        entries: dict[str, tuple[int, str]] = {}
        next_unlabelled = 0
        for lineno, line in enumerate(read_text(Path(path)).splitlines(), start=1):
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
            raise InputError(
                self.path, f"line {lineno} ({name}): a value is not a number: {text[:80]!r}", field=f"line {lineno}"
            ) from None
        if len(values) != count:
            raise InputError(
                self.path, f"line {lineno} ({name}) has {len(values)} numbers, expected {count}", field=f"line {lineno}"
            )
        if not np.all(np.isfinite(values)):
            raise InputError(self.path, f"line {lineno} ({name}) has a non-finite value", field=f"line {lineno}")
        return values

    def matrix(self, name: str, rows: int, cols: int) -> np.ndarray:
        return self.numbers(name, rows * cols).reshape(rows, cols)

    def _bad(self, name: str, what: str) -> InputError:
        lineno = self.entries[name][0]
        return InputError(self.path, f"line {lineno} ({name}) {what}", field=f"line {lineno}")

    def rotation(self, name: str, R: np.ndarray | None = None) -> np.ndarray:
        """The 3x3 rotation of entry ``name`` (or ``R``, read from it), checked to be one."""
        R = self.matrix(name, 3, 3) if R is None else R
        problem = rotation_problem(R)
        if problem:
            raise self._bad(name, f"is not a rotation: {problem}")
        return R

    def rigid(self, rotation: str, translation: str) -> np.ndarray:
        """4x4 ``[R | T]`` from a 9-number rotation entry and a 3-number translation entry."""
        return make_pose(self.rotation(rotation), self.numbers(translation, 3))

    def rigid_3x4(self, name: str) -> np.ndarray:
        """4x4 pose from a 12-number ``[R | t]`` entry (odometry ``Tr``)."""
        Rt = self.matrix(name, 3, 4)
        return make_pose(self.rotation(name, Rt[:, :3]), Rt[:, 3])

    def camera_matrix(self, name: str, cols: int = 3) -> np.ndarray:
        """A projection (``cols`` 4) or intrinsic matrix (3) whose left 3x3 block is invertible with positive focal
        lengths."""
        M = self.matrix(name, 3, cols)
        K = M[:, :3]
        s = np.linalg.svd(K, compute_uv=False)
        if not s[-1] > 1e-9 * s[0]:
            raise self._bad(name, "has a singular left 3x3 block: not a camera matrix")
        if not (K[0, 0] > 0 and K[1, 1] > 0 and np.allclose(K[2], [0, 0, 1], atol=1e-6)):
            raise self._bad(
                name,
                f"is not a rectified camera matrix (fx {K[0, 0]:g}, fy {K[1, 1]:g}, last row {K[2].tolist()} "
                "should be positive, positive, [0, 0, 1])",
            )
        return M


def rotation_problem(R: np.ndarray) -> str:
    """Why ``R`` is not a rotation ("" when it is one, within ``ORTHONORMAL_TOL``)."""
    departure = float(np.abs(R.T @ R - np.eye(3)).max())
    if departure > ORTHONORMAL_TOL:
        return f"R^T R departs from the identity by {departure:.3g} (tolerance {ORTHONORMAL_TOL:g})"
    if np.linalg.det(R) < 0:
        return "it is a reflection (determinant -1)"
    return ""


def screen_poses(stamps_ns: np.ndarray, poses: np.ndarray) -> list[str]:
    """Per pose, why it is physically impossible ("" when it is not): a rotation that is not one, or a
    move from the last accepted pose faster than ``MAX_SPEED_MPS``."""
    reasons: list[str] = []
    last: tuple[int, np.ndarray] | None = None
    for stamp, T in zip(stamps_ns.tolist(), poses, strict=True):
        problem = rotation_problem(T[:3, :3])
        if not problem and last is not None:
            problem = too_fast(last[0], last[1], stamp, T[:3, 3])
        if not problem:
            last = (stamp, T[:3, 3])
        reasons.append(problem)
    return reasons


def too_fast(stamp0_ns: int, p0: np.ndarray, stamp_ns: int, p: np.ndarray) -> str:
    """Why a move from ``p0`` to ``p`` is impossible ("" when it is possible); order is checked elsewhere."""
    dt = (stamp_ns - stamp0_ns) * 1e-9
    dist = float(np.linalg.norm(np.asarray(p) - np.asarray(p0)))
    if dt > 0 and dist > MAX_SPEED_MPS * dt:
        return f"moves {dist:.4g} m in {dt:.3g} s, faster than {MAX_SPEED_MPS:g} m/s"
    return ""


def rejection_summary(path: Path, what: str, total: int, rejected: dict[str, str]) -> str:
    """One warning's text: how many of ``total`` were rejected, why, and the first few by name."""
    listed = "; ".join(f"{where}: {why}" for where, why in list(rejected.items())[:_LISTED])
    more = f"; and {len(rejected) - _LISTED} more" if len(rejected) > _LISTED else ""
    return f"{path}: {len(rejected)} of {total} {what} rejected as physically impossible and skipped: {listed}{more}"


def read_stamps(path: Path, parse: Callable[[str], int], what: str) -> np.ndarray:
    """``read_stamp_lines`` with a byte that is not text named by its line."""
    with decode_errors_named(path):
        return read_stamp_lines(path, parse, what)


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
    t = {
        i: np.linalg.solve(P[:, :3], P[:, 3]) for i, P in projections.items()
    }  # P[:, :3] checked invertible on reading
    t0 = t.get(0, np.zeros(3))
    return {i: make_pose(np.eye(3), t0 - ti) for i, ti in t.items()}


def read_velodyne_bin(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(xyz (N, 3) float32, reflectance (N,)) of a KITTI scan; non-finite points are dropped."""
    raw = np.fromfile(path, dtype="<f4")
    if raw.size % 4:
        raise InputError(
            path, f"{raw.size * 4} bytes is not a whole number of 16-byte points (x, y, z, reflectance as float32)"
        )
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


def _holds_numbered(folder: Path, suffix: str) -> bool:
    """Whether ``folder`` holds a file named like KITTI's frames (``000000.png``, ``000000.bin``)."""
    return folder.is_dir() and any(p.suffix == suffix and p.stem.isdigit() for p in folder.iterdir())


def _require_same_count(path: Path, what: str, n: int, other: str, m: int) -> None:
    if n != m:
        raise InputError(path, f"{n} {what} but {m} {other}; the counts must agree")


# --- odometry -------------------------------------------------------------------------------------


class KittiOdometry(FolderLayoutLog):
    """A KITTI odometry sequence folder: camera folders (``image_0/`` or ``image_l/``, ...), or
    ``velodyne/`` scans alone (the odometry LiDAR download, SemanticKITTI), with ``calib.txt``.

    Topics (prefix ``/kitti``): ``/camera_i/image`` and ``/camera_i/camera_info`` per camera folder,
    ``/ground_truth`` (when ``poses.txt`` exists: ``world_from_camera_0``, where world is camera 0 at
    the first frame), ``/velodyne/points`` (with ``velodyne/``) and ``/tf_static``. Stamps come from
    ``times.txt``; without it, frames are 0.1 s apart from 0, with one ``InputWarning`` saying so.
    Every file lists one entry per frame: images of each camera, scans, times and poses must agree
    in number. ``calib.txt`` is required with images (their intrinsics); a LiDAR-only folder reads
    without it, but its ``poses.txt`` (of camera 0) then has no ``Tr`` to relate it to the scanner,
    and a warning says so.
    """

    format_name = "kitti-odometry"

    def __init__(self, path: str | Path, *, lidar: bool = True, topic_prefix: str = "/kitti"):
        super().__init__(path)
        prefix = topic_prefix.rstrip("/")
        self._gt_topic = f"{prefix}/ground_truth"
        self.image_dirs = self._camera_folders()
        image_paths = {i: sorted(p for p in d.iterdir() if p.suffix == ".png") for i, d in self.image_dirs.items()}
        scan_dir = self.path / "velodyne"
        scan_paths = sorted(scan_dir.glob("*.bin")) if lidar and scan_dir.is_dir() else []
        if self.image_dirs:
            n = len(image_paths[0])
            first_folder = self.image_dirs[0].name
            self._frames_what = f"images in {first_folder}/"
            if n == 0:
                raise InputError(self.image_dirs[0], "holds no .png images")
            for i, paths in image_paths.items():
                folder = self.image_dirs[i]
                _require_same_count(folder, f"images in {folder.name}/", len(paths), f"in {first_folder}/", n)
            if scan_paths:
                _require_same_count(scan_dir, "scans", len(scan_paths), self._frames_what, n)
        elif scan_paths:
            n = len(scan_paths)
            self._frames_what = "scans in velodyne/"
        else:
            what = "and lidar=False" if not lidar and _holds_numbered(scan_dir, ".bin") else "or velodyne/*.bin"
            raise InputError(
                self.path, f"no image_0/ or image_l/ folder {what}: nothing to read as a KITTI odometry sequence"
            )

        self.calib = self._read_calib()
        self.projections = self._projections()
        self.stamps_ns = self._read_stamps(n)
        #: which poses of poses.txt passed ``screen_poses`` (the others are not read)
        self.pose_accepted = np.ones(n, dtype=bool)
        self.world_from_camera_0 = self._read_poses(n)
        self.velodyne_paths = scan_paths

        first = int(self.stamps_ns[0])
        transforms = [
            FrameTransform(first, "camera_0", f"camera_{i}", T)
            for i, T in sorted(camera_0_from_rectified_cameras(self.projections).items())
            if i != 0 and i in self.image_dirs
        ]
        if self.calib is not None and "Tr" in self.calib:
            transforms.append(FrameTransform(first, "camera_0", "velodyne", self.calib.rigid_3x4("Tr")))
        elif self.velodyne_paths and self.world_from_camera_0 is not None:
            warnings.warn(
                f"{self.path}: no Tr in {'calib.txt' if self.calib is not None else 'a calib.txt (there is none)'}: "
                "the ground truth of poses.txt (camera 0) is not related to the velodyne frame",
                InputWarning,
                stacklevel=2,
            )
        self._add_static_transforms(f"{prefix}/tf_static", transforms)

        stamps = self.stamps_ns.tolist()
        for i in sorted(self.image_dirs):
            camera = f"camera_{i}"
            layout = probe_images(image_paths[i])
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
            self._add_records(self._gt_topic, StreamKind.POSE, self._ground_truth, count=int(self.pose_accepted.sum()))
        if self.velodyne_paths:
            self._add_records(f"{prefix}/velodyne/points", StreamKind.LIDAR, self._scans, count=n)

    @classmethod
    def detect(cls, path: Path) -> bool:
        path = Path(path)
        cameras = (path / name for name in ODOMETRY_CAMERA_FOLDERS[0])
        return any(_holds_numbered(folder, ".png") for folder in cameras) or _holds_numbered(path / "velodyne", ".bin")

    @property
    def calib_path(self) -> Path:
        return self.path / "calib.txt"

    def _camera_folders(self) -> dict[int, Path]:
        """Camera index -> its folder; a sequence with cameras must have camera 0's."""
        found: dict[int, Path] = {}
        for i, names in ODOMETRY_CAMERA_FOLDERS.items():
            folder = next((self.path / n for n in names if (self.path / n).is_dir()), None)
            if folder is not None:
                found[i] = folder
        if found and 0 not in found:
            listed = ", ".join(f"{f.name}/" for f in found.values())
            raise InputError(
                self.path, f"has {listed} but no image_0/ or image_l/ folder: not a KITTI odometry sequence"
            )
        return found

    def _read_calib(self) -> CalibFile | None:
        path = self.calib_path
        if not path.is_file():
            if not self.image_dirs:
                return None
            raise InputError(path, "missing calibration: a KITTI odometry sequence needs calib.txt (P0 ... P3)")
        calib = CalibFile.read(path, ODOMETRY_CALIB_ORDER)
        # every entry of an odometry calib.txt is a 3x4 matrix: check them all, used or not
        for name in calib.entries:
            calib.matrix(name, 3, 4)
        return calib

    def _projections(self) -> dict[int, np.ndarray]:
        projections = {}
        for i, folder in self.image_dirs.items():
            assert self.calib is not None  # required with images
            if f"P{i}" not in self.calib:
                raise InputError(
                    self.calib.path, f"missing calibration: no P{i} for the images in {folder.name}/", field=f"P{i}"
                )
            projections[i] = self.calib.camera_matrix(f"P{i}", 4)
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
        stamps = read_stamps(path, seconds_to_ns, "frame times")
        _require_same_count(path, "times", len(stamps), self._frames_what, n)
        return stamps

    def _read_poses(self, n: int) -> np.ndarray | None:
        path = self.path / "poses.txt"
        if not path.is_file():
            return None
        with decode_errors_named(path):
            poses = read_kitti_poses(path)
            # read_kitti_poses skips blank and comment lines: the line number of each pose, for messages
            linenos = [
                k
                for k, line in enumerate(read_text(path).splitlines(), start=1)
                if line.strip() and not line.strip().startswith("#")
            ]
        _require_same_count(path, "poses", len(poses), self._frames_what, n)
        reasons = screen_poses(self.stamps_ns, poses)
        self.pose_accepted = np.array([not r for r in reasons], dtype=bool)
        rejected = {f"line {k}": r for k, r in zip(linenos, reasons, strict=True) if r}
        if rejected:
            self.skipped[(self._gt_topic, "physically impossible pose")] += len(rejected)
            warnings.warn(rejection_summary(path, "poses", len(poses), rejected), InputWarning, stacklevel=3)
        return poses

    def _ground_truth(self) -> Iterator[PoseSample]:
        assert self.world_from_camera_0 is not None
        for stamp, T, ok in zip(self.stamps_ns.tolist(), self.world_from_camera_0, self.pose_accepted, strict=True):
            if ok:
                yield PoseSample(stamp, "world", "camera_0", T, source="ground_truth")

    def _scans(self) -> Iterator[LidarScan]:
        half_sweep_s = 0.5 * NOMINAL_PERIOD_NS * 1e-9
        for stamp, path in zip(self.stamps_ns.tolist(), self.velodyne_paths, strict=True):
            xyz, reflectance = read_velodyne_bin(path)
            times = sweep_point_times_s(xyz, -half_sweep_s, 2 * half_sweep_s)
            yield LidarScan(stamp, "velodyne", xyz, intensity=reflectance, point_time_s=times)


# --- raw ------------------------------------------------------------------------------------------


class KittiRaw(FolderLayoutLog):
    """A KITTI raw drive folder (``2011_09_26_drive_0001_sync/``: image_0X/, oxts/, velodyne_points/).

    Calibration files (calib_cam_to_cam.txt, calib_velo_to_cam.txt, calib_imu_to_velo.txt) are
    looked up in the drive folder, then in its parent (the date folder, where KITTI puts them).

    Topics (prefix ``/kitti``): ``/camera_i/image`` and ``/camera_i/camera_info`` per image_0i/,
    ``/oxts/gps`` (``GpsFix``), ``/oxts/imu`` (``ImuSample``), ``/oxts/pose`` (``PoseSample`` of
    ``imu``, source ``ins``; see the module docstring), ``/velodyne/points`` and ``/tf_static``.
    A drive with OXTS only thus has a pose stream for the trajectory stage (``source: poses``, which
    ``auto`` picks when there is no LiDAR) and for evaluation as ground truth.

    Options:
    - ``rectified``: whether images are rectified (``_sync``: intrinsics from ``P_rect_0i``, no
      distortion) or not (``_extract``: ``K_0i``, ``D_0i``); by default from the folder name.
    - ``imu_axes``: ``"body"`` (default) gives the OXTS rates ``wx wy wz`` and accelerations
      ``ax ay az``, measured in the vehicle body frame (x forward, y left, z up, turning with roll
      and pitch) -- the frame ``imu`` that calib_imu_to_velo.txt relates to the scanner, and what
      a strapdown IMU measures. ``"level"`` gives ``wf wl wu`` / ``af al au`` instead, which the
      devkit defines in the level frame (forward, left, up, rotated by heading only, parallel to
      the earth's surface); their ``frame_id`` is ``imu_level``.
    - ``oxts_origin``: ``"first_position"`` (default) gives ``oxts_enu_from_imu``, the devkit's
      Mercator pose with the first record's position subtracted: a levelled frame, x east, y north,
      as pykitti gives it; the default because heading and gravity then need no estimating, and a
      pose and the GPS fix of its record locate one point, the OXTS unit. ``"first_pose"`` gives
      ``oxts_first_pose_from_imu``, the devkit's ``convertOxtsToPose`` (the first pose is the
      identity, its frame the OXTS body at the first record).
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
        oxts_origin: OxtsOrigin = "first_position",
        rectified: bool | None = None,
        topic_prefix: str = "/kitti",
    ):
        super().__init__(path)
        if imu_axes not in IMU_AXES:
            raise ValueError(f"imu_axes must be one of {sorted(IMU_AXES)}, not {imu_axes!r}")
        if oxts_origin not in OXTS_POSE_FRAME:
            raise ValueError(f"oxts_origin must be one of {sorted(OXTS_POSE_FRAME)}, not {oxts_origin!r}")
        self.imu_axes = imu_axes
        self.oxts_origin = oxts_origin
        self.rectified = (not self.path.name.endswith("_extract")) if rectified is None else rectified
        prefix = topic_prefix.rstrip("/")

        cameras = {
            i: self.path / f"image_{i:02d}" for i in range(4) if (self.path / f"image_{i:02d}" / "data").is_dir()
        }
        camera_files = {i: self._stamped_files(folder, ".png") for i, folder in cameras.items()}
        oxts = self._stamped_files(self.path / "oxts", ".txt") if (self.path / "oxts" / "data").is_dir() else None
        velodyne_dir = self.path / "velodyne_points"
        velodyne = self._stamped_files(velodyne_dir, ".bin") if lidar and (velodyne_dir / "data").is_dir() else None
        if not camera_files and oxts is None and velodyne is None:
            raise InputError(
                self.path, "no image_0X/data, oxts/data or velodyne_points/data folder: not a KITTI raw drive"
            )

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
            layout = probe_images(paths)
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
        stamps = read_stamps(stamps_path, kitti_datetime_ns, "timestamps")
        paths = sorted(p for p in (folder / "data").iterdir() if p.suffix == suffix)
        _require_same_count(
            stamps_path, "timestamps", len(stamps), f"{suffix} files in {folder.name}/data/", len(paths)
        )
        return stamps, paths

    def _calib(self, name: str) -> CalibFile | None:
        for folder in (self.path, self.path.parent):
            if (folder / name).is_file():
                return CalibFile.read(folder / name)
        return None

    def _camera_info(
        self, camera: str, i: int, layout: ImageLayout, cam_to_cam: CalibFile, stamp_ns: int
    ) -> CameraInfo:
        if self.rectified:
            K = cam_to_cam.camera_matrix(f"P_rect_{i:02d}", 4)[:, :3]
            D = np.zeros(5)
        else:
            K = cam_to_cam.camera_matrix(f"K_{i:02d}")
            D = cam_to_cam.numbers(f"D_{i:02d}", 5)
        return CameraInfo(camera, layout.width, layout.height, K, "plumb_bob", D, stamp_ns)

    def _extrinsics(self, stamp_ns: int, cameras: list[int], cam_to_cam: CalibFile | None) -> list[FrameTransform]:
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
            rect_0_from_camera_0 = make_pose(cam_to_cam.rotation("R_rect_00"), np.zeros(3))
            projections = {i: cam_to_cam.camera_matrix(f"P_rect_{i:02d}", 4) for i in sorted({0, *cameras})}
            camera_0_from_camera_i = camera_0_from_rectified_cameras(projections)
        else:
            rect_0_from_camera_0 = np.eye(4)
            camera_0_from_camera_i = {
                i: invert_pose(cam_to_cam.rigid(f"R_{i:02d}", f"T_{i:02d}")) for i in sorted({0, *cameras})
            }
        if velo_to_cam is not None:
            camera_0_from_velodyne = rect_0_from_camera_0 @ velo_to_cam.rigid("R", "T")
            out.append(FrameTransform(stamp_ns, "velodyne", "camera_0", invert_pose(camera_0_from_velodyne)))
        for i in cameras:
            if i != 0:
                out.append(FrameTransform(stamp_ns, "camera_0", f"camera_{i}", camera_0_from_camera_i[i]))
        return out

    # --- OXTS and Velodyne ---------------------------------------------------------------------------
    def _add_oxts(self, prefix: str, stamps: np.ndarray, paths: list[Path]) -> None:
        gps_topic, imu_topic, pose_topic = f"{prefix}/oxts/gps", f"{prefix}/oxts/imu", f"{prefix}/oxts/pose"
        rate_names, accel_names, imu_frame = IMU_AXES[self.imu_axes]
        rate_idx = [_OXTS[c] for c in rate_names]
        accel_idx = [_OXTS[c] for c in accel_names]
        level = self.imu_axes == "level"
        pose_frame = OXTS_POSE_FRAME[self.oxts_origin]

        def iterate(wanted: Wanted) -> Iterator[Message]:
            want_gps, want_imu, want_pose = wanted(gps_topic), wanted(imu_topic), wanted(pose_topic)
            scale, origin_from_mercator = 1.0, np.eye(4)
            last: tuple[int, np.ndarray] | None = None  # stamp and position of the last accepted record
            rejected: dict[str, str] = {}
            for i, (stamp, path) in enumerate(zip(stamps.tolist(), paths, strict=True)):
                v = read_oxts_record(path)
                problem = oxts_problem(v)
                if not problem:
                    if last is None:  # the devkit's scale and origin both come from the first (accepted) record
                        scale = mercator_scale(v[_OXTS["lat"]])
                    mercator = mercator_from_imu(v, scale)
                    problem = "" if last is None else too_fast(*last, stamp, mercator[:3, 3])
                if problem:
                    rejected[f"{path.name} line 1"] = problem
                    for topic in (
                        t for t, w in ((gps_topic, want_gps), (imu_topic, want_imu), (pose_topic, want_pose)) if w
                    ):
                        self.skipped[(topic, "physically impossible OXTS record")] += 1
                    continue
                if last is None:
                    origin_from_mercator = self._origin_from_mercator(mercator)
                last = (stamp, mercator[:3, 3])
                if want_pose:
                    pose = PoseSample(stamp, pose_frame, "imu", origin_from_mercator @ mercator, source="ins")
                    yield Message(pose_topic, StreamKind.POSE, i, pose)
                if want_gps:
                    cov = np.eye(3) * v[_OXTS["pos_accuracy"]] ** 2
                    fix = GpsFix(
                        stamp, v[_OXTS["lat"]], v[_OXTS["lon"]], v[_OXTS["alt"]], GpsStatus.FIX, cov, frame_id="imu"
                    )
                    yield Message(gps_topic, StreamKind.GPS, i, fix)
                if want_imu:
                    # the level frame turns with heading only
                    roll, pitch = (0.0, 0.0) if level else (v[_OXTS["roll"]], v[_OXTS["pitch"]])
                    q_wxyz = matrix_to_quat_wxyz(enu_from_rpy(roll, pitch, v[_OXTS["yaw"]]))
                    yield Message(
                        imu_topic, StreamKind.IMU, i, ImuSample(stamp, imu_frame, v[rate_idx], v[accel_idx], q_wxyz)
                    )
            if rejected:
                warnings.warn(
                    rejection_summary(paths[0].parent, "OXTS records", len(paths), rejected), InputWarning, stacklevel=2
                )

        n = len(paths)
        kinds = {gps_topic: StreamKind.GPS, imu_topic: StreamKind.IMU, pose_topic: StreamKind.POSE}
        self._add([stream_info(topic, kind, n) for topic, kind in kinds.items()], iterate)

    def _origin_from_mercator(self, mercator_from_first: np.ndarray) -> np.ndarray:
        """The pose stream's frame from the devkit's Mercator frame, given the first record's pose (``oxts_origin``)."""
        if self.oxts_origin == "first_pose":
            return invert_pose(mercator_from_first)
        return make_pose(np.eye(3), -mercator_from_first[:3, 3])

    def _add_velodyne(self, prefix: str, stamps: np.ndarray, paths: list[Path]) -> None:
        folder = self.path / "velodyne_points"
        starts = ends = None
        if (folder / "timestamps_start.txt").is_file() and (folder / "timestamps_end.txt").is_file():
            starts = read_stamps(folder / "timestamps_start.txt", kitti_datetime_ns, "sweep start times")
            ends = read_stamps(folder / "timestamps_end.txt", kitti_datetime_ns, "sweep end times")
            _require_same_count(folder / "timestamps_start.txt", "start times", len(starts), "scans", len(paths))
            _require_same_count(folder / "timestamps_end.txt", "end times", len(ends), "scans", len(paths))

        def scans() -> Iterator[LidarScan]:
            for i, (stamp, path) in enumerate(zip(stamps.tolist(), paths, strict=True)):
                xyz, reflectance = read_velodyne_bin(path)
                times = None
                if starts is not None and ends is not None:
                    start, end = int(starts[i]), int(ends[i])
                    times = sweep_point_times_s(xyz, (start - stamp) * 1e-9, (end - start) * 1e-9)
                yield LidarScan(stamp, "velodyne", xyz, intensity=reflectance, point_time_s=times)

        self._add_records(f"{prefix}/velodyne/points", StreamKind.LIDAR, scans, count=len(paths))


def enu_from_rpy(roll: float | np.ndarray, pitch: float | np.ndarray, yaw: float | np.ndarray) -> np.ndarray:
    """``Rz(yaw) Ry(pitch) Rx(roll)``: the OXTS orientation(s) of a forward-left-up body in ENU."""
    return Rotation.from_euler("ZYX", np.stack(np.broadcast_arrays(yaw, pitch, roll), axis=-1)).as_matrix()


def mercator_scale(lat0_deg: float) -> float:
    """The devkit's Mercator scale (``latToScale.m``): cos of the first record's latitude."""
    return float(np.cos(np.radians(lat0_deg)))


def mercator_from_imu(oxts: np.ndarray, scale: float) -> np.ndarray:
    """(..., 4, 4) poses of the OXTS body in the devkit's frame from (..., 30) OXTS records.

    Position (``latlonToMercator.m``): x = s r lon, y = s r ln(tan(pi/4 + lat/2)) with s = ``scale``
    and r = 6378137 m, z = altitude; x is east and y north, in metres where the latitude is near the
    one ``scale`` was made from. Orientation: ``Rz(yaw) Ry(pitch) Rx(roll)`` (``enu_from_rpy``).
    """
    v = np.asarray(oxts, np.float64)
    lat, lon = np.radians(v[..., _OXTS["lat"]]), np.radians(v[..., _OXTS["lon"]])
    r = scale * MERCATOR_EARTH_RADIUS_M
    t = np.stack([r * lon, r * np.log(np.tan(np.pi / 4 + lat / 2)), v[..., _OXTS["alt"]]], axis=-1)
    return make_pose(enu_from_rpy(v[..., _OXTS["roll"]], v[..., _OXTS["pitch"]], v[..., _OXTS["yaw"]]), t)


def oxts_problem(v: np.ndarray) -> str:
    """Why an OXTS record cannot be a real one ("" when it can): latitude, longitude or an angle out of range."""
    lat, lon = v[_OXTS["lat"]], v[_OXTS["lon"]]
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
        return f"latitude {lat:g}, longitude {lon:g} out of range"
    angles = np.abs(v[[_OXTS["roll"], _OXTS["pitch"], _OXTS["yaw"]]])
    if angles.max() > 2 * np.pi:  # the devkit gives radians in [-pi, pi]
        return f"roll, pitch, yaw {v[_OXTS['roll']]:g}, {v[_OXTS['pitch']]:g}, {v[_OXTS['yaw']]:g} rad out of range"
    return ""


def read_oxts_record(path: Path) -> np.ndarray:
    """The 30 values of one OXTS file (one line); anything else is an error naming file and line."""
    lines = [(n, line) for n, line in enumerate(read_text(path).splitlines(), start=1) if line.strip()]
    if len(lines) != 1:
        raise InputError(path, f"holds {len(lines)} non-empty lines, expected one OXTS record", field="line 1")
    lineno, line = lines[0]
    parts = line.split()
    if len(parts) != len(OXTS_FIELDS):
        raise InputError(
            path, f"line {lineno} has {len(parts)} values, expected {len(OXTS_FIELDS)}", field=f"line {lineno}"
        )
    try:
        values = np.array([float(p) for p in parts])
    except ValueError:
        raise InputError(
            path, f"line {lineno} has a value that is not a number: {line[:80]!r}", field=f"line {lineno}"
        ) from None
    bad = np.nonzero(~np.isfinite(values))[0]
    if len(bad):
        raise InputError(
            path, f"line {lineno}: {OXTS_FIELDS[bad[0]]} is not finite", field=f"line {lineno}, {OXTS_FIELDS[bad[0]]}"
        )
    return values
