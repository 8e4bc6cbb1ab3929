"""KITTI odometry and raw readers: synthetic folders with known content read back, and the real clip."""

from __future__ import annotations

import shutil
import warnings
from datetime import datetime, timezone
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mapkit.core.config import TopicConfig, resolve_topics
from mapkit.core.errors import InputError, InputWarning
from mapkit.core.geodesy import LocalFrame
from mapkit.core.types import StreamKind
from mapkit.io import guess_format, open_log
from mapkit.io.kitti import KittiOdometry, KittiRaw
from mapkit.mapping.gps_align import align_to_gps
from mapkit.mapping.trajectory import TrajectoryConfig, choose_source, estimate_trajectory

REAL_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"

FX, FY, CX, CY = 700.0, 710.0, 320.5, 240.25
BASELINE_M = 0.54
# camera 2 of the real KITTI rig: its P holds small y and z offsets as well as the baseline
P2_KITTI = np.array(
    [
        [7.188560e02, 0.0, 6.071928e02, 4.538225e01],
        [0.0, 7.188560e02, 1.852157e02, -1.130887e-01],
        [0.0, 0.0, 1.0, 3.779761e-03],
    ]
)


def _records(log, topic: str) -> list:
    """Records of one topic (``DriveLog.records(kind, topic)`` returns every topic of ``kind``)."""
    return [m.record for m in log.messages(topics=[topic])]


def _K(fx=FX, fy=FY, cx=CX, cy=CY) -> np.ndarray:
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _line(values) -> str:
    return " ".join(f"{v:.12e}" for v in np.ravel(values))


def _gray(i: int, shape=(6, 8)) -> np.ndarray:
    img = (np.arange(shape[0] * shape[1]).reshape(shape) * 3 + 17 * i) % 256
    return img.astype(np.uint8)


def _random_poses(rng: np.random.Generator, n: int) -> np.ndarray:
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.from_rotvec(rng.normal(scale=0.3, size=(n, 3))).as_matrix()
    # a random walk of about 1 m per frame: poses a car can drive (the reader rejects moves faster than 100 m/s)
    T[:, :3, 3] = np.cumsum(rng.normal(scale=0.5, size=(n, 3)), axis=0)
    return T


def make_odometry(
    root: Path,
    rng: np.random.Generator,
    n: int = 4,
    *,
    times: list[str] | None = None,
    poses: bool = True,
    velodyne: np.ndarray | None = None,
    second_camera: bool = True,
) -> dict:
    """An odometry sequence folder; returns what was written."""
    root.mkdir(parents=True, exist_ok=True)
    (root / "image_0").mkdir()
    if second_camera:
        (root / "image_1").mkdir()
    for i in range(n):
        cv2.imwrite(str(root / "image_0" / f"{i:06d}.png"), _gray(i))
        if second_camera:
            cv2.imwrite(str(root / "image_1" / f"{i:06d}.png"), _gray(i + 100))
    P0 = np.hstack([_K(), np.zeros((3, 1))])
    P1 = np.hstack([_K(), np.array([[-FX * BASELINE_M], [0.0], [0.0]])])  # right camera, KITTI's convention
    Tr = np.hstack([Rotation.from_euler("xyz", [0.1, -0.2, 0.3]).as_matrix(), np.array([[0.27], [-0.08], [-0.06]])])
    (root / "calib.txt").write_text(
        f"P0: {_line(P0)}\nP1: {_line(P1)}\nP2: {_line(P2_KITTI)}\nP3: {_line(P2_KITTI)}\nTr: {_line(Tr)}\n"
    )
    T = _random_poses(rng, n)
    if poses:
        (root / "poses.txt").write_text("".join(_line(Ti[:3, :]) + "\n" for Ti in T))
    if times is not None:
        (root / "times.txt").write_text("\n".join(times) + "\n")
    if velodyne is not None:
        (root / "velodyne").mkdir()
        for i in range(n):
            (velodyne + i).astype("<f4").tofile(root / "velodyne" / f"{i:06d}.bin")
    return {"poses": T, "Tr": Tr}


TIMES = ["0.000000e+00", "1.036224e-01", "2.072449e-01", "3.108673e-01"]
TIMES_NS = [0, 103_622_400, 207_244_900, 310_867_300]  # the decimal strings read exactly


# --- odometry ---------------------------------------------------------------------------------------


