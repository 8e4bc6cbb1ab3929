"""The localization benchmark export and its evaluation: a workspace of real KITTI frames (every other one the
database, frames between them the queries) whose recorded poses are off the town's truth by a known rigid
transform; the export recovers that transform from the database images alone, so each query's ground truth is
its KITTI pose; the evaluator scores known answers; the 6-DoF localizer runs on the export end to end."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
from scipy.spatial.transform import Rotation
from test_index_vlad import FRAME, SMALL_VLAD, small_config
from test_reference_model import FAST, _kitti, _workspace

from mapkit.core.errors import InputError
from mapkit.core.geodesy import LocalFrame
from mapkit.core.geometry import invert_pose, make_pose, rotation_angle_rad, yaw_rotation
from mapkit.deploy.benchmark import BenchmarkExportConfig, export_benchmark, retrieval_recall
from mapkit.evaluation.benchmark import evaluate_benchmark, score_benchmark
from mapkit.io.benchmark import QUERIES, colmap_camera_params, read_pairs, read_queries_with_intrinsics
from mapkit.io.trajectory import read_benchmark_poses, write_benchmark_poses, write_tum
from mapkit.localization.colmap_registrator import ColmapRegistratorConfig, register_benchmark
from mapkit.localization.reference_model import ReferenceModelConfig, build_reference_model
from mapkit.localization.sixdof import localize_benchmark
from mapkit.retrieval.index_vlad import build_vlad_index

DB_FRAMES = list(range(0, 24, 2))
QUERY_FRAMES = [3, 7, 11, 15, 19]
#: the recorded (model) frame from the truth's, the known answer: 20 deg about the world z axis (KITTI's forward,
#: the roll that a straight drive's camera centres alone leave free) and a shift
MODEL_FROM_TRUTH = make_pose(yaw_rotation(np.radians(20.0)), [3.0, -2.0, 0.5])


def _stamps(frames: list[int]) -> np.ndarray:
    return np.array(frames, np.int64) * 100_000_000  # as test_reference_model's workspace stamps its frames


def _town(root: Path, poses: np.ndarray) -> Path:
    """A town folder 10 m east of the workspace's origin holding the true camera poses of both sessions: the
    KITTI poses taken out of the model's frame by MODEL_FROM_TRUTH."""
    lat, lon, alt = FRAME.enu_to_geodetic(np.array([[10.0, 0.0, 0.0]]))
    town_frame = LocalFrame(float(lat[0]), float(lon[0]), float(alt[0]), FRAME.utm_epsg)
    (root / "world").mkdir(parents=True)
    (root / "sessions").mkdir()
    (root / "world" / "origin.json").write_text(json.dumps(town_frame.to_dict()))
    sessions = [
        {"name": "kitti", "role": "train", "condition": "day-sunny", "weather": "sunny"},
        {"name": "query", "role": "test", "condition": "dusk-overcast", "weather": "overcast", "time_of_day": "19:30"},
    ]
    (root / "world" / "manifest.json").write_text(json.dumps({"sessions": sessions}))
    town_from_model = FRAME.to_frame(town_frame) @ invert_pose(MODEL_FROM_TRUTH)
    frames = list(range(24))
    write_tum(root / "sessions" / "kitti.camera.tum", _stamps(frames), town_from_model @ poses[frames])
    for session in ("query", "drive"):  # drive: a query session that is only a log
        write_tum(root / "sessions" / f"{session}.camera.tum", _stamps(frames), town_from_model @ poses[frames])
    return root


def _benchmark_workspace(root: Path, clip: Path) -> Path:
    """Session ``kitti`` (the database) and session ``query`` (frames between), georeferenced at FRAME."""
    ws = _workspace(root / "ws", clip, DB_FRAMES)
    queries = _workspace(root / "q", clip, QUERY_FRAMES)
    shutil.move(queries.session("kitti").imagedb.parent, ws.session("query").imagedb.parent)
    (ws.root / "origin.json").write_text(json.dumps(FRAME.to_dict()))
    return ws.root


