"""Oxford RobotCar drives (Maddern, Pascoe, Linegar, Newman, IJRR 2017), as the dataset unpacks.

Layout (every part optional, but a drive needs a camera or GPS/INS)::

    <drive>/stereo.timestamps, mono_left.timestamps, ...   "timestamp_us chunk" per line
    <drive>/stereo/centre|left|right/<timestamp_us>.png     Bayer GBRG
    <drive>/mono_left|mono_right|mono_rear/<timestamp_us>.png  Bayer RGGB
    <drive>/gps/gps.csv, gps/ins.csv, vo/vo.csv
    <drive>/lms_front|lms_rear|ldmrs/<timestamp_us>.bin, velodyne_left|velodyne_right/<timestamp_us>.bin

Stamps are microseconds in the files and integer nanoseconds here. CSV files stream row by row.

Frames. RobotCar's vehicle and sensor frames are x forward, y right, z down (its extrinsics put
the left Velodyne at negative y and the roof sensors at negative z); its INS reports roll, pitch
and yaw of that body in north-east-down (NED), composed ``Rz(yaw) Ry(pitch) Rx(roll)``. mapkit
uses x forward, y left, z up bodies in east-north-up worlds, so this reader converts:

- INS (``/robotcar/ins/pose``, source ``ins``): ``utm_local_from_ins`` where ``utm_local`` has
  x = easting - e0, y = northing - n0, z = up - up0 (up = -down) with (e0, n0, up0) the first INS
  row (see ``ins_origin()``), and ``ins`` is the INS body turned to forward-left-up::

      R = Rz(gamma) @ ENU_FROM_NED @ [Rz(yaw) Ry(pitch) Rx(roll)] @ FRD_FROM_FLU

  ``ENU_FROM_NED`` swaps x and y and negates z; ``FRD_FROM_FLU = diag(1, -1, -1)``. The INS
  heading is from true north while x/y are UTM grid axes, which differ by the meridian
  convergence ``gamma = atan(tan(lon - lon0) sin(lat))`` (about 1.4 degrees in Oxford): without
  ``Rz(gamma)`` the heading would disagree with the direction of travel in the grid. The SDK
  ignores it; pass ``grid_convergence=False`` to do the same.
- VO (``/robotcar/vo/odometry``, source ``odometry``): each row is ``destination_from_source``
  (source = the newer stereo frame) in the x-forward, y-right, z-down vehicle frame, as the SDK
  chains them. Poses are accumulated from identity at the first row's destination time and turned
  to forward-left-up: ``vo_origin_from_vehicle = FLU_FROM_FRD @ T_frd @ FRD_FROM_FLU``.
- GPS (``/robotcar/gps/fix``): covariance ``diag(longitude_sigma, latitude_sigma, altitude_sigma)^2``
  on east, north, up.

``ins_status`` and ``num_satellites`` are not interpreted: every row becomes a record, and the
records do not carry them.

Images: single-channel 8-bit PNGs are demosaiced with OpenCV (GBRG for stereo, RGGB for mono) to
``bgr8``; colour PNGs pass unchanged; ``demosaic=False`` keeps single-channel images as ``mono8``.
Images listed in a timestamps file but not on disk (chunks not downloaded) are skipped with a
warning. Raw Velodyne ``.png`` scans are not decoded (a warning says so); use the ``.bin`` scans.
"""

from __future__ import annotations

import re
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import partial
from itertools import islice
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from mapkit.core.errors import InputError, InputWarning
from mapkit.core.geometry import make_pose, yaw_rotation
from mapkit.core.types import GpsFix, GpsStatus, LidarScan, PoseSample, StreamKind
from mapkit.io.folder import MAX_STAMP_NS, CsvRow, CsvTable, FolderLayoutLog, ImageConvert, probe_images

