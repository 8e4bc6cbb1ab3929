"""`mapkit view`: a Rerun recording of a hand-built workspace of known content, read back with the SDK."""

from __future__ import annotations

import csv
import os
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from mapkit.core.geodesy import LocalFrame
from mapkit.core.runio import atomic_write_ply, mark_done, write_json
from mapkit.core.types import CameraInfo
from mapkit.core.workspace import Workspace
from mapkit.io.trajectory import write_tum
from mapkit.mapping.imagedb import ImageDbConfig, ImageDbWriter, write_images_csv
from mapkit.mapping.trajectory import Trajectory
from mapkit.retrieval.vlad_bundle import DATABASE_COLUMNS

pytest.importorskip("rerun", reason="rerun-sdk (the viewer extra) is not installed")

from mapkit.report.view import INSTALL_HINT, point_quotas, read_recording, render_top_view, write_recording

#: a real GPS log: the OXTS records of KITTI raw drive 0001 (108 fixes), the origin is its first fix
SHARED_DATA = Path(os.environ.get("MAPKIT_SHARED_DATA", Path(__file__).resolve().parents[1].parent / "shared" / "data"))
OXTS = SHARED_DATA / "kitti-raw-0001-oxts" / "2011_09_26" / "2011_09_26_drive_0001_sync"
FRAME = LocalFrame(49.015003823272, 8.4342971002335, 116.43032836914)
T0 = 1_317_042_145_964_389_445
MAP_POINTS = {"a": 3000, "b": 1000}
BUDGET = 2000
REJECTED = [5, 50]  # indices of the fixes gps_alignment.json lists as rejected
K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])
#: a camera looking east (optical z), x right (south), y down
EAST_CAMERA = np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]])


def _poses(xyz: np.ndarray, R: np.ndarray | None = None) -> np.ndarray:
    """Poses at ``xyz``, all with rotation ``R`` (the identity if None)."""
    T = np.tile(np.eye(4), (len(xyz), 1, 1))
    if R is not None:
        T[:, :3, :3] = R
    T[:, :3, 3] = xyz
    return T