@pytest.fixture(scope="module")
def exported(kitti_clip, tmp_path_factory):
    root = tmp_path_factory.mktemp("bench")
    ws = _benchmark_workspace(root, kitti_clip)
    build_reference_model(ws, ["kitti"], config=ReferenceModelConfig(**FAST))
    vlad = SMALL_VLAD.model_copy(update={"pca_dim": 8})  # 12 database images: a PCA of at most 11 dimensions
    build_vlad_index(ws, config=small_config(database_sessions=["kitti"], vlad=vlad), progress=False)
    _, poses = _kitti(kitti_clip)
    town = _town(root / "town", poses)
    out = export_benchmark(ws, root / "bench", ["query"], truth=town, config=BenchmarkExportConfig(retrieval_k=4))
    return ws, out, poses, town


def test_export_holds_the_model_queries_and_their_true_poses(exported):
    ws, out, poses, _ = exported
    rec = pycolmap.Reconstruction(str(out / "sfm"))
    assert rec.num_images() == len(DB_FRAMES) and rec.num_points3D() > 50
    for im in rec.images.values():  # every database image resolves under images/ by the model's own name
        assert (out / "images" / im.name).is_file()
    cams = read_queries_with_intrinsics(out / "queries_with_intrinsics.txt")
    names = [f"query/query/cam0/{i * 100_000_000}.png" for i in QUERY_FRAMES]
    assert list(cams) == names
    for n in names:
        assert (out / "images" / n).is_file()
        line = next(x for x in (out / "queries_with_intrinsics.txt").read_text().splitlines() if x.startswith(n))
        assert line.split()[1:4] == ["PINHOLE", "1226", "370"]
    # the truth came through MODEL_FROM_TRUTH, fitted on the database images: each query's truth is its KITTI pose
    gt_names, gt = read_benchmark_poses(out / "queries_gt.txt")
    assert gt_names == names
    for i, T in zip(QUERY_FRAMES, gt, strict=True):
        expected = invert_pose(poses[i])
        assert np.linalg.norm(invert_pose(T)[:3, 3] - poses[i][:3, 3]) < 1e-3  # images.csv keeps 0.1 mm
        assert np.degrees(rotation_angle_rad(T[:3, :3] @ expected[:3, :3].T)) < 1e-3
    m = json.loads((out / "metrics.json").read_text())
    assert m["truth"]["fit_images"] == len(DB_FRAMES) and m["truth"]["residual_max_m"] < 1e-3
    np.testing.assert_allclose(m["truth"]["model_from_truth"], MODEL_FROM_TRUTH, atol=1e-4)
    assert m["queries"] == len(QUERY_FRAMES) and m["queries_without_truth"] == {"query": 0}
    # retrieval pairs: each query's top 4, all images of the model
    pairs = read_pairs(out / "pairs-query-retrieval.txt")
    model_names = {im.name for im in rec.images.values()}
    assert list(pairs) == names and all(len(v) == 4 and set(v) <= model_names for v in pairs.values())
    cond = json.loads((out / "conditions.json").read_text())
    assert cond[names[0]] == {
        "session": "query",
        "condition": "dusk-overcast",
        "weather": "overcast",
        "time_of_day": "19:30",
    }
    readme = (out / "README.md").read_text()
    assert "local ENU frame" in readme and f"{FRAME.lat0_deg:.9f}" in readme and "RMSE" in readme
    # every query lies between database frames a metre or two apart: its first retrieved image shows its place
    assert m["retrieval"]["recall"]["sessions"] == {
        "query": {"queries": len(QUERY_FRAMES), "recall_at": {"1": 1.0, "4": 1.0}}
    }
    assert f"| query | {len(QUERY_FRAMES)} | 100.0 % | 100.0 % |" in readme
    assert (out / "config.yaml").is_file() and (out / "database.db").is_file()


