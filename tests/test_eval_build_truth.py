"""`mapkit eval build` against true trajectories of real drives: TUM and KITTI files and a log's pose
topic, in frames of their own, with known transforms, clock offsets and noise."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mapkit.cli import main
from mapkit.core.errors import InputError, InputWarning
from mapkit.core.geometry import make_pose, make_sim3
from mapkit.core.types import PoseSample, StreamKind
from mapkit.core.workspace import Workspace
from mapkit.evaluation.evaluate import evaluate_build
from mapkit.evaluation.truth import associate_truth
from mapkit.io import open_log
from mapkit.io.mcap_log import McapWriter
from mapkit.io.trajectory import write_kitti_poses, write_tum
from mapkit.mapping.build import build
from mapkit.mapping.trajectory import Trajectory

REAL_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
T0_NS = 1_700_000_000 * 10**9  # an epoch stamp, as a real log has
OFFSET_NS = 7_000_000  # the truth's clock runs 7 ms ahead: less than the 20 ms pairing window
# truth_from_estimate: a rotation about all three axes and a large offset (the truth's own frame)
RIGID = make_pose(Rotation.from_euler("zyx", [130.0, 4.0, -3.0], degrees=True).as_matrix(), [512.25, -301.5, 42.0])
SIM3 = make_sim3(7.5, Rotation.from_euler("zyx", [-60.0, 10.0, 5.0], degrees=True).as_matrix(), [-20.0, 3.5, 1.25])


def drive(t_s: np.ndarray) -> np.ndarray:
    """A 320 m drive at 8 m/s on a winding, gently climbing road (base_link: x forward, z up)."""
    x = 8.0 * t_s
    y = 15.0 * np.sin(t_s / 6.0)
    z = 0.02 * x + 0.5 * np.sin(t_s / 4.0)
    yaw = np.arctan2(np.gradient(y, t_s) if len(t_s) > 1 else 0.0 * t_s, 8.0)
    R = Rotation.from_euler(
        "zyx", np.stack([yaw, -0.02 + 0.01 * np.sin(t_s), 0.01 * np.cos(t_s / 3)], axis=1)
    ).as_matrix()
    return make_pose(R, np.stack([x, y, z], axis=1))


def moved(S: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """Poses in the frame S maps to (positions scaled by S's scale, rotations kept rigid)."""
    s = np.cbrt(np.linalg.det(S[:3, :3]))
    out = poses.copy()
    out[:, :3, :3] = (S[:3, :3] / s) @ poses[:, :3, :3]
    out[:, :3, 3] = poses[:, :3, 3] @ S[:3, :3].T + S[:3, 3]
    return out


EST_T = np.arange(400) * 0.1  # 10 Hz, 40 s
EST_NS = T0_NS + np.round(EST_T * 1e9).astype(np.int64)
EST = drive(EST_T)


def workspace(root, source: str = "lidar:/velodyne", names=("drive",)) -> Workspace:
    """A workspace whose sessions hold only the odometry trajectory (all ``eval build`` needs of them)."""
    ws = Workspace(root / "ws")
    for name in names:
        Trajectory(EST_NS, EST, source, frame="odom").save(ws.session(name).trajectory)
    return ws


def assert_transform(found, expected, tol):
    assert np.allclose(np.asarray(found), expected, atol=tol), np.asarray(found) - expected


def test_tum_truth_in_its_own_frame_with_a_clock_offset(tmp_path):
    ws = workspace(tmp_path)
    truth = write_tum(tmp_path / "gt.tum", EST_NS + OFFSET_NS, moved(RIGID, EST))
    r = evaluate_build(ws, truth)
    s = r["sessions"]["drive"]
    assert r["truth_kind"] == "tum" and s["alignment"]["mode"] == "se3"  # a LiDAR trajectory is metric
    # the truth is as dense as the estimate: every pose is paired with its own true pose, 7 ms away
    a = s["association"]
    assert a["associated"] == a["nearest"] == 400 and a["interpolated"] == 0
    assert a["nearest_dt_max_s"] == pytest.approx(0.007, abs=1e-9)
    assert s["ate"]["rmse_m"] < 1e-6 and s["ate"]["rotation_rmse_deg"] < 1e-5  # the TUM file's 6 decimals
    assert_transform(s["alignment"]["truth_from_estimate"], RIGID, 1e-6)
    assert s["rpe"]["segments"] > 150 and s["rpe"]["translation_percent_mean"] < 1e-6
    md = ws.eval_build_md.read_text()
    assert "SE(3) Umeyama" in md and "400 of 400 estimated poses" in md and "within 0.02 s" in md and "gt.tum" in md
    # a truth in the estimate's own frame, taken as it is: absolute figures, with horizontal and vertical parts
    same = evaluate_build(ws, write_tum(tmp_path / "same.tum", EST_NS, EST), align="none")["sessions"]["drive"]
    assert same["ate"]["rmse_m"] < 1e-6 and same["ate"]["vertical_rmse_m"] < 1e-6
    assert_transform(same["alignment"]["truth_from_estimate"], np.eye(4), 0.0)
    assert evaluate_build(ws, truth, align="none")["sessions"]["drive"]["ate"]["rmse_m"] > 100.0


def test_kitti_truth_with_relative_times_needs_the_offset(tmp_path):
    ws = workspace(tmp_path)
    write_kitti_poses(tmp_path / "poses.txt", moved(RIGID, EST))
    (tmp_path / "times.txt").write_text(
        "".join(f"{t:.6f}\n" for t in EST_T)
    )  # KITTI odometry's: from the drive's start
    with pytest.raises(InputError, match=r"do not overlap.*--truth-time-offset 1700000000\.000000") as e:
        evaluate_build(ws, tmp_path / "poses.txt")
    assert "poses.txt" in str(e.value)
    r = evaluate_build(ws, tmp_path / "poses.txt", time_offset_s=1_700_000_000.004)
    s = r["sessions"]["drive"]
    assert s["association"]["associated"] == 400 and s["association"]["nearest_dt_max_s"] == pytest.approx(
        0.004, abs=1e-6
    )
    assert s["ate"]["rmse_m"] < 1e-6
    assert_transform(s["alignment"]["truth_from_estimate"], RIGID, 1e-6)
    assert "times.txt (line i is pose i)" in s["truth"]["stamps"]


def test_kitti_truth_with_given_times(tmp_path):
    ws = workspace(tmp_path)
    (tmp_path / "gt").mkdir()
    write_kitti_poses(tmp_path / "gt" / "poses.txt", moved(RIGID, EST))
    with pytest.raises(InputError, match="times.txt beside them"):
        evaluate_build(ws, tmp_path / "gt" / "poses.txt")
    times = tmp_path / "stamps.txt"
    times.write_text("".join(f"{(s - OFFSET_NS) // 10**9}.{(s - OFFSET_NS) % 10**9:09d}\n" for s in EST_NS))
    s = evaluate_build(ws, tmp_path / "gt" / "poses.txt", truth_times=times)["sessions"]["drive"]
    assert s["association"]["associated"] == 400 and s["ate"]["rmse_m"] < 1e-6
    times.write_text("".join(f"{t}\n" for t in range(399)))
    with pytest.raises(InputError, match="399 times for the 400 poses"):
        evaluate_build(ws, tmp_path / "gt" / "poses.txt", truth_times=times)


def test_camera_only_trajectory_is_aligned_with_scale(tmp_path):
    """Structure from motion not scaled by GPS: auto picks Sim(3) and recovers the scale."""
    ws = workspace(tmp_path, source="camera:/cam")
    truth = write_tum(tmp_path / "gt.tum", EST_NS - OFFSET_NS, moved(SIM3, EST))
    s = evaluate_build(ws, truth)["sessions"]["drive"]
    assert s["alignment"]["mode"] == "sim3" and s["alignment"]["scale"] == pytest.approx(7.5, abs=1e-8)
    assert_transform(s["alignment"]["truth_from_estimate"], SIM3, 1e-6)
    assert s["ate"]["rmse_m"] < 1e-6
    # a rigid fit cannot absorb the scale: the error is then the trajectory's size
    assert evaluate_build(ws, truth, align="se3")["sessions"]["drive"]["ate"]["rmse_m"] > 100.0


def test_noisy_truth_gives_the_noise_and_a_scale_error_gives_the_rpe(tmp_path):
    ws = workspace(tmp_path)
    rng = np.random.default_rng(7)
    gt = moved(RIGID, EST)
    gt[:, :3, 3] += rng.normal(0.0, 0.5, (len(gt), 3))
    s = evaluate_build(ws, write_tum(tmp_path / "noisy.tum", EST_NS, gt))["sessions"]["drive"]
    # 0.5 m per axis: RMSE 0.5 sqrt(3) = 0.866 m, less the 6 of 1200 degrees of freedom the fit absorbs (0.864)
    assert s["ate"]["rmse_m"] == pytest.approx(0.5 * np.sqrt(3) * np.sqrt(1 - 6 / 1200), rel=0.05)
    assert np.allclose(np.asarray(s["alignment"]["truth_from_estimate"])[:3, 3], RIGID[:3, 3], atol=0.15)
    # an odometry 1 % too long: after a rigid fit, every 100 m stretch errs by 1 % of its chord, which on
    # this winding road is a little shorter than the 100 m of path the RPE divides by
    scaled = EST.copy()
    scaled[:, :3, 3] *= 1.01
    Trajectory(EST_NS, scaled, "lidar:/velodyne", frame="odom").save(ws.session("drive").trajectory)
    s = evaluate_build(ws, write_tum(tmp_path / "gt.tum", EST_NS, moved(RIGID, EST)))["sessions"]["drive"]
    assert 0.98 < s["rpe"]["translation_percent_mean"] <= 1.0 + 1e-9
    assert s["rpe"]["rotation_deg_per_100m_mean"] < 1e-4


def test_pose_topic_of_a_log_is_interpolated_where_dense(tmp_path):
    ws = workspace(tmp_path)
    truth_t = np.arange(-1.0, 41.0, 0.02) + 0.005  # 50 Hz, 5 ms off the estimate's stamps
    truth_poses = moved(RIGID, drive(truth_t))
    log = tmp_path / "truth.mcap"
    with McapWriter(log) as w:
        for t, T in zip(truth_t, truth_poses, strict=True):
            w.write("/gt/pose", PoseSample(T0_NS + int(round(t * 1e9)), "map", "base_link", T))
            w.write("/ins/pose", PoseSample(T0_NS + int(round(t * 1e9)), "map", "base_link", np.eye(4)))
    with pytest.raises(InputError, match=r"2 pose topics \(/gt/pose, /ins/pose\)"):
        evaluate_build(ws, log)
    with pytest.raises(InputError, match="no pose topic '/nope'"):
        evaluate_build(ws, log, truth_topic="/nope")
    for kwargs in ({"truth": f"{log}::/gt/pose"}, {"truth": log, "truth_topic": "/gt/pose"}):
        r = evaluate_build(ws, **kwargs)
        s = r["sessions"]["drive"]
        assert r["truth_kind"] == "topic" and s["truth"]["source"] == f"{log}::/gt/pose"
        assert s["association"]["interpolated"] == 400 and s["association"]["nearest"] == 0
        # lateral acceleration at most 15/36 m/s^2: linear interpolation over 20 ms errs by a dt^2 / 8 < 0.03 mm
        assert s["ate"]["rmse_m"] < 1e-4
        assert_transform(s["alignment"]["truth_from_estimate"], RIGID, 1e-4)


def test_association_interpolates_only_between_close_neighbours():
    est = np.array([0, 100, 200, 300], np.int64)
    truth = np.array([-5, 5, 95, 195, 250], np.int64)  # 300 has only a neighbour 50 away
    poses = make_pose(
        np.repeat(np.eye(3)[None], 5, axis=0), np.stack([truth, 0 * truth, 0 * truth], axis=1).astype(float)
    )
    a = associate_truth(est, truth, poses, max_dt_ns=10)
    assert list(a.est_index) == [0, 1, 2] and a.interpolated == 1 and a.nearest == 2
    assert np.allclose(a.truth_poses[:, 0, 3], [0.0, 95.0, 195.0])


def test_bad_truths_are_one_clear_error(tmp_path, capsys):
    ws = workspace(tmp_path)
    good = write_tum(tmp_path / "gt.tum", EST_NS, EST)
    lines = good.read_text().splitlines()
    lines[5] = lines[5].replace(" ", " x", 1)
    bad = tmp_path / "bad.tum"
    bad.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match="line 6 has a value that is not a number") as e:
        evaluate_build(ws, bad)
    assert e.value.path == bad and e.value.field == "line 6"
    five = tmp_path / "five.txt"
    five.write_text("1 2 3 4 5\n")
    with pytest.raises(InputError, match="has 5 values; expected a TUM trajectory file"):
        evaluate_build(ws, five)
    binary = tmp_path / "blob.bin"
    binary.write_bytes(bytes(range(256)))
    with pytest.raises(InputError, match="not a text file"):
        evaluate_build(ws, binary)
    with pytest.raises(InputError, match="do not overlap"):
        evaluate_build(ws, write_tum(tmp_path / "later.tum", EST_NS + 3600 * 10**9, EST))
    with pytest.raises(InputError, match="only 2 of the session's 400 poses"):
        evaluate_build(ws, write_tum(tmp_path / "sparse.tum", EST_NS[[0, 200]] + 10**7, EST[[0, 200]]))
    two = workspace(tmp_path / "two", names=("a", "b"))
    with pytest.raises(InputError, match=r"2 sessions \(a, b\); name the one the truth belongs to with --session"):
        evaluate_build(two, good)
    assert evaluate_build(two, good, session="b")["sessions"].keys() == {"b"}
    # the CLI: one line on stderr and exit code 2, never a traceback
    for args in (
        ["--truth", str(bad)],
        ["--truth", str(tmp_path / "missing.tum")],
        ["--truth", str(tmp_path)],
        ["--truth", str(good), "--align", "affine"],
    ):
        assert main(["eval", "build", str(ws.root), *args]) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: ") and len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert main(["eval", "build", str(ws.root), "--truth", str(good)]) == 0
    out = capsys.readouterr().out
    assert "| ATE RMSE m |" in out and "eval_build.json" in out


