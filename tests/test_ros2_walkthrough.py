""" "Your own ROS 2 bag in five steps" of docs/your-data.md, run as written on a small synthetic bag, and what a
build does with a sensor the bag's tf does not link to the vehicle.

The bag is the tiny town's drive cut to 70 m (long enough for GPS to fix its heading), recorded as a rosbag2
folder named ``my-bag``, the page's placeholder: camera, LiDAR with per-point times, GPS, IMU, ``/tf_static``
and the simulator's truth on ``/ground_truth/odom``. The bags with a missing link are copies of it whose
``/tf_static`` lacks one transform; every other message is copied byte for byte.
"""

from __future__ import annotations

import json
import re
import shlex
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
from test_docs import DOCS, _worked_example  # the docs-test block convention of your-data.md

from mapkit.core.errors import InputError, InputWarning
from mapkit.core.geometry import interpolate_poses
from mapkit.core.workspace import Workspace
from mapkit.mapping.build import build
from mapkit.mapping.imagedb import read_images_csv
from mapkit.mapping.trajectory import Trajectory
from mapkit.synth import gt_poses, session_log, synthesize

BAG = "my-bag"  # the page's placeholder for the user's bag
WS = "ws-my-bag"
#: one 70 m drive of the tiny town at 8 m/s, camera at 5 Hz, started at speed (no standstill for kiss-icp to slip on)
ONE_DRIVE = {
    "sessions": [
        {
            "name": BAG,
            "role": "train",
            "date": "2014-06-26",
            "time": "11:00",
            "weather": "overcast",
            "length_m": 70.0,
            "speed_mps": 8.0,
            "lane_offset_m": 0.0,
            "camera_rate_hz": 5.0,
        }
    ],
    "motion": {"start_from_rest": False},
}
#: builds that exercise the extrinsic lookups cheaply: the truth's pose stream as trajectory, no semi-dense map
# the pose stream instead of kiss-icp, and neither map: what these tests check is the tf lookups
POSES_NO_MAPS = "topics: {poses: /ground_truth/odom}\ntrajectory: {source: poses}\nmap: false\n"
FAST = POSES_NO_MAPS + "lidar_map: false\n"


@pytest.fixture(scope="module")
def town(tmp_path_factory) -> Path:
    return synthesize(
        preset="tiny", out=tmp_path_factory.mktemp("ros2-bag") / "town", overrides=ONE_DRIVE, progress=False
    )


def _section() -> str:
    """The walkthrough's text on the page, from its heading to the next one of the same level."""
    text = (DOCS / "your-data.md").read_text()
    match = re.search(r"^## Your own ROS 2 bag in five steps.*?(?=^## )", text, flags=re.DOTALL | re.MULTILINE)
    assert match, "your-data.md has no section 'Your own ROS 2 bag in five steps'"
    return match.group(0)


def _argv(line: str, bag: Path) -> list[str]:
    """A command of the page with the user's bag (``my-bag``, also in ``my-bag::/topic``) replaced by ``bag``."""
    argv = shlex.split(line)
    assert argv[0] == "mapkit"
    return [str(bag) + tok[len(BAG) :] if tok == BAG or tok.startswith(BAG + "::") else tok for tok in argv[1:]]


