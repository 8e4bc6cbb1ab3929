"""Folders of geotagged photos: GPS, time and focal length from each photo's EXIF, no frame table.

Layout (``PhotoFolder``)::

    <folder>/               JPEG, PNG or TIFF photos (or the same under <folder>/images/)

A folder that also holds a frame table is the generic folder's (``mapkit.io.folder.FolderLog``);
the two readers never claim the same folder. Pillow reads the tags and decodes the pixels.

What each tag becomes (one warning per missing tag kind, naming how many photos lack it):

- **GPS fix** (``GpsFix``, status FIX) from GPSLatitude/Ref and GPSLongitude/Ref (degrees, minutes,
  seconds as rationals), GPSAltitude/Ref (metres as written: cameras mostly write height above sea
  level, which differs from the ellipsoidal height by the geoid undulation, a constant over a walk
  that the alignment's translation absorbs). A photo without altitude gets the median altitude of
  the photos that have one (0 m if none has): the georeferencing stage needs finite heights.
  Horizontal sigma: GPSHPositioningError (metres) if present, else GPSDOP x ``uere_m`` (5 m per DOP
  unit by default, a typical user-equivalent range error of single-frequency GPS), else unknown; the
  covariance is sigma^2 on east, north and up, as the generic folder's ``gps_sigma``. GPSStatus
  ``V`` (measurement void) and a position of exactly 0, 0 (what cameras without a fix write) count
  as no fix.
- **Time** (integer ns since the Unix epoch, UTC): DateTimeOriginal + SubSecTimeOriginal, shifted
  by OffsetTimeOriginal; without an offset the camera's local clock is read as if it were UTC.
  Else GPSDateStamp + GPSTimeStamp (UTC). If any photo has no time at all, every photo is ordered
  by file name, 1 s apart from 0, since times of some photos cannot place the others.
  Photos are ordered by (time, name); a stamp equal to the previous one is moved 1 ns after it, in
  name order, so that every photo keeps a unique, strictly increasing stamp (the reader base skips
  duplicates).
- **Intrinsics** (``CameraInfo`` per photo, no distortion): FocalLengthIn35mmFilm converted by the
  diagonal (f_px = f35 * image diagonal in px / 43.27, the 36x24 mm diagonal), else FocalLength
  with FocalPlaneX/YResolution and FocalPlaneResolutionUnit (scaled when PixelX/YDimension says the
  photo was resized), else COLMAP's prior 1.2 * max(width, height). Principal point at the image
  centre ((w - 1) / 2, (h - 1) / 2: pixel centres at integers, as OpenCV and ROS). Intrinsics are
  a prior here; structure from motion refines them.
- **Orientation**: pixels are turned upright as Pillow's ``ImageOps.exif_transpose`` does, and fx
  and fy swap for the orientations that transpose (5-8).

The photos of the most common size and pixel mode are kept (a portrait shot in a landscape walk is
skipped with a warning naming it, rather than every other photo for the sake of the first).

Topics: ``<prefix>/camera/image`` (``CameraFrame``, decoded on first access, OpenCV channel order
``bgr8``/``mono8`` like the other readers), ``<prefix>/camera/camera_info`` and ``<prefix>/gps/fix``
(the photos with a fix only, at the photo's stamp).
"""

from __future__ import annotations

import calendar
import math
import re
import struct
import warnings
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import datetime
from fractions import Fraction
from itertools import pairwise
from pathlib import Path

import numpy as np
from PIL import Image, ImageOps, UnidentifiedImageError

from mapkit.core.errors import InputError, InputWarning
from mapkit.core.types import CameraFrame, CameraInfo, GpsFix, GpsStatus, Message, StreamKind
from mapkit.io.folder import FolderLayoutLog, FolderLog, ImageLayout, Wanted, stream_info

PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff")
# detect() reads tags of these only: Pillow may decode a whole PNG to reach an eXIf chunk stored after the pixels
DETECT_SUFFIXES = (".jpg", ".jpeg", ".tif", ".tiff")
DETECT_MIN_GEOTAGGED = 3
DETECT_MAX_FILES = 64  # detect() looks at the first files by name only, so that probing a large folder stays quick

FULL_FRAME_DIAGONAL_MM = math.hypot(36.0, 24.0)  # 43.27 mm: "35 mm equivalent" focal lengths are scaled by the diagonal
DEFAULT_FOCAL_FACTOR = 1.2  # COLMAP's prior focal length without EXIF: 1.2 * max(width, height)
DEFAULT_UERE_M = 5.0  # metres of horizontal error per unit of GPSDOP
NAME_ONLY_SPACING_NS = 1_000_000_000
# what Pillow raises on a file it cannot open or a corrupt EXIF block
_UNREADABLE = (
    OSError,
    UnidentifiedImageError,
    ValueError,
    SyntaxError,
    KeyError,
    struct.error,
    Image.DecompressionBombError,
)

# EXIF tag numbers (EXIF 2.32 / CIPA DC-008); Pillow >= 9.1 has no named constants for all of them
TAG_ORIENTATION = 0x0112
TAG_EXIF_IFD = 0x8769
TAG_GPS_IFD = 0x8825
TAG_DATETIME_ORIGINAL = 0x9003
TAG_OFFSET_TIME_ORIGINAL = 0x9011
TAG_SUBSEC_TIME_ORIGINAL = 0x9291
TAG_FOCAL_LENGTH = 0x920A
TAG_PIXEL_X_DIMENSION = 0xA002
TAG_PIXEL_Y_DIMENSION = 0xA003
TAG_FOCAL_PLANE_X_RESOLUTION = 0xA20E
TAG_FOCAL_PLANE_Y_RESOLUTION = 0xA20F
TAG_FOCAL_PLANE_RESOLUTION_UNIT = 0xA210
TAG_FOCAL_LENGTH_35MM = 0xA405
GPS_LATITUDE_REF, GPS_LATITUDE, GPS_LONGITUDE_REF, GPS_LONGITUDE = 1, 2, 3, 4
GPS_ALTITUDE_REF, GPS_ALTITUDE, GPS_TIMESTAMP, GPS_STATUS, GPS_DOP = 5, 6, 7, 9, 11
GPS_DATESTAMP, GPS_H_POSITIONING_ERROR = 29, 31

RESOLUTION_UNIT_MM = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}  # inch, cm, mm, um (1 = no unit: unusable)
_OFFSET = re.compile(r"^([+-])(\d{2}):(\d{2})$")


# --- tag values --------------------------------------------------------------------------------------


def _fraction(value) -> Fraction | None:
    """An EXIF number (Pillow's IFDRational, int, float or (num, den)) exactly, None if not a finite number."""
    try:
        if isinstance(value, tuple) and len(value) == 2:
            num, den = value
        else:
            num, den = getattr(value, "numerator", value), getattr(value, "denominator", 1)
        if isinstance(num, float) or isinstance(den, float):
            if not (math.isfinite(num) and math.isfinite(den)):
                return None
            num, den = Fraction(num), Fraction(den)
        return None if den == 0 else Fraction(num) / Fraction(den)
    except (TypeError, ValueError):
        return None


def _text(value) -> str:
    if isinstance(value, bytes):
        value = value.decode("ascii", errors="replace")
    return str(value).strip().strip("\x00").strip() if value is not None else ""


def _degrees(value, ref, positive: str, negative: str) -> tuple[float | None, bool]:
    """Signed degrees of a (deg, min, sec) tag and its reference letter; (None, _) if unusable,
    and whether the reference letter was missing (then the value is taken as ``positive``)."""
    parts = value if isinstance(value, (tuple, list)) else (value,)
    if not 1 <= len(parts) <= 3:
        return None, False
    numbers = [_fraction(p) for p in parts]
    if any(n is None or n < 0 for n in numbers):
        return None, False
    deg = sum(n / 60**i for i, n in enumerate(numbers))
    letter = _text(ref).upper()[:1]
    if letter not in (positive, negative, ""):
        return None, False
    return float(-deg if letter == negative else deg), letter == ""