def test_real_kitti_oxts_pose_topic_as_truth(tmp_path):
    """The real KITTI raw OXTS drive, built from its own INS pose stream and GPS: evaluated against that
    pose stream, the fit must undo exactly the GPS alignment's transform (enu_from_map), leaving no error."""
    drive_dir = REAL_DATA / "kitti-raw-0001-oxts" / "2011_09_26" / "2011_09_26_drive_0001_sync"
    if not drive_dir.is_dir():
        pytest.skip(f"real data not found at {drive_dir}")
    with open_log(drive_dir) as log:
        pose_topics = log.topics_of(StreamKind.POSE)
    if len(pose_topics) != 1:
        pytest.skip(f"the KITTI raw reader offers {len(pose_topics)} OXTS pose streams here, not one")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputWarning)  # the image stages are skipped: the clip has no images
        ws = build([drive_dir], tmp_path / "ws", progress=False)
    name = drive_dir.name
    s = evaluate_build(ws, f"{drive_dir}::{pose_topics[0]}")["sessions"][name]
    assert s["estimate"]["georeferenced"] and s["alignment"]["mode"] == "se3"
    assert s["association"]["associated"] == 108 and s["association"]["nearest_dt_max_s"] == 0.0
    assert s["ate"]["rmse_m"] < 1e-6 and s["ate"]["rotation_rmse_deg"] < 1e-6
    enu_from_map = np.asarray(json.loads(Workspace(ws).session(name).gps_alignment.read_text())["enu_from_map"])
    assert_transform(s["alignment"]["truth_from_estimate"], np.linalg.inv(enu_from_map), 1e-6)
