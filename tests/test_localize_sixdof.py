"""The 6-DoF refinement of the MCVL localizer (``refine: 6dof``) on the real KITTI clip: even frames are the
database (a VLAD bundle and a reference model of one workspace), odd frames the queries (a KITTI folder read as
a log, or a session of the workspace with a town's truth for ``mapkit eval localize``). The registered poses lie
an order of magnitude closer to poses.txt than the filter's, a query that does not register keeps the filter's
pose and says why, a missing model is one error before any work, the evaluation scores the 6-DoF poses beside
the filter's and retrieval's, and its benchmark scores of camera poses meet a known answer."""

from __future__ import annotations

import json
import shutil
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
from test_index_vlad import FRAME
from test_sixdof import FAST, _kitti

from mapkit.cli import main
from mapkit.core.errors import InputError, InputWarning
from mapkit.core.geometry import invert_pose, make_pose, rotation_angle_rad
from mapkit.core.runio import mark_done
from mapkit.core.workspace import Workspace
from mapkit.evaluation.benchmark import band_key
from mapkit.evaluation.localization import evaluate_localization, format_localization, pose_band_scores
from mapkit.io.trajectory import read_benchmark_poses, read_tum, write_tum
from mapkit.localization import localize as localize_module
from mapkit.localization.localize import localize_log
from mapkit.localization.reference_model import ReferenceModelConfig, build_reference_model
from mapkit.localization.sixdof import SixDofLocalizer
from mapkit.mapping.imagedb import ImageDbConfig, ImageDbWriter
from mapkit.retrieval.dsift import DsiftConfig
from mapkit.retrieval.index_vlad import VladIndexConfig, build_vlad_index
from mapkit.retrieval.vlad import VladConfig

#: the first frames of the clip (1.2 m apart): even ones the database, odd ones the queries
FRAMES = 30
#: the odd frames of the query session of ``mapkit eval localize``
EVAL_QUERIES = [1, 3, 5, 7, 9]
#: KITTI's world (camera 0 at the first frame: x right, y down, z forward) turned z up, as a workspace's ENU frame
ENU_FROM_KITTI = make_pose(np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]), np.zeros(3))
#: VLAD small enough to learn on 15 images in seconds (half-resolution dense SIFT, 16 words, 12 dimensions)
KITTI_VLAD = VladConfig(
    dsift=DsiftConfig(half_resolution=True),
    num_words=16,
    pca_dim=12,
    kmeans_max_descriptors=30_000,
    kmeans_iterations=10,
)


def _query_log(clip: Path, frames: list[int], folder: Path) -> Path:
    """A KITTI odometry folder of ``frames`` (their images, the clip's calibration, stamps 0.1 s per frame)."""
    (folder / "image_l").mkdir(parents=True)
    for f in frames:
        shutil.copy(clip / "image_l" / f"{f:06d}.png", folder / "image_l")
    shutil.copy(clip / "calib.txt", folder)
    (folder / "times.txt").write_text("".join(f"{0.1 * f:.6e}\n" for f in frames))
    return folder


def _session(ws: Path, name: str, clip: Path, frames: list[int], poses: np.ndarray) -> None:
    """Session ``name`` of the workspace: an image database (images, table, COLMAP cameras) of ``frames``."""
    cam, _ = _kitti(clip)
    writer = ImageDbWriter(Workspace(ws).session(name).imagedb, ImageDbConfig(image_format="png"), {"cam0": cam})
    for f in frames:
        writer.add(
            100_000_000 * f, "cam0", cv2.imread(str(clip / "image_l" / f"{f:06d}.png"), cv2.IMREAD_UNCHANGED), poses[f]
        )
    writer.close(None)
    mark_done(Workspace(ws).session(name).imagedb, "test")  # as mapkit build finishes it


def _town(root: Path, sessions: dict[str, list[int]], poses: np.ndarray) -> Path:
    """A synthetic town's truth for ``mapkit eval localize``: the sessions' roles and their true camera poses, in a
    frame at the workspace's origin."""
    (root / "world").mkdir(parents=True)
    (root / "sessions").mkdir()
    (root / "world" / "origin.json").write_text(json.dumps(FRAME.to_dict()))
    entries = [{"name": n, "role": "train" if n == "kitti" else "test", "condition": "day-sunny"} for n in sessions]
    (root / "world" / "manifest.json").write_text(json.dumps({"sessions": entries}))
    for name, frames in sessions.items():
        write_tum(root / "sessions" / f"{name}.camera.tum", 100_000_000 * np.array(frames, np.int64), poses[frames])
    return root


