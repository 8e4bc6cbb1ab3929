"""Geotagged photo folders: photos written by Pillow with known EXIF tags, read back exactly.

``write_geotagged_folder`` writes such a folder from arrays (for end-to-end tests too).
"""

from __future__ import annotations

import math
import shutil
import warnings
from collections.abc import Sequence
from datetime import datetime, timezone
from fractions import Fraction
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image
from PIL.TiffImagePlugin import IFDRational

from mapkit.core.errors import InputError, InputWarning
from mapkit.core.geodesy import LocalFrame
from mapkit.core.types import StreamKind
from mapkit.io import guess_format, open_log
from mapkit.io.folder import FolderLog
from mapkit.io.photos import (
    GPS_ALTITUDE,
    GPS_ALTITUDE_REF,
    GPS_DATESTAMP,
    GPS_DOP,
    GPS_H_POSITIONING_ERROR,
    GPS_LATITUDE,
    GPS_LATITUDE_REF,
    GPS_LONGITUDE,
    GPS_LONGITUDE_REF,
    GPS_STATUS,
    GPS_TIMESTAMP,
    TAG_DATETIME_ORIGINAL,
    TAG_EXIF_IFD,
    TAG_FOCAL_LENGTH,
    TAG_FOCAL_LENGTH_35MM,
    TAG_FOCAL_PLANE_RESOLUTION_UNIT,
    TAG_FOCAL_PLANE_X_RESOLUTION,
    TAG_FOCAL_PLANE_Y_RESOLUTION,
    TAG_GPS_IFD,
    TAG_OFFSET_TIME_ORIGINAL,
    TAG_ORIENTATION,
    TAG_PIXEL_X_DIMENSION,
    TAG_PIXEL_Y_DIMENSION,
    TAG_SUBSEC_TIME_ORIGINAL,
    PhotoFolder,
)

TOPIC_IMAGE, TOPIC_INFO, TOPIC_GPS = "/photos/camera/image", "/photos/camera/camera_info", "/photos/gps/fix"


# --- writing photos with EXIF ----------------------------------------------------------------------


def _dms(deg: float) -> tuple[IFDRational, IFDRational, IFDRational]:
    """|deg| as (degrees, minutes, seconds) rationals; seconds to 1e-6 (3e-5 m on the ground)."""
    micro_arcsec = round(abs(deg) * 3600 * 1_000_000)
    d, rest = divmod(micro_arcsec, 3600 * 1_000_000)
    m, s = divmod(rest, 60 * 1_000_000)
    return IFDRational(d), IFDRational(m), IFDRational(Fraction(s, 1_000_000))


def gps_tags(lat: float, lon: float, alt: float | None = None) -> dict:
    tags = {
        GPS_LATITUDE_REF: "N" if lat >= 0 else "S",
        GPS_LATITUDE: _dms(lat),
        GPS_LONGITUDE_REF: "E" if lon >= 0 else "W",
        GPS_LONGITUDE: _dms(lon),
    }
    if alt is not None:
        tags[GPS_ALTITUDE_REF] = b"\x01" if alt < 0 else b"\x00"
        tags[GPS_ALTITUDE] = IFDRational(Fraction(round(abs(alt) * 1000), 1000))
    return tags


def time_tags(stamp_ns: int, offset_minutes: int | None = 0) -> dict:
    """DateTimeOriginal + SubSecTimeOriginal (9 digits) in the local time of the offset, and the offset."""
    seconds, frac = divmod(stamp_ns, 1_000_000_000)
    local = datetime.fromtimestamp(seconds + 60 * (offset_minutes or 0), tz=timezone.utc)
    tags = {TAG_DATETIME_ORIGINAL: local.strftime("%Y:%m:%d %H:%M:%S"), TAG_SUBSEC_TIME_ORIGINAL: f"{frac:09d}"}
    if offset_minutes is not None:
        sign = "-" if offset_minutes < 0 else "+"
        tags[TAG_OFFSET_TIME_ORIGINAL] = f"{sign}{abs(offset_minutes) // 60:02d}:{abs(offset_minutes) % 60:02d}"
    return tags


