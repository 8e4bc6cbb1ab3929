"""Drive logs stored as folders of files, and the generic image folder with a frame table.

The first half of this module is the plumbing every folder layout shares (KITTI, RobotCar and the
generic folder below): a reader is a set of *sources*, each a generator of time-ordered messages on
one or more topics, merged by stamp; images decode lazily and are checked against the first image
of their camera; text tables stream row by row and every bad value names its file, line and column.

Generic folder layout (``FolderLog``)::

    <folder>/
        frames.csv             the frame table (or the one *.csv whose header names the columns below)
        images/                the images (png/jpg); without images/, the folder itself
        intrinsics.json        optional: {"fx", "fy", "cx", "cy", "width"?, "height"?,
                               "distortion_model"?, "D"?}
        camera.yaml            optional, if no intrinsics.json: ROS camera_info YAML
                               (camera_matrix.data, distortion_model, distortion_coefficients.data,
                               image_width, image_height) or plain fx/fy/cx/cy keys

Columns of the frame table (header required, order free, other columns ignored):

- time, exactly one needed; the most precise present wins: ``timestamp_ns`` (integer ns),
  ``timestamp_us`` (integer microseconds) or ``timestamp`` (decimal seconds, converted to
  nanoseconds exactly, never through a float);
- ``image``: file name relative to the images folder (required);
- GPS, giving a ``GpsFix`` stream: ``lat`` and ``lon`` (degrees WGS84, both or neither), optional
  ``alt`` (metres; NaN when absent) and ``gps_sigma`` (1-sigma metres, the same for east, north
  and up). A row whose lat/lon cells are empty has no fix;
- pose, giving a ``PoseSample`` stream ``world_from_camera``: ``x y z`` (camera position in the
  world frame, metres) and ``qw qx qy qz`` (rotation world_from_camera, unit quaternion), all seven
  or none; a row with all seven empty has no pose;
- intrinsics ``fx fy cx cy`` (pixels, all four or none); they override intrinsics.json/camera.yaml.

Width and height come from the first image; every image must have the same size and channels.
"""

from __future__ import annotations

import csv
import heapq
import json
import warnings
from collections import Counter
from collections.abc import Callable, Generator, Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from mapkit.core.errors import InputError, InputWarning
from mapkit.core.geometry import make_pose, quat_wxyz_to_matrix
from mapkit.core.types import (
    CameraFrame,
    CameraInfo,
    FrameTransform,
    GpsFix,
    GpsStatus,
    Message,
    PoseSample,
    Record,
    StreamInfo,
    StreamKind,
)
from mapkit.io.base import DriveLog
from mapkit.io.trajectory import seconds_to_ns as exact_seconds_to_ns

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")

# ROS message types named in StreamInfo.msgtype, as the MCAP reader names them
MSGTYPE = {
    StreamKind.IMAGE: "sensor_msgs/Image",
    StreamKind.CAMERA_INFO: "sensor_msgs/CameraInfo",
    StreamKind.GPS: "sensor_msgs/NavSatFix",
    StreamKind.LIDAR: "sensor_msgs/PointCloud2",
    StreamKind.IMU: "sensor_msgs/Imu",
    StreamKind.POSE: "nav_msgs/Odometry",
    StreamKind.TF: "tf2_msgs/TFMessage",
}


def stream_info(topic: str, kind: StreamKind, count: int | None = None) -> StreamInfo:
    return StreamInfo(topic, kind, MSGTYPE[kind], count)


def undecodable(path: Path, expected: str) -> InputError:
    """The error for a text file holding bytes that are not UTF-8, naming the first such line and column."""
    for lineno, line in enumerate(path.read_bytes().split(b"\n"), start=1):
        try:
            line.decode("utf-8")
        except UnicodeDecodeError as exc:
            return InputError(
                path,
                f"line {lineno}: byte 0x{line[exc.start]:02x} at column {exc.start + 1} is not UTF-8 text ({expected})",
                field=f"line {lineno}",
            )
    return InputError(path, f"is not UTF-8 text ({expected})")


