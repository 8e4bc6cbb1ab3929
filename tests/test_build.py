"""`mapkit build` on a cut of the real KITTI clip: outputs, formats, and resuming after a crash."""

import json
import shutil
import warnings

import numpy as np
import open3d as o3d
import pycolmap
import pytest

from mapkit.cli import main
from mapkit.core.errors import ConfigError, InputError, InputWarning
from mapkit.core.geometry import make_pose
from mapkit.core.runio import is_done
from mapkit.core.types import CameraFrame, CameraInfo, FrameTransform, PoseSample
from mapkit.core.workspace import Workspace
from mapkit.io.mcap_log import McapWriter
from mapkit.mapping.build import build
from mapkit.mapping.imagedb import read_images_csv

N = 12  # frames of the clip12 fixture (tests/conftest.py)


def test_build_writes_every_stage_in_the_fields_formats(clip12, tmp_path):
    ws = build([clip12], tmp_path / "ws", progress=False)
    s = ws / "sessions" / "clip12"
    for stage in ("trajectory", "georef", "map", "imagedb"):
        assert is_done(s / stage), stage
    pcd = o3d.io.read_point_cloud(str(s / "map" / "points.ply"))
    assert len(pcd.points) > 5000
    rec = pycolmap.Reconstruction(str(s / "imagedb" / "colmap"))
    assert rec.num_images() >= 8  # frames at least 0.5 m apart
    assert rec.num_points3D() > 1000
    # every COLMAP point reprojects onto its track's keypoints
    pid, pt = next(iter(rec.points3D.items()))
    for el in pt.track.elements:
        im = rec.image(el.image_id)
        uv = im.project_point(pt.xyz)
        np.testing.assert_allclose(uv, im.points2D[el.point2D_idx].xy, atol=1e-6)
    table = read_images_csv(s / "imagedb" / "images.csv")
    assert len(table["stamp_ns"]) == rec.num_images() and np.all(
        np.isnan(table["lat_deg"])
    )  # no GPS: not georeferenced
    ga = json.loads((s / "georef" / "gps_alignment.json").read_text())
    assert ga["georeferenced"] is False
    m = json.loads((ws / "metrics.json").read_text())["sessions"]["clip12"]["stages"]
    assert m["trajectory"]["source"] == "poses:/kitti/ground_truth" and m["semidense"]["points"] == len(pcd.points)
    assert (s / "map" / "top_view.png").stat().st_size > 10_000
    assert (s / "trajectory" / "poses_tum.txt").is_file() and (s / "trajectory" / "poses_kitti.txt").is_file()