def test_odometry_reads_back_stamps_pixels_poses_and_intrinsics(tmp_path, rng):
    written = make_odometry(tmp_path / "seq", rng, times=TIMES)
    log = KittiOdometry(tmp_path / "seq")

    frames = _records(log, "/kitti/camera_0/image")
    assert [f.stamp_ns for f in frames] == TIMES_NS
    assert all(isinstance(f.stamp_ns, int) for f in frames)
    assert not frames[2].is_loaded  # decoding waits for the first access
    for i, f in enumerate(frames):
        assert f.encoding == "mono8"
        np.testing.assert_array_equal(f.image, _gray(i))
    right = _records(log, "/kitti/camera_1/image")
    np.testing.assert_array_equal(right[3].image, _gray(103))

    gt = _records(log, "/kitti/ground_truth")
    assert [p.stamp_ns for p in gt] == TIMES_NS
    assert {(p.parent_frame, p.child_frame, p.source) for p in gt} == {("world", "camera_0", "ground_truth")}
    np.testing.assert_allclose(np.stack([p.parent_from_child for p in gt]), written["poses"], atol=1e-9)

    infos = log.camera_infos()
    assert set(infos) == {"camera_0", "camera_1"}
    np.testing.assert_allclose(infos["camera_0"].K, _K())
    assert (infos["camera_0"].width, infos["camera_0"].height) == (8, 6)


def test_odometry_extrinsics_follow_the_projection_matrices(tmp_path, rng):
    written = make_odometry(tmp_path / "seq", rng, times=TIMES)
    (tmp_path / "seq" / "image_2").mkdir()
    for i in range(4):
        cv2.imwrite(str(tmp_path / "seq" / "image_2" / f"{i:06d}.png"), np.dstack([_gray(i)] * 3))
    log = KittiOdometry(tmp_path / "seq")
    tf = {(t.parent_frame, t.child_frame): t.parent_from_child for t in log.transforms()}

    # the right camera sits one baseline along +x (right) of the left one
    camera_0_from_camera_1 = np.eye(4)
    camera_0_from_camera_1[0, 3] = BASELINE_M
    np.testing.assert_allclose(tf[("camera_0", "camera_1")], camera_0_from_camera_1, atol=1e-12)
    # projecting a camera-0 point with P2 must equal moving it into camera 2 and applying K2
    X0 = np.array([1.5, -0.7, 12.0, 1.0])
    camera_2_from_camera_0 = np.linalg.inv(tf[("camera_0", "camera_2")])
    uvw_p = P2_KITTI @ X0
    uvw_k = P2_KITTI[:, :3] @ (camera_2_from_camera_0 @ X0)[:3]
    np.testing.assert_allclose(uvw_k[:2] / uvw_k[2], uvw_p[:2] / uvw_p[2], atol=1e-9)
    Tr = written["Tr"]
    np.testing.assert_allclose(tf[("camera_0", "velodyne")][:3, :], Tr, atol=1e-12)
    assert log.camera_infos()["camera_2"].fx == pytest.approx(P2_KITTI[0, 0])


def test_odometry_without_times_uses_10hz_and_warns_once(tmp_path, rng):
    make_odometry(tmp_path / "seq", rng)
    with pytest.warns(InputWarning, match="times.txt") as record:
        log = KittiOdometry(tmp_path / "seq")
    assert len([w for w in record if issubclass(w.category, InputWarning)]) == 1
    stamps = [f.stamp_ns for f in _records(log, "/kitti/camera_0/image")]
    assert stamps == [0, 100_000_000, 200_000_000, 300_000_000]


def test_odometry_velodyne_points_and_sweep_times(tmp_path, rng):
    # front, left, right and rear-left points; reflectance in the 4th column
    pts = np.array([[10.0, 0.0, 0.5, 0.1], [0.0, 10.0, 0.5, 0.2], [0.0, -10.0, 0.5, 0.3], [-10.0, 1e-6, 0.5, 0.4]])
    make_odometry(tmp_path / "seq", rng, times=TIMES, velodyne=pts)
    log = KittiOdometry(tmp_path / "seq")
    scans = list(log.records(StreamKind.LIDAR))
    assert [s.stamp_ns for s in scans] == TIMES_NS
    np.testing.assert_allclose(scans[2].points_xyz, (pts + 2)[:, :3].astype(np.float32))
    np.testing.assert_allclose(scans[2].intensity, (pts + 2)[:, 3].astype(np.float32))
    s0 = scans[0]
    # the scanner turns clockwise seen from above (rear, left, front, right, rear) and faces
    # forward at the frame stamp: left points come 1/4 sweep early, right ones 1/4 sweep late
    np.testing.assert_allclose(s0.point_time_s, [0.0, -0.025, 0.025, -0.05], atol=1e-6)


def test_odometry_unlabelled_calib_lines_are_p0_p1_in_order(tmp_path, rng):
    make_odometry(tmp_path / "seq", rng, times=TIMES)
    P0 = np.hstack([_K(fx=500.0), np.zeros((3, 1))])
    P1 = np.hstack([_K(fx=500.0), np.array([[-500.0 * 0.3], [0.0], [0.0]])])
    (tmp_path / "seq" / "calib.txt").write_text(f"{_line(P0)}\n{_line(P1)}")  # no labels, no final newline
    log = KittiOdometry(tmp_path / "seq")
    assert log.camera_infos()["camera_0"].fx == 500.0
    tf = {(t.parent_frame, t.child_frame): t.parent_from_child for t in log.transforms()}
    np.testing.assert_allclose(tf[("camera_0", "camera_1")][:3, 3], [0.3, 0.0, 0.0], atol=1e-12)