def test_retrieval_recall_counts_the_first_database_image_at_the_querys_place():
    """Cameras on a street looking east (+x), one facing west: a retrieved image counts where it is within the
    radius and looks within the angle, from the rank where the first such image comes."""

    def cam(x: float, yaw_deg: float = 0.0) -> np.ndarray:
        # optical frame: z forward along the yaw, x right, y down
        fwd = np.array([np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg)), 0.0])
        right = np.cross(fwd, [0.0, 0.0, 1.0])
        R = np.stack([right, np.cross(fwd, right), fwd], axis=1)
        return make_pose(R, [x, 0.0, 0.0])

    db = {"d0": cam(0), "d8": cam(8), "d25": cam(25), "d0west": cam(0, 180), "d3turned": cam(3, 40)}
    queries = {"a": cam(0.5), "b": cam(-0.5), "c": cam(30), "n": cam(100), "lone": cam(0)}
    pairs = [
        ("a", "d0"),  # rank 1 at the place
        ("b", "d25"),
        ("b", "d0west"),  # same spot, looking the other way: not the place
        ("b", "d3turned"),  # 40 deg off a 30 deg bound: not the place
        ("b", "d8"),  # 8.5 m: at rank 4
        ("c", "d25"),  # 5 m: rank 1
        ("n", "d25"),  # 75 m away: never
    ]  # "lone" has no pairs at all: a miss
    sessions = {"a": "s", "b": "s", "c": "t", "n": "t", "lone": "t"}
    r = retrieval_recall(pairs, queries, db, sessions, k=4, radius_m=10.0, max_angle_deg=30.0)
    assert r["sessions"]["s"] == {"queries": 2, "recall_at": {"1": 0.5, "4": 1.0}}
    assert r["sessions"]["t"] == {"queries": 3, "recall_at": {"1": pytest.approx(1 / 3), "4": pytest.approx(1 / 3)}}
    # b's first image of its place is the fourth: not within three
    assert retrieval_recall(pairs, queries, db, sessions, 3, 10.0, 30.0)["sessions"]["s"]["recall_at"]["3"] == 0.5
    # a tighter radius drops b's 8.5 m neighbour and c's 5 m one
    r = retrieval_recall(pairs, queries, db, sessions, k=50, radius_m=4.0, max_angle_deg=30.0)
    assert r["sessions"]["s"]["recall_at"] == {"1": 0.5, "5": 0.5, "10": 0.5, "20": 0.5, "50": 0.5}
    assert r["sessions"]["t"]["recall_at"]["50"] == 0.0


def test_evaluator_scores_known_answers(exported, tmp_path):
    _, out, _, _ = exported
    names, gt = read_benchmark_poses(out / "queries_gt.txt")
    ev = evaluate_benchmark(out / "queries_gt.txt", out / "queries_gt.txt", out / "conditions.json")
    assert set(ev.overall.recall.values()) == {1.0} and ev.overall.missing == 0
    assert ev.overall.median_translation_m == 0.0 and list(ev.conditions) == ["dusk-overcast"]
    # every camera 1 m off along its own x axis (world_from_cam's translation moved by 1 m), orientation kept
    world = np.array([invert_pose(T) for T in gt])
    world[:, :3, 3] += world[:, :3, 0]
    write_benchmark_poses(tmp_path / "off.txt", names, np.array([invert_pose(T) for T in world]))
    ev = evaluate_benchmark(out / "queries_gt.txt", tmp_path / "off.txt")
    assert ev.overall.recall == {"0.25m_2deg": 0.0, "0.5m_5deg": 0.0, "5m_10deg": 1.0}
    assert ev.overall.median_translation_m == pytest.approx(1.0, abs=1e-6)
    assert ev.overall.median_rotation_deg == pytest.approx(0.0, abs=1e-6)
    # every camera turned 3 deg about its own y axis, centres kept: only the orientation fails the first band
    world = np.array([invert_pose(T) for T in gt])
    world[:, :3, :3] = world[:, :3, :3] @ Rotation.from_euler("y", 3.0, degrees=True).as_matrix()
    write_benchmark_poses(tmp_path / "turned.txt", names, np.array([invert_pose(T) for T in world]))
    ev = evaluate_benchmark(out / "queries_gt.txt", tmp_path / "turned.txt")
    assert ev.overall.recall == {"0.25m_2deg": 0.0, "0.5m_5deg": 1.0, "5m_10deg": 1.0}
    assert ev.overall.median_rotation_deg == pytest.approx(3.0, abs=1e-6)
    assert ev.overall.median_translation_m == pytest.approx(0.0, abs=1e-6)
    # two queries missing: failures at every threshold, and counted
    write_benchmark_poses(tmp_path / "part.txt", names[2:], gt[2:])
    ev = evaluate_benchmark(out / "queries_gt.txt", tmp_path / "part.txt", {n: "c" for n in names})
    assert ev.overall.missing == 2 and ev.overall.recall["5m_10deg"] == pytest.approx(3 / 5)
    assert ev.errors[names[0]] is None and ev.conditions["c"].missing == 2