def write_photo(
    path: Path,
    image: np.ndarray,
    *,
    exif: dict | None = None,
    gps: dict | None = None,
    orientation: int | None = None,
    quality: int = 95,
) -> Path:
    """``image`` (grey, or BGR as mapkit holds frames) with the given Exif-IFD and GPS-IFD tags."""
    rgb = image if image.ndim == 2 else image[..., ::-1]
    tags = Image.Exif()
    if orientation is not None:
        tags[TAG_ORIENTATION] = orientation
    if exif:
        tags.get_ifd(TAG_EXIF_IFD).update(exif)
    if gps:
        tags.get_ifd(TAG_GPS_IFD).update(gps)
    extra = {"quality": quality} if path.suffix.lower() in (".jpg", ".jpeg") else {}
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.ascontiguousarray(rgb)).save(path, exif=tags.tobytes(), **extra)
    return path


def write_geotagged_folder(
    folder: Path,
    images: Sequence[np.ndarray],
    latlonalt: np.ndarray,
    stamps_ns: Sequence[int],
    f35mm: int | None,
    *,
    quality: int = 95,
) -> Path:
    """A folder of JPEGs ``NNNNNN.jpg`` as a phone writes them: GPS (a NaN latitude: no GPS, a NaN
    altitude: no altitude), DateTimeOriginal in UTC with nanosecond SubSecTimeOriginal and offset
    +00:00, FocalLengthIn35mmFilm (None: none). ``images`` are grey or BGR uint8 arrays."""
    latlonalt = np.asarray(latlonalt, np.float64)
    for i, (image, (lat, lon, alt), stamp) in enumerate(zip(images, latlonalt, stamps_ns, strict=True)):
        exif = time_tags(int(stamp))
        if f35mm is not None:
            exif[TAG_FOCAL_LENGTH_35MM] = int(f35mm)
        gps = None if math.isnan(lat) else gps_tags(lat, lon, None if math.isnan(alt) else alt)
        write_photo(folder / f"{i:06d}.jpg", image, exif=exif, gps=gps, quality=quality)
    return folder


def _image(i: int, h: int = 24, w: int = 32) -> np.ndarray:
    return ((np.arange(h * w * 3).reshape(h, w, 3) * 5 + 37 * i) % 256).astype(np.uint8)


def _fixes(log) -> list:
    return [m.record for m in log.messages(topics=[TOPIC_GPS])]


def _by_kind(caught) -> list[str]:
    return [str(w.message) for w in caught if issubclass(w.category, InputWarning)]


# --- known answers ------------------------------------------------------------------------------------

T0 = 1_714_566_896_000_000_000  # 2024-05-01 12:34:56 UTC


def test_gps_time_and_35mm_focal_read_back_exactly(tmp_path):
    # names in the reverse of time order: the reader must order by time
    truth = [  # name, lat, lon, alt, stamp (UTC ns), UTC offset of the camera clock (minutes)
        ("c.jpg", 48.137154, 11.576124, 519.25, T0 + 123_456_789, 120),
        ("b.jpg", -33.8567844, 151.2152967, -12.5, T0 + 1_500_000_000, -330),
        ("a.jpg", 40.6892494, -74.0445004, 3.0, T0 + 2_000_000_001, 0),
    ]
    for name, lat, lon, alt, stamp, offset in truth:
        exif = {**time_tags(stamp, offset), TAG_FOCAL_LENGTH_35MM: 28}
        gps = gps_tags(lat, lon, alt)
        if name == "c.jpg":
            gps[GPS_H_POSITIONING_ERROR] = IFDRational(Fraction(7, 2))
            gps[GPS_DOP] = IFDRational(Fraction(3, 2))  # the positioning error wins over DOP
        if name == "b.jpg":
            gps[GPS_DOP] = IFDRational(Fraction(3, 2))
        write_photo(tmp_path / name, _image(0), exif=exif, gps=gps)

    log = PhotoFolder(tmp_path)
    frames = [m.record for m in log.messages(topics=[TOPIC_IMAGE])]
    assert [Path(f.source).name for f in frames] == ["c.jpg", "b.jpg", "a.jpg"]
    assert [f.stamp_ns for f in frames] == [t[4] for t in truth]
    fixes = _fixes(log)
    assert [f.stamp_ns for f in fixes] == [t[4] for t in truth]
    for fix, (_, lat, lon, alt, *_rest) in zip(fixes, truth, strict=True):
        assert abs(fix.lat_deg - lat) < 1e-7 and abs(fix.lon_deg - lon) < 1e-7
        assert fix.alt_m == pytest.approx(alt, abs=1e-9)
    assert fixes[0].horizontal_sigma_m == pytest.approx(3.5)
    assert fixes[1].horizontal_sigma_m == pytest.approx(1.5 * 5.0)  # DOP x 5 m
    assert math.isnan(fixes[2].horizontal_sigma_m) and fixes[2].covariance_enu_m2 is None

    infos = [m.record for m in log.messages(topics=[TOPIC_INFO])]
    f = 28 * math.hypot(32, 24) / math.hypot(36, 24)  # 35 mm equivalent, by the diagonal: 40 px * 28 / 43.27
    for info in infos:
        assert (info.width, info.height) == (32, 24)
        assert (info.fx, info.fy, info.cx, info.cy) == pytest.approx((f, f, 15.5, 11.5), abs=1e-9)
    assert [i.stamp_ns for i in infos] == [t[4] for t in truth]
    assert log.streams()[2].count == 3