def test_odometry_missing_calib_is_named(tmp_path, rng):
    make_odometry(tmp_path / "seq", rng, times=TIMES)
    (tmp_path / "seq" / "calib.txt").unlink()
    with pytest.raises(InputError, match="missing calibration") as exc:
        KittiOdometry(tmp_path / "seq")
    assert exc.value.path == tmp_path / "seq" / "calib.txt"


def test_odometry_malformed_calib_line_names_file_and_line(tmp_path, rng):
    make_odometry(tmp_path / "seq", rng, times=TIMES)
    calib = tmp_path / "seq" / "calib.txt"
    lines = calib.read_text().splitlines()
    lines[1] = "P1: " + " ".join(lines[1].split()[1:12])  # 11 numbers
    calib.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match="line 2") as exc:
        KittiOdometry(tmp_path / "seq")
    assert exc.value.path == calib and "11" in str(exc.value)


def test_odometry_pose_count_mismatch_names_poses_and_counts(tmp_path, rng):
    make_odometry(tmp_path / "seq", rng, times=TIMES)
    poses = tmp_path / "seq" / "poses.txt"
    poses.write_text("".join(poses.read_text().splitlines(keepends=True)[:3]))
    with pytest.raises(InputError) as exc:
        KittiOdometry(tmp_path / "seq")
    assert exc.value.path == poses
    assert "3 poses" in str(exc.value) and "4 images" in str(exc.value)


def test_odometry_malformed_pose_line_names_line(tmp_path, rng):
    make_odometry(tmp_path / "seq", rng, times=TIMES)
    poses = tmp_path / "seq" / "poses.txt"
    lines = poses.read_text().splitlines()
    lines[2] = lines[2].replace(lines[2].split()[5], "x1.0", 1)
    poses.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match="line 3") as exc:
        KittiOdometry(tmp_path / "seq")
    assert exc.value.path == poses


def test_odometry_camera_folders_must_agree(tmp_path, rng):
    make_odometry(tmp_path / "seq", rng, times=TIMES)
    (tmp_path / "seq" / "image_1" / "000003.png").unlink()
    with pytest.raises(InputError, match="3 images") as exc:
        KittiOdometry(tmp_path / "seq")
    assert exc.value.path == tmp_path / "seq" / "image_1"


def test_odometry_malformed_times_line_is_named(tmp_path, rng):
    make_odometry(tmp_path / "seq", rng, times=["0.0", "0.1", "zero point two", "0.3"])
    with pytest.raises(InputError, match="line 3") as exc:
        KittiOdometry(tmp_path / "seq")
    assert exc.value.path == tmp_path / "seq" / "times.txt"


# --- the real clip -----------------------------------------------------------------------------------


@pytest.mark.realdata
def test_real_kitti_clip(kitti_clip):
    assert guess_format(kitti_clip) == "kitti-odometry"
    with pytest.warns(InputWarning, match="times.txt"):  # the clip keeps no times.txt
        log = open_log(kitti_clip)
    assert isinstance(log, KittiOdometry)
    info = log.camera_infos()["camera_0"]
    assert (info.width, info.height) == (1226, 370)
    assert info.fx == pytest.approx(707.0912)
    assert info.cx == pytest.approx(601.8873)
    frames = list(log.records(StreamKind.IMAGE))
    assert len(frames) == 51
    img = frames[-1].image
    assert img.shape == (370, 1226) and img.dtype == np.uint8 and img.std() > 10
    gt = [p.parent_from_child for p in _records(log, "/kitti/ground_truth")]
    assert len(gt) == 51
    np.testing.assert_allclose(gt[0], np.eye(4), atol=1e-6)
    forward_m = gt[-1][2, 3] - gt[0][2, 3]  # camera z is forward
    assert 55.0 < forward_m < 65.0
    assert abs(gt[-1][0, 3]) < 0.1 * forward_m  # mostly straight


# --- raw ----------------------------------------------------------------------------------------------

# fractions stay within (0.05, 0.95) so that the sweep start/end below need no carry
STAMP_TEXT = ["2011-09-26 13:02:25.164389445", "2011-09-26 13:02:25.268554659", "2011-09-26 13:02:25.372719873"]


def _expected_ns(text: str) -> int:
    whole, frac = text.split(".")
    epoch = datetime.strptime(whole, "%Y-%m-%d %H:%M:%S").replace(tzinfo=timezone.utc).timestamp()
    return int(epoch) * 10**9 + int(frac)