# --- time -------------------------------------------------------------------------------------------

#: stamps are int64 nanoseconds: about 292 years either side of 1970
MAX_STAMP_NS = 2**63 - 1


def seconds_to_ns(text: str) -> int:
    """Decimal seconds to integer nanoseconds, exactly; a value outside int64 nanoseconds is a ``ValueError``,
    refused before the exact conversion (which would build a huge integer from an exponent like ``1e999999999``)."""
    try:
        approx = float(text)
    except ValueError:
        approx = 0.0  # not a float: the exact parser says why
    if not abs(approx) < MAX_STAMP_NS * 1e-9:
        raise ValueError(f"{text.strip()[:40]!r} is not a time in seconds within +-{MAX_STAMP_NS * 1e-9:.3g} s")
    return exact_seconds_to_ns(text)


def check_stamp_ns(stamp: int) -> int:
    """``stamp`` when it fits int64 nanoseconds; a ``ValueError`` otherwise."""
    if not -MAX_STAMP_NS <= stamp <= MAX_STAMP_NS:
        raise ValueError(f"{stamp} ns is outside the range of int64 nanoseconds")
    return stamp


def read_stamp_lines(path: Path, parse: Callable[[str], int], what: str) -> np.ndarray:
    """int64 stamps of a file holding one stamp per line (blank lines ignored)."""
    if not path.is_file():
        raise InputError(path, f"missing {what}")
    stamps: list[int] = []
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise undecodable(path, f"{what} are text") from None
    for lineno, line in enumerate(text.split("\n"), start=1):
        if not line.strip():
            continue
        try:
            stamps.append(check_stamp_ns(parse(line)))
        except ValueError as exc:
            raise InputError(path, f"line {lineno}: {exc}", field=f"line {lineno}") from None
    return np.asarray(stamps, dtype=np.int64)


# --- images -----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ImageLayout:
    """Size and pixel layout of a decoded image; one camera keeps one layout."""

    width: int
    height: int
    encoding: str

    @classmethod
    def of(cls, img: np.ndarray) -> ImageLayout:
        h, w = img.shape[:2]
        channels = 1 if img.ndim == 2 else img.shape[2]
        depth = {np.dtype(np.uint8): "8", np.dtype(np.uint16): "16"}.get(img.dtype)
        # OpenCV decodes colour as BGR(A)
        names = {1: "mono", 3: "bgr", 4: "bgra"}
        if depth is None or channels not in names:
            return cls(w, h, f"{img.dtype}x{channels}")
        return cls(w, h, f"{names[channels]}{depth}")

    def __str__(self) -> str:
        return f"{self.width}x{self.height} {self.encoding}"


def read_image(path: Path) -> np.ndarray:
    """The decoded pixels of an image file; a missing or undecodable file is an ``InputError`` naming it."""
    try:
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:  # e.g. a header claiming more pixels than OpenCV allows
        raise InputError(path, f"could not be decoded as an image ({str(exc).strip().splitlines()[-1]})") from None
    if img is None:
        what = "could not be decoded as an image" if path.is_file() else "image file is missing"
        raise InputError(path, what)
    return img


ImageConvert = Callable[[np.ndarray], np.ndarray]


def probe_image(path: Path, convert: ImageConvert | None = None) -> ImageLayout:
    """Layout of one image after ``convert``: decodes it once (the first image of a camera)."""
    img = read_image(path)
    return ImageLayout.of(img if convert is None else convert(img))


#: how many images of a camera are tried, in order, for its layout before a damaged start is an error
PROBE_TRIES = 10