def _first_byte(value) -> int | None:
    if isinstance(value, (bytes, bytearray)):
        return value[0] if value else None
    if isinstance(value, (tuple, list)):
        return _first_byte(value[0]) if value else None
    try:
        return int(value)
    except (TypeError, ValueError):
        return None


def _exif_time_ns(exif: dict) -> tuple[int | None, bool]:
    """(UTC ns, True) from DateTimeOriginal with OffsetTimeOriginal; (clock ns read as UTC, False) without
    an offset; (None, False) when absent or unreadable (cameras with an unset clock write blanks or zeros)."""
    text = _text(exif.get(TAG_DATETIME_ORIGINAL))
    try:
        dt = datetime.strptime(text.replace("-", ":"), "%Y:%m:%d %H:%M:%S")
    except ValueError:
        return None, False
    subsec = _text(exif.get(TAG_SUBSEC_TIME_ORIGINAL))
    # SubSecTime holds the digits after the decimal point: "5" is 0.5 s, "050" is 0.05 s
    frac_ns = int((subsec + "0" * 9)[:9]) if subsec.isdigit() else 0
    ns = calendar.timegm(dt.timetuple()) * 1_000_000_000 + frac_ns
    m = _OFFSET.match(_text(exif.get(TAG_OFFSET_TIME_ORIGINAL)))
    if m is None:
        return ns, False
    offset_s = (int(m.group(2)) * 3600 + int(m.group(3)) * 60) * (-1 if m.group(1) == "-" else 1)
    return ns - offset_s * 1_000_000_000, True


def _gps_time_ns(gps: dict) -> int | None:
    """UTC ns from GPSDateStamp and GPSTimeStamp (hours, minutes, seconds as rationals)."""
    try:
        day = datetime.strptime(_text(gps.get(GPS_DATESTAMP)).replace("-", ":"), "%Y:%m:%d")
    except ValueError:
        return None
    hms = gps.get(GPS_TIMESTAMP)
    if not isinstance(hms, (tuple, list)) or len(hms) != 3:
        return None
    h, m, s = (_fraction(v) for v in hms)
    if h is None or m is None or s is None or h < 0 or m < 0 or s < 0:
        return None
    seconds = h * 3600 + m * 60 + s
    return calendar.timegm(day.timetuple()) * 1_000_000_000 + round(seconds * 1_000_000_000)


def _focal_px(exif: dict, width: int, height: int) -> tuple[float, float] | None:
    """(fx, fy) in pixels of the stored (not yet rotated) image, None without the tags for it."""
    f35 = _fraction(exif.get(TAG_FOCAL_LENGTH_35MM))
    if f35 is not None and f35 > 0:
        f = float(f35) * math.hypot(width, height) / FULL_FRAME_DIAGONAL_MM
        return f, f
    f_mm = _fraction(exif.get(TAG_FOCAL_LENGTH))
    xres = _fraction(exif.get(TAG_FOCAL_PLANE_X_RESOLUTION))
    yres = _fraction(exif.get(TAG_FOCAL_PLANE_Y_RESOLUTION))
    unit_mm = RESOLUTION_UNIT_MM.get(_first_byte(exif.get(TAG_FOCAL_PLANE_RESOLUTION_UNIT, 2)) or 0)
    if f_mm is None or f_mm <= 0 or xres is None or xres <= 0 or yres is None or yres <= 0 or unit_mm is None:
        return None
    fx, fy = float(f_mm * xres) / unit_mm, float(f_mm * yres) / unit_mm
    # the focal plane resolution is of the image the camera recorded; a resized copy scales it
    px, py = (_fraction(exif.get(t)) for t in (TAG_PIXEL_X_DIMENSION, TAG_PIXEL_Y_DIMENSION))
    if px is not None and py is not None and px > 0 and py > 0:
        fx, fy = fx * width / float(px), fy * height / float(py)
    return fx, fy