@pytest.fixture(scope="module")
def workspace(tmp_path_factory) -> Workspace:
    """Two sessions, built and aligned: a drives 100 m east (201 poses, an image every metre, 3000
    map points), b 60 m north (151 poses, no images, 1000 points); aligned = built + 1 m north.
    One `mapkit localize` run (50 filter poses, 48 retrieval poses) and a hits cache for a."""
    root = tmp_path_factory.mktemp("view") / "ws"
    ws = Workspace(root)
    write_json(ws.origin, FRAME.to_dict())
    rng = np.random.default_rng(0)
    shift = np.array([0.0, 1.0, 0.0])
    paths = {
        "a": np.c_[np.arange(201) * 0.5, np.zeros(201), np.zeros(201)],
        "b": np.c_[np.zeros(151), np.arange(151) * 0.4, np.zeros(151)],
    }
    write_json(ws.align_done, {"sessions": ["a", "b"]})
    fix_stamps = _fix_stamps()
    for name, xyz in paths.items():
        d = ws.session(name)
        stamps = T0 + np.arange(len(xyz), dtype=np.int64) * 100_000_000
        Trajectory(stamps, _poses(xyz), "poses", frame="enu").save(d.georef_trajectory)
        Trajectory(stamps, _poses(xyz + shift), "poses", frame="enu").save(ws.aligned(name).trajectory)
        mark_done(d.georef, "test")
        write_json(
            d.gps_alignment,
            {
                "georeferenced": True,
                **FRAME.to_dict(),
                "rejected_fixes": [
                    {"index": i, "stamp_ns": int(s), "residual_m": 9.0}
                    for i, s in enumerate(fix_stamps)
                    if i in REJECTED
                ],
            },
        )
        write_json(d.metrics, {"session": name, "log": str(OXTS) if name == "a" else str(root / "gone")})
        pts = xyz[rng.integers(0, len(xyz), MAP_POINTS[name])] + rng.normal(0, 3, (MAP_POINTS[name], 3))
        atomic_write_ply(d.map / "points.ply", pts, np.full((len(pts), 3), 0.5), frame=FRAME)
        atomic_write_ply(ws.aligned(name).map / "points.ply", pts + shift, np.full((len(pts), 3), 0.5), frame=FRAME)
    # images of a: one per metre, 640x480
    d = ws.session("a")
    writer = ImageDbWriter(d.imagedb, ImageDbConfig(), {"cam": CameraInfo("cam", 640, 480, K)})
    stamps = T0 + np.arange(201, dtype=np.int64) * 100_000_000
    cams = _poses(paths["a"], EAST_CAMERA)
    for k in range(0, 201, 2):
        writer.add(int(stamps[k]), "cam", rng.integers(0, 255, (480, 640, 3), dtype=np.uint8), cams[k], "bgr8")
    writer.close(FRAME)
    ims = writer.images
    rel = [os.path.relpath(d.imagedb / im.relpath, ws.aligned("a").root) for im in ims]
    aligned = np.stack([im.world_from_cam for im in ims])
    aligned[:, :3, 3] += shift
    write_images_csv(
        ws.aligned("a").images_csv,
        [im.image_id for im in ims],
        [im.stamp_ns for im in ims],
        ["cam"] * len(ims),
        rel,
        aligned,
        FRAME,
    )
    # a `mapkit localize` run and the hits of an evaluation, against a bundle of 10 database images
    run = ws.localize_dir / "run1"
    write_tum(run / "poses_tum.txt", stamps[:50], cams[:50])
    write_tum(run / "retrieval_tum.txt", stamps[2:50], cams[2:50])
    bundle = root.parent / "bundle"
    bundle.mkdir()
    with open(bundle / "database.csv", "w", newline="") as f:
        w = csv.DictWriter(f, DATABASE_COLUMNS)
        w.writeheader()
        for e in range(10):
            w.writerow(
                {c: 0 for c in DATABASE_COLUMNS}
                | {"entry_id": e, "session": "a", "x_m": 10.0 * e, "qw": 1.0, "image": "x.jpg"}
            )
    ids = np.tile(np.arange(3), (len(ims), 1))
    ids[::4, 2] = -1  # fewer hits for some queries
    ws.localize_cache.mkdir(parents=True)
    np.savez(
        ws.localize_cache / "hits-a-k3-test.npz",
        version=1,
        bundle="test",
        bundle_path=str(bundle),
        session="a",
        top_k=3,
        images="x",
        ids=ids,
        distances=np.zeros(ids.shape, np.float32),
    )
    return ws


def _fix_stamps() -> np.ndarray:
    """Stamps of the OXTS fixes as the KITTI raw reader gives them (empty without the real data)."""
    if not OXTS.is_dir():
        return np.zeros(0, np.int64)
    from mapkit.core.types import StreamKind
    from mapkit.io import open_log

    with open_log(OXTS) as lg:
        return np.array([f.stamp_ns for f in lg.records(StreamKind.GPS) if f.has_fix], np.int64)


@pytest.fixture(scope="module")
def recording(workspace, tmp_path_factory):
    out = tmp_path_factory.mktemp("rec") / "view.rrd"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        summary = write_recording(workspace, out, budget_points=BUDGET, image_spacing_m=10.0, progress=False)
    return summary, read_recording(out), [str(w.message) for w in caught]


def test_point_quotas_share_the_budget():
    assert point_quotas([3000, 3000, 1000, 1000], 2000) == [750, 750, 250, 250]
    assert point_quotas([10, 20], 100) == [10, 20]  # under budget: everything
    assert sum(point_quotas([7, 11, 13], 10)) <= 10


def test_entity_tree_holds_both_maps_cameras_and_localization(recording):
    _, data, _ = recording
    expected = {"world", "notes", "world/align/a/camera", "world/localize/hits/a/retrieved"}
    for source in ("build", "align"):
        for name in ("a", "b"):
            expected |= {f"world/{source}/{name}/{leaf}" for leaf in ("trajectory", "vehicle", "map")}
    for key in ("filter", "retrieval"):
        expected |= {f"world/localize/run1/{key}/trajectory", f"world/localize/run1/{key}/vehicle"}
    entities = {e for e in data if not e.startswith("__") and "/gps/" not in e}
    assert entities == expected
    assert "world/build/a/camera" not in data  # images go with the aligned poses when align holds the session
    from rerun.chunk import RrdReader

    assert len(RrdReader(str(recording[0].path)).blueprints()) == 1  # the default layout travels with the file