def probe_images(paths: Iterable[Path], convert: ImageConvert | None = None) -> ImageLayout:
    """Layout of the first image among ``paths`` that decodes; the damaged ones before it are skipped with a
    warning naming them (their frames fail again when read, and are skipped there). After ``PROBE_TRIES``
    failures the first error is raised."""
    first_error: InputError | None = None
    for n, path in enumerate(paths):
        if n == PROBE_TRIES:
            break
        try:
            layout = probe_image(path, convert)
        except InputError as exc:
            first_error = first_error or exc
            warnings.warn(f"{exc}; the layout of its camera is taken from the next image", InputWarning, stacklevel=2)
            continue
        return layout
    if first_error is None:
        raise InputError(None, "no image to read the camera's layout from")
    raise first_error


def lazy_frame(
    stamp_ns: int, camera: str, path: Path, layout: ImageLayout, convert: ImageConvert | None = None
) -> CameraFrame:
    """A frame that decodes ``path`` on first access and checks it has its camera's layout."""

    def load() -> np.ndarray:
        img = read_image(path)
        if convert is not None:
            img = convert(img)
        got = ImageLayout.of(img)
        if got != layout:
            raise InputError(path, f"image is {got}, but the first image of {camera} is {layout}")
        return img

    return CameraFrame(stamp_ns, camera, loader=load, encoding=layout.encoding, source=str(path))


# --- CSV tables ------------------------------------------------------------------------------------


class CsvTable:
    """A CSV file with a header line, read row by row with the ``csv`` module.

    Every malformed value raises an ``InputError`` naming the file, the line and the column.
    """

    def __init__(self, path: Path, required: Sequence[str] = ()):
        self.path = Path(path)
        if not self.path.is_file():
            raise InputError(self.path, "no such file")
        with open(self.path, newline="", encoding="utf-8") as f:
            reader = csv.reader(f)
            with self._errors_named(reader):
                header = next(reader, None)
        if not header:
            raise InputError(self.path, "is empty: no header line", field="header")
        self.columns = [c.strip() for c in header]
        self._index = {c: i for i, c in enumerate(self.columns)}
        missing = [c for c in required if c not in self._index]
        if missing:
            raise InputError(
                self.path,
                f"header has no column {', '.join(map(repr, missing))} (columns: {', '.join(self.columns)})",
                field="header",
            )

    @contextmanager
    def _errors_named(self, reader) -> Iterator[None]:
        """Turns bytes that are not UTF-8 and what ``csv`` cannot parse into an ``InputError`` naming the line."""
        try:
            yield
        except UnicodeDecodeError:
            raise undecodable(self.path, "a CSV table is UTF-8 text") from None
        except csv.Error as exc:
            raise InputError(self.path, f"line {reader.line_num}: {exc}", field=f"line {reader.line_num}") from None

    def has(self, column: str) -> bool:
        return column in self._index

    def column_index(self, column: str) -> int:
        return self._index[column]

    def first_row(self) -> CsvRow | None:
        rows = self.rows()
        try:
            return next(rows, None)
        finally:
            rows.close()  # releases the file now, not when the generator is collected

    def rows(self) -> Generator[CsvRow, None, None]:
        with open(self.path, newline="", encoding="utf-8") as f:
            reader = csv.reader(f)
            with self._errors_named(reader):
                yield from self._rows_of(reader)

    def _rows_of(self, reader) -> Iterator[CsvRow]:
        n = len(self.columns)
        next(reader, None)
        for values in reader:
            if not values or (len(values) == 1 and not values[0].strip()):
                continue
            line = reader.line_num
            if len(values) < n:
                col = self.columns[len(values)]
                raise InputError(
                    self.path,
                    f"{len(values)} values but the header names {n} columns (no value for {col!r})",
                    field=f"line {line}, column {col}",
                )
            if len(values) > n:
                col = self.columns[-1]
                raise InputError(
                    self.path,
                    f"{len(values)} values but the header names {n} columns (extra values after {col!r})",
                    field=f"line {line}, column {col}",
                )
            yield CsvRow(self, line, values)