def test_evaluator_takes_poses_named_by_file_name_where_it_is_unique(tmp_path):
    """hloc's localize_sfm names a pose by the query's file name alone: it scores the query of that file name,
    unless two queries share it (then it names no query, and both count as missing)."""
    names = ["night/cam/1.jpg", "day/cam/1.jpg", "day/cam/2.jpg"]
    gt = np.array([make_pose(yaw_rotation(0.1 * i), [i, 2.0 * i, 0.0]) for i in range(3)])
    write_benchmark_poses(tmp_path / "gt.txt", names, gt)
    est = gt.copy()
    est[2, 0, 3] += 0.3  # 0.3 m off: scored, so within (0.5 m, 5 deg) and not (0.25 m, 2 deg)
    write_benchmark_poses(tmp_path / "poses.txt", ["2.jpg", "1.jpg"], est[[2, 0]])
    ev = evaluate_benchmark(tmp_path / "gt.txt", tmp_path / "poses.txt")
    assert ev.errors["day/cam/2.jpg"] == pytest.approx((0.3, 0.0), abs=1e-6)
    assert ev.errors["night/cam/1.jpg"] is None and ev.errors["day/cam/1.jpg"] is None
    assert ev.unknown_names == ["1.jpg"] and ev.overall.missing == 2
    # a full name and its file name for one query are two poses of it
    write_benchmark_poses(tmp_path / "twice.txt", ["2.jpg", "day/cam/2.jpg"], est[[2, 2]])
    with pytest.raises(InputError, match="query day/cam/2.jpg has two poses"):
        evaluate_benchmark(tmp_path / "gt.txt", tmp_path / "twice.txt")


def test_localizer_on_the_export_end_to_end(exported, tmp_path):
    """The 6-DoF localizer registers the exported queries from their pairs; the scores land beside its poses."""
    _, out, _, _ = exported
    poses = localize_benchmark(out, tmp_path / "run" / "poses.txt")
    ev = score_benchmark(out, poses)
    outcome = json.loads((tmp_path / "run" / "poses.queries.json").read_text())
    assert outcome["queries"] == len(QUERY_FRAMES)
    assert all(q["accepted"] for q in outcome["per_query"].values()), outcome["per_query"]
    # between database images 2.4 m apart, 150 to 250 inliers each: about 1 cm and 0.04 deg off (measured)
    assert ev.overall.recall["0.25m_2deg"] == 1.0 and ev.overall.median_translation_m < 0.05, ev.overall
    saved = json.loads((tmp_path / "run" / "eval_benchmark.json").read_text())
    assert saved["overall"]["recall"] == ev.overall.recall
    assert "| overall | 5 |" in (tmp_path / "run" / "eval_benchmark.md").read_text()


def test_colmap_registrator_reads_the_export_as_it_is(exported, tmp_path):
    """An outside localizer on the export: COLMAP's own image registrator (its mapper's 2D-3D correspondences and
    absolute pose) registers every query against the model, at the KITTI truth like mapkit's localizer (about 1 cm
    and 0.03 deg, measured); the export is not changed, the query features land in a copy of its database."""
    _, out, _, _ = exported
    before = (out / "database.db").read_bytes()
    poses = register_benchmark(out, tmp_path / "colmap" / "poses.txt")
    ev = score_benchmark(out, poses)
    assert ev.overall.recall["0.25m_2deg"] == 1.0 and ev.overall.median_translation_m < 0.05, ev.overall
    outcome = json.loads((tmp_path / "colmap" / "poses.queries.json").read_text())
    assert outcome["registered"] == outcome["queries"] == len(QUERY_FRAMES)
    assert all(q["points3D"] >= 30 for q in outcome["per_query"].values()), outcome["per_query"]
    assert (out / "database.db").read_bytes() == before
    db = pycolmap.Database.open(str(tmp_path / "colmap" / "poses.colmap.db"))
    try:
        names = {im.name for im in db.read_all_images()}
    finally:
        db.close()
    assert len(names) == len(DB_FRAMES) + len(QUERY_FRAMES)
    assert set(read_pairs(out / "pairs-query-retrieval.txt")) <= names
    assert sorted(p.name for p in (tmp_path / "colmap").iterdir()) == [
        "eval_benchmark.json",
        "eval_benchmark.md",
        "poses.colmap.db",
        "poses.queries.json",
        "poses.txt",
    ]
    # its acceptance is COLMAP's own options: asking more inliers than an image has features refuses every query
    strict = register_benchmark(
        out, tmp_path / "strict" / "poses.txt", config=ColmapRegistratorConfig(abs_pose_min_num_inliers=100_000)
    )
    assert json.loads((tmp_path / "strict" / "poses.queries.json").read_text())["registered"] == 0
    assert len(read_benchmark_poses(strict)[0]) == 0