def _oxts_values(i: int) -> list[float]:
    v = [49.0 + 1e-5 * i, 8.4 + 2e-5 * i, 115.0 + i] + [0.02, -0.03, 1.2 + 0.1 * i] + [float(k) for k in range(5)]
    v += [0.1, 0.2, 9.8] + [0.11, 0.21, 9.81] + [0.01, 0.02, 0.03] + [0.011, 0.021, 0.031]
    v += [0.05 + 0.01 * i, 0.02, 4, 9, 5, 5, 6]
    assert len(v) == 30
    return v


R_IMU_TO_VELO = Rotation.from_euler("z", 0.02).as_matrix()
T_IMU_TO_VELO = np.array([-0.81, 0.32, -0.8])
R_VELO_TO_CAM = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
T_VELO_TO_CAM = np.array([-0.004, -0.076, -0.27])
R_RECT_00 = Rotation.from_euler("xyz", [0.01, -0.005, 0.002]).as_matrix()


def make_raw(root: Path, n: int = 3, *, oxts_override: dict | None = None) -> Path:
    """A date folder with calibration and one _sync drive; returns the drive folder."""
    drive = root / "2011_09_26" / "2011_09_26_drive_0001_sync"
    for sub in ("image_02/data", "oxts/data", "velodyne_points/data"):
        (drive / sub).mkdir(parents=True)
    stamps = STAMP_TEXT[:n]
    for i in range(n):
        colour = np.dstack([_gray(i), _gray(i + 1), _gray(i + 2)])
        cv2.imwrite(str(drive / "image_02" / "data" / f"{i:010d}.png"), colour)
        values = (oxts_override or {}).get(i) or " ".join(repr(v) for v in _oxts_values(i))
        (drive / "oxts" / "data" / f"{i:010d}.txt").write_text(values + "\n")
        pts = np.array([[10.0, 0.0, 0.0, 0.5], [-10.0, 1e-6, 0.0, 0.5], [0.0, -10.0, 0.0, 0.5]], "<f4")
        pts.tofile(drive / "velodyne_points" / "data" / f"{i:010d}.bin")
    for sub in ("image_02", "oxts", "velodyne_points"):
        (drive / sub / "timestamps.txt").write_text("\n".join(stamps) + "\n")
    # sweeps start 50 ms before the camera trigger and end 50 ms after
    starts = [s[:-9] + f"{int(s[-9:]) - 50_000_000:09d}" for s in stamps]
    ends = [s[:-9] + f"{int(s[-9:]) + 50_000_000:09d}" for s in stamps]
    (drive / "velodyne_points" / "timestamps_start.txt").write_text("\n".join(starts) + "\n")
    (drive / "velodyne_points" / "timestamps_end.txt").write_text("\n".join(ends) + "\n")
    date = drive.parent
    P_rect_00 = np.hstack([_K(), np.zeros((3, 1))])
    (date / "calib_cam_to_cam.txt").write_text(
        "calib_time: 09-Jan-2012 13:57:47\ncorner_dist: 9.950000e-02\n"
        f"R_rect_00: {_line(R_RECT_00)}\nP_rect_00: {_line(P_rect_00)}\n"
        f"S_rect_02: 8.0 6.0\nR_rect_02: {_line(np.eye(3))}\nP_rect_02: {_line(P2_KITTI)}\n"
    )
    (date / "calib_velo_to_cam.txt").write_text(
        f"calib_time: 15-Mar-2012 11:37:16\nR: {_line(R_VELO_TO_CAM)}\nT: {_line(T_VELO_TO_CAM)}\ndelta_f: 0 0\n"
    )
    (date / "calib_imu_to_velo.txt").write_text(
        f"calib_time: 25-May-2012 16:47:16\nR: {_line(R_IMU_TO_VELO)}\nT: {_line(T_IMU_TO_VELO)}\n"
    )
    return drive


def test_raw_reads_exact_stamps_and_colour_pixels(tmp_path):
    drive = make_raw(tmp_path)
    log = KittiRaw(drive)
    frames = _records(log, "/kitti/camera_2/image")
    expected = [_expected_ns(s) for s in STAMP_TEXT]
    assert [f.stamp_ns for f in frames] == expected
    # premise: going through float64 seconds would lose these nanoseconds
    assert round(float(expected[0] / 10**9) * 1e9) != expected[0]
    assert frames[1].encoding == "bgr8"
    np.testing.assert_array_equal(frames[1].image, np.dstack([_gray(1), _gray(2), _gray(3)]))
    info = log.camera_infos()["camera_2"]
    np.testing.assert_allclose(info.K, P2_KITTI[:, :3])
    assert (info.width, info.height) == (8, 6)