def test_the_walkthrough_runs_as_written_on_a_synthetic_bag(town, tmp_path, monkeypatch, capsys):
    from mapkit.cli import main

    bag = session_log(town, BAG)
    lines, files = _worked_example("ros2")
    assert [shlex.split(x)[1] for x in lines] == ["info", "build", "eval"]
    assert "my-bag.yaml" in files and "-c my-bag.yaml" in lines[1]
    for name, content in files.items():
        (tmp_path / name).write_text(content)
    monkeypatch.chdir(tmp_path)
    out: dict[str, str] = {}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for line in lines:
            code = main(_argv(line, bag))
            printed = capsys.readouterr()
            assert code == 0, (line, printed.err[-2000:])
            out[shlex.split(line)[1]] = printed.out
    assert not [str(w.message) for w in caught if "identity" in str(w.message)]  # every sensor is in the bag's tf

    # step 1: the streams the config names, and the GPS summary the page says to read
    for topic in (
        "/camera/front/image",
        "/camera/front/camera_info",
        "/lidar/points",
        "/gps/fix",
        "/imu/data",
        "/tf_static",
    ):
        assert topic in out["info"] and topic in files["my-bag.yaml"] + "/tf_static", topic
    covered = re.search(r"GPS /gps/fix: ([\d.]+) m covered, (\d+)/(\d+) fixes", out["info"])
    assert covered and 60 < float(covered.group(1)) < 100 and covered.group(2) == covered.group(3)

    # step 3-4: one session, georeferenced, fused with the IMU and a GPS bias, a map and an image database
    ws = Workspace(tmp_path / WS)
    s = ws.session(BAG)
    ga = json.loads(s.gps_alignment.read_text())
    assert ga["georeferenced"] and ga["alignment"]["mode"] == "yaw"
    assert ga["alignment"]["residual_rmse_m"] < 6.0  # the fixes' own noise: 1.5 m white, a 2 m bias, multipath
    fused = ga["fused"]
    assert fused["imu"] == "preintegrated" and fused["imu_factors"] > 20 and fused["gps_bias_nodes"] >= 1
    assert s.enu_trajectory == s.fused_trajectory  # the map and database stand on the fused poses
    assert json.loads((s.map / "metrics.json").read_text())["points"] > 2000
    table = read_images_csv(s.images_csv)
    assert len(table["stamp_ns"]) > 20 and np.isfinite(table["lat_deg"]).all()
    import pycolmap

    rec = pycolmap.Reconstruction(str(s.imagedb / "colmap"))
    assert rec.num_images() == len(table["stamp_ns"]) and rec.num_points3D() > 1000
    # the georeferenced poses lie where the vehicle was, within the GPS bias (2 m in the preset)
    from mapkit.evaluation.truth import ws_from_town

    stamps, truth = gt_poses(town, BAG)
    est = Trajectory.load(s.enu_trajectory)
    true_enu, ok = interpolate_poses(stamps, ws_from_town(town, ws.frame()) @ truth, est.stamps_ns)
    offset = np.linalg.norm(est.world_from_base[ok, :2, 3] - true_enu[:, :2, 3], axis=1)
    assert ok.sum() > 80 and np.sqrt(np.mean(offset**2)) < 5.0

    # step 4: eval build against the bag's reference pose topic: the LiDAR/IMU/GPS trajectory's shape
    ev = json.loads(ws.eval_build_json.read_text())["sessions"][BAG]
    assert ev["association"]["associated"] == ev["estimate"]["poses"] > 80
    assert ev["ate"]["rmse_m"] < 0.3  # a slipping odometry or a wrong mount gives metres
    assert "ATE" in out["eval"] and (tmp_path / WS / "eval_build.md").is_file()

    # every file the walkthrough tells the user to open is there
    paths = set(re.findall(rf"`({WS}/[^`* ]+)`", _section()))
    assert len(paths) >= 6, paths
    missing = [p for p in sorted(paths) if not (tmp_path / p).exists()]
    assert not missing, f"the walkthrough names files the build did not write: {missing}"


# --- a sensor the bag's tf does not link ---------------------------------------------------------------------


def _bag_without(src: Path, dst: Path, child: str | None) -> Path:
    """A copy of the rosbag2 folder ``src`` whose ``/tf_static`` lacks the transform to ``child`` (``None``: holds
    no transform at all); every other message byte for byte."""
    from mcap.reader import make_reader
    from mcap.writer import Writer
    from mcap_ros2._dynamic import serialize_dynamic
    from mcap_ros2.decoder import DecoderFactory

    dst.mkdir(parents=True)
    shutil.copy(src / "metadata.yaml", dst)
    (mcap_file,) = src.glob("*.mcap")
    with open(mcap_file, "rb") as fin, open(dst / mcap_file.name, "wb") as fout:
        reader = make_reader(fin)
        writer = Writer(fout)
        writer.start(profile="ros2", library="mapkit tests")
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            if schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, schemas[schema.id], channel.metadata
                )
            data = message.data
            if channel.topic == "/tf_static":
                msg = DecoderFactory().decoder_for(channel.message_encoding, schema)(data)
                kept = [] if child is None else [t for t in msg.transforms if t.child_frame_id != child]
                assert len(kept) < len(msg.transforms)
                data = serialize_dynamic(schema.name, schema.data.decode())[schema.name]({"transforms": kept})
            writer.add_message(channels[channel.id], message.log_time, data, message.publish_time, message.sequence)
        writer.finish()
    return dst


def _identity_warnings(caught) -> list[str]:
    return [str(w.message) for w in caught if issubclass(w.category, InputWarning) and "identity" in str(w.message)]