class CsvRow:
    """One data row; accessors convert a cell or raise an error naming file, line and column."""

    __slots__ = ("table", "line", "values")

    def __init__(self, table: CsvTable, line: int, values: list[str]):
        self.table = table
        self.line = line
        self.values = values

    def error(self, column: str, what: str) -> InputError:
        return InputError(self.table.path, what, field=f"line {self.line}, column {column}")

    def text(self, column: str) -> str:
        return self.values[self.table.column_index(column)].strip()

    def is_empty(self, column: str) -> bool:
        return self.text(column) == ""

    def number(self, column: str) -> float:
        cell = self.text(column)
        try:
            value = float(cell)
        except ValueError:
            raise self.error(column, f"{cell!r} is not a number") from None
        if not np.isfinite(value):
            raise self.error(column, f"{cell!r} is not a finite number")
        return value

    def integer(self, column: str) -> int:
        cell = self.text(column)
        try:
            return int(cell)
        except ValueError:
            raise self.error(column, f"{cell!r} is not an integer") from None

    def stamp_ns(self, column: str, ns_per_unit: int = 1) -> int:
        """An integer stamp in ``ns_per_unit`` ns units, as int64 nanoseconds."""
        try:
            return check_stamp_ns(self.integer(column) * ns_per_unit)
        except ValueError as exc:
            raise self.error(column, str(exc)) from None

    def seconds_ns(self, column: str) -> int:
        try:
            return seconds_to_ns(self.text(column))
        except ValueError as exc:
            raise self.error(column, str(exc)) from None


# --- the reader base for folder layouts --------------------------------------------------------------

Wanted = Callable[[str], bool]


@dataclass(frozen=True)
class Source:
    """Messages of some topics, in non-decreasing stamp order, from ``iterate(wanted)``."""

    infos: tuple[StreamInfo, ...]
    iterate: Callable[[Wanted], Iterator[Message]]


def _stamp_of(msg: Message) -> int:
    return msg.record.stamp_ns


class FolderLayoutLog(DriveLog):
    """A drive stored as files in a folder: sources merged by time, one message of each in memory."""

    def __init__(self, path: str | Path):
        super().__init__(path)
        if not self.path.is_dir():
            raise InputError(self.path, "no such folder")
        self._sources: list[Source] = []

    def _add(self, infos: Iterable[StreamInfo], iterate: Callable[[Wanted], Iterator[Message]]) -> None:
        self._sources.append(Source(tuple(infos), iterate))

    def _add_static_transforms(self, topic: str, transforms: list[FrameTransform]) -> None:
        if not transforms:
            return

        def iterate(wanted: Wanted) -> Iterator[Message]:
            for i, t in enumerate(transforms):
                yield Message(topic, StreamKind.TF, i, t)

        self._add([stream_info(topic, StreamKind.TF, len(transforms))], iterate)

    def _add_records(
        self, topic: str, kind: StreamKind, records: Callable[[], Iterator[Record]], count: int | None = None
    ) -> None:
        """One topic whose records ``records()`` yields in time order."""

        def iterate(wanted: Wanted) -> Iterator[Message]:
            for i, record in enumerate(records()):
                yield Message(topic, kind, i, record)

        self._add([stream_info(topic, kind, count)], iterate)

    def _add_camera(
        self,
        camera: str,
        image_topic: str,
        frames: Callable[[], Iterable[tuple[int, Path]]],
        layout: ImageLayout,
        *,
        info: CameraInfo | None = None,
        info_topic: str | None = None,
        count: int | None = None,
        convert: ImageConvert | None = None,
    ) -> None:
        """A camera from (stamp, image path) pairs; with ``info``, one CameraInfo per frame (as ROS)."""
        infos = [stream_info(info_topic, StreamKind.CAMERA_INFO, count)] if info is not None and info_topic else []
        infos.append(stream_info(image_topic, StreamKind.IMAGE, count))

        def iterate(wanted: Wanted) -> Iterator[Message]:
            want_info = info is not None and info_topic is not None and wanted(info_topic)
            want_image = wanted(image_topic)
            for i, (stamp, path) in enumerate(frames()):
                if want_info and info is not None and info_topic is not None:
                    yield Message(info_topic, StreamKind.CAMERA_INFO, i, replace(info, stamp_ns=stamp))
                if want_image:
                    yield Message(image_topic, StreamKind.IMAGE, i, lazy_frame(stamp, camera, path, layout, convert))

        self._add(infos, iterate)

    def streams(self) -> list[StreamInfo]:
        return [info for s in self._sources for info in s.infos]

    def _iter_messages(self, topics: set[str] | None) -> Iterator[Message]:
        def wanted(topic: str) -> bool:
            return topics is None or topic in topics

        active = [s.iterate(wanted) for s in self._sources if any(wanted(i.topic) for i in s.infos)]
        # equal stamps keep source order: static transforms, added first, precede the data they relate
        yield from heapq.merge(*active, key=_stamp_of)


