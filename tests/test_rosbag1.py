"""ROS 1 bags and rosbag2 sqlite3 folders, read through rosbags, against their MCAP twins.

The twins are made with the ecosystem's tools, not mapkit's: mapkit's MCAP is deserialised by
rosbags (ROS 2 typestore), turned field by field into the ROS 1 Noetic dataclasses (``D``/``K``
for CameraInfo, a ``seq`` in every header) and written with ``rosbags.rosbag1.Writer``; the
sqlite3 folder gets the same CDR payloads through ``rosbags.rosbag2.Writer``.
"""

from __future__ import annotations

import dataclasses
import shutil
import sqlite3
import warnings
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.rosbag1 import Writer as Rosbag1Writer
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Rosbag2SqliteWriter
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from mapkit.cli import main
from mapkit.core.errors import InputError, InputWarning
from mapkit.core.geometry import make_pose, quat_wxyz_to_matrix
from mapkit.core.types import (
    CameraFrame,
    CameraInfo,
    FrameTransform,
    GpsFix,
    ImuSample,
    LidarScan,
    PoseSample,
    StreamKind,
)
from mapkit.io import guess_format, open_log
from mapkit.io.info import summarize
from mapkit.io.mcap_log import McapLog, Rosbag2Writer
from mapkit.io.rosbag import RosbagLog
from mapkit.synth import session_log, synthesize

T0 = 1_700_000_000_123_456_789
ROS1 = get_typestore(Stores.ROS1_NOETIC)
# rosbags' Noetic store has neither tf2_msgs/TFMessage nor tf's older tfMessage; both are this one field
for _name in ("tf2_msgs/msg/TFMessage", "tf/msg/tfMessage"):
    ROS1.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms\n", _name))
ROS2 = get_typestore(Stores.ROS2_JAZZY)


def _drive(n: int = 10) -> list[tuple[str, object, dict]]:
    """Every message type both readers know, 10 Hz (GPS 5 Hz), with known values."""
    rng = np.random.default_rng(7)
    K = np.array([[5.0, 0, 4], [0, 6, 3], [0, 0, 1]])
    items: list[tuple[str, object, dict]] = [
        ("/tf_static", FrameTransform(T0, "base_link", "lidar", make_pose(np.eye(3), [1.2, 0, 1.9]), static=True), {}),
    ]
    for i in range(n):
        t = T0 + i * 100_000_000
        q = np.array([np.cos(0.05 * i), 0, 0, np.sin(0.05 * i)])  # yaw 0.1 i rad
        items += [
            ("/cam/camera_info", CameraInfo("cam", 8, 6, K, "plumb_bob", np.array([0.1, -0.02, 0, 0, 0.003]), t), {}),
            (
                "/cam/image",
                CameraFrame(t, "cam", rng.integers(0, 255, (6, 8, 3), dtype=np.uint8), encoding="rgb8"),
                {"compress": "png"},
            ),
            (
                "/mono/image_raw",
                CameraFrame(t, "mono", rng.integers(0, 255, (6, 8), dtype=np.uint8), encoding="mono8"),
                {},
            ),
            (
                "/lidar/points",
                LidarScan(
                    t,
                    "lidar",
                    rng.normal(size=(40, 3)).astype(np.float32),
                    rng.random(40).astype(np.float32),
                    np.linspace(0, 0.1, 40).astype(np.float32),
                    np.arange(40, dtype=np.uint16) % 16,
                ),
                {},
            ),
            ("/imu/data", ImuSample(t, "imu", rng.normal(size=3), rng.normal(size=3), q), {}),
            (
                "/odom",
                PoseSample(
                    t,
                    "odom",
                    "base_link",
                    make_pose(quat_wxyz_to_matrix(q), [i, 0.5 * i, 0]),
                    covariance=np.diag(np.arange(1.0, 7.0)),
                ),
                {},
            ),
            (
                "/pose",
                PoseSample(t, "map", "base_link", make_pose(np.eye(3), [0, i, 0])),
                {"pose_msgtype": "geometry_msgs/PoseStamped"},
            ),
            (
                "/tf",
                FrameTransform(t, "odom", "base_link", make_pose(quat_wxyz_to_matrix(q), [i, 0, 0]), static=False),
                {},
            ),
        ]
        if i % 2 == 0:
            cov = None if i == 4 else np.diag([4.0, 4.0, 9.0])
            items.append(("/gps/fix", GpsFix(t, 49.0 + i * 1e-5, 8.4, 110.0 + i, covariance_enu_m2=cov), {}))
    return items


def _write_mcap(folder: Path, items) -> Path:
    with Rosbag2Writer(folder) as w:
        for topic, rec, kw in items:
            w.write(topic, rec, **kw)
    return w.path