def test_colmap_registrator_keeps_the_benchmarks_intrinsics(exported, tmp_path):
    """The queries' cameras are the benchmark's: COLMAP's mapper estimates and refines the focal length and
    distortion of a camera it is not told is known, so each query would get intrinsics of its own fitted to its
    matches."""
    _, out, _, _ = exported
    given = {n: colmap_camera_params(info)[1] for n, info in read_queries_with_intrinsics(out / QUERIES).items()}
    runs = {}
    for refine in (False, True):
        run = tmp_path / f"refine-{refine}"
        register_benchmark(out, run / "poses.txt", config=ColmapRegistratorConfig(refine_intrinsics=refine))
        runs[refine] = json.loads((run / "poses.queries.json").read_text())["per_query"]
    for name, params in given.items():
        assert runs[False][name]["accepted"], name
        np.testing.assert_allclose(runs[False][name]["camera_params"], params, rtol=1e-12, err_msg=name)
    refined = [n for n in given if runs[True][n]["accepted"] and runs[True][n]["camera_params"][0] != given[n][0]]
    assert refined, runs[True]  # the switch reaches COLMAP: fitted focal lengths differ from the given ones


def test_missing_model_or_index_is_one_error(kitti_clip, tmp_path):
    ws = _benchmark_workspace(tmp_path, kitti_clip)
    with pytest.raises(InputError, match=f"run mapkit model {ws} first") as err:
        export_benchmark(ws, tmp_path / "out", ["query"])
    assert err.value.field == "reference_model"
    model = ws / "reference_model" / "sfm"
    model.mkdir(parents=True)
    for f in ("cameras.bin", "images.bin", "points3D.bin"):
        (model / f).write_bytes(b"")
    (ws / "reference_model" / "database.db").write_bytes(b"")
    with pytest.raises(InputError, match="run mapkit index vlad") as err:
        export_benchmark(ws, tmp_path / "out", ["query"])
    assert err.value.field == "vlad"
    assert not (tmp_path / "out").exists()


def test_colmap_registrator_refuses_a_missing_query_image_and_writes_nothing(exported, tmp_path):
    _, out, _, _ = exported
    bench = shutil.copytree(out, tmp_path / "bench")
    name = next(iter(read_queries_with_intrinsics(bench / "queries_with_intrinsics.txt")))
    (bench / "images" / name).unlink()
    with pytest.raises(InputError, match=r"no such query image \(1 of 5 missing\)") as err:
        register_benchmark(bench, tmp_path / "run" / "poses.txt")
    assert err.value.path == bench / "images" / name and not (tmp_path / "run").exists()


def test_a_model_of_sessions_not_aligned_is_one_error(kitti_clip, tmp_path):
    """Two sessions that no alignment holds are refused before anything is written; one of them alone, or both
    with allow_unaligned (their KITTI poses share one frame), make a model."""
    ws = _benchmark_workspace(tmp_path, kitti_clip)
    with pytest.raises(InputError, match=r"sessions \['kitti', 'query'\] are not aligned.*mapkit align") as err:
        build_reference_model(ws, config=ReferenceModelConfig(**FAST))
    assert err.value.field == "align" and err.value.path == ws / "align"
    assert not (ws / "reference_model").exists()
    both = build_reference_model(ws, out=tmp_path / "both", config=ReferenceModelConfig(**FAST, allow_unaligned=True))
    assert pycolmap.Reconstruction(str(both / "sfm")).num_images() == len(DB_FRAMES) + len(QUERY_FRAMES)