@pytest.fixture(scope="module")
def kitti_ws(kitti_clip, tmp_path_factory):
    """A workspace of the clip's frames on their true poses (ENU): session ``kitti`` the even frames, with its VLAD
    bundle and its reference model (``WORKSPACE/reference_model``), session ``query`` a few odd frames; a log of
    every odd frame; the true poses (ENU) by stamp; the town of both sessions."""
    _, kitti_poses = _kitti(kitti_clip)
    poses = ENU_FROM_KITTI @ kitti_poses
    root = tmp_path_factory.mktemp("localize_sixdof")
    ws = root / "ws"
    ws.mkdir()
    (ws / "origin.json").write_text(json.dumps(FRAME.to_dict()))
    database, queries = list(range(0, FRAMES, 2)), list(range(1, FRAMES, 2))
    _session(ws, "kitti", kitti_clip, database, poses)
    _session(ws, "query", kitti_clip, EVAL_QUERIES, poses)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # 15 images: the PCA is capped below its dimensions, and says so
        config = VladIndexConfig(vlad=KITTI_VLAD, train_sessions=["kitti"], database_sessions=["kitti"])
        bundle = build_vlad_index(ws, config=config, progress=False)
    build_reference_model(ws, ["kitti"], config=ReferenceModelConfig(**FAST))
    log = _query_log(kitti_clip, queries, root / "queries")
    truth = {100_000_000 * f: poses[f] for f in queries}
    town = _town(root / "town", {"kitti": database, "query": EVAL_QUERIES}, poses)
    return ws, bundle, log, truth, town


