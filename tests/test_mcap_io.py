"""MCAP writer/reader: every message type round-trips; damaged and disordered logs are reported."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from mcap_ros2.writer import Writer as Ros2Writer

from mapkit.core.errors import InputError, InputWarning
from mapkit.core.geometry import make_pose, yaw_rotation
from mapkit.core.types import (
    CameraFrame,
    CameraInfo,
    FrameTransform,
    GpsFix,
    GpsStatus,
    ImuSample,
    LidarScan,
    PoseSample,
    StreamKind,
)
from mapkit.io import open_log, ros2
from mapkit.io.mcap_log import McapLog, McapWriter

T0 = 1_700_000_000_123_456_789  # an epoch stamp with nanoseconds that float seconds would lose


def _read_all(path: Path) -> dict[str, list]:
    out: dict[str, list] = {}
    with McapLog(path) as log:
        for msg in log.messages():
            out.setdefault(msg.topic, []).append(msg.record)
    return out


def _write(path: Path, items: list[tuple[str, object, dict]]) -> Path:
    with McapWriter(path) as w:
        for topic, rec, kw in items:
            w.write(topic, rec, **kw)
    return path


@pytest.mark.parametrize(
    "encoding, shape, dtype",
    [
        ("mono8", (48, 64), np.uint8),
        ("rgb8", (48, 64, 3), np.uint8),
        ("bgr8", (10, 7, 3), np.uint8),
        ("mono16", (12, 9), np.uint16),
    ],
)
def test_raw_image_round_trip(tmp_path, rng, encoding, shape, dtype):
    img = rng.integers(0, np.iinfo(dtype).max, size=shape, dtype=dtype)
    path = _write(tmp_path / "img.mcap", [("/cam/image", CameraFrame(T0, "cam", img, encoding=encoding), {})])
    (frame,) = _read_all(path)["/cam/image"]
    assert frame.stamp_ns == T0 and frame.camera == "cam" and frame.encoding == encoding
    np.testing.assert_array_equal(frame.image, img)


def test_compressed_image_round_trip_png_exact_jpeg_close(tmp_path, rng):
    # a smooth image, so that JPEG's error is small and measurable
    yy, xx = np.mgrid[0:60, 0:80]
    img = np.stack([(xx * 3) % 256, (yy * 4) % 256, ((xx + yy) * 2) % 256], -1).astype(np.uint8)
    path = _write(
        tmp_path / "c.mcap",
        [
            ("/png", CameraFrame(T0, "cam", img, encoding="rgb8"), {"compress": "png"}),
            ("/jpg", CameraFrame(T0, "cam", img, encoding="rgb8"), {"compress": "jpeg"}),
        ],
    )
    recs = _read_all(path)
    png, jpg = recs["/png"][0], recs["/jpg"][0]
    assert not png.is_loaded  # decoding waits until the pixels are asked for
    assert png.encoding == "bgr8"
    np.testing.assert_array_equal(png.image[..., ::-1], img)
    assert np.abs(jpg.image[..., ::-1].astype(int) - img).mean() < 4.0


def test_camera_info_round_trip(tmp_path):
    K = np.array([[707.0912, 0, 601.8873], [0, 707.0912, 183.1104], [0, 0, 1]])
    info = CameraInfo("camera_0", 1226, 370, K, D=np.array([0.1, -0.2, 0.0, 0.0, 0.01]), stamp_ns=T0)
    path = _write(tmp_path / "ci.mcap", [("/cam/camera_info", info, {})])
    with McapLog(path) as log:
        infos = log.camera_infos()
    assert infos == {"camera_0": info}
    assert infos["camera_0"].fx == pytest.approx(707.0912)


def test_gps_round_trip_with_and_without_covariance(tmp_path):
    cov = np.diag([4.0, 9.0, 16.0])
    fixes = [
        GpsFix(T0, 49.011, 8.4161, 112.5, GpsStatus.FIX, cov, "gps"),
        GpsFix(T0 + 200_000_000, 49.0111, 8.4162, 112.7, GpsStatus.NO_FIX, None, "gps"),
    ]
    path = _write(tmp_path / "g.mcap", [("/gps/fix", f, {}) for f in fixes])
    back = _read_all(path)["/gps/fix"]
    assert [f.stamp_ns for f in back] == [f.stamp_ns for f in fixes]
    assert back[0].lat_deg == fixes[0].lat_deg and back[0].lon_deg == fixes[0].lon_deg
    np.testing.assert_array_equal(back[0].covariance_enu_m2, cov)
    assert back[0].horizontal_sigma_m == pytest.approx(np.sqrt(6.5))
    assert back[1].covariance_enu_m2 is None and not back[1].has_fix


def test_point_cloud_round_trip_drops_nans_with_their_times(tmp_path, rng):
    n = 5000
    xyz = rng.normal(size=(n, 3)).astype(np.float32) * 20
    t = np.linspace(0, 0.1, n, dtype=np.float32)
    inten = rng.random(n).astype(np.float32)
    ring = (np.arange(n) % 32).astype(np.uint16)
    bad = np.array([3, 100, 4999])
    xyz[bad[0], 0] = np.nan
    xyz[bad[1], 2] = np.inf
    xyz[bad[2]] = np.nan
    path = _write(tmp_path / "p.mcap", [("/lidar/points", LidarScan(T0, "lidar", xyz, inten, t, ring), {})])
    (scan,) = _read_all(path)["/lidar/points"]
    keep = np.setdiff1d(np.arange(n), bad)
    assert len(scan) == n - 3
    np.testing.assert_array_equal(scan.points_xyz, xyz[keep])
    np.testing.assert_array_equal(scan.point_time_s, t[keep])  # times stay paired with their points
    np.testing.assert_array_equal(scan.intensity, inten[keep])
    np.testing.assert_array_equal(scan.ring, ring[keep])


def _foreign_cloud(path: Path, data: bytes, fields: list[dict], point_step: int, n: int, stamp: int, big_endian=False):
    """A PointCloud2 laid out as another driver would (padding, other time fields)."""
    with open(path, "wb") as fh:
        w = Ros2Writer(fh)
        schema = w.register_msgdef("sensor_msgs/msg/PointCloud2", ros2.full_msgdef("sensor_msgs/PointCloud2"))
        msg = {
            "header": {"stamp": {"sec": stamp // 10**9, "nanosec": stamp % 10**9}, "frame_id": "os_lidar"},
            "height": 1,
            "width": n,
            "fields": fields,
            "is_bigendian": big_endian,
            "point_step": point_step,
            "row_step": point_step * n,
            "data": data,
            "is_dense": False,
        }
        w.write_message("/os/points", schema, msg, log_time=stamp)
        w.finish()


def test_point_cloud_with_padding_and_ouster_nanosecond_times(tmp_path):
    n = 100
    dt = np.dtype(
        {
            "names": ["x", "y", "z", "intensity", "t"],
            "formats": ["<f4", "<f4", "<f4", "<f4", "<u4"],
            "offsets": [0, 4, 8, 16, 20],
            "itemsize": 32,
        }
    )
    arr = np.zeros(n, dt)
    arr["x"] = np.arange(n)
    arr["y"] = -np.arange(n)
    arr["z"] = 1.5
    arr["t"] = np.arange(n) * 1_000_000  # 1 ms apart, in ns
    fields = [{"name": k, "offset": dt.fields[k][1], "datatype": 6 if k == "t" else 7, "count": 1} for k in dt.names]
    _foreign_cloud(tmp_path / "os.mcap", arr.tobytes(), fields, 32, n, T0)
    (scan,) = _read_all(tmp_path / "os.mcap")["/os/points"]
    np.testing.assert_array_equal(scan.points_xyz[:, 0], np.arange(n, dtype=np.float32))
    np.testing.assert_allclose(scan.point_time_s, np.arange(n) * 1e-3, atol=1e-7)
    assert scan.ring is None


def test_point_cloud_big_endian_and_absolute_times(tmp_path):
    n = 10
    stamp = T0
    dt = np.dtype([("x", ">f4"), ("y", ">f4"), ("z", ">f4"), ("timestamp", ">f8")])
    arr = np.zeros(n, dt)
    arr["x"] = np.arange(n)
    arr["timestamp"] = stamp * 1e-9 + np.arange(n) * 0.01  # Hesai style: absolute seconds
    fields = [
        {"name": k, "offset": dt.fields[k][1], "datatype": 8 if k == "timestamp" else 7, "count": 1} for k in dt.names
    ]
    _foreign_cloud(tmp_path / "be.mcap", arr.tobytes(), fields, dt.itemsize, n, stamp, big_endian=True)
    (scan,) = _read_all(tmp_path / "be.mcap")["/os/points"]
    np.testing.assert_array_equal(scan.points_xyz[:, 0], np.arange(n, dtype=np.float32))
    np.testing.assert_allclose(scan.point_time_s, np.arange(n) * 0.01, atol=1e-4)


def test_imu_pose_and_tf_round_trip(tmp_path):
    q = np.array([np.cos(0.2), 0.0, 0.0, np.sin(0.2)])
    imu = [
        ImuSample(T0, "imu", np.array([0.01, 0.02, 0.3]), np.array([0.1, 0.0, 9.81]), q),
        ImuSample(T0 + 10_000_000, "imu", np.zeros(3), np.array([0, 0, 9.8]), None),
    ]
    pose = PoseSample(
        T0, "world", "base_link", make_pose(yaw_rotation(0.7), [10.0, -3.0, 0.5]), covariance=np.eye(6) * 0.01
    )
    stamped = PoseSample(T0, "map", "base_link", make_pose(yaw_rotation(-0.3), [1.0, 2.0, 3.0]))
    tfs = [
        FrameTransform(0, "base_link", "camera_front", make_pose(yaw_rotation(0.1), [1.5, 0, 1.4])),
        FrameTransform(0, "base_link", "lidar", make_pose(np.eye(3), [0, 0, 1.8])),
    ]
    with McapWriter(tmp_path / "x.mcap") as w:
        for s in imu:
            w.write("/imu/data", s)
        w.write("/gt/odom", pose)
        w.write("/gt/pose", stamped, pose_msgtype="geometry_msgs/PoseStamped")
        w.write_transforms("/tf_static", tfs)
    recs = _read_all(tmp_path / "x.mcap")
    np.testing.assert_allclose(recs["/imu/data"][0].orientation_quat_wxyz, q)
    assert recs["/imu/data"][1].orientation_quat_wxyz is None
    np.testing.assert_array_equal(recs["/imu/data"][0].linear_acceleration_m_s2, imu[0].linear_acceleration_m_s2)
    odo = recs["/gt/odom"][0]
    assert (odo.parent_frame, odo.child_frame) == ("world", "base_link")
    np.testing.assert_allclose(odo.parent_from_child, pose.parent_from_child, atol=1e-12)
    np.testing.assert_allclose(odo.covariance, pose.covariance)
    np.testing.assert_allclose(recs["/gt/pose"][0].parent_from_child, stamped.parent_from_child, atol=1e-12)
    with McapLog(tmp_path / "x.mcap") as log:
        got = {(t.parent_frame, t.child_frame): t for t in log.transforms()}
        kinds = {s.topic: s.kind for s in log.streams()}
    assert set(got) == {("base_link", "camera_front"), ("base_link", "lidar")}
    assert all(t.static for t in got.values())
    np.testing.assert_allclose(
        got[("base_link", "camera_front")].parent_from_child, tfs[0].parent_from_child, atol=1e-12
    )
    assert kinds == {
        "/imu/data": StreamKind.IMU,
        "/gt/odom": StreamKind.POSE,
        "/gt/pose": StreamKind.POSE,
        "/tf_static": StreamKind.TF,
    }


def test_logs_are_readable_by_the_bare_mcap_library(tmp_path, rng):
    """What mapkit writes is standard ROS 2 MCAP: the mcap library decodes it on its own."""
    img = rng.integers(0, 255, (8, 8), dtype=np.uint8)
    path = _write(
        tmp_path / "s.mcap",
        [("/cam/image", CameraFrame(T0, "cam", img), {}), ("/gps/fix", GpsFix(T0, 1.0, 2.0, 3.0), {})],
    )
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        decoded = {ch.topic: (sch.name, m) for sch, ch, _, m in reader.iter_decoded_messages()}
    assert decoded["/cam/image"][0] == "sensor_msgs/msg/Image"
    assert bytes(decoded["/cam/image"][1].data) == img.tobytes()
    assert decoded["/gps/fix"][1].latitude == 1.0


def _big_log(path: Path, n: int = 60) -> Path:
    """Many chunks (small chunk size), so that truncation cuts through the middle of the data."""
    rng = np.random.default_rng(0)
    with McapWriter(path, chunk_size=4096, compression="none") as w:
        for i in range(n):
            w.write(
                "/cam/image", CameraFrame(T0 + i * 100_000_000, "cam", rng.integers(0, 255, (32, 32), dtype=np.uint8))
            )
            w.write("/gps/fix", GpsFix(T0 + i * 100_000_000, 49.0 + i * 1e-6, 8.4, 100.0))
    return path


@pytest.mark.parametrize("keep_fraction", [0.3, 0.7, 0.97])
def test_truncated_log_reads_what_it_can_and_says_where_it_stopped(tmp_path, keep_fraction):
    full = _big_log(tmp_path / "full.mcap")
    data = full.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * keep_fraction)])
    with pytest.warns(InputWarning, match=r"truncated or corrupt near byte \d+"), McapLog(cut) as log:
        recs = list(log.messages())
        truncated_at = log.truncated_at
    assert truncated_at is not None and truncated_at <= len(data)
    assert 0 < len(recs) <= 120
    if keep_fraction < 0.9:
        assert len(recs) < 120  # the cut went through the data
    # what was read is correct, in order, with the right stamps
    cams = [m.record.stamp_ns for m in recs if m.topic == "/cam/image"]
    assert cams == [T0 + i * 100_000_000 for i in range(len(cams))]


def test_corrupt_chunk_is_reported(tmp_path):
    full = _big_log(tmp_path / "full.mcap")
    data = bytearray(full.read_bytes())
    mid = len(data) // 2
    data[mid : mid + 64] = b"\xff" * 64
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    with pytest.warns(InputWarning, match="truncated or corrupt"), McapLog(bad) as log:
        n = sum(1 for _ in log.messages())
    assert 0 < n < 120


def test_not_an_mcap_is_a_clear_error(tmp_path):
    p = tmp_path / "x.mcap"
    p.write_bytes(b"hello world, not a log")
    with pytest.raises(InputError, match="not an MCAP"):
        McapLog(p)
    with pytest.raises(InputError, match="no such file"):
        McapLog(tmp_path / "missing.mcap")


def test_out_of_order_and_duplicate_stamps_are_warned_and_skipped(tmp_path):
    stamps = [10, 20, 20, 15, 30]  # duplicate at index 2, backwards at index 3
    with McapWriter(tmp_path / "o.mcap") as w:
        for i, s in enumerate(stamps):
            # log times increase so the file order is the order written
            w.write("/gps/fix", GpsFix(T0 + s, 49.0, 8.4, 100.0), log_time_ns=T0 + i)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with McapLog(tmp_path / "o.mcap") as log:
            got = [m.record.stamp_ns - T0 for m in log.messages()]
            skipped = dict(log.skipped)
    assert got == [10, 20, 30]
    texts = [str(c.message) for c in caught if issubclass(c.category, InputWarning)]
    assert any("/gps/fix message 2: duplicate timestamp" in t for t in texts)
    assert any("/gps/fix message 3: timestamp earlier than the previous" in t for t in texts)
    assert all(str(tmp_path / "o.mcap") in t for t in texts)
    assert skipped == {("/gps/fix", "duplicate timestamp"): 1, ("/gps/fix", "timestamp earlier than the previous"): 1}


def test_undecodable_message_is_skipped_with_its_index(tmp_path):
    with open(tmp_path / "u.mcap", "wb") as fh:
        w = Ros2Writer(fh)
        schema = w.register_msgdef("sensor_msgs/msg/Image", ros2.full_msgdef("sensor_msgs/Image"))
        hdr = {"stamp": {"sec": 1, "nanosec": 0}, "frame_id": "cam"}
        good = {
            "header": hdr,
            "height": 2,
            "width": 2,
            "encoding": "mono8",
            "is_bigendian": 0,
            "step": 2,
            "data": b"\x01\x02\x03\x04",
        }
        bad = dict(good, header={"stamp": {"sec": 2, "nanosec": 0}, "frame_id": "cam"}, data=b"\x01")  # too short
        w.write_message("/cam", schema, good, log_time=1)
        w.write_message("/cam", schema, bad, log_time=2)
        w.finish()
    with pytest.warns(InputWarning, match=r"/cam message 1: could not be decoded"), McapLog(tmp_path / "u.mcap") as log:
        frames = list(log.records(StreamKind.IMAGE))
    assert len(frames) == 1 and frames[0].image.tolist() == [[1, 2], [3, 4]]


def test_records_of_one_topic_keep_to_that_topic(tmp_path):
    path = _write(
        tmp_path / "two.mcap", [("/gps/a", GpsFix(T0, 1.0, 2.0, 3.0), {}), ("/gps/b", GpsFix(T0, 4.0, 5.0, 6.0), {})]
    )
    with McapLog(path) as log:
        assert [f.lat_deg for f in log.records(StreamKind.GPS, topic="/gps/b")] == [4.0]
        assert sorted(f.lat_deg for f in log.records(StreamKind.GPS)) == [1.0, 4.0]
        with pytest.raises(InputError, match="carries gps, not lidar"):
            list(log.records(StreamKind.LIDAR, topic="/gps/a"))


def test_missing_topic_is_named(tmp_path):
    path = _write(tmp_path / "g.mcap", [("/gps/fix", GpsFix(T0, 49.0, 8.4, 100.0), {})])
    with McapLog(path) as log, pytest.raises(InputError, match="no topic '/lidar' in this log"):
        list(log.messages(topics=["/lidar"]))


def test_writer_is_atomic(tmp_path):
    target = tmp_path / "a.mcap"
    with pytest.raises(RuntimeError), McapWriter(target) as w:
        w.write("/gps/fix", GpsFix(T0, 49.0, 8.4, 100.0))
        raise RuntimeError("crash while writing")
    assert not target.exists()
    assert not list(tmp_path.glob("*.partial"))


def test_open_log_guesses_mcap(tmp_path):
    path = _write(tmp_path / "g.mcap", [("/gps/fix", GpsFix(T0, 49.0, 8.4, 100.0), {})])
    with open_log(path) as log:
        assert isinstance(log, McapLog)
    txt = tmp_path / "notes.txt"
    txt.write_text("x")
    with pytest.raises(InputError, match="not an MCAP"):
        open_log(txt)