def test_the_commands(exported, tmp_path, capsys):
    from mapkit.cli import main

    _, out, _, _ = exported
    shutil.copy(out / "queries_gt.txt", tmp_path / "poses.txt")
    assert main(["eval", "benchmark", str(out), "--poses", str(tmp_path / "poses.txt")]) == 0
    assert "| overall | 5 | 0 | 100.0 % | 100.0 % | 100.0 % |" in capsys.readouterr().out
    assert (tmp_path / "eval_benchmark.json").is_file()
    assert main(["export", "benchmark", "--help"]) == 0 and "--queries" in capsys.readouterr().out
    assert main(["eval", "benchmark", str(tmp_path), "--poses", str(tmp_path / "poses.txt")]) == 2
    assert "not a benchmark folder" in capsys.readouterr().err


def test_a_query_session_from_its_log(exported, clip12, tmp_path):
    """A query session without an image database: its camera frames come from its log (a KITTI folder, stamps
    from times.txt), written as PNG, with the log's intrinsics; its truth is the town's at the frames' stamps."""
    ws, _, poses, town = exported
    with pytest.raises(InputError, match="has no image database: give its log"):
        export_benchmark(ws, tmp_path / "none", ["drive"], truth=town)
    out = export_benchmark(ws, tmp_path / "log", ["drive"], truth=town, logs={"drive": clip12})
    cams = read_queries_with_intrinsics(out / "queries_with_intrinsics.txt")
    names = [f"query/drive/camera_0/{i * 100_000_000}.png" for i in range(12)]
    assert list(cams) == names and cams[names[0]].fx == pytest.approx(707.0912)
    image = cv2.imread(str(out / "images" / names[5]), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(image, cv2.imread(str(clip12 / "image_l" / "000005.png"), cv2.IMREAD_UNCHANGED))
    gt_names, gt = read_benchmark_poses(out / "queries_gt.txt")
    assert gt_names == names
    centres = np.array([invert_pose(T)[:3, 3] for T in gt])
    np.testing.assert_allclose(centres, poses[:12, :3, 3], atol=1e-3)
    assert "its log" in (out / "README.md").read_text()


def test_the_deployment_bundle_carries_the_reference_model_with_checksums(exported, tmp_path):
    """`mapkit index export` copies the finished reference model beside the indexes, listed in the top manifest
    with its own manifest of checksums; loaded back, it is a folder the 6-DoF localizer opens; a changed byte of
    its features database is refused by name."""
    from mapkit.deploy.export import export_bundles, load_bundle
    from mapkit.localization.sixdof import SixDofLocalizer

    ws, _, _, _ = exported
    out = export_bundles(ws, tmp_path / "bundle")
    entry = json.loads((out / "manifest.json").read_text())["indexes"]["reference_model"]
    assert entry["kind"] == "mapkit reference model" and entry["source_sessions"] == ["kitti"]
    assert entry["images"] == len(DB_FRAMES) and entry["parameters"]["max_features"] == FAST["max_features"]
    files = json.loads((out / "reference_model" / "manifest.json").read_text())["files"]
    assert {"database.db", "config.yaml", "metrics.json", "sfm/points3D.bin"} <= set(files)
    bundle = load_bundle(out)
    db = out / "reference_model" / "database.db"
    before, listing = db.read_bytes(), sorted(p.name for p in db.parent.iterdir())
    loc = SixDofLocalizer(bundle["reference_model"])
    try:
        model = pycolmap.Reconstruction(str(ws / "reference_model" / "sfm"))
        assert sorted(loc.image_names) == sorted(im.name for im in model.images.values())
        for name in loc.image_names:  # every image's descriptors, one per keypoint of the model
            assert len(loc._database_features(name)[0]) == model.find_image_with_name(name).num_points2D()
    finally:
        loc.close()
    # reading the model leaves its files as they were (COLMAP's own Database.open rewrites the database's header
    # and leaves a journal beside it), so the bundle still verifies
    assert db.read_bytes() == before and sorted(p.name for p in db.parent.iterdir()) == listing
    load_bundle(out)
    assert "reference_model" not in load_bundle(export_bundles(ws, tmp_path / "vlad-only", ["vlad"])).indexes
    data = bytearray(db.read_bytes())
    data[-1] ^= 0xFF
    db.write_bytes(bytes(data))
    with pytest.raises(InputError, match="database.db") as err:
        load_bundle(out)
    assert err.value.field == "sha256"


def test_eval_localize_scores_the_sixdof_poses_in_the_model_frame(exported, tmp_path):
    """The workspace's poses sit off the town's truth by MODEL_FROM_TRUTH (20 deg and 3.7 m), as an aligned map
    sits off the truth by the drives' common GPS bias: eval localize fits that transform on the model's database
    images (the known answer) and scores the 6-DoF poses against the truth moved by it, within (0.25 m, 2 deg),
    where against the unmoved truth every query would be metres off."""
    from mapkit.evaluation.localization import evaluate_localization

    ws, _, _, town = exported
    r = evaluate_localization(
        ws,
        town,
        ws / "indexes" / "vlad",
        test_sessions=["query"],
        overrides={"refine": "6dof"},
        out=tmp_path / "eval",
        progress=False,
    )
    fit = r["model_from_truth"]
    np.testing.assert_allclose(fit["matrix"], MODEL_FROM_TRUTH, atol=1e-4)
    assert fit["fit_images"] == len(DB_FRAMES) and fit["residual_max_m"] < 1e-3
    s = r["sessions"]["query"]["sixdof"]
    assert s["6dof"]["recall"]["0.25m_2deg"] >= 0.8 and s["6dof"]["median_translation_m"] < 0.05, s["6dof"]


def test_a_model_on_the_towns_true_poses(exported, tmp_path):
    """`mapkit model --truth TOWN`: the database images take their true poses, the recorded ones moved by the
    inverse of MODEL_FROM_TRUTH (the known answer); a session the town did not drive is one error."""
    ws, _, poses, town = exported
    model = build_reference_model(ws, ["kitti"], out=tmp_path / "true", config=ReferenceModelConfig(**FAST), truth=town)
    rec = pycolmap.Reconstruction(str(model / "sfm"))
    for im in rec.images.values():
        frame = int(Path(im.name).stem) // 100_000_000
        T = invert_pose(np.vstack([im.cam_from_world().matrix(), [0, 0, 0, 1]]))
        np.testing.assert_allclose(T, invert_pose(MODEL_FROM_TRUTH) @ poses[frame], atol=1e-3)
    assert rec.num_points3D() > 50 and "depth_check" not in json.loads((model / "metrics.json").read_text())
    partial = shutil.copytree(town, tmp_path / "town-without-query")
    (partial / "sessions" / "query.camera.tum").unlink()
    with pytest.raises(InputError, match="session 'query'") as err:
        build_reference_model(ws, ["kitti", "query"], out=tmp_path / "none", truth=partial)
    assert err.value.field == "truth" and not (tmp_path / "none").exists()


def test_an_export_takes_the_query_encodings_a_localization_kept(exported, tmp_path, monkeypatch):
    """With a cache of encodings, the retrieval pairs are those encoded afresh, found by the query images'
    own files in the session (the exported copies hold the same bytes): a second export encodes nothing."""
    import mapkit.retrieval.vlad_index as vlad_index

    ws, out, _, town = exported
    cache = tmp_path / "cache"
    cache.mkdir()
    cfg = BenchmarkExportConfig(retrieval_k=4)
    first = export_benchmark(ws, tmp_path / "first", ["query"], truth=town, config=cfg, cache_dir=cache)
    assert (first / "pairs-query-retrieval.txt").read_text() == (out / "pairs-query-retrieval.txt").read_text()
    (stored,) = cache.glob("encodings-*.npz")
    with np.load(stored) as z:
        keys = [k.split("|")[0] for k in z["keys"].tolist()]
    assert len(keys) == len(QUERY_FRAMES) and all(str(ws / "sessions" / "query") in k for k in keys)

    def encode(*args, **kwargs):
        raise AssertionError("encoded again")

    monkeypatch.setattr(vlad_index, "encode_images", encode)
    again = export_benchmark(ws, tmp_path / "again", ["query"], truth=town, config=cfg, cache_dir=cache)
    assert (again / "pairs-query-retrieval.txt").read_text() == (out / "pairs-query-retrieval.txt").read_text()