def _errors(world_from_cam: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(position error m, rotation error deg) of stacks of camera poses."""
    dR = np.swapaxes(world_from_cam[:, :3, :3], 1, 2) @ truth[:, :3, :3]
    return np.linalg.norm(world_from_cam[:, :3, 3] - truth[:, :3, 3], axis=1), np.degrees(rotation_angle_rad(dR))


def _read(path: Path, truth: dict[int, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(stamps, poses, true poses) of a TUM file of the run."""
    stamps, poses = read_tum(path)
    return stamps, poses, np.array([truth[int(s)] for s in stamps]).reshape(-1, 4, 4)


def test_sixdof_poses_are_ten_times_closer_than_the_filter(kitti_ws, tmp_path, capsys):
    """``mapkit localize --refine 6dof`` (the model found in the bundle's workspace): the registered poses' median
    error is at least ten times below the filter's and three quarters of the queries lie within (0.25 m, 2 deg)
    of poses.txt. The benchmark pose file holds the inverse of the TUM poses, named by stamp; sixdof.json and
    metrics.json count the same accepted queries; the evaluation's band scores agree with the errors."""
    ws, bundle, log, truth, _ = kitti_ws
    config = tmp_path / "localize.yaml"
    config.write_text("top_k: 10\n")
    out = tmp_path / "run"
    assert main(["localize", str(bundle), str(log), "-o", str(out), "-c", str(config), "--refine", "6dof"]) == 0
    assert "sixdof_tum.txt" in capsys.readouterr().out

    stamps, sixdof, gt = _read(out / "sixdof_tum.txt", truth)
    f_stamps, filt, f_gt = _read(out / "poses_tum.txt", truth)
    assert set(f_stamps.tolist()) <= set(stamps.tolist())  # the filter's pose where a query does not register
    t6, r6 = _errors(sixdof, gt)
    tf, _ = _errors(filt, f_gt)
    within = (t6 <= 0.25) & (r6 <= 2.0)
    assert np.median(t6) * 10 <= np.median(tf), (np.median(t6), np.median(tf))
    assert np.sum(within) >= 0.75 * len(truth), (t6, r6)  # a query without a pose is a failure

    names, cam_from_world = read_benchmark_poses(out / "sixdof_poses.txt")
    assert names == [str(s) for s in stamps]
    np.testing.assert_allclose(invert_pose(cam_from_world), sixdof, atol=1e-5)
    record = json.loads((out / "sixdof.json").read_text())
    metrics = json.loads((out / "metrics.json").read_text())["sixdof"]
    assert record["model"] == metrics["model"] == str(ws / "reference_model")
    accepted = [q for q in record["per_query"] if q["accepted"]]
    assert len(record["per_query"]) == len(truth) and metrics["accepted"] == len(accepted)
    assert metrics["accepted_share"] == pytest.approx(len(accepted) / len(truth))
    timings = json.loads((out / "timings.json").read_text())  # the run record: times stay out of the outputs
    assert 0 < timings["sixdof_median_s_per_query"] <= timings["sixdof_max_s_per_query"]
    assert "seconds" not in record["per_query"][0] and "median_s_per_query" not in record
    assert all(q["inliers"] >= record["config"]["min_inliers"] for q in accepted)
    # each registration's position std (camera axes), from its covariance: a few centimetres on KITTI's streets
    stds = np.array([q["position_std_m"] for q in accepted])
    assert stds.shape == (len(accepted), 3) and np.all((stds > 0) & (stds < 0.5)), stds

    scores = pose_band_scores(gt, sixdof)
    assert scores.recall[band_key(0.25, 2.0)] == pytest.approx(np.mean(within))
    assert scores.median_translation_m == pytest.approx(np.median(t6), abs=1e-5)


def test_a_query_that_does_not_register_keeps_the_filters_pose(kitti_ws, kitti_clip, tmp_path, monkeypatch):
    """With more inliers required than any query has matches (five queries), none is accepted: each keeps the
    filter's pose (the same TUM rows), and its reason names both attempts, from the retrieved images and from
    those near the filter's pose; the query's features are extracted once for both."""
    _, bundle, _, _, _ = kitti_ws
    log = _query_log(kitti_clip, [1, 3, 5, 7, 9], tmp_path / "queries")
    extracted = []
    extract = SixDofLocalizer.extract
    monkeypatch.setattr(SixDofLocalizer, "extract", lambda self, image: extracted.append(1) or extract(self, image))
    out = localize_log(
        bundle, log, tmp_path / "run", progress=False, overrides={"refine": "6dof", "sixdof": {"min_inliers": 100_000}}
    )
    record = json.loads((out / "sixdof.json").read_text())
    assert record["accepted"] == 0 and len(record["per_query"]) == 5 and len(extracted) == 5
    for q in record["per_query"]:
        assert not q["accepted"] and q["inliers"] == 0 and q["matches"] > 30 and q["position_std_m"] is None
        assert q["reason"].startswith("retrieved images: ") and "; images near the filter's pose: " in q["reason"]
        assert q["reason"].endswith("2D-3D matches, fewer than min_inliers 100000"), q["reason"]
    stamps, sixdof = read_tum(out / "sixdof_tum.txt")
    f_stamps, filt = read_tum(out / "poses_tum.txt")
    assert len(f_stamps) == 5
    np.testing.assert_array_equal(stamps, f_stamps)
    np.testing.assert_allclose(sixdof, filt, atol=1e-6)


def test_a_missing_model_is_one_error_before_any_work(kitti_ws, tmp_path, capsys):
    """A reference model folder that does not exist: one InputError naming it, before the log is read or the
    output folder made; on the command line, one line and exit code 2."""
    _, bundle, log, _, _ = kitti_ws
    missing = tmp_path / "no-model"
    out = tmp_path / "run"
    with pytest.raises(InputError, match="no reference model folder") as err:
        localize_log(bundle, log, out, progress=False, overrides={"refine": "6dof", "reference_model": str(missing)})
    assert err.value.path == missing
    assert not out.exists()
    assert main(["localize", str(bundle), str(log), "-o", str(out), "--refine", "6dof", "--model", str(missing)]) == 2
    assert f"error: {missing}: no reference model folder" in capsys.readouterr().err
    assert not out.exists()


def test_eval_localize_scores_the_sixdof_poses_beside_the_filter(kitti_ws, tmp_path, capsys):
    """``mapkit eval localize --refine 6dof`` on the query session: the 6-DoF poses, the filter and retrieval
    alone scored on the same queries at the benchmark's bands, in eval_localize.json and the second table of
    eval_localize.md; the 6-DoF poses lie within (0.25 m, 2 deg), ten times closer than the filter's, and the
    session's folder holds them named by image. A model that holds a test session's images is refused, naming
    it, before anything is written."""
    ws, bundle, _, _, town = kitti_ws
    out = tmp_path / "eval"
    args = ["eval", "localize", str(ws), "--truth", str(town), "--bundle", str(bundle), "-o", str(out)]
    assert main([*args, "--refine", "6dof"]) == 0
    assert "| query | 5 | 6-DoF |" in capsys.readouterr().out
    session = json.loads((out / "eval_localize.json").read_text())["sessions"]["query"]
    s = session["sixdof"]
    assert session["queries"] == s["6dof"]["queries"] == s["filter"]["queries"] == s["retrieval"]["queries"] == 5
    assert s["6dof"]["recall"][band_key(0.25, 2.0)] >= 0.8 and s["accepted_share"] >= 0.8
    assert s["6dof"]["median_translation_m"] * 10 <= s["filter"]["median_translation_m"], s
    # the registrations joined by the query session's odometry: every query placed, as close as the registrations
    assert s["sequence"]["queries"] == 5 and s["sequence"]["recall"][band_key(0.25, 2.0)] == 1.0, s["sequence"]
    md = (out / "eval_localize.md").read_text()
    assert "| query | 5 | 6-DoF |" in md and "| query | 5 | MCVL |" in md and "| query | 5 | retrieval |" in md
    assert "| query | 5 | 6-DoF + odometry |" in md
    names, _ = read_benchmark_poses(out / "query" / "sixdof_poses.txt")
    assert names == [f"sessions/query/imagedb/images/cam0/{100_000_000 * f}.png" for f in EVAL_QUERIES]
    seq_names, seq_poses = read_benchmark_poses(out / "query" / "sequence_poses.txt")
    stamps, seq_tum = read_tum(out / "query" / "sequence_tum.txt")
    assert seq_names == names and len(stamps) == 5
    np.testing.assert_allclose(np.array([invert_pose(T) for T in seq_poses]), seq_tum, atol=1e-6)

    both = ReferenceModelConfig(**FAST, allow_unaligned=True)  # the two sessions' KITTI poses share one frame
    wrong = build_reference_model(ws, ["kitti", "query"], out=tmp_path / "all", config=both)
    with pytest.raises(InputError, match=r"test session\(s\) \['query'\] are in the reference model") as err:
        evaluate_localization(
            ws, town, bundle, overrides={"refine": "6dof", "reference_model": str(wrong)}, out=tmp_path / "refused"
        )
    assert err.value.path == wrong and not (tmp_path / "refused").exists()


def test_band_scores_of_camera_poses_known_answer():
    """Four queries of a camera 100 m from the origin: 0.1 m off, 0.4 m and 3 deg off (about the camera centre),
    3 m off, and none. The bands hold 1, 2 and 3 of the 4 and the median position error is (0.4 + 3) / 2 m; the
    second table of eval_localize.md gives them as shares."""
    gt = np.tile(make_pose(np.eye(3), np.array([100.0, 50.0, 2.0])), (4, 1, 1))
    turn = np.radians(3.0)
    est = gt.copy()
    est[0, 0, 3] += 0.1
    est[1, :3, :3] = [[np.cos(turn), -np.sin(turn), 0], [np.sin(turn), np.cos(turn), 0], [0, 0, 1]]
    est[1, 1, 3] += 0.4
    est[2, 2, 3] += 3.0
    est[3] = np.nan
    s = pose_band_scores(gt, est)
    assert (s.queries, s.localized, s.missing) == (4, 3, 1)
    assert [s.recall[band_key(a, b)] for a, b in ((0.25, 2.0), (0.5, 5.0), (5.0, 10.0))] == [0.25, 0.5, 0.75]
    assert s.median_translation_m == pytest.approx(1.7)
    assert s.median_rotation_deg == pytest.approx(1.5)

    from dataclasses import asdict

    session = {
        "condition": "night",
        "queries": 4,
        "retrieval": {},
        "filter": {},
        "recall_at_1": 0.5,
        "sixdof": {
            "accepted_share": 0.75,
            "6dof": asdict(s),
            "filter": asdict(s),
            "retrieval": asdict(s),
        },
    }
    md = format_localization({"sessions": {"test-night": session}})
    assert "| test-night | 4 | 6-DoF | 25.0 % | 50.0 % | 75.0 % | 1.700 / 1.50 | 75.0 % |" in md
    assert "| test-night | 4 | retrieval | 25.0 % | 50.0 % | 75.0 % | 1.700 / 1.50 |  |" in md


def test_sequence_check_refuses_a_pose_its_neighbours_disagree_with():
    """Nine queries 5 m apart along a turning street, the odometry exact. Query 2 slid 2 m along the street and
    query 6 turned 10 deg: each disagrees with its registered neighbours and keeps its fallback, said in its reason.
    Query 4, 0.3 m off, lies within the band of its neighbours and stays; query 3, next to the slid one, agrees with
    query 4 and stays (the verdicts use the poses as registered); query 8, whose only neighbour was not registered,
    stays unchecked."""
    from mapkit.localization.localize import check_sequence
    from mapkit.localization.sixdof import SixDofResult

    def turn(deg: float) -> np.ndarray:
        a = np.radians(deg)
        return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])

    n = 9
    truth = [make_pose(turn(3.0 * k), np.array([5.0 * k, 0.1 * k * k, 0.0])) for k in range(n)]
    odometry = [None] + [invert_pose(truth[k - 1]) @ truth[k] for k in range(1, n)]
    registered = [T.copy() for T in truth]
    registered[2][:3, 3] += [2.0, 0.0, 0.0]
    registered[4][:3, 3] += [0.3, 0.0, 0.0]
    registered[6][:3, :3] = registered[6][:3, :3] @ turn(10.0)
    accepted = [True] * 7 + [False, True]
    fallback = [make_pose(np.eye(3), np.array([float(k), 9.0, 0.0])) for k in range(n)]
    results = [
        SixDofResult(f"q{k}", invert_pose(T), T, ok, "20 inliers of 60 2D-3D matches", 20, 60)
        for k, (T, ok) in enumerate(zip(registered, accepted, strict=True))
    ]
    out = check_sequence(results, odometry, fallback, 0.5, 5.0)
    assert [r.accepted for r in out] == [True, True, False, True, True, True, False, False, True]
    assert "2.00 m / 0.0 deg from its registered neighbours moved by the odometry" in out[2].reason
    assert "/ 10.0 deg from its registered neighbours" in out[6].reason
    for k in (2, 6):
        np.testing.assert_array_equal(out[k].world_from_cam, fallback[k])
        np.testing.assert_allclose(out[k].cam_from_world, invert_pose(fallback[k]))
    for k in (0, 1, 3, 4, 5, 7, 8):
        assert out[k] is results[k]
    with pytest.raises(ValueError, match="9 results, 8 odometry steps"):
        check_sequence(results, odometry[1:], fallback, 0.5, 5.0)