def _to_ros1(msg, seq: int):
    """A ROS 2 dataclass as the ROS 1 Noetic one: same fields, upper-case CameraInfo arrays, header seq."""
    cls = ROS1.types[msg.__msgtype__]
    values = {}
    for f in dataclasses.fields(cls):
        if f.name == "seq":
            values["seq"] = seq
            continue
        v = getattr(msg, f.name) if hasattr(msg, f.name) else getattr(msg, f.name.lower())
        if dataclasses.is_dataclass(v):
            v = _to_ros1(v, seq)
        elif isinstance(v, list):
            v = [_to_ros1(x, seq) if dataclasses.is_dataclass(x) else x for x in v]
        values[f.name] = v
    return cls(**values)


def _twins(
    mcap_folder: Path, out: Path, extra: tuple[str, str, list] | None = None, bz2: bool = False
) -> tuple[Path, Path]:
    """The MCAP folder as a ROS 1 bag (chunks bz2-compressed with ``bz2``, as ``rosbag record --bz2``)
    and as a rosbag2 sqlite3 folder, message by message (with ``extra`` = (topic, ROS 1/2 type,
    [(stamp, ros1 msg, ros2 msg)]) added to both)."""
    bag, sq = out / "drive.bag", out / "drive_sqlite"
    seq: Counter[str] = Counter()
    w1 = Rosbag1Writer(bag)
    if bz2:
        w1.set_compression(Rosbag1Writer.CompressionFormat.BZ2)
    with (
        AnyReader([mcap_folder], default_typestore=ROS2) as reader,
        w1,
        Rosbag2SqliteWriter(sq, version=9, storage_plugin=StoragePlugin.SQLITE3) as w2,
    ):
        conns1, conns2 = {}, {}
        for conn in reader.connections:
            conns1[conn.topic] = w1.add_connection(conn.topic, conn.msgtype, typestore=ROS1)
            conns2[conn.topic] = w2.add_connection(conn.topic, conn.msgtype, typestore=ROS2)
        for conn, stamp, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            w1.write(conns1[conn.topic], stamp, ROS1.serialize_ros1(_to_ros1(msg, seq[conn.topic]), conn.msgtype))
            w2.write(conns2[conn.topic], stamp, raw)
            seq[conn.topic] += 1
        if extra:
            topic, msgtype, msgs = extra
            c1, c2 = (
                w1.add_connection(topic, msgtype, typestore=ROS1),
                w2.add_connection(topic, msgtype, typestore=ROS2),
            )
            for stamp, m1, m2 in msgs:
                w1.write(c1, stamp, ROS1.serialize_ros1(m1, msgtype))
                w2.write(c2, stamp, ROS2.serialize_cdr(m2, msgtype))
    return bag, sq


def _canon(record) -> tuple:
    """A record as a comparable tuple; arrays by dtype, shape and bytes (exact equality)."""
    if isinstance(record, CameraFrame):
        img = record.image
        return (
            "frame",
            record.stamp_ns,
            record.camera,
            record.encoding,
            record.source,
            img.dtype.str,
            img.shape,
            img.tobytes(),
        )
    values = []
    for f in dataclasses.fields(record):
        v = getattr(record, f.name)
        values.append((f.name, (v.dtype.str, v.shape, v.tobytes()) if isinstance(v, np.ndarray) else v))
    return (type(record).__name__, tuple(values))


def _read(path: Path) -> tuple[list, dict, dict]:
    """(streams, stamps per topic, decoded messages per topic) as mapkit reads them."""
    with open_log(path) as log:
        streams = [(s.topic, s.kind, s.msgtype, s.count) for s in log.streams()]
        stamps, msgs = defaultdict(list), defaultdict(list)
        for topic, stamp in log.stamps():
            stamps[topic].append(stamp)
        for m in log.messages():
            msgs[m.topic].append((m.index, m.stamp_ns, m.kind, _canon(m.record)))
    return streams, dict(stamps), dict(msgs)


@pytest.fixture(scope="module")
def twins(tmp_path_factory) -> dict[str, Path]:
    out = tmp_path_factory.mktemp("rosbag1")
    mcap = _write_mcap(out / "drive_mcap", _drive())
    bag, sq = _twins(mcap, out)
    (out / "bz2").mkdir()
    bag_bz2, _ = _twins(mcap, out / "bz2", bz2=True)
    return {"mcap": mcap, "ros1": bag, "ros1-bz2": bag_bz2, "sqlite3": sq}


# --- the same records as the MCAP twin -----------------------------------------------------------------