def test_focal_plane_resolution_and_resized_copy(tmp_path):
    # a 4.5 mm lens on a sensor of 2000 px per 0.7 cm (x) and 2100 px per 0.7 cm (y), recorded at 64x48
    # and stored resized to 32x24: fx = 4.5 mm * 2000/7 px/mm / 2 and fy = 4.5 * 2100/7 / 2
    exif = {
        **time_tags(T0),
        TAG_FOCAL_LENGTH: IFDRational(Fraction(9, 2)),
        TAG_FOCAL_PLANE_X_RESOLUTION: IFDRational(Fraction(2000, 7) * 10),
        TAG_FOCAL_PLANE_Y_RESOLUTION: IFDRational(Fraction(2100, 7) * 10),
        TAG_FOCAL_PLANE_RESOLUTION_UNIT: 3,
        TAG_PIXEL_X_DIMENSION: 64,
        TAG_PIXEL_Y_DIMENSION: 48,
    }
    for i in range(3):
        write_photo(
            tmp_path / f"p{i}.jpg",
            _image(i),
            exif={**exif, **time_tags(T0 + i)},
            gps=gps_tags(48.0, 11.0 + i * 1e-4, 500.0),
        )
    (info,) = PhotoFolder(tmp_path).camera_infos().values()
    assert (info.fx, info.fy) == pytest.approx((4.5 * 2000 / 7 / 2, 4.5 * 2100 / 7 / 2), rel=1e-9)


@pytest.mark.parametrize(
    "orientation, upright",
    [
        (1, lambda a: a),
        (2, lambda a: a[:, ::-1]),
        (3, lambda a: a[::-1, ::-1]),
        (4, lambda a: a[::-1]),
        (5, lambda a: a.swapaxes(0, 1)),
        (6, lambda a: np.rot90(a, -1)),
        (7, lambda a: np.rot90(a, 2).swapaxes(0, 1)),
        (8, lambda a: np.rot90(a, 1)),
    ],
)
def test_orientation_turns_pixels_and_intrinsics_upright(tmp_path, orientation, upright):
    """Stored pixels turned as EXIF orientation says (1: as stored, 6: the camera was turned 90 degrees
    clockwise, so the stored image is turned clockwise to show it); lossless PNG, so exact."""
    stored = _image(0, 24, 32)
    exif = {
        TAG_FOCAL_LENGTH: IFDRational(4),
        TAG_FOCAL_PLANE_X_RESOLUTION: IFDRational(10),
        TAG_FOCAL_PLANE_Y_RESOLUTION: IFDRational(12),
        TAG_FOCAL_PLANE_RESOLUTION_UNIT: 4,
    }
    for i in range(3):
        write_photo(
            tmp_path / f"p{i}.png",
            stored,
            exif={**exif, **time_tags(T0 + i)},
            gps=gps_tags(1.0, 2.0 + i * 1e-4),
            orientation=orientation,
        )
    log = PhotoFolder(tmp_path)
    frame = next(log.records(StreamKind.IMAGE))
    assert frame.encoding == "bgr8" and not frame.is_loaded
    np.testing.assert_array_equal(frame.image, upright(stored))
    info = next(log.records(StreamKind.CAMERA_INFO))
    h, w = upright(stored).shape[:2]
    transposed = orientation >= 5
    assert (info.width, info.height) == (w, h) == ((24, 32) if transposed else (32, 24))
    assert (info.fx, info.fy) == ((48.0, 40.0) if transposed else (40.0, 48.0))
    assert (info.cx, info.cy) == ((w - 1) / 2, (h - 1) / 2)