def test_map_points_are_decimated_to_the_budget(recording, workspace):
    import open3d as o3d

    s, data, _ = recording
    counts = {e: len(c["Points3D:positions"][0]) for e, c in data.items() if e.endswith("/map")}
    assert counts == {
        "world/build/a/map": 750,
        "world/align/a/map": 750,
        "world/build/b/map": 250,
        "world/align/b/map": 250,
    }
    assert sum(counts.values()) <= BUDGET and s.points == sum(counts.values())
    # the logged points are points of the map, not new ones
    ply = np.asarray(o3d.io.read_point_cloud(str(workspace.aligned("b").map / "points.ply")).points)
    logged = np.asarray(data["world/align/b/map"]["Points3D:positions"][0], np.float64)
    assert np.isin(np.round(logged[:, 0], 3), np.round(ply[:, 0], 3)).all()


def test_trajectories_have_every_pose_on_the_drive_timeline(recording):
    _, data, _ = recording
    for source, shift in (("build", 0.0), ("align", 1.0)):
        strip = data[f"world/{source}/a/trajectory"]["LineStrips3D:strips"][0][0]
        assert len(strip) == 201
        assert np.allclose(np.asarray(strip)[[0, -1]], [[0, shift, 0], [100, shift, 0]], atol=1e-4)
        vehicle = data[f"world/{source}/b/vehicle"]
        assert len(vehicle["Transform3D:translation"]) == 151
        t = np.asarray(vehicle["drive_time"], np.float64)
        assert t[0] == pytest.approx(0.0) and t[-1] == pytest.approx(15.0)
    filt = data["world/localize/run1/filter/trajectory"]["LineStrips3D:strips"][0][0]
    assert len(filt) == 50 and len(data["world/localize/run1/retrieval/trajectory"]["LineStrips3D:strips"][0][0]) == 48


def test_one_thumbnail_per_spacing_at_its_pose(recording):
    import cv2

    s, data, _ = recording
    cam = data["world/align/a/camera"]
    xyz = np.asarray([r[0] for r in cam["Transform3D:translation"] if r is not None and len(r)], np.float64)
    assert len(xyz) == 11 == s.images["world/align/a/camera"]  # 101 images a metre apart, one per 10 m
    assert np.allclose(xyz[:, 1], 1.0, atol=1e-4)  # the aligned poses
    assert (np.linalg.norm(np.diff(xyz, axis=0), axis=1) >= 10.0 - 1e-4).all()
    blobs = [b for b in cam["EncodedImage:blob"] if b is not None and len(b)]
    assert len(blobs) == 11
    thumb = cv2.imdecode(np.asarray(blobs[0], np.uint8), cv2.IMREAD_COLOR)
    assert thumb.shape == (240, 320, 3)
    K_thumb = np.asarray(cam["Pinhole:image_from_camera"][0], np.float64).reshape(3, 3).T  # column-major
    assert K_thumb[0, 0] == pytest.approx(250.0) and K_thumb[0, 2] == pytest.approx(159.5)
    assert np.asarray(cam["drive_time"], np.float64)[-1] == pytest.approx(20.0)


def test_retrieved_database_poses_per_query(recording):
    _, data, _ = recording
    rows = [r for r in data["world/localize/hits/a/retrieved"]["Points3D:positions"] if r is not None]
    assert len(rows) == 101
    assert [len(r) for r in rows[:5]] == [2, 3, 3, 3, 2]  # -1 ids are not drawn
    assert np.allclose(np.asarray(rows[1])[:, 0], [0, 10, 20])


@pytest.mark.realdata
def test_gps_fixes_from_the_sessions_log(recording):
    if not OXTS.is_dir():
        pytest.skip(f"real data not found at {OXTS}")
    s, data, messages = recording
    fixes = np.asarray(data["world/build/a/gps/fixes"]["Points3D:positions"][0], np.float64)
    rejected = np.asarray(data["world/build/a/gps/rejected"]["Points3D:positions"][0], np.float64)
    assert len(fixes) + len(rejected) == 108 and len(rejected) == len(REJECTED)
    assert np.linalg.norm(fixes[0]) < 1e-3  # the workspace origin is the first fix
    span = np.linalg.norm(fixes[-1, :2] - fixes[0, :2])
    assert 90.0 < span < 120.0  # the drive covers about 107 m
    assert any("session 'b'" in m and "not found" in m for m in messages)  # b's log is gone: said, not fatal