def test_localize_moves_the_filter_by_the_logs_own_odometry(kitti_ws, kitti_clip, tmp_path, monkeypatch):
    """``odometry: true`` on a log with a pose stream (a KITTI folder with its poses.txt): the filter and the 6-DoF
    neighbour check get the camera's motion between consecutive images, here poses.txt's own (to its 7 digits),
    and metrics.json names the source; without a LiDAR or pose stream there is no metric odometry: one warning,
    and the run goes on without it."""
    _, bundle, _, _, _ = kitti_ws
    frames = [1, 3, 5, 7, 9]
    log = _query_log(kitti_clip, frames, tmp_path / "with_poses")
    rows = np.loadtxt(kitti_clip / "poses.txt")[frames]
    np.savetxt(log / "poses.txt", rows)
    poses = np.tile(np.eye(4), (len(frames), 1, 1))
    poses[:, :3] = rows.reshape(-1, 3, 4)
    seen = {}
    check = localize_module.check_sequence

    def spy(results, odometry, *args):
        seen.setdefault("odometry", odometry)
        return check(results, odometry, *args)

    monkeypatch.setattr(localize_module, "check_sequence", spy)
    run = localize_module.run_localizer

    def filter_spy(index, images, cfg, odometry, **kwargs):
        seen["filter"] = odometry
        return run(index, images, cfg, odometry, **kwargs)

    monkeypatch.setattr(localize_module, "run_localizer", filter_spy)
    out = localize_log(bundle, log, tmp_path / "run", progress=False, overrides={"odometry": True, "refine": "6dof"})
    assert json.loads((out / "metrics.json").read_text())["odometry"] == {
        "source": "poses:/kitti/ground_truth",
        "steps": 4,
    }
    steps = seen["odometry"]
    assert seen["filter"] is steps and steps[0] is None and len(steps) == len(frames)
    for k in range(1, len(frames)):
        np.testing.assert_allclose(steps[k], invert_pose(poses[k - 1]) @ poses[k], atol=1e-6)

    bare = _query_log(kitti_clip, frames, tmp_path / "images_only")
    with pytest.warns(InputWarning, match="no LiDAR and no pose stream"):
        out = localize_log(bundle, bare, tmp_path / "bare", progress=False, overrides={"odometry": True})
    assert json.loads((out / "metrics.json").read_text())["odometry"]["source"] is None
    assert len(read_tum(out / "poses_tum.txt")[0]) > 0