def test_tiff_photos_and_images_subfolder(tmp_path):
    for i in range(3):
        write_photo(
            tmp_path / "images" / f"t{i}.tif",
            _image(i)[..., 0],
            exif=time_tags(T0 + i * 10**8),
            gps=gps_tags(10.5, -20.25 - i * 1e-5, 7.0),
        )
    assert PhotoFolder.detect(tmp_path)
    log = PhotoFolder(tmp_path)
    frames = list(log.records(StreamKind.IMAGE))
    assert frames[1].encoding == "mono8"
    np.testing.assert_array_equal(frames[1].image, _image(1)[..., 0])
    assert [round(f.lon_deg, 7) for f in _fixes(log)] == [-20.25, -20.25001, -20.25002]


def test_missing_tags_warn_once_per_kind(tmp_path):
    """Six photos: two without GPS, one geotagged without altitude, none with accuracy, local clock
    time, no focal length; one portrait photo that is skipped. One warning per kind, with counts."""
    for i in range(6):
        gps = None if i in (1, 4) else gps_tags(48.0 + i * 1e-4, 11.0, None if i == 2 else 500.0 + i)
        write_photo(tmp_path / f"p{i}.jpg", _image(i), exif=time_tags(T0 + i * 10**9, offset_minutes=None), gps=gps)
    write_photo(
        tmp_path / "portrait.jpg",
        _image(0, 32, 24),
        exif=time_tags(T0 + 10**10, offset_minutes=None),
        gps=gps_tags(48, 11, 1),
    )

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        log = PhotoFolder(tmp_path)
    messages = _by_kind(caught)
    expected = [
        "7 of 7 photos have DateTimeOriginal without OffsetTimeOriginal",  # counted before the size filter
        "skipped 1 of 7 photos that are not 32x24 RGB like the others: portrait.jpg",
        "6 of 6 photos have no focal length",
        "2 of 6 photos have no GPS fix",
        "1 of 4 geotagged photos have no GPSAltitude: 503.00 m (the median of the others)",
        "4 of 4 geotagged photos have no GPS accuracy",
    ]
    assert len(messages) == len(expected), messages
    for text in expected:
        assert sum(text in m for m in messages) == 1, (text, messages)

    assert [p.path.name for p in log.photos] == [f"p{i}.jpg" for i in range(6)]
    assert [p.stamp_ns for p in log.photos] == [T0 + i * 10**9 for i in range(6)]  # local clock read as UTC
    fixes = _fixes(log)
    assert [f.stamp_ns for f in fixes] == [T0 + i * 10**9 for i in (0, 2, 3, 5)]
    assert [f.alt_m for f in fixes] == [500.0, 503.0, 503.0, 505.0]
    info = log.camera_infos()["camera"]
    assert info.fx == info.fy == 1.2 * 32