# --- one photo ----------------------------------------------------------------------------------------

_MODES_KEPT = {"L": "mono8", "I;16": "mono16", "RGB": "bgr8", "RGBA": "bgra8"}


def _pixel_mode(mode: str) -> str:
    """The Pillow mode a photo is decoded to (others are converted to RGB or RGBA)."""
    if mode in _MODES_KEPT or mode.startswith("I;16"):
        return mode
    return "RGBA" if mode in ("LA", "PA", "La") else "RGB"


def read_photo(path: Path) -> np.ndarray:
    """The pixels of a photo upright (EXIF orientation applied as ``ImageOps.exif_transpose``), in
    OpenCV's channel order (BGR, BGRA or one channel), as the other readers deliver images."""
    try:
        with Image.open(path) as im:
            upright = ImageOps.exif_transpose(im)
            mode = _pixel_mode(upright.mode)
            pixels = np.asarray(upright if upright.mode == mode else upright.convert(mode))
    except _UNREADABLE as exc:
        raise InputError(path, f"could not be decoded as an image ({exc})") from None
    if pixels.dtype.byteorder == ">":  # "I;16B"
        pixels = pixels.astype(np.uint16)
    if pixels.ndim == 3:
        pixels = pixels[..., [2, 1, 0, 3][: pixels.shape[2]]]
    return np.ascontiguousarray(pixels)


@dataclass
class _Tags:
    """What one photo's EXIF says, before the folder-wide choices (order, size, fill-ins)."""

    path: Path
    size: tuple[int, int]  # upright (width, height)
    mode: str
    time_ns: int | None = None
    time_kind: str = "none"  # "utc" (with offset), "local" (no offset), "gps" (GPS date and time), "none"
    latlon: tuple[float, float] | None = None
    gps_problem: str = ""  # why a photo with GPS tags has no fix
    ref_missing: bool = False
    alt_m: float | None = None
    sigma_m: float | None = None
    focal_px: tuple[float, float] | None = None  # upright (fx, fy)

    @property
    def stamp_ns(self) -> int:
        """``time_ns`` once the folder-wide order has given every photo one."""
        assert self.time_ns is not None, "photos are stamped by PhotoFolder._order"
        return self.time_ns


def _read_tags(path: Path, uere_m: float) -> _Tags:
    """The tags of one photo (reads the header, not the pixels)."""
    with Image.open(path) as im:
        exif_all = im.getexif()
        base = dict(exif_all)
        exif = dict(exif_all.get_ifd(TAG_EXIF_IFD))
        gps = dict(exif_all.get_ifd(TAG_GPS_IFD))
        width, height, mode = im.width, im.height, _pixel_mode(im.mode)
    orientation = base.get(TAG_ORIENTATION, 1)
    transposed = orientation in (5, 6, 7, 8)
    t = _Tags(path, (height, width) if transposed else (width, height), mode)

    t.time_ns, has_offset = _exif_time_ns(exif)
    if t.time_ns is not None:
        t.time_kind = "utc" if has_offset else "local"
    else:
        t.time_ns = _gps_time_ns(gps)
        t.time_kind = "none" if t.time_ns is None else "gps"

    if GPS_LATITUDE in gps or GPS_LONGITUDE in gps:
        lat, lat_ref_missing = _degrees(gps.get(GPS_LATITUDE), gps.get(GPS_LATITUDE_REF), "N", "S")
        lon, lon_ref_missing = _degrees(gps.get(GPS_LONGITUDE), gps.get(GPS_LONGITUDE_REF), "E", "W")
        if _text(gps.get(GPS_STATUS)).upper() == "V":
            t.gps_problem = "GPSStatus V (measurement void)"
        elif lat is None or lon is None or abs(lat) > 90 or abs(lon) > 180:
            t.gps_problem = "unreadable GPSLatitude/GPSLongitude"
        elif lat == 0.0 and lon == 0.0:
            t.gps_problem = "latitude and longitude 0 (cameras without a fix write zeros)"
        else:
            t.latlon, t.ref_missing = (lat, lon), lat_ref_missing or lon_ref_missing
            alt = _fraction(gps.get(GPS_ALTITUDE))
            if alt is not None:
                # 0/1: above/below sea level; 2/3: above/below the ellipsoid (EXIF 3.0)
                t.alt_m = float(-alt if _first_byte(gps.get(GPS_ALTITUDE_REF, 0)) in (1, 3) else alt)
            error = _fraction(gps.get(GPS_H_POSITIONING_ERROR))
            dop = _fraction(gps.get(GPS_DOP))
            if error is not None and error > 0:
                t.sigma_m = float(error)
            elif dop is not None and dop > 0:
                t.sigma_m = float(dop) * uere_m

    focal = _focal_px(exif, width, height)
    if focal is not None:
        t.focal_px = (focal[1], focal[0]) if transposed else focal
    return t