@pytest.mark.parametrize("kind", ["ros1", "ros1-bz2", "sqlite3"])
def test_bag_reads_the_same_records_as_its_mcap_twin(twins, kind):
    path = twins[kind]
    assert guess_format(path) == "rosbag" and guess_format(twins["mcap"]) == "mcap"
    with open_log(path) as log:
        assert isinstance(log, RosbagLog) and log.is_ros1 == kind.startswith("ros1")
    got, want = _read(path), _read(twins["mcap"])
    assert got[0] == want[0]  # streams: topics, kinds, types, counts from the index / metadata
    assert got[1] == want[1]  # header stamps read without decoding
    assert got[2] == want[2]  # every record, arrays byte for byte
    items = _drive()
    assert sum(len(v) for v in got[2].values()) == len(items)
    counts = {t: c for t, _, _, c in got[0]}
    assert counts["/lidar/points"] == 10 and counts["/gps/fix"] == 5 and counts["/tf_static"] == 1


def test_ros1_bag_records_hold_the_known_values(twins):
    """Not only equal to the twin: the values written come back (CameraInfo from ROS 1's D/K)."""
    with RosbagLog(twins["ros1"]) as log:
        (info,) = log.camera_infos().values()
        np.testing.assert_array_equal(info.K, [[5.0, 0, 4], [0, 6, 3], [0, 0, 1]])
        np.testing.assert_array_equal(info.D, [0.1, -0.02, 0, 0, 0.003])
        (static,) = log.transforms()
        assert (static.parent_frame, static.child_frame) == ("base_link", "lidar")
        np.testing.assert_allclose(static.parent_from_child[:3, 3], [1.2, 0, 1.9])
        fixes = list(log.records(StreamKind.GPS))
        assert [f.stamp_ns for f in fixes] == [T0 + i * 100_000_000 for i in range(0, 10, 2)]
        assert [f.alt_m for f in fixes] == [110.0, 112.0, 114.0, 116.0, 118.0]
        assert fixes[2].covariance_enu_m2 is None and fixes[1].covariance_enu_m2[2, 2] == 9.0
        odom = list(log.records(StreamKind.POSE, "/odom"))
        np.testing.assert_allclose(odom[3].parent_from_child[:3, 3], [3, 1.5, 0])
        assert odom[3].covariance[5, 5] == 6.0 and odom[3].child_frame == "base_link"
        tf = list(log.records(StreamKind.TF, "/tf"))
        assert len(tf) == 10 and not tf[0].static
    with AnyReader([twins["ros1"]]) as reader:  # the ROS 1 bag really holds ROS 1 messages
        conn = next(c for c in reader.connections if c.topic == "/cam/camera_info")
        raw = next(raw for _, _, raw in reader.messages(connections=[conn]))
        msg = reader.deserialize(raw, conn.msgtype)
        assert msg.header.seq == 0 and list(msg.K[:3]) == [5.0, 0, 4]


def test_guess_format_and_the_mcap_reader_on_a_sqlite3_folder(twins):
    sq = twins["sqlite3"]
    assert guess_format(sq / "metadata.yaml") == "rosbag"
    with open_log(sq / "metadata.yaml") as log:
        assert log.path == sq
    with pytest.raises(InputError, match="read by the 'rosbag' reader") as exc:
        McapLog(sq)
    assert exc.value.field == "storage_identifier"


@pytest.mark.parametrize("keep", ["", "sensor_msgs/msg/NavSatFix"])
def test_sqlite3_bags_without_stored_definitions_read_with_the_standard_types(twins, tmp_path, keep):
    """Humble and older record no definitions in sqlite3 bags; a bag may also define only some types."""
    sq = tmp_path / "sq"
    shutil.copytree(twins["sqlite3"], sq)
    (db,) = sq.glob("*.db3")
    with sqlite3.connect(db) as con:
        con.execute("DELETE FROM message_definitions WHERE topic_type != ?", (keep,))
    with AnyReader([sq], default_typestore=ROS2) as reader:  # what the bag defines itself now
        assert {c.msgdef.data != "" for c in reader.connections} == ({True, False} if keep else {False})
    assert _read(sq) == _read(twins["mcap"])


def test_tf_of_ros1_tf_package_reads_as_tf2(twins, tmp_path):
    """Older ROS 1 bags publish /tf as tf/tfMessage, with tf2_msgs/TFMessage's exact layout."""
    old = tmp_path / "old_tf.bag"
    with AnyReader([twins["ros1"]]) as reader, Rosbag1Writer(old) as w:
        conns = {c.topic: c for c in reader.connections if c.topic in ("/tf", "/tf_static")}
        out = {t: w.add_connection(t, "tf/msg/tfMessage", typestore=ROS1) for t in conns}
        for conn, stamp, raw in reader.messages(connections=list(conns.values())):
            w.write(out[conn.topic], stamp, raw)
    got, want = _read(old), _read(twins["mcap"])
    assert [s for s in got[0]] == [
        (t, k, "tf2_msgs/TFMessage", c) for t, k, _, c in want[0] if t in ("/tf", "/tf_static")
    ]
    assert got[2] == {t: want[2][t] for t in ("/tf", "/tf_static")}


