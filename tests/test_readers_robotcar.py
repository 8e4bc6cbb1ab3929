"""Oxford RobotCar reader: synthetic drive folders with known content read back."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from pyproj import Transformer

from mapkit.core.errors import InputError, InputWarning
from mapkit.core.types import StreamKind
from mapkit.io import guess_format, open_log
from mapkit.io.robotcar import RobotCar

STAMPS_US = [1418381798076682, 1418381798139182, 1418381798201682]
BGR = (50, 100, 200)

GPS_HEADER = (
    "timestamp,num_satellites,latitude,longitude,altitude,latitude_sigma,longitude_sigma,altitude_sigma,"
    "northing,easting,down,utm_zone"
)
INS_HEADER = (
    "timestamp,ins_status,latitude,longitude,altitude,northing,easting,down,utm_zone,"
    "velocity_north,velocity_east,velocity_down,roll,pitch,yaw"
)
VO_HEADER = "source_timestamp,destination_timestamp,x,y,z,roll,pitch,yaw"


def _records(log, topic: str) -> list:
    return [m.record for m in log.messages(topics=[topic])]


def bayer_mosaic(bgr: tuple[int, int, int], pattern: str, shape=(8, 10)) -> np.ndarray:
    """What a Bayer sensor records of a uniform colour; ``pattern`` reads the 2x2 tile row by row."""
    value = {"B": bgr[0], "G": bgr[1], "R": bgr[2]}
    mosaic = np.zeros(shape, np.uint8)
    for letter, (dy, dx) in zip(pattern, [(0, 0), (0, 1), (1, 0), (1, 1)], strict=True):
        mosaic[dy::2, dx::2] = value[letter]
    return mosaic


def write_camera(drive: Path, folder: str, stamps_file: str, images: list[np.ndarray], stamps_us=STAMPS_US) -> None:
    (drive / folder).mkdir(parents=True, exist_ok=True)
    for ts, img in zip(stamps_us, images, strict=True):
        cv2.imwrite(str(drive / folder / f"{ts}.png"), img)
    (drive / stamps_file).write_text("".join(f"{ts} 1\n" for ts in stamps_us))


def write_csv(path: Path, header: str, rows: list[list]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(header + "\n" + "".join(",".join(map(str, r)) + "\n" for r in rows))


GPS_ROWS = [
    [STAMPS_US[0], 9, 51.7601, -1.2581, 110.5, 1.5, 1.25, 3.0, 5735000.0, 620000.0, -110.5, "30U"],
    [STAMPS_US[1], 8, 51.7602, -1.2583, 111.0, 2.0, 0.5, 4.0, 5735011.0, 619986.0, -111.0, "30U"],
]


def ins_row(ts, lat, lon, northing, easting, down, roll, pitch, yaw, zone="30U") -> list:
    return [ts, "INS_SOLUTION_GOOD", lat, lon, -down, northing, easting, down, zone, 0.0, 0.0, 0.0, roll, pitch, yaw]


def make_drive(root: Path) -> Path:
    drive = root / "2014-12-09-13-21-02"
    write_camera(drive, "stereo/centre", "stereo.timestamps", [bayer_mosaic(BGR, "GBRG")] * 3)
    write_camera(drive, "mono_left", "mono_left.timestamps", [bayer_mosaic(BGR, "RGGB")] * 2, STAMPS_US[:2])
    write_csv(drive / "gps" / "gps.csv", GPS_HEADER, GPS_ROWS)
    # on the zone's central meridian (3 W) grid north is true north
    write_csv(
        drive / "gps" / "ins.csv",
        INS_HEADER,
        [
            ins_row(STAMPS_US[0], 51.75, -3.0, 5735000.0, 500000.0, -100.0, 0.0, 0.0, 0.0),
            ins_row(STAMPS_US[1], 51.75, -3.0, 5735004.0, 500003.0, -101.5, 0.0, 0.0, np.pi / 2),
            ins_row(STAMPS_US[2], 51.75, -3.0, 5735004.0, 500003.0, -101.5, 0.0, 0.1, 0.0),
            ins_row(STAMPS_US[2] + 20000, 51.75, -3.0, 5735004.0, 500003.0, -101.5, 0.2, 0.0, 0.0),
        ],
    )
    t = [STAMPS_US[0] - 62500] + STAMPS_US
    write_csv(
        drive / "vo" / "vo.csv",
        VO_HEADER,
        [
            [t[1], t[0], 1.0, 0.0, 0.0, 0.0, 0.0, 0.1],
            [t[2], t[1], 1.0, 0.0, 0.0, 0.0, 0.0, 0.1],
            [t[3], t[2], 1.0, 0.5, 0.0, 0.0, 0.0, 0.0],
        ],
    )
    (drive / "lms_front").mkdir()
    scan = np.array([[1.0, 2.0, 30.0], [3.0, -4.0, 40.0]])
    for i, ts in enumerate(STAMPS_US):
        (scan + i).astype("<f8").tofile(drive / "lms_front" / f"{ts}.bin")
    return drive


# --- cameras ------------------------------------------------------------------------------------------


def test_cameras_are_demosaiced_with_their_bayer_patterns(tmp_path):
    log = RobotCar(make_drive(tmp_path))
    centre = _records(log, "/robotcar/stereo_centre/image")
    assert [f.stamp_ns for f in centre] == [ts * 1000 for ts in STAMPS_US]
    assert centre[0].encoding == "bgr8" and centre[0].camera == "stereo_centre"
    # a uniform colour comes back exactly away from the border only with the right pattern
    assert (centre[2].image[2:-2, 2:-2] == BGR).all()
    mono = _records(log, "/robotcar/mono_left/image")
    assert [f.stamp_ns for f in mono] == [ts * 1000 for ts in STAMPS_US[:2]]
    assert (mono[1].image[2:-2, 2:-2] == BGR).all()


def test_plain_images_pass_unchanged(tmp_path):
    drive = tmp_path / "drive"
    colour = np.dstack([np.full((6, 8), c, np.uint8) for c in (1, 2, 3)])
    write_camera(drive, "stereo/centre", "stereo.timestamps", [colour] * 3)
    write_camera(drive, "mono_rear", "mono_rear.timestamps", [bayer_mosaic(BGR, "RGGB")] * 3)
    log = RobotCar(drive, demosaic=False)
    np.testing.assert_array_equal(_records(log, "/robotcar/stereo_centre/image")[0].image, colour)
    rear = _records(log, "/robotcar/mono_rear/image")[0]
    assert rear.encoding == "mono8"
    np.testing.assert_array_equal(rear.image, bayer_mosaic(BGR, "RGGB"))


def test_image_listed_but_missing_is_skipped_with_a_warning(tmp_path):
    drive = make_drive(tmp_path)
    (drive / "stereo" / "centre" / f"{STAMPS_US[1]}.png").unlink()
    log = RobotCar(drive)
    with pytest.warns(InputWarning, match="not on disk"):
        frames = _records(log, "/robotcar/stereo_centre/image")
    assert [f.stamp_ns for f in frames] == [STAMPS_US[0] * 1000, STAMPS_US[2] * 1000]


def test_images_without_a_timestamps_file_are_read_in_stamp_order(tmp_path):
    drive = tmp_path / "drive"
    stamps = [999_000, 1_000_000, 10_000_000]  # name order differs from numeric order
    write_camera(drive, "stereo/centre", "stereo.timestamps", [bayer_mosaic(BGR, "GBRG")] * 3, stamps)
    (drive / "stereo.timestamps").unlink()
    frames = _records(RobotCar(drive), "/robotcar/stereo_centre/image")
    assert [f.stamp_ns for f in frames] == [s * 1000 for s in stamps]


# --- GPS, INS, VO ---------------------------------------------------------------------------------------


def test_gps_fixes(tmp_path):
    fixes = list(RobotCar(make_drive(tmp_path)).records(StreamKind.GPS))
    assert [f.stamp_ns for f in fixes] == [STAMPS_US[0] * 1000, STAMPS_US[1] * 1000]
    row = GPS_ROWS[1]
    assert (fixes[1].lat_deg, fixes[1].lon_deg, fixes[1].alt_m) == (row[2], row[3], row[4])
    # east is the longitude sigma, north the latitude sigma
    np.testing.assert_allclose(fixes[1].covariance_enu_m2, np.diag([0.5**2, 2.0**2, 4.0**2]))


def test_ins_poses_in_the_local_utm_frame(tmp_path):
    log = RobotCar(make_drive(tmp_path))
    poses = _records(log, "/robotcar/ins/pose")
    assert [p.stamp_ns for p in poses[:3]] == [ts * 1000 for ts in STAMPS_US]
    assert {(p.parent_frame, p.child_frame, p.source) for p in poses} == {("utm_local", "ins", "ins")}
    origin = log.ins_origin()
    assert (origin.epsg, origin.easting_m, origin.northing_m, origin.up_m) == (32630, 500000.0, 5735000.0, 100.0)

    # yaw 0 faces north; forward-left-up body: forward -> north, left -> west, up -> up
    np.testing.assert_allclose(
        poses[0].parent_from_child, [[0, -1, 0, 0], [1, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], atol=1e-12
    )
    # x = easting - e0, y = northing - n0, z = -(down - down0); NED yaw +90 deg faces east
    np.testing.assert_allclose(poses[1].parent_from_child[:3, 3], [3.0, 4.0, 1.5])
    np.testing.assert_allclose(poses[1].parent_from_child[:3, 0], [1.0, 0.0, 0.0], atol=1e-12)
    # NED pitch positive = nose up
    np.testing.assert_allclose(poses[2].parent_from_child[:3, 0], [0.0, np.cos(0.1), np.sin(0.1)], atol=1e-12)
    # NED roll positive = right side down, so the left side rises
    np.testing.assert_allclose(poses[3].parent_from_child[:3, 1], [-np.cos(0.2), 0.0, np.sin(0.2)], atol=1e-12)


def test_ins_heading_agrees_with_the_grid_direction_of_travel(tmp_path):
    # drive due true north through Oxford (1.25 W, 1.75 deg east of zone 30's central meridian)
    to_utm = Transformer.from_crs(4326, 32630, always_xy=True)
    lats = 51.75 + 1e-4 * np.arange(4)
    east, north = to_utm.transform(np.full(4, -1.25), lats)
    rows = [
        ins_row(STAMPS_US[0] + 50000 * k, lats[k], -1.25, north[k], east[k], -60.0, 0.0, 0.0, 0.0) for k in range(4)
    ]
    drive = tmp_path / "drive"
    write_csv(
        drive / "gps" / "ins.csv",
        INS_HEADER,
        [[repr(float(v)) if isinstance(v, float) else v for v in r] for r in rows],
    )
    travel = np.diff(np.column_stack([east, north]), axis=0)
    travel /= np.linalg.norm(travel, axis=1, keepdims=True)

    def angle_to_travel(log) -> np.ndarray:
        forward = np.stack([p.parent_from_child[:2, 0] for p in _records(log, "/robotcar/ins/pose")])[:-1]
        cross = forward[:, 0] * travel[:, 1] - forward[:, 1] * travel[:, 0]
        return np.abs(np.arctan2(cross, np.sum(forward * travel, axis=1)))

    assert angle_to_travel(RobotCar(drive)).max() < 1e-6
    # ignoring the meridian convergence (as the SDK does) leaves about 1.37 degrees
    assert np.degrees(angle_to_travel(RobotCar(drive, grid_convergence=False))).min() == pytest.approx(1.37, abs=0.01)


def test_vo_accumulates_relative_poses_in_a_forward_left_up_frame(tmp_path):
    poses = _records(RobotCar(make_drive(tmp_path)), "/robotcar/vo/odometry")
    assert [p.stamp_ns for p in poses] == [(STAMPS_US[0] - 62500) * 1000] + [ts * 1000 for ts in STAMPS_US]
    assert {(p.parent_frame, p.child_frame, p.source) for p in poses} == {("vo_origin", "vehicle", "odometry")}
    # planar truth: yaw +0.1 about z-down is a right turn, i.e. -0.1 about z-up
    heading, position, expected = 0.0, np.zeros(2), [np.eye(4)]
    for forward_m, right_m, turn in [(1.0, 0.0, -0.1), (1.0, 0.0, -0.1), (1.0, 0.5, 0.0)]:
        fwd = np.array([np.cos(heading), np.sin(heading)])
        left = np.array([-np.sin(heading), np.cos(heading)])
        position = position + forward_m * fwd - right_m * left
        heading += turn
        T = np.eye(4)
        T[:2, :2] = [[np.cos(heading), -np.sin(heading)], [np.sin(heading), np.cos(heading)]]
        T[:2, 3] = position
        expected.append(T)
    np.testing.assert_allclose(np.stack([p.parent_from_child for p in poses]), np.stack(expected), atol=1e-12)


def test_vo_chain_break_warns(tmp_path):
    drive = make_drive(tmp_path)
    lines = (drive / "vo" / "vo.csv").read_text().splitlines()
    lines[3] = lines[3].replace(str(STAMPS_US[1]), str(STAMPS_US[1] + 1), 1)  # destination of row 3
    (drive / "vo" / "vo.csv").write_text("\n".join(lines) + "\n")
    with pytest.warns(InputWarning, match="line 4"):
        assert len(_records(RobotCar(drive), "/robotcar/vo/odometry")) == 4


# --- lidar ------------------------------------------------------------------------------------------------


def test_lms_scans_lie_in_their_scan_plane(tmp_path):
    scans = list(RobotCar(make_drive(tmp_path)).records(StreamKind.LIDAR))
    assert [s.stamp_ns for s in scans] == [ts * 1000 for ts in STAMPS_US]
    assert scans[1].frame_id == "lms_front"
    np.testing.assert_array_equal(scans[1].points_xyz, [[2.0, 3.0, 0.0], [4.0, -3.0, 0.0]])
    np.testing.assert_array_equal(scans[1].intensity, [31.0, 41.0])


def test_velodyne_binary_planes_and_raw_png_warning(tmp_path):
    drive = make_drive(tmp_path)
    (drive / "velodyne_left").mkdir()
    planes = np.array(
        [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [7.0, 8.0, 9.0], [10.0, 11.0, 12.0]], "<f4"
    )  # x, y, z, intensity
    planes.tofile(drive / "velodyne_left" / f"{STAMPS_US[0]}.bin")
    (drive / "velodyne_right").mkdir()
    cv2.imwrite(str(drive / "velodyne_right" / f"{STAMPS_US[0]}.png"), np.zeros((4, 4), np.uint8))
    with pytest.warns(InputWarning, match="raw Velodyne"):
        log = RobotCar(drive)
    assert "/robotcar/velodyne_right/points" not in log.topics_of(StreamKind.LIDAR)
    scan = _records(log, "/robotcar/velodyne_left/points")[0]
    np.testing.assert_array_equal(scan.points_xyz, [[1.0, 4.0, 7.0], [2.0, 5.0, 8.0], [3.0, 6.0, 9.0]])
    np.testing.assert_array_equal(scan.intensity, [10.0, 11.0, 12.0])


# --- errors and layout --------------------------------------------------------------------------------------


def test_csv_row_with_a_missing_value_names_file_line_and_column(tmp_path):
    drive = make_drive(tmp_path)
    gps = drive / "gps" / "gps.csv"
    gps.write_text(gps.read_text().rstrip("\n").rsplit(",", 1)[0] + "\n")  # line 3 loses utm_zone
    log = RobotCar(drive)
    with pytest.raises(InputError) as exc:
        list(log.records(StreamKind.GPS))
    assert exc.value.path == gps
    assert "line 3" in str(exc.value) and "utm_zone" in str(exc.value)


def test_csv_cell_that_is_not_a_number_names_file_line_and_column(tmp_path):
    drive = make_drive(tmp_path)
    ins = drive / "gps" / "ins.csv"
    lines = ins.read_text().splitlines()
    cells = lines[3].split(",")
    cells[13] = "0.1x"  # pitch
    lines[3] = ",".join(cells)
    ins.write_text("\n".join(lines) + "\n")
    log = RobotCar(drive)
    with pytest.raises(InputError) as exc:
        _records(log, "/robotcar/ins/pose")
    assert exc.value.path == ins
    assert "line 4" in str(exc.value) and "pitch" in str(exc.value) and "0.1x" in str(exc.value)


def test_header_without_a_needed_column_is_an_error(tmp_path):
    drive = make_drive(tmp_path)
    write_csv(drive / "vo" / "vo.csv", "source_timestamp,destination_timestamp,x,y,z,roll,pitch", [])
    with pytest.raises(InputError, match="yaw"):
        RobotCar(drive)


def test_optional_streams_are_absent_and_nothing_at_all_is_an_error(tmp_path):
    drive = tmp_path / "drive"
    write_camera(drive, "stereo/centre", "stereo.timestamps", [bayer_mosaic(BGR, "GBRG")] * 3)
    assert [s.topic for s in RobotCar(drive).streams()] == ["/robotcar/stereo_centre/image"]

    empty = tmp_path / "vo_only"
    write_csv(empty / "vo" / "vo.csv", VO_HEADER, [])
    with pytest.raises(InputError, match="no camera images"):
        RobotCar(empty)


def test_guess_format_picks_robotcar(tmp_path):
    drive = make_drive(tmp_path)
    assert guess_format(drive) == "robotcar"
    log = open_log(drive)
    assert isinstance(log, RobotCar)
    stamps = [m.stamp_ns for m in log.messages()]
    assert stamps == sorted(stamps)