@dataclass(frozen=True)
class Photo:
    """One photo as the reader delivers it: its stamp, intrinsics and fix (None without GPS)."""

    path: Path
    stamp_ns: int
    info: CameraInfo
    fix: GpsFix | None


# --- the reader ------------------------------------------------------------------------------------


def _photo_files(image_dir: Path, suffixes: tuple[str, ...]) -> list[Path]:
    return sorted(p for p in image_dir.iterdir() if p.suffix.lower() in suffixes and p.is_file())


def _has_gps(path: Path) -> bool:
    try:
        with Image.open(path) as im:
            gps = im.getexif().get_ifd(TAG_GPS_IFD)
            return GPS_LATITUDE in gps and GPS_LONGITUDE in gps
    except _UNREADABLE:
        return False


def _names(paths: list[Path], limit: int = 5) -> str:
    shown = ", ".join(p.name for p in paths[:limit])
    return shown + (f" and {len(paths) - limit} more" if len(paths) > limit else "")


class PhotoFolder(FolderLayoutLog):
    """Geotagged photos in a folder, read from their EXIF (see the module docstring).

    ``photos`` lists what is delivered, in stamp order.
    """

    format_name = "photos"

    def __init__(
        self, path: str | Path, *, camera: str = "camera", topic_prefix: str = "/photos", uere_m: float = DEFAULT_UERE_M
    ):
        super().__init__(path)
        self.camera = camera
        self.image_dir = self.path / "images" if (self.path / "images").is_dir() else self.path
        files = _photo_files(self.image_dir, PHOTO_SUFFIXES)
        if not files:
            raise InputError(self.image_dir, f"holds no photos ({', '.join(PHOTO_SUFFIXES)})")
        tags, unreadable = [], []
        for p in files:
            try:
                tags.append(_read_tags(p, uere_m))
            except _UNREADABLE:
                unreadable.append(p)
        if unreadable:
            self._warn(
                f"skipped {len(unreadable)} of {len(files)} files that Pillow cannot read: {_names(unreadable)}",
                stacklevel=3,
            )
        if not tags:
            raise InputError(self.image_dir, "holds no photo Pillow can read")
        self.photos = self._photos(self._keep_one_size(self._order(tags)))

        first = self.photos[0]
        self.layout = ImageLayout.of(read_photo(first.path))
        prefix = topic_prefix.rstrip("/")
        self.topics = {
            StreamKind.CAMERA_INFO: f"{prefix}/{camera}/camera_info",
            StreamKind.IMAGE: f"{prefix}/{camera}/image",
            StreamKind.GPS: f"{prefix}/gps/fix",
        }
        n_fix = sum(ph.fix is not None for ph in self.photos)
        counts = {StreamKind.CAMERA_INFO: len(self.photos), StreamKind.IMAGE: len(self.photos), StreamKind.GPS: n_fix}
        kinds = [k for k in self.topics if counts[k]]
        self._add([stream_info(self.topics[k], k, counts[k]) for k in kinds], self._iterate)

    @classmethod
    def detect(cls, path: Path) -> bool:
        """A folder (or its images/) with at least 3 JPEG/TIFF photos carrying EXIF GPS and no frame table."""
        path = Path(path)
        if not path.is_dir() or FolderLog.detect(path):
            return False
        image_dir = path / "images" if (path / "images").is_dir() else path
        geotagged = 0
        for p in _photo_files(image_dir, DETECT_SUFFIXES)[:DETECT_MAX_FILES]:
            geotagged += _has_gps(p)
            if geotagged >= DETECT_MIN_GEOTAGGED:
                return True
        return False

    # --- folder-wide choices ---------------------------------------------------------------------
    def _warn(self, what: str, stacklevel: int = 4) -> None:
        """One warning per kind of problem; ``stacklevel`` points it at the code that opened the folder."""
        warnings.warn(f"{self.image_dir}: {what}", InputWarning, stacklevel=stacklevel)

    def _order(self, tags: list[_Tags]) -> list[_Tags]:
        """Photos in time order (name order without time), each with a unique stamp."""
        n = len(tags)
        timeless = [t for t in tags if t.time_ns is None]
        if timeless:
            self._warn(
                f"{len(timeless)} of {n} photos have no time (DateTimeOriginal or GPSDateStamp+GPSTimeStamp): "
                f"{_names([t.path for t in timeless])}; all photos are ordered by file name, 1 s apart"
            )
            ordered = sorted(tags, key=lambda t: t.path.name)
            for i, t in enumerate(ordered):
                t.time_ns = i * NAME_ONLY_SPACING_NS
            return ordered
        local = sum(t.time_kind == "local" for t in tags)
        if local:
            self._warn(
                f"{local} of {n} photos have DateTimeOriginal without OffsetTimeOriginal: their stamps are the "
                "camera's local clock read as UTC"
            )
        from_gps = sum(t.time_kind == "gps" for t in tags)
        if from_gps:
            self._warn(
                f"{from_gps} of {n} photos have no DateTimeOriginal: their time is GPSDateStamp+GPSTimeStamp (UTC)"
            )
        ordered = sorted(tags, key=lambda t: (t.time_ns, t.path.name))
        nudged = 0
        for prev, t in pairwise(ordered):  # none is timeless here
            if t.stamp_ns <= prev.stamp_ns:
                t.time_ns, nudged = prev.stamp_ns + 1, nudged + 1
        if nudged:
            self._warn(
                f"{nudged} of {n} photos have the same time as the one before: each is stamped 1 ns after it, "
                "in file name order"
            )
        return ordered

    def _keep_one_size(self, tags: list[_Tags]) -> list[_Tags]:
        """The photos of the most common (upright size, pixel mode); ties go to the earliest photo's."""
        counts = Counter((t.size, t.mode) for t in tags)
        keep = max(counts, key=counts.__getitem__)  # max keeps the first of equals, and a Counter counts in order seen
        other = [t.path for t in tags if (t.size, t.mode) != keep]
        if other:
            (w, h), mode = keep
            self._warn(
                f"skipped {len(other)} of {len(tags)} photos that are not {w}x{h} {mode} like the others: "
                f"{_names(other)}"
            )
        return [t for t in tags if (t.size, t.mode) == keep]

    def _photos(self, tags: list[_Tags]) -> list[Photo]:
        """Records of the kept photos, with one warning per kind of missing tag."""
        n = len(tags)
        (w, h) = tags[0].size
        no_focal = sum(t.focal_px is None for t in tags)
        if no_focal:
            self._warn(
                f"{no_focal} of {n} photos have no focal length (FocalLengthIn35mmFilm, or FocalLength with "
                f"FocalPlaneX/YResolution): fx = fy = {DEFAULT_FOCAL_FACTOR} * max(width, height) = "
                f"{DEFAULT_FOCAL_FACTOR * max(w, h):.1f} px assumed"
            )
        focals = {round(t.focal_px[0], 1) for t in tags if t.focal_px is not None}
        if len(focals) > 1:
            self._warn(
                f"the photos have {len(focals)} different focal lengths ({min(focals)} to {max(focals)} px): "
                "each photo's camera_info carries its own, but a single camera model is refined from them"
            )

        geotagged = [t for t in tags if t.latlon is not None]
        if len(geotagged) < n:
            problems = Counter(t.gps_problem for t in tags if t.latlon is None)
            why = "; ".join(f"{k}: {c}" for k, c in problems.items() if k)
            self._warn(
                f"{n - len(geotagged)} of {n} photos have no GPS fix"
                + (f" ({why})" if why else "")
                + ": their images are read, without a fix"
            )
        if any(t.ref_missing for t in geotagged):
            self._warn(
                f"{sum(t.ref_missing for t in geotagged)} of {len(geotagged)} geotagged photos have no "
                "GPSLatitudeRef/GPSLongitudeRef: taken as north/east"
            )
        alts = [t.alt_m for t in geotagged if t.alt_m is not None]
        fill_alt = float(np.median(alts)) if alts else 0.0
        if len(alts) < len(geotagged):
            self._warn(
                f"{len(geotagged) - len(alts)} of {len(geotagged)} geotagged photos have no GPSAltitude: "
                f"{fill_alt:.2f} m ({'the median of the others' if alts else 'no photo has one'}) is used"
            )
        no_sigma = sum(t.sigma_m is None for t in geotagged)
        if no_sigma:
            self._warn(
                f"{no_sigma} of {len(geotagged)} geotagged photos have no GPS accuracy (GPSHPositioningError "
                "or GPSDOP): their fixes carry no covariance"
            )

        photos = []
        for t in tags:
            fx, fy = t.focal_px if t.focal_px is not None else (DEFAULT_FOCAL_FACTOR * max(w, h),) * 2
            K = np.array([[fx, 0.0, (w - 1) / 2.0], [0.0, fy, (h - 1) / 2.0], [0.0, 0.0, 1.0]])
            info = CameraInfo(self.camera, w, h, K, "plumb_bob", np.zeros(5), t.stamp_ns)
            fix = None
            if t.latlon is not None:
                cov = None if t.sigma_m is None else np.eye(3) * t.sigma_m**2
                alt = fill_alt if t.alt_m is None else t.alt_m
                fix = GpsFix(t.stamp_ns, t.latlon[0], t.latlon[1], alt, GpsStatus.FIX, cov)
            photos.append(Photo(t.path, t.stamp_ns, info, fix))
        return photos

    # --- messages --------------------------------------------------------------------------------
    def _frame(self, photo: Photo) -> CameraFrame:
        layout, camera = self.layout, self.camera

        def load() -> np.ndarray:
            img = read_photo(photo.path)
            got = ImageLayout.of(img)
            if got != layout:
                raise InputError(photo.path, f"image is {got}, but the first photo of {camera} is {layout}")
            return img

        return CameraFrame(photo.stamp_ns, camera, loader=load, encoding=layout.encoding, source=str(photo.path))

    def _iterate(self, wanted: Wanted) -> Iterator[Message]:
        t = self.topics
        want_info, want_image, want_gps = (
            wanted(t[k]) for k in (StreamKind.CAMERA_INFO, StreamKind.IMAGE, StreamKind.GPS)
        )
        n_fix = 0
        for i, photo in enumerate(self.photos):
            if want_info:
                yield Message(t[StreamKind.CAMERA_INFO], StreamKind.CAMERA_INFO, i, photo.info)
            if want_image:
                yield Message(t[StreamKind.IMAGE], StreamKind.IMAGE, i, self._frame(photo))
            if want_gps and photo.fix is not None:
                yield Message(t[StreamKind.GPS], StreamKind.GPS, n_fix, photo.fix)
                n_fix += 1