def test_raw_oxts_gps_and_imu(tmp_path):
    drive = make_raw(tmp_path)
    log = KittiRaw(drive)
    fixes = list(log.records(StreamKind.GPS))
    v = _oxts_values(2)
    assert fixes[2].stamp_ns == _expected_ns(STAMP_TEXT[2])
    assert (fixes[2].lat_deg, fixes[2].lon_deg, fixes[2].alt_m) == (v[0], v[1], v[2])
    np.testing.assert_allclose(fixes[2].covariance_enu_m2, np.eye(3) * v[23] ** 2)

    imu = list(log.records(StreamKind.IMU))[2]
    assert imu.frame_id == "imu"
    np.testing.assert_array_equal(imu.angular_velocity_rad_s, v[17:20])  # wx wy wz
    np.testing.assert_array_equal(imu.linear_acceleration_m_s2, v[11:14])  # ax ay az
    level = list(KittiRaw(drive, imu_axes="level").records(StreamKind.IMU))[2]
    np.testing.assert_array_equal(level.angular_velocity_rad_s, v[20:23])  # wf wl wu
    np.testing.assert_array_equal(level.linear_acceleration_m_s2, v[14:17])  # af al au


@pytest.mark.parametrize(
    "roll, pitch, yaw, axis, expected",
    [
        (0.0, 0.0, np.pi / 2, 0, [0.0, 1.0, 0.0]),  # yaw 0 = east, counter-clockwise: pi/2 faces north
        (0.0, 0.3, 0.0, 0, [np.cos(0.3), 0.0, -np.sin(0.3)]),  # pitch positive = front down
        (0.2, 0.0, 0.0, 1, [0.0, np.cos(0.2), np.sin(0.2)]),  # roll positive = left side up
    ],
)
def test_raw_imu_orientation_follows_the_oxts_angle_conventions(tmp_path, roll, pitch, yaw, axis, expected):
    values = _oxts_values(0)
    values[3:6] = [roll, pitch, yaw]
    drive = make_raw(tmp_path, n=1, oxts_override={0: " ".join(map(repr, values))})
    imu = next(KittiRaw(drive).records(StreamKind.IMU))
    enu_from_imu = Rotation.from_quat(np.roll(imu.orientation_quat_wxyz, -1)).as_matrix()
    np.testing.assert_allclose(enu_from_imu[:, axis], expected, atol=1e-12)


def test_raw_velodyne_point_times_span_the_sweep(tmp_path):
    drive = make_raw(tmp_path)
    scan = list(KittiRaw(drive).records(StreamKind.LIDAR))[1]
    assert scan.stamp_ns == _expected_ns(STAMP_TEXT[1])
    # front = at the trigger (midway), rear just left of +pi = sweep start, right = 3/4 of the sweep
    np.testing.assert_allclose(scan.point_time_s, [0.0, -0.05, 0.025], atol=1e-6)


def test_raw_extrinsics_tree(tmp_path):
    drive = make_raw(tmp_path)
    tf = {(t.parent_frame, t.child_frame): t.parent_from_child for t in KittiRaw(drive).transforms()}
    assert set(tf) == {("imu", "velodyne"), ("velodyne", "camera_0"), ("camera_0", "camera_2")}
    p_imu = np.array([1.0, 2.0, 3.0])
    p_velo = R_IMU_TO_VELO @ p_imu + T_IMU_TO_VELO  # what calib_imu_to_velo.txt means
    np.testing.assert_allclose((tf[("imu", "velodyne")] @ np.append(p_velo, 1))[:3], p_imu, atol=1e-12)
    p_rect_cam0 = R_RECT_00 @ (R_VELO_TO_CAM @ p_velo + T_VELO_TO_CAM)  # KITTI devkit: R_rect * Tr_velo_to_cam
    np.testing.assert_allclose((tf[("velodyne", "camera_0")] @ np.append(p_rect_cam0, 1))[:3], p_velo, atol=1e-12)
    uvw = P2_KITTI @ np.append(p_rect_cam0, 1)
    p_cam2 = (np.linalg.inv(tf[("camera_0", "camera_2")]) @ np.append(p_rect_cam0, 1))[:3]
    uvw_k = P2_KITTI[:, :3] @ p_cam2
    np.testing.assert_allclose(uvw_k[:2] / uvw_k[2], uvw[:2] / uvw[2], atol=1e-9)


def test_raw_malformed_oxts_row_names_file_and_line(tmp_path):
    drive = make_raw(tmp_path, oxts_override={1: " ".join(["1.0"] * 29)})
    log = KittiRaw(drive)
    with pytest.raises(InputError, match="line 1") as exc:
        list(log.records(StreamKind.GPS))
    assert exc.value.path == drive / "oxts" / "data" / "0000000001.txt"
    assert "29 values" in str(exc.value)


def test_raw_timestamp_count_must_match_files(tmp_path):
    drive = make_raw(tmp_path)
    (drive / "oxts" / "timestamps.txt").write_text("\n".join(STAMP_TEXT[:2]) + "\n")
    with pytest.raises(InputError) as exc:
        KittiRaw(drive)
    assert exc.value.path == drive / "oxts" / "timestamps.txt"
    assert "2 timestamps" in str(exc.value) and "3 .txt files" in str(exc.value)