# --- damaged bags and unknown types -------------------------------------------------------------------


def test_a_truncated_bag_is_one_input_error_naming_the_file(twins, tmp_path):
    data = twins["ros1"].read_bytes()
    for keep in (len(data) // 2, len(data) - 40, 20):
        cut = tmp_path / f"cut_{keep}.bag"
        cut.write_bytes(data[:keep])
        with pytest.raises(InputError, match="could not be read as a ROS 1 bag") as exc, open_log(cut) as log:
            list(log.messages())
        assert exc.value.path == cut
    not_a_bag = tmp_path / "notes.bag"
    not_a_bag.write_text("hello")
    with pytest.raises(InputError, match="not a ROS 1 bag") as exc:
        open_log(not_a_bag)
    assert exc.value.path == not_a_bag


def test_a_truncated_sqlite3_storage_file_is_one_input_error(twins, tmp_path):
    sq = tmp_path / "sq"
    shutil.copytree(twins["sqlite3"], sq)
    (db,) = sq.glob("*.db3")
    db.write_bytes(db.read_bytes()[: db.stat().st_size // 3])
    with pytest.raises(InputError, match="could not be read as a rosbag2 folder") as exc, open_log(sq) as log:
        list(log.messages())
    assert exc.value.path == sq


def test_an_unknown_message_type_is_skipped_with_one_warning_per_topic(twins, tmp_path):
    S1, S2 = ROS1.types["std_msgs/msg/String"], ROS2.types["std_msgs/msg/String"]
    notes = [(T0 + i, S1(data=f"note {i}"), S2(data=f"note {i}")) for i in range(3)]
    bag, sq = _twins(twins["mcap"], tmp_path, extra=("/notes", "std_msgs/msg/String", notes))
    for path in (bag, sq):
        with open_log(path) as log:
            streams = {s.topic: s for s in log.streams()}
            assert streams["/notes"].kind == StreamKind.OTHER and streams["/notes"].count == 3
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                first = list(log.messages())
                second = list(log.messages())
                stamps = list(log.stamps())
        about = [str(w.message) for w in caught if issubclass(w.category, InputWarning) and "/notes" in str(w.message)]
        assert len(about) == 1 and "std_msgs/String" in about[0] and "skipped" in about[0]
        assert len(first) == len(second) == len(_drive()) and not any(m.topic == "/notes" for m in first)
        assert [s for t, s in stamps if t == "/notes"] == [T0, T0 + 1, T0 + 2]  # counted by mapkit info, never decoded


# --- a synthetic session as a ROS 1 bag -------------------------------------------------------------------

ONE_DRIVE = {
    "sessions": [{"name": "drive", "role": "train", "weather": "overcast", "length_m": 30.0, "speed_mps": 8.0}],
    "motion": {"start_from_rest": False},
    "lidar": {"beams": 32, "vertical_fov_deg": [-30.67, 10.67], "azimuth_steps": 512},
}


def test_synthetic_session_as_a_ros1_bag_builds_the_same_trajectory(tmp_path, capsys):
    from mapkit.mapping.trajectory import TrajectoryConfig, trajectory_from_lidar

    town = synthesize(preset="tiny", out=tmp_path / "town", overrides=ONE_DRIVE, progress=False)
    folder = session_log(town, "drive")
    bag, _ = _twins(folder, tmp_path)
    a, b = summarize(folder), summarize(bag)
    assert [(r["topic"], r["kind"], r["count"], r.get("start_ns"), r.get("end_ns")) for r in a["streams"]] == [
        (r["topic"], r["kind"], r["count"], r.get("start_ns"), r.get("end_ns")) for r in b["streams"]
    ]
    assert a["gps"] == b["gps"]
    assert main(["info", str(bag)]) == 0 and "/lidar/points" in capsys.readouterr().out
    trajectories = []
    cfg = TrajectoryConfig(kiss_icp={"max_threads": 1})
    for path in (folder, bag):
        with open_log(path) as log, warnings.catch_warnings():
            warnings.simplefilter("ignore")
            trajectories.append(trajectory_from_lidar(log, "/lidar/points", cfg))
    mcap_traj, bag_traj = trajectories
    assert len(bag_traj) == len(mcap_traj) == 39
    np.testing.assert_array_equal(bag_traj.stamps_ns, mcap_traj.stamps_ns)
    # the scans are identical (test above); kiss-icp's thread pool is set by the first run in the process
    # (another test may have run it on every core), so sums may come in another order: equal to rounding
    np.testing.assert_allclose(bag_traj.world_from_base, mcap_traj.world_from_base, rtol=0, atol=1e-9)