# --- the generic folder ------------------------------------------------------------------------------

TIME_COLUMNS = ("timestamp_ns", "timestamp_us", "timestamp")  # most precise first
GPS_COLUMNS = ("lat", "lon")
POSE_COLUMNS = ("x", "y", "z", "qw", "qx", "qy", "qz")
INTRINSICS_COLUMNS = ("fx", "fy", "cx", "cy")


def _csv_header(path: Path) -> list[str]:
    try:
        with open(path, newline="") as f:
            return [c.strip() for c in next(csv.reader(f), [])]
    except (OSError, UnicodeDecodeError, csv.Error):
        return []


def _lists_frames(path: Path) -> bool:
    header = _csv_header(path)
    return "image" in header and any(c in header for c in TIME_COLUMNS)


def _all_or_none(table: CsvTable, group: Sequence[str], name: str) -> bool:
    present = [c for c in group if table.has(c)]
    if present and len(present) != len(group):
        missing = [c for c in group if not table.has(c)]
        raise InputError(
            table.path, f"{name} columns need all of {', '.join(group)}; missing {', '.join(missing)}", field="header"
        )
    return bool(present)


@dataclass(frozen=True)
class _Intrinsics:
    K: np.ndarray
    D: np.ndarray
    distortion_model: str
    size: tuple[int, int] | None  # (width, height) when the file states it


def _intrinsics_from_mapping(d: object, path: Path) -> _Intrinsics:
    if not isinstance(d, dict):
        raise InputError(path, "is not a mapping of intrinsics")
    try:
        if "camera_matrix" in d:
            K = np.asarray(d["camera_matrix"]["data"], dtype=np.float64).reshape(3, 3)
        else:
            K = np.array([[d["fx"], 0.0, d["cx"]], [0.0, d["fy"], d["cy"]], [0.0, 0.0, 1.0]], dtype=np.float64)
        coeffs = d.get("distortion_coefficients", {}).get("data") if "distortion_coefficients" in d else d.get("D", [])
        D = np.asarray(coeffs or [], dtype=np.float64).ravel()
        w = d.get("image_width", d.get("width"))
        h = d.get("image_height", d.get("height"))
        size = (int(w), int(h)) if w is not None and h is not None else None
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise InputError(path, f"intrinsics are incomplete or not numbers ({type(exc).__name__}: {exc})") from None
    if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(path, "focal lengths must be positive finite numbers", field="fx/fy")
    return _Intrinsics(K, D, str(d.get("distortion_model", "plumb_bob")), size)


def _read_intrinsics_file(folder: Path) -> _Intrinsics | None:
    json_path, yaml_path = folder / "intrinsics.json", folder / "camera.yaml"
    if json_path.is_file():
        try:
            return _intrinsics_from_mapping(json.loads(json_path.read_text(encoding="utf-8")), json_path)
        except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as exc:
            raise InputError(json_path, f"is not valid JSON: {type(exc).__name__}: {str(exc)[:200]}") from None
    if yaml_path.is_file():
        import yaml

        try:
            return _intrinsics_from_mapping(yaml.safe_load(yaml_path.read_text(encoding="utf-8")), yaml_path)
        except (yaml.YAMLError, UnicodeDecodeError, RecursionError) as exc:
            raise InputError(yaml_path, f"is not valid YAML: {type(exc).__name__}: {str(exc)[:200]}") from None
    return None