def test_top_view_png_rendered_from_the_recording(recording, tmp_path):
    s, _, _ = recording
    png = render_top_view(s.path, tmp_path / "view.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    import matplotlib.image

    assert matplotlib.image.imread(png).shape[0] > 500


def test_cli_writes_into_the_workspace_under_its_lock_only(workspace, tmp_path, capsys):
    """The default recording lands in the workspace: written under its lock (refused while another
    command holds it); written elsewhere with -o, it takes no lock."""
    from mapkit.cli import main

    assert main(["view", str(workspace.root), "--budget-points", "100", "--no-gps", "--image-spacing", "50"]) == 0
    out = capsys.readouterr().out
    assert str(workspace.recording) in out and "98 of 8,000 map points" in out and "3 thumbnails" in out
    data = read_recording(workspace.recording)
    assert sum(len(c["Points3D:positions"][0]) for e, c in data.items() if e.endswith("/map")) == 98
    assert not any("/gps/" in e for e in data)

    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time\nfrom mapkit.core.lock import workspace_lock\n"
            f"with workspace_lock({str(workspace.root)!r}, 'mapkit align'):\n"
            " print('held', flush=True); time.sleep(60)",
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        assert main(["view", str(workspace.root), "--no-gps"]) == 2
        assert "mapkit align" in capsys.readouterr().err
        assert main(["view", str(workspace.root), "--no-gps", "-o", str(tmp_path / "elsewhere.rrd")]) == 0
        assert (tmp_path / "elsewhere.rrd").stat().st_size > 0
    finally:
        holder.kill()
        holder.wait()


def test_spawn_without_a_display_is_refused(workspace, tmp_path, monkeypatch):
    from mapkit.core.errors import MapkitError

    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(MapkitError, match="no display"):
        write_recording(workspace, tmp_path / "x.rrd", spawn=True, gps=False, progress=False)


def test_without_the_sdk_mapkit_works_and_view_says_how_to_install(workspace):
    code = (
        "import sys; sys.modules['rerun'] = None\n"
        "import mapkit.report.view, mapkit.cli\n"
        f"sys.exit(mapkit.cli.main(['view', {str(workspace.root)!r}, '-o', '/dev/null/x.rrd']))"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip() == f"error: {INSTALL_HINT}"


def test_gps_fixes_saved_by_the_georef_stage_are_drawn_without_the_log(tmp_path):
    """A session built since the georef stage saves its screened fixes: they are drawn from
    gps_fixes.npz as saved (the log is not needed), rejected = associated but not an inlier."""
    ws = Workspace(tmp_path / "ws")
    write_json(ws.origin, FRAME.to_dict())
    d = ws.session("c")
    stamps = T0 + np.arange(20, dtype=np.int64) * 100_000_000
    Trajectory(stamps, _poses(np.c_[np.arange(20.0), np.zeros(20), np.zeros(20)]), "poses", frame="enu").save(
        d.georef_trajectory
    )
    write_json(d.gps_alignment, {"georeferenced": True, **FRAME.to_dict(), "rejected_fixes": []})
    mark_done(d.georef, "test")
    write_json(d.metrics, {"session": "c", "log": str(tmp_path / "gone")})
    enu = np.c_[np.arange(6) * 4.0, np.full(6, 0.5), np.zeros(6)]
    associated = np.array([1, 1, 1, 1, 1, 0], bool)
    inlier = np.array([1, 0, 1, 1, 0, 0], bool)
    np.savez(d.gps_fixes, stamps_ns=stamps[:6], enu=enu, sigma_m=np.ones(6), associated=associated, inlier=inlier)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no "log not found" warning: the log is not read
        s = write_recording(ws, tmp_path / "c.rrd", progress=False)
    data = read_recording(s.path)
    fixes = np.asarray(data["world/build/c/gps/fixes"]["Points3D:positions"][0], np.float64)
    rejected = np.asarray(data["world/build/c/gps/rejected"]["Points3D:positions"][0], np.float64)
    np.testing.assert_allclose(rejected, enu[[1, 4]], atol=1e-4)
    np.testing.assert_allclose(fixes, enu[[0, 2, 3, 5]], atol=1e-4)