def test_raw_malformed_timestamp_names_line(tmp_path):
    drive = make_raw(tmp_path)
    (drive / "image_02" / "timestamps.txt").write_text(
        f"{STAMP_TEXT[0]}\n2011-09-26 13:02:26,068554659\n{STAMP_TEXT[2]}\n"
    )
    with pytest.raises(InputError, match="line 2"):
        KittiRaw(drive)


def test_messages_come_in_time_order_across_streams(tmp_path):
    stamps = [m.stamp_ns for m in KittiRaw(make_raw(tmp_path)).messages()]
    assert stamps == sorted(stamps) and len(stamps) > 10


def test_guess_format_picks_the_kitti_readers(tmp_path, rng):
    make_odometry(tmp_path / "seq", rng, times=TIMES)
    drive = make_raw(tmp_path / "raw")
    assert guess_format(tmp_path / "seq") == "kitti-odometry"
    assert guess_format(drive) == "kitti-raw"
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a complete raw drive reads without warnings
        assert isinstance(open_log(drive), KittiRaw)


# --- OXTS as an INS pose stream ----------------------------------------------------------------------


def _oxts_only(root: Path, n: int = 3) -> Path:
    """A raw drive with OXTS records and calibration, no images and no scans."""
    drive = make_raw(root, n)
    shutil.rmtree(drive / "image_02")
    shutil.rmtree(drive / "velodyne_points")
    return drive


def _poses(log) -> np.ndarray:
    return np.stack([p.parent_from_child for p in _records(log, "/kitti/oxts/pose")])


def test_raw_oxts_pose_is_the_devkit_mercator_pose(tmp_path):
    drive = _oxts_only(tmp_path)
    log = KittiRaw(drive)
    samples = _records(log, "/kitti/oxts/pose")
    assert [p.stamp_ns for p in samples] == [_expected_ns(s) for s in STAMP_TEXT]
    assert {(p.parent_frame, p.child_frame, p.source) for p in samples} == {("oxts_enu", "imu", "ins")}
    T = _poses(log)
    v0, v2 = _oxts_values(0), _oxts_values(2)
    # the spherical Mercator scaled by cos(lat0) is a local isometry at lat0 on a sphere of 6378137 m:
    # east = r cos(lat0) dlon exactly, north = r dlat to second order (< 1 um over these 2 m)
    r = 6378137.0
    np.testing.assert_allclose(T[0][:3, 3], 0.0, atol=1e-9)  # origin at the first record's position
    np.testing.assert_allclose(T[2][0, 3], r * np.cos(np.radians(v0[0])) * np.radians(v2[1] - v0[1]), atol=1e-6)
    np.testing.assert_allclose(T[2][1, 3], r * np.radians(v2[0] - v0[0]), atol=1e-6)
    assert T[2][2, 3] == pytest.approx(v2[2] - v0[2], abs=1e-9)
    # the orientation is the IMU's: Rz(yaw) Ry(pitch) Rx(roll) of the forward-left-up body in ENU
    imu = _records(log, "/kitti/oxts/imu")[2]
    np.testing.assert_allclose(
        T[2][:3, :3], Rotation.from_quat(np.roll(imu.orientation_quat_wxyz, -1)).as_matrix(), atol=1e-12
    )
    assert np.arctan2(T[2][1, 0], T[2][0, 0]) == pytest.approx(v2[5])  # heading of x: the OXTS yaw from east

    # the devkit's convertOxtsToPose: the first pose is the identity, the rest relative to it
    T_devkit = _poses(KittiRaw(drive, oxts_origin="first_pose"))
    np.testing.assert_allclose(T_devkit[0], np.eye(4), atol=1e-12)
    np.testing.assert_allclose(T_devkit, np.linalg.inv(T[0]) @ T, atol=1e-9)
    assert _records(KittiRaw(drive, oxts_origin="first_pose"), "/kitti/oxts/pose")[0].parent_frame == "oxts_first_pose"
    with pytest.raises(ValueError, match="oxts_origin"):
        KittiRaw(drive, oxts_origin="first")


def test_raw_oxts_only_drive_gives_a_pose_trajectory_and_lidar_wins_when_present(tmp_path):
    drive = _oxts_only(tmp_path / "a")
    log = KittiRaw(drive)
    assert choose_source(log, TrajectoryConfig(), resolve_topics(log, TopicConfig())) == "poses"
    traj = estimate_trajectory(log, TrajectoryConfig())
    assert traj.source == "poses:/kitti/oxts/pose" and traj.body_frame == "imu"
    np.testing.assert_allclose(traj.world_from_base, _poses(log), atol=1e-12)
    full = KittiRaw(make_raw(tmp_path / "b"))  # velodyne too: its pose stream stays, LiDAR odometry is chosen
    assert choose_source(full, TrajectoryConfig(), resolve_topics(full, TopicConfig())) == "lidar"
    assert resolve_topics(full, TopicConfig())[StreamKind.POSE] == ["/kitti/oxts/pose"]
    asked = estimate_trajectory(full, TrajectoryConfig(source="poses"))  # trajectory: {source: poses}
    assert asked.source == "poses:/kitti/oxts/pose" and len(asked) == 3