#: name, image folder, timestamps file, OpenCV conversion of its Bayer pattern (SDK image.py)
CAMERAS: tuple[tuple[str, str, str, int], ...] = (
    ("stereo_centre", "stereo/centre", "stereo.timestamps", cv2.COLOR_BayerGBRG2BGR),
    ("stereo_left", "stereo/left", "stereo.timestamps", cv2.COLOR_BayerGBRG2BGR),
    ("stereo_right", "stereo/right", "stereo.timestamps", cv2.COLOR_BayerGBRG2BGR),
    ("mono_left", "mono_left", "mono_left.timestamps", cv2.COLOR_BayerRGGB2BGR),
    ("mono_right", "mono_right", "mono_right.timestamps", cv2.COLOR_BayerRGGB2BGR),
    ("mono_rear", "mono_rear", "mono_rear.timestamps", cv2.COLOR_BayerRGGB2BGR),
)

#: name (= folder and frame), binary layout
LIDARS: tuple[tuple[str, str], ...] = (
    ("lms_front", "lms"),
    ("lms_rear", "lms"),
    ("ldmrs", "ldmrs"),
    ("velodyne_left", "velodyne"),
    ("velodyne_right", "velodyne"),
)

GPS_COLUMNS = ("timestamp", "latitude", "longitude", "altitude", "latitude_sigma", "longitude_sigma", "altitude_sigma")
INS_COLUMNS = ("timestamp", "latitude", "longitude", "northing", "easting", "down", "utm_zone", "roll", "pitch", "yaw")
VO_COLUMNS = ("source_timestamp", "destination_timestamp", "x", "y", "z", "roll", "pitch", "yaw")

FRD_FROM_FLU = np.diag([1.0, -1.0, -1.0, 1.0])  # its own inverse: also FLU_FROM_FRD
ENU_FROM_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])

_CHUNK_ROWS = 1024  # rows turned into poses at once: vectorised, yet streaming
_UTM_ZONE = re.compile(r"^(\d{1,2})([C-HJ-NP-X])?$")


@dataclass(frozen=True)
class UtmOrigin:
    """Where ``utm_local`` starts: the first INS row, in its UTM zone (WGS84)."""

    epsg: int
    easting_m: float
    northing_m: float
    up_m: float

    @property
    def zone(self) -> int:
        return self.epsg % 100