def test_a_corrupt_image_costs_its_frame_not_the_build(clip12, tmp_path):
    """A corrupt PNG costs its frame, not the build: that frame is skipped with a warning that names the
    file, and the map and the image database are built from the others."""
    d = tmp_path / "clip12"
    shutil.copytree(clip12, d)
    bad = d / "image_l" / "000005.png"
    data = bytearray(bad.read_bytes())
    data[len(data) // 2 :] = bytes(len(data) - len(data) // 2)  # the second half of the file zeroed
    bad.write_bytes(bytes(data))
    with pytest.warns(InputWarning, match=r"000005\.png.*frame 5 of camera_0 skipped"):
        ws = build([d], tmp_path / "ws", progress=False)
    s = Workspace(ws).session("clip12")
    assert is_done(s.map) and is_done(s.imagedb)
    stages = json.loads(Workspace(ws).metrics.read_text())["sessions"]["clip12"]["stages"]
    assert stages["semidense"]["points"] > 5000
    stamps = read_images_csv(s.images_csv)["stamp_ns"]
    assert len(stamps) >= 7 and not np.isin(stamps, [int(round(0.5e9))]).any()  # frame 5 (t = 0.5 s) is not in it


def test_interrupted_build_resumes_without_redoing_finished_stages(clip12, tmp_path, monkeypatch):
    ws = tmp_path / "ws"

    def crash(self, *a, **k):
        raise RuntimeError("power cut while writing the image database")

    monkeypatch.setattr("mapkit.mapping.imagedb.ImageDbWriter.close", crash)
    with pytest.raises(RuntimeError):
        build([clip12], ws, progress=False)
    s = ws / "sessions" / "clip12"
    assert is_done(s / "map") and not is_done(s / "imagedb")  # the half-written stage is not finished
    ply_mtime = (s / "map" / "points.ply").stat().st_mtime_ns
    monkeypatch.undo()
    build([clip12], ws, progress=False)
    assert is_done(s / "imagedb")
    assert (s / "map" / "points.ply").stat().st_mtime_ns == ply_mtime  # the finished map was not redone


def test_changed_config_redoes_only_what_depends_on_it(clip12, tmp_path):
    ws = tmp_path / "ws"
    build([clip12], ws, progress=False)
    s = ws / "sessions" / "clip12"
    traj_mtime = (s / "trajectory" / "trajectory.npz").stat().st_mtime_ns
    n_before = len(read_images_csv(s / "imagedb" / "images.csv")["stamp_ns"])
    cfg = tmp_path / "c.yaml"
    cfg.write_text("imagedb:\n  min_spacing_m: 2.0\n")
    build([clip12], ws, config=cfg, progress=False)
    assert (s / "trajectory" / "trajectory.npz").stat().st_mtime_ns == traj_mtime
    assert len(read_images_csv(s / "imagedb" / "images.csv")["stamp_ns"]) < n_before


def test_build_cli_errors_are_one_line(tmp_path, capsys):
    bad = tmp_path / "c.yaml"
    bad.write_text("imagedb:\n  min_spacing: 2\n")
    assert main(["build", str(tmp_path), "--out", str(tmp_path / "ws"), "--config", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "imagedb.min_spacing" in err and "Traceback" not in err


def test_missing_intrinsics_is_one_clear_error_before_any_stage_runs(tmp_path, rng, capsys):
    """A generic folder with poses but no intrinsics: refused before the trajectory is built (the
    trajectory and georeferencing do not need intrinsics, so only an early check spares their work); with
    map and image database off the same log builds its trajectory."""
    import cv2

    d = tmp_path / "drive"
    (d / "images").mkdir(parents=True)
    rows = ["timestamp_ns,image,x,y,z,qw,qx,qy,qz"]
    for i in range(6):
        cv2.imwrite(str(d / "images" / f"{i}.png"), rng.integers(0, 255, (48, 64), dtype=np.uint8))
        rows.append(f"{1000 + i * 100_000_000},{i}.png,0,0,{i * 0.5},1,0,0,0")
    (d / "frames.csv").write_text("\n".join(rows) + "\n")
    assert main(["build", str(d), "--out", str(tmp_path / "ws")]) == 2
    err = capsys.readouterr().err
    assert "no camera intrinsics" in err and str(d) in err and "Traceback" not in err
    s = tmp_path / "ws" / "sessions" / "drive"
    assert not (s / "trajectory").exists()
    (tmp_path / "c.yaml").write_text("map: false\nimagedb: false\n")
    assert main(["build", str(d), "--out", str(tmp_path / "ws"), "-c", str(tmp_path / "c.yaml")]) == 0
    assert is_done(s / "trajectory") and not (s / "map").exists()


def test_two_logs_with_one_session_name_are_refused_before_anything_is_written(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    logs = [tmp_path / "a" / "drive.mcap", tmp_path / "b" / "drive.mcap"]
    with pytest.raises(InputError, match="same session name 'drive'"):
        build(logs, tmp_path / "ws", progress=False)
    assert not (tmp_path / "ws").exists()


def test_a_misspelt_semidense_key_fails_when_the_config_loads_before_any_stage(tmp_path):
    """``semidense`` is typed: a typo is refused with the other keys, not after two stages have run."""
    cfg = tmp_path / "c.yaml"
    cfg.write_text("semidense:\n  max_depht_m: 50.0\n")
    with pytest.raises(ConfigError, match=r"semidense\.max_depht_m"):
        build([tmp_path / "drive.mcap"], tmp_path / "ws", config=cfg, progress=False)
    cfg.write_text("semidense:\n  max_depth_m: 0.5\n")  # a value its own validator refuses (below min_depth_m)
    with pytest.raises(ConfigError, match="semidense"):
        build([tmp_path / "drive.mcap"], tmp_path / "ws", config=cfg, progress=False)
    assert not (tmp_path / "ws").exists()  # nothing ran


T0 = 1_700_000_000_000_000_000


def _two_camera_log(path, front_grey: int, rear_grey: int):
    """2 s at 10 Hz: poses of base_link, and two cameras (each with intrinsics, an extrinsic and one
    image topic) whose frames are flat grey images, one grey level per camera, 20 ms apart."""
    K = np.array([[40.0, 0, 32], [0, 40, 24], [0, 0, 1]])
    with McapWriter(path) as w:
        w.write_transforms(
            "/tf_static",
            [FrameTransform(0, "base_link", cam, make_pose(np.eye(3), [1.0, 0, 1.5])) for cam in ("front", "rear")],
        )
        for cam in ("front", "rear"):
            w.write(f"/{cam}/camera_info", CameraInfo(cam, 64, 48, K, stamp_ns=T0))
        for i in range(20):
            t = T0 + i * 100_000_000
            w.write("/odom", PoseSample(t, "map", "base_link", make_pose(np.eye(3), [0.5 * i, 0, 0])))
            if 0 < i < 19:
                w.write("/front/image", CameraFrame(t, "front", np.full((48, 64), front_grey, np.uint8)))
                w.write("/rear/image", CameraFrame(t + 20_000_000, "rear", np.full((48, 64), rear_grey, np.uint8)))
    return path


def test_build_reads_images_from_the_topics_named_in_topics_images(tmp_path):
    import cv2

    log = _two_camera_log(tmp_path / "two_cams.mcap", front_grey=60, rear_grey=190)
    cfg = tmp_path / "c.yaml"
    cfg.write_text(
        "topics:\n  images: [/rear/image]\ntrajectory:\n  source: poses\nmap: false\n"
        "imagedb:\n  min_spacing_m: 0.0\n  image_format: png\n"
    )
    with pytest.warns(InputWarning, match="no GPS stream"):
        ws = build([log], tmp_path / "ws", config=cfg, progress=False)
    db = Workspace(ws).session("two_cams").imagedb
    table = read_images_csv(db / "images.csv")
    assert set(table["camera"]) == {"rear"}
    assert table["stamp_ns"].tolist() == [T0 + i * 100_000_000 + 20_000_000 for i in range(1, 19)]
    for rel in table["image"]:
        assert (cv2.imread(str(db / rel), cv2.IMREAD_UNCHANGED) == 190).all()


def test_a_map_that_would_be_empty_is_one_error_and_nothing_of_it_is_written(tmp_path, capsys):
    """Flat grey frames (a lens cap on, say) give no depth: the map stage fails in one line naming the log, the
    session and the way out, and publishes no map; the stages before it stay finished."""
    log = _two_camera_log(tmp_path / "capped.mcap", front_grey=60, rear_grey=190)
    cfg = tmp_path / "c.yaml"
    cfg.write_text("topics:\n  images: [/front/image]\ntrajectory:\n  source: poses\nimagedb: false\n")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputWarning)  # no GPS stream
        assert main(["build", str(log), "--out", str(tmp_path / "ws"), "-c", str(cfg)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "capped.mcap [map]" in err[0] and "0 points" in err[0] and "map: false" in err[0], err
    dirs = Workspace(tmp_path / "ws").session("capped")
    assert not dirs.map.exists() or not any(dirs.map.glob("*.ply"))
    assert is_done(dirs.trajectory)


def _imageless_log(path, yaw_deg: float = 37.0, faults: bool = False):
    """A log as an INS-equipped car without a camera records it: 30 s of fused poses of base_link
    at 10 Hz along a 300 m bend, and GPS at 1 Hz (1 m noise) in an ENU frame turned by ``yaw_deg``
    from the pose frame. No image, no LiDAR. ``faults``: the first fix reports FIX at (0, 0), the
    tenth is 1 km off, and the last five have no altitude (NaN)."""
    from mapkit.core.geodesy import LocalFrame
    from mapkit.core.geometry import yaw_rotation
    from mapkit.core.types import GpsFix

    rng = np.random.default_rng(5)
    frame = LocalFrame(49.0, 8.4, 110.0)
    R = yaw_rotation(np.radians(yaw_deg))
    with McapWriter(path) as w:
        for i in range(300):
            t = T0 + i * 100_000_000
            s = i * 1.0
            xyz = np.array([s, 0.002 * s**2, 0.0])
            w.write("/ins/pose", PoseSample(t, "map", "base_link", make_pose(yaw_rotation(np.arctan(0.004 * s)), xyz)))
            if i % 10 == 0:
                noisy = R @ xyz + rng.normal(scale=1.0, size=3) + ([1000.0, 0, 0] if faults and i == 90 else 0.0)
                lat, lon, alt = (
                    (np.array([v]) for v in (0.0, 0.0, 0.0))
                    if faults and i == 0
                    else frame.enu_to_geodetic(noisy[None])
                )
                alt = np.array([np.nan]) if faults and i >= 250 else alt
                w.write(
                    "/gps/fix",
                    GpsFix(t, float(lat[0]), float(lon[0]), float(alt[0]), covariance_enu_m2=np.diag([1.0, 1.0, 4.0])),
                )
    return path


def test_a_log_without_images_builds_its_trajectory_and_georef_and_skips_the_image_stages(tmp_path, capsys):
    """``mapkit build`` on an image-less log exits 0: trajectory and GPS alignment (the known 37 deg
    yaw recovered), the map and image database skipped with the reason in metrics.json, a warning
    and the summary."""
    log = _imageless_log(tmp_path / "highway.mcap")
    with pytest.warns(InputWarning, match="semidense skipped: the log has no image stream"):
        assert main(["build", str(log), "--out", str(tmp_path / "ws")]) == 0
    captured = capsys.readouterr()
    assert "semidense skipped: the log has no image stream" in captured.out
    assert "imagedb skipped: the log has no image stream" in captured.out
    s = Workspace(tmp_path / "ws").session("highway")
    assert is_done(s.trajectory) and is_done(s.georef) and not s.map.exists() and not s.imagedb.exists()
    st = json.loads((tmp_path / "ws" / "metrics.json").read_text())["sessions"]["highway"]["stages"]
    assert st["semidense"] == {"skipped": "the log has no image stream"} and st["imagedb"] == st["semidense"]
    s_m = np.arange(300.0)
    length = np.linalg.norm(np.diff(np.stack([s_m, 0.002 * s_m**2], axis=1), axis=0), axis=1).sum()  # 359.7 m
    assert st["trajectory"]["source"] == "poses:/ins/pose" and st["trajectory"]["length_m"] == pytest.approx(length)
    assert st["georef"]["georeferenced"] and st["georef"]["yaw_deg"] == pytest.approx(37.0, abs=0.5)
    assert st["georef"]["units"] == "m" and st["georef"]["residual_rmse_m"] < 3.0
    # a later stage that needs a map names why this session has none
    from mapkit.multisession.align import align_workspace

    with (
        pytest.warns(InputWarning, match=r"has no semi-dense map \(skipped at build: the log has no image stream\)"),
        pytest.raises(InputError, match="0 alignable session"),
    ):
        align_workspace(tmp_path / "ws", progress=False)


def test_wild_gps_fixes_are_screened_before_one_can_become_the_origin(tmp_path):
    """Null island: a first fix at (0, 0) with FIX status must not become origin.json. It and a 1 km
    jump are rejected and counted, fixes without altitude take the others' median, the
    origin is the first good fix, and the alignment is as good as without the faults."""
    from mapkit.mapping.gps_screen import JUMP, NULL_ISLAND

    log = _imageless_log(tmp_path / "highway.mcap", faults=True)
    with pytest.warns(InputWarning) as caught:
        ws = build([log], tmp_path / "ws", progress=False)
    msgs = [str(w.message) for w in caught]
    assert any("2 of 30 GPS fixes rejected" in m and "null island" in m and "jump" in m for m in msgs), msgs
    assert any("5 of 28 GPS fixes have no altitude" in m for m in msgs), msgs
    origin = Workspace(ws).frame()
    assert origin.lat0_deg == pytest.approx(49.0, abs=1e-3) and origin.lon0_deg == pytest.approx(8.4, abs=1e-3)
    s = Workspace(ws).session("highway")
    ga = json.loads(s.gps_alignment.read_text())
    assert ga["gps_screen"]["rejected"] == {NULL_ISLAND: 1, JUMP: 1} and ga["gps_screen"]["altitude_filled"] == 5
    assert ga["alignment"]["yaw_deg"] == pytest.approx(37.0, abs=0.5) and ga["alignment"]["residual_rmse_m"] < 3.0
    with np.load(s.gps_fixes) as f:
        assert len(f["stamps_ns"]) == 28 and f["enu"].shape == (28, 3) and np.isfinite(f["enu"]).all()
        assert f["inlier"].sum() >= 25 and not (f["inlier"] & ~f["associated"]).any()
        # the fixes are where the workspace frame puts them: the first good one is the origin
        assert np.linalg.norm(f["enu"][0]) < 1e-6


def test_imagedb_false_and_map_false_skip_those_stages_without_a_warning(tmp_path):
    log = _two_camera_log(tmp_path / "two_cams.mcap", front_grey=60, rear_grey=190)
    cfg = tmp_path / "c.yaml"
    cfg.write_text("trajectory:\n  source: poses\nmap: false\nimagedb: false\n")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ws = build([log], tmp_path / "ws", config=cfg, progress=False)
    assert [str(w.message) for w in caught if "skipped" in str(w.message)] == []
    s = Workspace(ws).session("two_cams")
    assert is_done(s.georef) and not s.map.exists() and not s.imagedb.exists()
    st = json.loads((ws / "metrics.json").read_text())["sessions"]["two_cams"]["stages"]
    assert st["semidense"] == {"skipped": "map: false in the config"} and st["imagedb"] == {
        "skipped": "imagedb: false in the config"
    }


def test_image_database_at_2hz_keeps_the_frames_it_skips_for_encoder_training(tmp_path):
    """MCVL's database is its training drives sub-sampled to 2 Hz (Sec. IV-B): from a 10 Hz camera
    ``min_interval_s: 0.5`` keeps every fifth frame; with ``training_frames`` the skipped ones (at
    most one per ``training_interval_s``) go to training.csv, disjoint from the database."""
    log = _two_camera_log(tmp_path / "two_cams.mcap", front_grey=60, rear_grey=190)
    cfg = tmp_path / "c.yaml"
    cfg.write_text(
        "topics:\n  images: [/front/image]\ntrajectory:\n  source: poses\nmap: false\n"
        "imagedb:\n  min_spacing_m: 0.0\n  min_interval_s: 0.5\n  training_frames: true\n  training_interval_s: 0.2\n"
        "  image_format: png\n"
    )
    with pytest.warns(InputWarning, match="no GPS stream"):
        ws = build([log], tmp_path / "ws", config=cfg, progress=False)
    s = Workspace(ws).session("two_cams")
    db, training = read_images_csv(s.images_csv), read_images_csv(s.training_csv)
    stamp = [T0 + i * 100_000_000 for i in range(20)]
    assert db["stamp_ns"].tolist() == [stamp[i] for i in (1, 6, 11, 16)]
    assert training["stamp_ns"].tolist() == [stamp[i] for i in (3, 5, 8, 10, 13, 15, 18)]
    assert all(rel.startswith("training/") and (s.imagedb / rel).is_file() for rel in training["image"])
    # the training frames keep their poses: 0.5 m a frame along x
    np.testing.assert_allclose(training["x_m"], [0.5 * i + 1.0 for i in (3, 5, 8, 10, 13, 15, 18)], atol=1e-9)
    assert json.loads((s.imagedb / "metrics.json").read_text())["training_frames"] == 7


def test_per_session_overrides_sub_sample_the_database_drives_and_leave_the_query_drives(tmp_path):
    """One build of database and query drives, as MCVL's: ``sessions: {"train-*": ...}`` puts the
    training drives' database at 2 Hz with their training frames; the query drive keeps every frame."""
    logs = [_two_camera_log(tmp_path / f"{name}.mcap", front_grey=60, rear_grey=190) for name in ("train-x", "test-y")]
    cfg = tmp_path / "c.yaml"
    cfg.write_text(
        "topics:\n  images: [/front/image]\ntrajectory:\n  source: poses\nmap: false\n"
        "imagedb:\n  min_spacing_m: 0.0\n  image_format: png\n"
        "sessions:\n  'train-*':\n    imagedb:\n      min_interval_s: 0.5\n      training_frames: true\n"
    )
    with pytest.warns(InputWarning, match="no GPS stream"):
        ws = Workspace(build(logs, tmp_path / "ws", config=cfg, progress=False))
    train, test = ws.session("train-x"), ws.session("test-y")
    assert (
        len(read_images_csv(train.images_csv)["stamp_ns"]) == 4
        and len(read_images_csv(train.training_csv)["stamp_ns"]) == 14
    )
    assert len(read_images_csv(test.images_csv)["stamp_ns"]) == 18 and not test.training_csv.exists()
    import yaml

    resolved = yaml.safe_load(train.config.read_text())
    assert resolved["imagedb"]["min_interval_s"] == 0.5 and resolved["imagedb"]["min_spacing_m"] == 0.0
    assert yaml.safe_load(test.config.read_text())["imagedb"]["min_interval_s"] == 0.0


def test_a_per_session_pattern_that_matches_no_session_is_a_warning_naming_it(tmp_path):
    log = _two_camera_log(tmp_path / "test-y.mcap", front_grey=60, rear_grey=190)
    cfg = tmp_path / "c.yaml"
    cfg.write_text(
        "trajectory:\n  source: poses\nmap: false\nimagedb: false\n"
        "sessions:\n  'trian-*':\n    imagedb:\n      min_interval_s: 0.5\n"
    )
    with pytest.warns(InputWarning, match=r"sessions\.trian-\* matches none of this build's sessions \['test-y'\]"):
        build([log], tmp_path / "ws", config=cfg, progress=False)


def test_a_misspelt_per_session_override_is_one_error_naming_it(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("sessions:\n  'train-*':\n    imagedb:\n      min_intervall_s: 0.5\n")
    with pytest.raises(ConfigError, match=r"sessions\.train-\*\.imagedb\.min_intervall_s"):
        build([tmp_path / "none.mcap"], tmp_path / "ws", config=cfg, progress=False)