def _build(bag: Path, ws: Path, config: str) -> list[str]:
    """Build ``bag`` into ``ws`` with ``config``; the warnings that say an identity was assumed."""
    cfg = ws.parent / f"{ws.name}.yaml"
    cfg.write_text(config)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        build([bag], ws, config=cfg, progress=False)
    return _identity_warnings(caught)


def test_a_camera_tf_does_not_link_is_one_error_naming_the_frames_and_the_tree(town, tmp_path):
    bag = _bag_without(session_log(town, BAG), tmp_path / "no-camera-tf", "camera_front")
    with pytest.raises(InputError) as exc:
        _build(bag, tmp_path / "ws", FAST)
    err = exc.value
    assert err.path == bag and err.field == "tf"
    msg = str(err)
    assert "'camera_front'" in msg and "'base_link'" in msg  # the two frames
    assert "'gps', 'imu', 'lidar'" in msg  # what the tree links to the base
    assert "extrinsics.assume_identity" in msg  # and the way out


def test_assume_identity_builds_a_camera_tf_does_not_link_with_one_warning(town, tmp_path):
    bag = _bag_without(session_log(town, BAG), tmp_path / "no-camera-tf", "camera_front")
    said = _build(bag, tmp_path / "ws", FAST + "extrinsics: {assume_identity: [camera_front]}\n")
    assert len(said) == 1, said
    assert (
        "camera frame 'camera_front'" in said[0]
        and "'base_link'" in said[0]
        and "extrinsics.assume_identity" in said[0]
    )
    mount = json.loads(Workspace(tmp_path / "ws").session(bag.name).camera_mount.read_text())
    assert mount["base_frame"] == "base_link" and np.array_equal(mount["base_from_camera"], np.eye(4))


def test_a_gps_antenna_tf_does_not_link_is_one_error_naming_the_frames_and_the_tree(town, tmp_path):
    bag = _bag_without(session_log(town, BAG), tmp_path / "no-gps-tf", "gps")
    with pytest.raises(InputError) as exc:
        _build(bag, tmp_path / "ws", FAST + "imagedb: false\n")
    err = exc.value
    assert err.path == bag and err.field == "tf"
    msg = str(err)
    assert "GPS antenna frame 'gps'" in msg and "'base_link'" in msg
    assert "'camera_front', 'imu', 'lidar'" in msg and "extrinsics.assume_identity" in msg
    assert not Workspace(tmp_path / "ws").session(bag.name).gps_alignment.exists()  # nothing georeferenced on a guess


def test_assume_identity_builds_a_gps_antenna_tf_does_not_link_with_one_warning(town, tmp_path):
    """Both lookups of the antenna (the rigid GPS fit and the factor graph) take the identity; it is said once."""
    bag = _bag_without(session_log(town, BAG), tmp_path / "no-gps-tf", "gps")
    said = _build(
        bag, tmp_path / "ws", FAST + "imagedb: false\ngeoref: {fuse: true}\nextrinsics: {assume_identity: [gps]}\n"
    )
    assert len(said) == 1, said
    assert "GPS antenna frame 'gps'" in said[0] and "'base_link'" in said[0] and "extrinsics.assume_identity" in said[0]
    ga = json.loads(Workspace(tmp_path / "ws").session(bag.name).gps_alignment.read_text())
    assert ga["georeferenced"] and ga["fused"]["gps"] == "used"


def test_a_bag_without_any_extrinsic_takes_the_antenna_at_the_base_saying_so_and_refuses_the_camera(town, tmp_path):
    """A bag recorded without /tf_static: the GPS antenna and the LiDAR (whose scans the LiDAR map places) are taken
    at the base with one warning each (nothing in the bag could place them); a camera, whose orientation a map
    needs, is an error until the config allows the identity."""
    bag = _bag_without(session_log(town, BAG), tmp_path / "no-tf", None)
    said = sorted(_build(bag, tmp_path / "ws", POSES_NO_MAPS + "imagedb: false\n"))  # the LiDAR map on
    assert len(said) == 2, said
    assert "GPS antenna frame 'gps'" in said[0] and "LiDAR frame 'lidar'" in said[1], said
    assert all("no extrinsics" in s for s in said), said
    with pytest.raises(InputError, match=r"camera frame 'camera_front'.*the log's tf holds no transform"):
        _build(bag, tmp_path / "ws-camera", FAST)