class FolderLog(FolderLayoutLog):
    """Images plus a frame table (see the module docstring for the accepted columns).

    Topics: ``<prefix>/<camera>/image``, ``<prefix>/<camera>/camera_info`` (when intrinsics are
    given), ``<prefix>/gps/fix`` (lat/lon columns) and ``<prefix>/pose`` (pose columns).
    """

    format_name = "folder"

    def __init__(
        self,
        path: str | Path,
        *,
        frames_csv: str | Path | None = None,
        camera: str = "camera",
        topic_prefix: str = "/folder",
    ):
        super().__init__(path)
        self.camera = camera
        self.image_dir = self.path / "images" if (self.path / "images").is_dir() else self.path
        self.table = CsvTable(self._find_csv(frames_csv), required=("image",))
        time_column = next((c for c in TIME_COLUMNS if self.table.has(c)), None)
        if time_column is None:
            raise InputError(
                self.table.path, f"header names no time column (one of {', '.join(TIME_COLUMNS)})", field="header"
            )
        self.time_column: str = time_column
        self.has_gps = _all_or_none(self.table, GPS_COLUMNS, "GPS")
        self.has_pose = _all_or_none(self.table, POSE_COLUMNS, "pose")
        self._intrinsics_in_columns = _all_or_none(self.table, INTRINSICS_COLUMNS, "intrinsics")
        self._intrinsics_file = None if self._intrinsics_in_columns else _read_intrinsics_file(self.path)
        if self.table.first_row() is None:
            raise InputError(self.table.path, "lists no frames")
        self.layout = probe_images(self._image_path(row) for row in self.table.rows())
        size = self._intrinsics_file.size if self._intrinsics_file is not None else None
        if size is not None and size != (self.layout.width, self.layout.height):
            raise InputError(self.path, f"intrinsics are for {size[0]}x{size[1]} images, the images are {self.layout}")

        p = topic_prefix.rstrip("/")
        self.topics = {
            StreamKind.IMAGE: f"{p}/{camera}/image",
            StreamKind.CAMERA_INFO: f"{p}/{camera}/camera_info",
            StreamKind.GPS: f"{p}/gps/fix",
            StreamKind.POSE: f"{p}/pose",
        }
        kinds = [StreamKind.CAMERA_INFO] if self.has_intrinsics else []
        kinds.append(StreamKind.IMAGE)
        kinds += [StreamKind.GPS] if self.has_gps else []
        kinds += [StreamKind.POSE] if self.has_pose else []
        self._add([stream_info(self.topics[k], k) for k in kinds], self._rows)

    @property
    def has_intrinsics(self) -> bool:
        return self._intrinsics_in_columns or self._intrinsics_file is not None

    @classmethod
    def detect(cls, path: Path) -> bool:
        path = Path(path)
        if not path.is_dir():
            return False
        tables = [path / "frames.csv"] if (path / "frames.csv").is_file() else sorted(path.glob("*.csv"))
        if not any(_lists_frames(t) for t in tables):
            return False
        image_dir = path / "images" if (path / "images").is_dir() else path
        return any(p.suffix.lower() in IMAGE_SUFFIXES for p in image_dir.iterdir())

    def _find_csv(self, csv_name: str | Path | None) -> Path:
        if csv_name is not None:
            return self.path / csv_name
        if (self.path / "frames.csv").is_file():
            return self.path / "frames.csv"
        candidates = [t for t in sorted(self.path.glob("*.csv")) if _lists_frames(t)]
        if not candidates:
            raise InputError(self.path, "no frames.csv and no *.csv whose header names 'image' and a time column")
        if len(candidates) > 1:
            names = ", ".join(c.name for c in candidates)
            raise InputError(self.path, f"several CSV files could list the frames ({names}); name one with csv=...")
        return candidates[0]

    def _image_path(self, row: CsvRow) -> Path:
        """The image a row names, which must exist: the error names both the table and the image."""
        name = row.text("image")
        if not name:
            raise row.error("image", "is empty")
        path = self.image_dir / name
        try:
            exists = path.is_file()
        except (ValueError, OSError) as exc:  # a NUL byte, a name too long for the file system
            raise row.error("image", f"names {name[:80]!r}, which cannot be a file name ({exc})") from None
        if not exists:
            raise row.error("image", f"names image {str(path)!r}, which does not exist")
        return path

    def _stamp_ns(self, row: CsvRow) -> int:
        col = self.time_column
        if col == "timestamp_ns":
            return row.stamp_ns(col)
        if col == "timestamp_us":
            return row.stamp_ns(col, 1000)
        return row.seconds_ns(col)

    def _camera_info(self, row: CsvRow, stamp_ns: int) -> CameraInfo:
        w, h = self.layout.width, self.layout.height
        if self._intrinsics_in_columns:
            fx, fy, cx, cy = (row.number(c) for c in INTRINSICS_COLUMNS)
            K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
            return CameraInfo(self.camera, w, h, K, D=np.zeros(5), stamp_ns=stamp_ns)
        intr = self._intrinsics_file
        assert intr is not None
        return CameraInfo(self.camera, w, h, intr.K, intr.distortion_model, intr.D, stamp_ns)

    def _gps(self, row: CsvRow, stamp_ns: int) -> GpsFix | None:
        if row.is_empty("lat") and row.is_empty("lon"):
            return None
        alt = row.number("alt") if self.table.has("alt") and not row.is_empty("alt") else float("nan")
        cov = None
        if self.table.has("gps_sigma") and not row.is_empty("gps_sigma"):
            sigma = row.number("gps_sigma")
            if sigma < 0:
                raise row.error("gps_sigma", f"{sigma} is negative")
            cov = np.eye(3) * sigma**2
        return GpsFix(stamp_ns, row.number("lat"), row.number("lon"), alt, GpsStatus.FIX, cov)

    def _pose(self, row: CsvRow, stamp_ns: int) -> PoseSample | None:
        if all(row.is_empty(c) for c in POSE_COLUMNS):
            return None
        v = [row.number(c) for c in POSE_COLUMNS]
        q_wxyz = np.asarray(v[3:])
        norm = float(np.linalg.norm(q_wxyz))
        if abs(norm - 1.0) > 1e-3:
            raise row.error("qw", f"quaternion (qw, qx, qy, qz) has norm {norm:.4f}, not 1")
        world_from_camera = make_pose(quat_wxyz_to_matrix(q_wxyz / norm), v[:3])
        return PoseSample(stamp_ns, "world", self.camera, world_from_camera, source="pose")

    def _rows(self, wanted: Wanted) -> Iterator[Message]:
        """All records of one table row share its stamp: one pass over the table serves every topic."""
        t = self.topics
        index: Counter[str] = Counter()

        def message(kind: StreamKind, record) -> Message:
            topic = t[kind]
            index[topic] += 1
            return Message(topic, kind, index[topic] - 1, record)

        for row in self.table.rows():
            stamp = self._stamp_ns(row)
            image_path = self._image_path(row)
            if self.has_intrinsics and wanted(t[StreamKind.CAMERA_INFO]):
                yield message(StreamKind.CAMERA_INFO, self._camera_info(row, stamp))
            if wanted(t[StreamKind.IMAGE]):
                yield message(StreamKind.IMAGE, lazy_frame(stamp, self.camera, image_path, self.layout))
            fix = self._gps(row, stamp) if self.has_gps and wanted(t[StreamKind.GPS]) else None
            if fix is not None:
                yield message(StreamKind.GPS, fix)
            pose = self._pose(row, stamp) if self.has_pose and wanted(t[StreamKind.POSE]) else None
            if pose is not None:
                yield message(StreamKind.POSE, pose)