def test_time_from_gps_then_from_names(tmp_path):
    gps_time = {
        GPS_DATESTAMP: "2024:05:01",
        GPS_TIMESTAMP: (IFDRational(12), IFDRational(34), IFDRational(Fraction(5625, 100))),
    }
    for i in range(3):
        write_photo(
            tmp_path / f"g{2 - i}.jpg",
            _image(i),
            gps={
                **gps_tags(1.0, 1.0 + i * 1e-4),
                **gps_time,
                GPS_TIMESTAMP: (IFDRational(12), IFDRational(34), IFDRational(56 + i)),
            },
        )
    with pytest.warns(InputWarning, match="3 of 3 photos have no DateTimeOriginal: their time is GPSDateStamp"):
        log = PhotoFolder(tmp_path)
    assert [p.stamp_ns for p in log.photos] == [T0, T0 + 10**9, T0 + 2 * 10**9]
    assert [p.path.name for p in log.photos] == ["g2.jpg", "g1.jpg", "g0.jpg"]

    # one photo without any time: every photo is placed by name, 1 s apart
    write_photo(tmp_path / "g9.jpg", _image(0), gps=gps_tags(1.0, 1.1))
    with pytest.warns(InputWarning, match="1 of 4 photos have no time .*g9.jpg; all photos are ordered by file name"):
        log = PhotoFolder(tmp_path)
    assert [p.path.name for p in log.photos] == ["g0.jpg", "g1.jpg", "g2.jpg", "g9.jpg"]
    assert [p.stamp_ns for p in log.photos] == [0, 10**9, 2 * 10**9, 3 * 10**9]


def test_equal_times_get_unique_stamps_in_name_order(tmp_path):
    for name in ("b.jpg", "a.jpg", "c.jpg"):
        write_photo(
            tmp_path / name,
            _image(0),
            exif={TAG_DATETIME_ORIGINAL: "2024:05:01 12:34:56", TAG_OFFSET_TIME_ORIGINAL: "+00:00"},
            gps=gps_tags(1.0, 1.0),
        )
    write_photo(tmp_path / "d.jpg", _image(0), exif=time_tags(T0 - 1), gps=gps_tags(1.0, 1.0))
    with pytest.warns(InputWarning, match="2 of 4 photos have the same time as the one before"):
        log = PhotoFolder(tmp_path)
    assert [p.path.name for p in log.photos] == ["d.jpg", "a.jpg", "b.jpg", "c.jpg"]
    assert [p.stamp_ns for p in log.photos] == [T0 - 1, T0, T0 + 1, T0 + 2]
    assert len(list(log.records(StreamKind.IMAGE))) == 4  # none is dropped as a duplicate


def test_void_or_zero_gps_is_no_fix_and_no_photos_is_an_error(tmp_path):
    for i in range(4):
        gps = {**(gps_tags(0.0, 0.0) if i == 3 else gps_tags(1.0, 1.0 + i * 1e-4)), GPS_STATUS: "V" if i == 1 else "A"}
        write_photo(tmp_path / f"p{i}.jpg", _image(i), exif=time_tags(T0 + i), gps=gps)
    with pytest.warns(
        InputWarning,
        match=r"2 of 4 photos have no GPS fix \(GPSStatus V \(measurement void\): 1; latitude and longitude 0",
    ):
        log = PhotoFolder(tmp_path)
    assert [f.stamp_ns for f in _fixes(log)] == [T0, T0 + 2]
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="holds no photos"):
        PhotoFolder(tmp_path / "empty")


def test_detect_never_claims_a_folder_of_the_frame_table_reader(tmp_path):
    for i in range(3):
        write_photo(tmp_path / f"p{i}.jpg", _image(i), exif=time_tags(T0 + i), gps=gps_tags(1.0, 1.0 + i * 1e-4))
    assert PhotoFolder.detect(tmp_path) and not FolderLog.detect(tmp_path)
    assert guess_format(tmp_path) == "photos"
    assert isinstance(open_log(tmp_path), PhotoFolder)

    (tmp_path / "frames.csv").write_text("timestamp_ns,image\n1,p0.jpg\n2,p1.jpg\n3,p2.jpg\n")
    assert FolderLog.detect(tmp_path) and not PhotoFolder.detect(tmp_path)
    assert guess_format(tmp_path) == "folder"

    # two geotagged photos and one without GPS are not enough
    other = tmp_path / "few"
    for i in range(3):
        write_photo(other / f"p{i}.jpg", _image(i), exif=time_tags(T0 + i), gps=None if i == 2 else gps_tags(1.0, 1.0))
    assert not PhotoFolder.detect(other)


# --- real images ------------------------------------------------------------------------------------