@pytest.fixture(scope="module")
def kitti_oxts() -> Path:
    """The real OXTS records of KITTI raw 2011_09_26_drive_0001; skipped with a reason when absent."""
    drive = REAL_DATA / "kitti-raw-0001-oxts" / "2011_09_26" / "2011_09_26_drive_0001_sync"
    if not (drive / "oxts" / "timestamps.txt").is_file():
        pytest.skip(f"real data not found at {drive} (expected ../shared/data/kitti-raw-0001-oxts beside the project)")
    return drive


def _real_poses_and_gps_enu(drive: Path) -> tuple[np.ndarray, np.ndarray, list]:
    log = open_log(drive)
    T = _poses(log)
    fixes = _records(log, "/kitti/oxts/gps")
    frame = LocalFrame(fixes[0].lat_deg, fixes[0].lon_deg, fixes[0].alt_m)
    enu = frame.geodetic_to_enu([f.lat_deg for f in fixes], [f.lon_deg for f in fixes], [f.alt_m for f in fixes])
    return T, enu, fixes


@pytest.mark.realdata
def test_real_oxts_heading_follows_the_gps_travel_direction(kitti_oxts):
    assert guess_format(kitti_oxts) == "kitti-raw"
    T, enu, _ = _real_poses_and_gps_enu(kitti_oxts)
    assert len(T) == 108
    heading = np.exp(1j * np.arctan2(T[:, 1, 0], T[:, 0, 0]))  # yaw of the body's x axis in the E/N plane
    errors = []
    for i in range(len(enu)):
        far = np.nonzero(np.linalg.norm(enu[i + 1 :, :2] - enu[i, :2], axis=1) >= 2.0)[0]
        if not len(far):
            break
        j = i + 1 + far[0]  # the first fix at least 2 m on
        travel = np.exp(1j * np.arctan2(enu[j, 1] - enu[i, 1], enu[j, 0] - enu[i, 0]))
        errors.append(abs(np.degrees(np.angle((heading[i] + heading[j]) / travel))))
    errors = np.array(errors)
    assert len(errors) > 90
    # measured on this drive: max 0.59 deg, median 0.35 deg over 103 segments
    assert errors.max() < 1.0


@pytest.mark.realdata
def test_real_oxts_positions_are_the_fixes_up_to_the_devkit_mercator_scales(kitti_oxts):
    T, enu, fixes = _real_poses_and_gps_enu(kitti_oxts)
    p = T[:, :3, 3]
    assert np.linalg.norm(enu[-1, :2]) > 100.0
    # the devkit's sphere (radius a) against WGS84 at the first fix: east scale a/N, north a/M
    a, f = 6378137.0, 1 / 298.257223563
    e2, lat = f * (2 - f), np.radians(fixes[0].lat_deg)
    N = a / np.sqrt(1 - e2 * np.sin(lat) ** 2)
    M = a * (1 - e2) / (1 - e2 * np.sin(lat) ** 2) ** 1.5
    # measured: the poses are 0.19 m from the fixes' exact ENU at the far end, 2.6 mm after these scales
    assert np.linalg.norm(p - enu, axis=1).max() < 0.2
    np.testing.assert_allclose(p, enu * [a / N, a / M, 1.0], atol=0.005)
    # what the build's georeferencing gets from them: 'yaw' (auto for a pose stream) 4.6 cm RMSE, 'yaw_scale' 1.9 mm
    sigma = np.array([f.horizontal_sigma_m for f in fixes])
    assert align_to_gps(p, enu, sigma, mode="yaw").stats()["residual_rmse_m"] < 0.06
    yaw_scale = align_to_gps(p, enu, sigma, mode="yaw_scale").stats()
    assert yaw_scale["residual_rmse_m"] < 0.005
    assert yaw_scale["scale"] == pytest.approx(1.00144, abs=2e-4)


@pytest.mark.realdata
def test_real_oxts_drive_gives_a_107_m_pose_trajectory(kitti_oxts):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # calib_imu_to_velo.txt and friends are there: nothing to warn about
        log = open_log(kitti_oxts)
        traj = estimate_trajectory(log, TrajectoryConfig())
    assert traj.source == "poses:/kitti/oxts/pose" and len(traj) == 108
    assert traj.body_frame == "imu"  # no base_link in KITTI's calibration: the trajectory is of the OXTS unit
    length = np.linalg.norm(np.diff(traj.world_from_base[:, :3, 3], axis=0), axis=1).sum()
    assert length == pytest.approx(107.0, abs=0.5)  # 106.97 m in the devkit's Mercator, 107.12 m in exact ENU


# --- KITTI odometry with velodyne/ only ---------------------------------------------------------------