def rotation_from_rpy(roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """RobotCar's Euler angles (SDK ``euler_to_so3``): ``Rz(yaw) Ry(pitch) Rx(roll)``, (N, 3, 3)."""
    return Rotation.from_euler("ZYX", np.stack([yaw, pitch, roll], axis=-1)).as_matrix()


def grid_convergence_rad(lat_deg: np.ndarray, lon_deg: np.ndarray, zone: int) -> np.ndarray:
    """Angle from UTM grid north to true north, counter-clockwise (spherical formula, < 1e-5 deg off)."""
    central_meridian_deg = 6.0 * zone - 183.0
    dlon = np.radians(np.asarray(lon_deg) - central_meridian_deg)
    return np.arctan(np.tan(dlon) * np.sin(np.radians(lat_deg)))


def utm_local_from_ins(
    east_north_up_m: np.ndarray,
    roll: np.ndarray,
    pitch: np.ndarray,
    yaw: np.ndarray,
    convergence_rad: np.ndarray,
    origin_enu_m: np.ndarray,
) -> np.ndarray:
    """(N, 4, 4) poses of the forward-left-up INS body in the local UTM frame (module docstring)."""
    R = yaw_rotation(convergence_rad) @ ENU_FROM_NED @ rotation_from_rpy(roll, pitch, yaw) @ FRD_FROM_FLU[:3, :3]
    return make_pose(R, east_north_up_m - origin_enu_m)


def _chunks(rows: Iterator[CsvRow], size: int = _CHUNK_ROWS) -> Iterator[list[CsvRow]]:
    while chunk := list(islice(rows, size)):
        yield chunk


def _utm_zone(row: CsvRow) -> int:
    match = _UTM_ZONE.match(row.text("utm_zone"))
    if match is None or not 1 <= int(match.group(1)) <= 60:
        raise row.error("utm_zone", f"{row.text('utm_zone')!r} is not a UTM zone like '30U'")
    return int(match.group(1))


def _stamp_ns(row: CsvRow, column: str) -> int:
    return row.stamp_ns(column, 1000)


def _microseconds(text: str) -> int | None:
    """A RobotCar stamp (ASCII digits, microseconds) as int64 ns; None when ``text`` is not one."""
    if not (text.isascii() and text.isdigit()) or len(text) > 19:
        return None
    stamp = int(text) * 1000
    return stamp if stamp <= MAX_STAMP_NS else None


def _read_lidar(path: Path, layout: str) -> tuple[np.ndarray, np.ndarray | None]:
    """(xyz, reflectance) of one RobotCar scan file (SDK build_pointcloud.py and velodyne.py)."""
    if layout == "velodyne":
        raw = np.fromfile(path, dtype="<f4")
        if raw.size % 4:
            raise InputError(path, f"{raw.size * 4} bytes is not a whole number of Velodyne points (4 float32 each)")
        planes = raw.reshape(4, -1)  # stored as planes x..., y..., z..., intensity...
        xyz, reflectance = planes[:3].T, planes[3]
    else:
        raw = np.fromfile(path, dtype="<f8")
        if raw.size % 3:
            raise InputError(path, f"{raw.size * 8} bytes is not a whole number of {layout} points (3 float64 each)")
        rows = raw.reshape(-1, 3)
        if layout == "lms":  # a 2D scanner: (x, y, reflectance) in its scan plane
            xyz = np.column_stack([rows[:, 0], rows[:, 1], np.zeros(len(rows))])
            reflectance = rows[:, 2]
        else:
            xyz, reflectance = rows, None
    valid = np.isfinite(xyz).all(axis=1)
    if not valid.all():
        xyz = xyz[valid]
        reflectance = None if reflectance is None else reflectance[valid]
    return np.ascontiguousarray(xyz), None if reflectance is None else np.ascontiguousarray(reflectance)


class RobotCar(FolderLayoutLog):
    """An Oxford RobotCar drive folder; frame conventions in the module docstring.

    Topics (prefix ``/robotcar``): ``/<camera>/image`` (stereo_centre, stereo_left, stereo_right,
    mono_left, mono_right, mono_rear), ``/gps/fix``, ``/ins/pose``, ``/vo/odometry`` and
    ``/<lidar>/points`` (lms_front, lms_rear, ldmrs, velodyne_left, velodyne_right), each only
    where its files exist.
    """

    format_name = "robotcar"

    def __init__(
        self, path: str | Path, *, demosaic: bool = True, grid_convergence: bool = True, topic_prefix: str = "/robotcar"
    ):
        super().__init__(path)
        prefix = topic_prefix.rstrip("/")
        self.grid_convergence = grid_convergence
        self.cameras: list[str] = []
        for name, folder, stamps_file, bayer in CAMERAS:
            convert = partial(_demosaic, code=bayer) if demosaic else None
            if self._add_robotcar_camera(prefix, name, self.path / folder, self.path / stamps_file, convert):
                self.cameras.append(name)

        gps, ins, vo = self.path / "gps" / "gps.csv", self.path / "gps" / "ins.csv", self.path / "vo" / "vo.csv"
        self.gps_table = CsvTable(gps, GPS_COLUMNS) if gps.is_file() else None
        self.ins_table = CsvTable(ins, INS_COLUMNS) if ins.is_file() else None
        self.vo_table = CsvTable(vo, VO_COLUMNS) if vo.is_file() else None
        if not self.cameras and self.gps_table is None and self.ins_table is None:
            raise InputError(
                self.path,
                "no camera images (stereo/centre, mono_left, ...) and no gps/gps.csv or gps/ins.csv: nothing to read",
            )
        if self.gps_table is not None:
            self._add_records(f"{prefix}/gps/fix", StreamKind.GPS, self._gps_fixes)
        if self.ins_table is not None:
            self._add_records(f"{prefix}/ins/pose", StreamKind.POSE, self._ins_poses)
        if self.vo_table is not None:
            self._add_records(f"{prefix}/vo/odometry", StreamKind.POSE, self._vo_poses)
        for name, layout in LIDARS:
            self._add_lidar(prefix, name, layout)

    @classmethod
    def detect(cls, path: Path) -> bool:
        path = Path(path)
        markers = [stamps for _, _, stamps, _ in CAMERAS] + [folder for _, folder, _, _ in CAMERAS]
        markers += ["gps/gps.csv", "gps/ins.csv", "vo/vo.csv"]
        return path.is_dir() and any((path / m).exists() for m in markers)

    # --- sensors stored as one file per stamp --------------------------------------------------------
    def _stamped_files(
        self, topic: str, folder: Path, stamps_file: Path, suffix: str
    ) -> Callable[[], Iterator[tuple[int, Path]]]:
        """(stamp ns, path) of each file: from the timestamps file if there is one, else the folder."""

        def listed() -> Iterator[tuple[int, Path]]:
            for lineno, raw in enumerate(stamps_file.read_bytes().splitlines(), start=1):
                line = raw.decode("utf-8", "replace")
                parts = line.split()
                if not parts:
                    continue
                stamp = _microseconds(parts[0])
                if len(parts) > 2 or stamp is None:
                    what = f"line {lineno} is not 'timestamp_us chunk': {line.strip()[:80]!r}"
                    raise InputError(stamps_file, what, field=f"line {lineno}")
                path = folder / f"{parts[0]}{suffix}"
                if path.is_file():
                    yield stamp, path
                else:
                    self._skip(topic, lineno - 1, f"listed in {stamps_file.name} but not on disk", str(path))

        def on_disk() -> Iterator[tuple[int, Path]]:
            paths = [p for p in folder.iterdir() if p.suffix == suffix]
            stamps: dict[Path, int] = {}
            for p in paths:
                stamp = _microseconds(p.stem)
                if stamp is None:
                    raise InputError(
                        p, f"file name is not a timestamp in microseconds ({folder.name}/<timestamp_us>{suffix})"
                    )
                stamps[p] = stamp
            for p in sorted(paths, key=stamps.__getitem__):
                yield stamps[p], p

        return listed if stamps_file.is_file() else on_disk

    def _add_robotcar_camera(
        self, prefix: str, name: str, folder: Path, stamps_file: Path, convert: ImageConvert | None
    ) -> bool:
        if not folder.is_dir():
            return False
        topic = f"{prefix}/{name}/image"
        frames = self._stamped_files(topic, folder, stamps_file, ".png")
        images = sorted(p for p in folder.iterdir() if p.suffix == ".png")
        if not images:
            return False
        self._add_camera(name, topic, frames, probe_images(images, convert), convert=convert)
        return True

    def _add_lidar(self, prefix: str, name: str, layout: str) -> None:
        folder = self.path / name
        if not folder.is_dir():
            return
        if not any(p.suffix == ".bin" for p in folder.iterdir()):
            if any(p.suffix == ".png" for p in folder.iterdir()):
                warnings.warn(
                    f"{folder}: raw Velodyne .png scans are not read (use the SDK's .bin point clouds); no {name} "
                    "stream",
                    InputWarning,
                    stacklevel=3,
                )
            return
        topic = f"{prefix}/{name}/points"
        files = self._stamped_files(topic, folder, self.path / f"{name}.timestamps", ".bin")

        def scans() -> Iterator[LidarScan]:
            for stamp, path in files():
                xyz, reflectance = _read_lidar(path, layout)
                yield LidarScan(stamp, name, xyz, intensity=reflectance)

        self._add_records(topic, StreamKind.LIDAR, scans)

    # --- GPS, INS and VO ---------------------------------------------------------------------------------
    def _gps_fixes(self) -> Iterator[GpsFix]:
        assert self.gps_table is not None
        for row in self.gps_table.rows():
            sigmas_enu = np.array(
                [row.number("longitude_sigma"), row.number("latitude_sigma"), row.number("altitude_sigma")]
            )
            yield GpsFix(
                _stamp_ns(row, "timestamp"),
                row.number("latitude"),
                row.number("longitude"),
                row.number("altitude"),
                GpsStatus.FIX,
                np.diag(sigmas_enu**2),
            )

    def ins_origin(self) -> UtmOrigin:
        """The first INS row: the origin of ``utm_local``."""
        if self.ins_table is None:
            raise InputError(self.path / "gps" / "ins.csv", "no INS file: no utm_local origin")
        row = self.ins_table.first_row()
        if row is None:
            raise InputError(self.ins_table.path, "holds no rows")
        hemisphere = 32600 if row.number("latitude") >= 0 else 32700
        return UtmOrigin(
            hemisphere + _utm_zone(row), row.number("easting"), row.number("northing"), -row.number("down")
        )

    def _ins_poses(self) -> Iterator[PoseSample]:
        assert self.ins_table is not None
        origin = self.ins_origin()
        origin_enu = np.array([origin.easting_m, origin.northing_m, origin.up_m])
        for chunk in _chunks(self.ins_table.rows()):
            for row in chunk:
                zone = _utm_zone(row)
                if zone != origin.zone:
                    raise row.error(
                        "utm_zone", f"zone {zone} differs from the first row's {origin.zone}; utm_local spans one zone"
                    )
            columns = ("easting", "northing", "down", "roll", "pitch", "yaw", "latitude", "longitude")
            v = np.array([[row.number(c) for c in columns] for row in chunk])
            enu = v[:, :3] * np.array([1.0, 1.0, -1.0])
            gamma = grid_convergence_rad(v[:, 6], v[:, 7], origin.zone) if self.grid_convergence else np.zeros(len(v))
            poses = utm_local_from_ins(enu, v[:, 3], v[:, 4], v[:, 5], gamma, origin_enu)
            for row, T in zip(chunk, poses, strict=True):
                yield PoseSample(_stamp_ns(row, "timestamp"), "utm_local", "ins", T, source="ins")

    def _vo_poses(self) -> Iterator[PoseSample]:
        assert self.vo_table is not None
        vo_origin_from_vehicle_frd = np.eye(4)
        previous_stamp: int | None = None
        breaks: list[int] = []
        for chunk in _chunks(self.vo_table.rows()):
            v = np.array([[row.number(c) for c in VO_COLUMNS[2:]] for row in chunk])
            destination_from_source = make_pose(rotation_from_rpy(v[:, 3], v[:, 4], v[:, 5]), v[:, :3])
            for row, relative in zip(chunk, destination_from_source, strict=True):
                source_ns, destination_ns = _stamp_ns(row, "source_timestamp"), _stamp_ns(row, "destination_timestamp")
                if previous_stamp is None:
                    previous_stamp = destination_ns
                    yield PoseSample(destination_ns, "vo_origin", "vehicle", np.eye(4), source="odometry")
                elif destination_ns != previous_stamp:
                    breaks.append(row.line)
                vo_origin_from_vehicle_frd = vo_origin_from_vehicle_frd @ relative
                previous_stamp = source_ns
                T = FRD_FROM_FLU @ vo_origin_from_vehicle_frd @ FRD_FROM_FLU
                yield PoseSample(source_ns, "vo_origin", "vehicle", T, source="odometry")
        if breaks:
            warnings.warn(
                f"{self.vo_table.path}: {len(breaks)} rows (first at line {breaks[0]}) do not continue from the "
                "previous row's source_timestamp; chained anyway, as the RobotCar SDK does",
                InputWarning,
                stacklevel=2,
            )


def _demosaic(img: np.ndarray, code: int) -> np.ndarray:
    """Bayer mosaics (one 8-bit channel) to BGR; anything else is already an image."""
    if img.ndim == 2 and img.dtype == np.uint8:
        return cv2.cvtColor(img, code)
    return img