def test_kitti_frames_geotagged_along_their_poses_read_back(kitti_clip, tmp_path):
    """Eight real KITTI frames as JPEGs, geotagged along the ground-truth poses (camera z forward driving
    on a heading of 30 degrees east of north from a Karlsruhe origin): positions, stamps and focal length
    come back."""
    poses = np.loadtxt(kitti_clip / "poses.txt").reshape(-1, 3, 4)
    idx = np.arange(0, 48, 6)
    xyz = poses[idx, :, 3]  # camera positions in frame 0: x right, y down, z forward
    az = np.radians(30.0)
    forward, right = np.array([np.sin(az), np.cos(az), 0.0]), np.array([np.cos(az), -np.sin(az), 0.0])
    enu = xyz[:, :1] * right + xyz[:, 2:] * forward - xyz[:, 1:2] * np.array([0.0, 0.0, 1.0])
    frame = LocalFrame(49.011, 8.4236, 115.0)
    lat, lon, alt = frame.enu_to_geodetic(enu)
    images = [cv2.imread(str(kitti_clip / "image_l" / f"{i:06d}.png"), cv2.IMREAD_GRAYSCALE) for i in idx]
    stamps = [1_317_384_506_000_000_000 + int(i) * 100_000_000 for i in idx]
    fx_kitti = 707.0912
    f35 = round(fx_kitti * math.hypot(36, 24) / math.hypot(1226, 370))  # 24 mm: EXIF stores whole millimetres
    write_geotagged_folder(tmp_path / "walk", images, np.c_[lat, lon, alt], stamps, f35)

    log = open_log(tmp_path / "walk")
    assert isinstance(log, PhotoFolder)
    fixes = _fixes(log)
    assert [f.stamp_ns for f in fixes] == stamps
    np.testing.assert_allclose([f.lat_deg for f in fixes], lat, atol=1e-9)
    np.testing.assert_allclose([f.lon_deg for f in fixes], lon, atol=1e-9)
    back = frame.geodetic_to_enu([f.lat_deg for f in fixes], [f.lon_deg for f in fixes], [f.alt_m for f in fixes])
    assert np.abs(back - enu).max() < 1e-3  # metres: DMS seconds to 1e-6 and altitude to 1 mm
    assert np.linalg.norm(enu[-1] - enu[0]) > 30.0  # the clip drives forward

    info = log.camera_infos()["camera"]
    assert (info.width, info.height) == (1226, 370)
    assert info.fx == pytest.approx(fx_kitti, rel=0.01)  # the integer 35 mm focal length costs < 1 %
    assert (info.cx, info.cy) == (612.5, 184.5)
    frames = list(log.records(StreamKind.IMAGE))
    assert frames[3].encoding == "mono8"
    assert np.abs(frames[3].image.astype(int) - images[3]).mean() < 3.0  # JPEG at quality 95


def test_write_geotagged_folder_marks_missing_gps_and_altitude(tmp_path):
    latlonalt = np.array([[48.0, 11.0, 500.0], [np.nan, np.nan, np.nan], [48.001, 11.0, np.nan], [48.002, 11.0, 510.0]])
    write_geotagged_folder(tmp_path, [_image(i) for i in range(4)], latlonalt, [T0 + i for i in range(4)], None)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputWarning)
        log = PhotoFolder(tmp_path)
    fixes = _fixes(log)
    assert [f.stamp_ns for f in fixes] == [T0, T0 + 2, T0 + 3]
    assert [f.alt_m for f in fixes] == [500.0, 505.0, 510.0]


def test_unreadable_file_is_skipped(tmp_path):
    for i in range(3):
        write_photo(tmp_path / f"p{i}.jpg", _image(i), exif=time_tags(T0 + i), gps=gps_tags(1.0, 1.0))
    (tmp_path / "broken.jpg").write_bytes(b"not a jpeg")
    shutil.copy(tmp_path / "p0.jpg", tmp_path / "notes.txt")
    with pytest.warns(InputWarning, match="skipped 1 of 4 files that Pillow cannot read: broken.jpg"):
        log = PhotoFolder(tmp_path)
    assert len(log.photos) == 3