def make_lidar_odometry(
    root: Path, rng: np.random.Generator, n: int = 4, *, calib: bool = True, poses: bool = True
) -> dict:
    """An odometry sequence as the LiDAR download unpacks (velodyne/, calib.txt, times.txt, poses.txt)."""
    written = make_odometry(root, rng, n, times=TIMES[:n], poses=poses, velodyne=np.zeros((1, 4)), second_camera=False)
    shutil.rmtree(root / "image_0")
    scans = [rng.normal(size=(5 + 3 * i, 4)).astype("<f4") for i in range(n)]
    for i, pts in enumerate(scans):
        pts.tofile(root / "velodyne" / f"{i:06d}.bin")
    if not calib:
        (root / "calib.txt").unlink()
    return {**written, "scans": scans}


def test_lidar_only_odometry_folder_reads_scans_poses_and_extrinsic(tmp_path, rng):
    written = make_lidar_odometry(tmp_path / "seq", rng)
    assert guess_format(tmp_path / "seq") == "kitti-odometry"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        log = open_log(tmp_path / "seq")
    assert {s.topic: s.kind for s in log.streams()} == {
        "/kitti/tf_static": StreamKind.TF,
        "/kitti/ground_truth": StreamKind.POSE,
        "/kitti/velodyne/points": StreamKind.LIDAR,
    }
    scans = _records(log, "/kitti/velodyne/points")
    assert [s.stamp_ns for s in scans] == TIMES_NS
    for scan, pts in zip(scans, written["scans"], strict=True):
        np.testing.assert_array_equal(scan.points_xyz, pts[:, :3])
        np.testing.assert_array_equal(scan.intensity, pts[:, 3])
    gt = _records(log, "/kitti/ground_truth")
    np.testing.assert_allclose(np.stack([p.parent_from_child for p in gt]), written["poses"], atol=1e-9)
    tf = {(t.parent_frame, t.child_frame): t.parent_from_child for t in log.transforms()}
    np.testing.assert_allclose(tf[("camera_0", "velodyne")][:3, :], written["Tr"], atol=1e-12)
    assert choose_source(log, TrajectoryConfig(), resolve_topics(log, TopicConfig())) == "lidar"


def test_lidar_only_odometry_without_calib_warns_only_when_poses_need_it(tmp_path, rng):
    make_lidar_odometry(tmp_path / "gt", rng, calib=False)
    with pytest.warns(InputWarning, match="poses.txt"):
        log = KittiOdometry(tmp_path / "gt")
    assert list(log.transforms()) == [] and len(_records(log, "/kitti/ground_truth")) == 4
    make_lidar_odometry(tmp_path / "plain", rng, calib=False, poses=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert len(list(KittiOdometry(tmp_path / "plain").records(StreamKind.LIDAR))) == 4


def test_lidar_only_odometry_counts_must_agree_and_lidar_off_is_named(tmp_path, rng):
    make_lidar_odometry(tmp_path / "seq", rng)
    with pytest.raises(InputError, match="lidar=False"):
        KittiOdometry(tmp_path / "seq", lidar=False)
    (tmp_path / "seq" / "velodyne" / "000003.bin").unlink()
    with pytest.raises(InputError) as exc:
        KittiOdometry(tmp_path / "seq")
    assert exc.value.path == tmp_path / "seq" / "times.txt" and "3 scans in velodyne/" in str(exc.value)
    assert not KittiOdometry.detect(tmp_path / "seq" / "velodyne")  # the scans' folder itself is no sequence


# --- bytes that are not text ----------------------------------------------------------------------


@pytest.mark.parametrize("name, line", [("calib.txt", 2), ("times.txt", 3), ("poses.txt", 4)])
def test_odometry_non_text_byte_names_file_and_line(tmp_path, rng, name, line):
    make_odometry(tmp_path / "seq", rng, times=TIMES)
    path = tmp_path / "seq" / name
    lines = path.read_bytes().splitlines(keepends=True)
    lines[line - 1] = lines[line - 1][:3] + b"\xe9" + lines[line - 1][3:]  # a Latin-1 e-acute
    path.write_bytes(b"".join(lines))
    with pytest.raises(InputError, match=f"line {line}") as exc:
        KittiOdometry(tmp_path / "seq")
    assert exc.value.path == path


def test_raw_non_text_byte_names_file_and_line(tmp_path):
    drive = _oxts_only(tmp_path)
    record = drive / "oxts" / "data" / "0000000001.txt"
    record.write_bytes(b"\xff" + record.read_bytes())
    with pytest.raises(InputError, match="line 1.*0xff") as exc:
        list(KittiRaw(drive).records(StreamKind.POSE))
    assert exc.value.path == record
    stamps = drive / "oxts" / "timestamps.txt"
    stamps.write_bytes(stamps.read_bytes().replace(b"13:02:25.268", b"13:02:25\xa0268"))
    with pytest.raises(InputError, match="line 2") as exc:
        KittiRaw(drive)
    assert exc.value.path == stamps
