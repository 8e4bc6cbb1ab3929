"""The reference 6-DoF localizer: real KITTI frames held out of the reference model register to a few
centimetres of their ground-truth poses, a query that does not register keeps its fallback pose and
says why, a damaged model is one error naming the file, and benchmark pose files round-trip and read
as COLMAP's quaternions."""

from __future__ import annotations

import shutil
import threading
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
from scipy.spatial.transform import Rotation
from test_reference_model import _kitti

from mapkit.core.errors import InputError
from mapkit.core.geometry import invert_pose, rotation_angle_rad
from mapkit.io.trajectory import read_benchmark_poses, write_benchmark_poses
from mapkit.localization.reference_model import PosedImage, ReferenceModelConfig, triangulate_reference_model
from mapkit.localization.sixdof import (
    SixDofConfig,
    SixDofLocalizer,
    SixDofQuery,
    _drift_px,
    guided_matches,
    localize_images,
    mutual_ratio_matches,
)

#: every other frame of the first 19 (2.4 m apart) but 10 and 16, the held-out queries
MODEL_FRAMES = [0, 2, 4, 6, 8, 12, 14, 18]
HELD_OUT = [10, 16]
#: full-resolution SIFT, 4096 features: a model of 8 frames in a few seconds
FAST = {"first_octave": 0, "max_features": 4096, "pair_neighbours": 3}


def _image(clip: Path, frame: int) -> Path:
    return clip / "image_l" / f"{frame:06d}.png"


@pytest.fixture(scope="module")
def model(kitti_clip, tmp_path_factory):
    """The reference model of MODEL_FRAMES on their ground-truth poses: the held-out frames are not in it."""
    cam, poses = _kitti(kitti_clip)
    out = tmp_path_factory.mktemp("sixdof") / "model"
    images = [PosedImage(_image(kitti_clip, i), cam, poses[i]) for i in MODEL_FRAMES]
    triangulate_reference_model(images, out, ReferenceModelConfig(**FAST))
    return out, cam, poses


def _errors(world_from_cam: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """(position error in m, rotation error in deg) of a camera pose."""
    dR = world_from_cam[:3, :3].T @ truth[:3, :3]
    return float(np.linalg.norm(world_from_cam[:3, 3] - truth[:3, 3])), float(np.degrees(rotation_angle_rad(dR)))


def _offset(world_from_cam: np.ndarray, metres: float, yaw_deg: float) -> np.ndarray:
    """The pose moved ``metres`` along its camera x axis and turned ``yaw_deg`` about its camera y axis."""
    step = np.eye(4)
    step[0, 3] = metres
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    step[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    return world_from_cam @ step


def test_held_out_frames_register_to_their_ground_truth(model, kitti_clip):
    """Frames 10 and 16, absent from the model, registered from retrieval-like candidates (10) and from
    the images near a prior 2 m and 10 deg off (16): within 0.25 m and 2 deg of poses.txt (measured:
    2 to 5 cm, about 0.1 deg), with far more inliers than the gate; the prior was not kept."""
    folder, cam, poses = model
    cfg = SixDofConfig()
    queries = [
        SixDofQuery("10", _image(kitti_clip, 10), cam, _offset(poses[10], 2.0, 10.0)),
        SixDofQuery(
            "16", cv2.imread(str(_image(kitti_clip, 16)), cv2.IMREAD_GRAYSCALE), cam, _offset(poses[16], 2.0, 10.0)
        ),
    ]
    retrieved = ["000012.png", "000008.png", "000014.png", "000006.png"]
    results = localize_images(folder, queries, [retrieved, None], cfg, progress=False)
    assert [r.name for r in results] == ["10", "16"]
    assert results[0].candidates == retrieved
    assert results[1].candidates[:2] == ["000014.png", "000018.png"]  # the two nearest, 2.4 m either side
    for r, frame in zip(results, HELD_OUT, strict=True):
        assert r.accepted, r.reason
        assert r.inliers >= cfg.min_inliers and r.inliers >= 60 and r.matches >= r.inliers
        assert r.world_from_cam is not None and r.cam_from_world is not None
        np.testing.assert_allclose(r.cam_from_world @ r.world_from_cam, np.eye(4), atol=1e-9)
        position_m, rotation_deg = _errors(r.world_from_cam, poses[frame])
        assert position_m < 0.25 and rotation_deg < 2.0, (frame, position_m, rotation_deg)
        assert r.seconds > 0


def test_queries_registered_on_threads_get_the_poses_of_one_thread_in_query_order(model, kitti_clip, monkeypatch):
    """Nine frames between and beside the model's, registered from the images near a prior 1 m off: with two
    threads (both used) the same results, bit for bit and in the queries' order, as with one."""
    folder, cam, poses = model
    frames = [1, 3, 5, 7, 9, 10, 11, 13, 16]
    queries = [SixDofQuery(str(i), _image(kitti_clip, i), cam, _offset(poses[i], 1.0, 3.0)) for i in frames]
    threads: set[int] = set()
    localize = SixDofLocalizer.localize

    def on_thread(self, *args, **kwargs):
        threads.add(threading.get_ident())
        return localize(self, *args, **kwargs)

    monkeypatch.setattr(SixDofLocalizer, "localize", on_thread)
    runs = {}
    for n in (1, 2):
        threads.clear()
        runs[n] = localize_images(folder, queries, [None] * len(queries), SixDofConfig(num_threads=n), progress=False)
        assert len(threads) == n
    assert [r.name for r in runs[2]] == [str(i) for i in frames]
    assert sum(r.accepted for r in runs[1]) >= 7
    for one, two in zip(runs[1], runs[2], strict=True):
        assert (one.name, one.accepted, one.inliers, one.matches, one.reason) == (
            two.name,
            two.accepted,
            two.inliers,
            two.matches,
            two.reason,
        )
        np.testing.assert_array_equal(one.cam_from_world, two.cam_from_world)


def test_prior_candidates_are_the_nearest_that_look_its_way(model):
    """The candidates of a prior: nearest camera centres first; a prior turned around sees none."""
    folder, _, poses = model
    with SixDofLocalizer(folder, SixDofConfig(prior_neighbours=3)) as loc:
        assert loc.candidates_near(poses[17]) == ["000018.png", "000014.png", "000012.png"]
        assert loc.candidates_near(_offset(poses[17], 0.0, 180.0)) == []
        np.testing.assert_allclose(loc.world_from_cam("000012.png"), poses[12], atol=1e-6)


def test_a_query_that_does_not_register_keeps_its_fallback(model, kitti_clip):
    """Random noise matches nothing: the fallback pose stays, not accepted, and the reason counts what was
    missing. A real frame held to more inliers than RANSAC finds is refused after RANSAC the same way; without
    a fallback the pose is None."""
    folder, cam, poses = model
    fallback = _offset(poses[10], 3.0, 0.0)
    noise = np.random.default_rng(0).integers(0, 256, (cam.height, cam.width), dtype=np.uint8)
    with SixDofLocalizer(folder) as loc:
        r = loc.localize(noise, cam, loc.candidates_near(fallback), fallback, name="noise")
        assert not r.accepted and r.inliers < loc.cfg.min_inliers
        assert f"2D-3D matches, fewer than min_inliers {loc.cfg.min_inliers}" in r.reason or (
            f"2D-3D matches, matched guided from the fallback pose, fewer than min_inliers {loc.cfg.min_inliers}"
            in r.reason
        )
        assert r.world_from_cam is not None and r.cam_from_world is not None
        np.testing.assert_array_equal(r.world_from_cam, fallback)
        np.testing.assert_allclose(r.cam_from_world, invert_pose(fallback), atol=1e-12)

        registered = loc.localize(_image(kitti_clip, 10), cam, ["000008.png", "000012.png"], fallback)
    assert registered.accepted and 60 <= registered.inliers < registered.matches
    # as many inliers needed as there are matches: RANSAC runs, finds fewer, and the fallback stays
    strict = SixDofConfig(min_inliers=registered.matches)
    with SixDofLocalizer(folder, strict) as loc:
        r = loc.localize(_image(kitti_clip, 10), cam, ["000008.png", "000012.png"], fallback)
        assert not r.accepted and r.inliers == registered.inliers and r.matches == registered.matches
        assert f"{r.inliers} inliers of {r.matches} 2D-3D matches, fewer than min_inliers {r.matches}" == r.reason
        np.testing.assert_array_equal(r.world_from_cam, fallback)
        r = loc.localize(_image(kitti_clip, 10), cam, ["000008.png"])
        assert not r.accepted and r.world_from_cam is None and r.cam_from_world is None


def test_a_pose_that_could_not_have_seen_its_candidates_is_not_accepted(model, kitti_clip):
    """Frame 10 registers between frames 8 and 12 (1.2-1.3 m from their cameras, looking their way). Held to a
    co-visibility gate it cannot meet (its candidates within 0.5 m, or looking within 0.01 deg of it), the same
    RANSAC pose is refused and the fallback stays, the reason saying which gate failed."""
    folder, cam, poses = model
    fallback = _offset(poses[10], 3.0, 0.0)
    image, cands = _image(kitti_clip, 10), ["000008.png", "000012.png"]
    with SixDofLocalizer(folder) as loc:
        ok = loc.localize(image, cam, cands, fallback)
    assert ok.accepted and np.linalg.norm(ok.world_from_cam[:3, 3] - poses[10][:3, 3]) < 0.25
    for gate, why in (
        ({"prior_max_distance_m": 0.5}, "m from the nearest candidate image (more than 0.5)"),
        ({"prior_max_angle_deg": 0.01}, "deg away from the candidate images near it (more than 0.01)"),
    ):
        with SixDofLocalizer(folder, SixDofConfig(**gate)) as loc:
            r = loc.localize(image, cam, cands, fallback)
        assert not r.accepted and r.inliers == ok.inliers and why in r.reason, r.reason
        np.testing.assert_array_equal(r.world_from_cam, fallback)


def test_a_damaged_model_or_query_is_one_error_naming_the_file(model, kitti_clip, tmp_path):
    folder, cam, _ = model
    truncated = tmp_path / "truncated"
    shutil.copytree(folder, truncated)
    points = truncated / "sfm" / "points3D.bin"
    with points.open("r+b") as f:  # cut inside the points: COLMAP's own reader would run for minutes
        f.truncate(points.stat().st_size // 2)
    with pytest.raises(InputError, match="damaged COLMAP points3D") as err:
        SixDofLocalizer(truncated)
    assert err.value.path == points

    no_db = tmp_path / "no_db"
    shutil.copytree(folder, no_db)
    (no_db / "database.db").unlink()
    with pytest.raises(InputError, match="no such file") as err:
        SixDofLocalizer(no_db)
    assert err.value.path == no_db / "database.db"
    assert not (no_db / "database.db").exists()  # not created empty by opening it

    with pytest.raises(InputError, match="no reference model"):
        SixDofLocalizer(tmp_path / "nowhere")

    with SixDofLocalizer(folder) as loc:
        path = _image(kitti_clip, 10)
        with pytest.raises(InputError, match="query without intrinsics") as err:
            loc.localize(path, None, ["000008.png"])
        assert err.value.path == path
        with pytest.raises(InputError, match="not an image of the model"):
            loc.localize(path, cam, ["000010.png"])


def test_matches_are_mutual_nearest_neighbours_that_pass_the_ratio_test():
    """Database descriptors are the query's, shuffled and slightly perturbed, plus a copy of query 0's match
    (repeated structure: the ratio test drops it) and unrelated ones; a last query descriptor is a rougher copy
    of query 1 whose nearest is query 1's match, which prefers query 1 (the mutual check drops it). Each other
    query descriptor finds its own."""
    rng = np.random.default_rng(3)

    def unit512(x: np.ndarray) -> np.ndarray:
        x = np.abs(x)
        return np.clip(np.round(512 * x / np.linalg.norm(x, axis=1, keepdims=True)), 0, 255).astype(np.uint8)

    raw = rng.random((50, 128)) ** 4  # peaked like SIFT histograms: unrelated descriptors lie far apart
    query = unit512(np.vstack([raw, raw[1:2] * (1 + 0.1 * rng.random((1, 128)))]))
    perm = rng.permutation(50)
    own = raw[perm] * (1 + 0.02 * rng.random((50, 128)))
    twin = own[np.nonzero(perm == 0)[0]]  # repeated structure: query 0's match twice
    database = unit512(np.vstack([own, twin, rng.random((30, 128)) ** 4]))
    i, j = mutual_ratio_matches(query, database, max_ratio=0.8, max_distance=0.7)
    expected = {int(q): int(np.nonzero(perm == q)[0][0]) for q in range(1, 50)}
    assert dict(zip(i.tolist(), j.tolist(), strict=True)) == expected


def _unit512(x: np.ndarray) -> np.ndarray:
    """COLMAP's uint8 SIFT descriptors: unit vectors times 512, clipped."""
    x = np.abs(x)
    return np.clip(np.round(512 * x / np.linalg.norm(x, axis=1, keepdims=True)), 0, 255).astype(np.uint8)


def test_guided_matches_tell_look_alikes_apart_by_where_they_project():
    """A facade of 150 points, each with a look-alike 3 m along it (the next window: the same descriptor in the
    model, slightly perturbed, and the same in the query), seen by a query 8-20 m away. Matched whole, most
    look-alikes are refused by the ratio test and a third of what passes is the twin. Guided from a pose 0.5 m
    and 1 deg off within 40 px, each look-alike projects a hundred pixels from the other and every point finds
    its own keypoint (within 400 px both look-alikes are in reach and the ratio test refuses them rather than
    guess); from a pose 3 m along the facade, where each look-alike lands on its twin's keypoint, no match is
    right: the matching trusts the pose it starts from. Turned round, or with no descriptor near enough, none."""
    rng = np.random.default_rng(11)
    camera = pycolmap.Camera(model="PINHOLE", width=640, height=480, params=[500.0, 500.0, 320.0, 240.0])
    n = 150
    own = np.c_[rng.uniform(-6, 3, n), rng.uniform(-3, 2, n), rng.uniform(8, 20, n)]
    twin = own + [3.0, 0.0, 0.0]
    X = np.vstack([own, twin])  # world = the true camera's frame
    raw = rng.random((n, 128)) ** 4
    obs_desc = _unit512(np.vstack([raw, raw * (1 + 0.02 * rng.random((n, 128)))]))
    obs_pid = np.arange(2 * n) + 100
    xyz = {int(p): X[k] for k, p in enumerate(obs_pid)}
    uv = camera.img_from_cam(X)
    inside = (uv[:, 0] > 0) & (uv[:, 0] < 640) & (uv[:, 1] > 0) & (uv[:, 1] < 480)
    kp = uv[inside] + rng.normal(0, 0.5, (int(inside.sum()), 2))
    seen = raw * (1 + 0.02 * rng.random((n, 128)))  # a look-alike and its twin look the same to the query
    q_desc = _unit512(np.vstack([seen, seen])[inside])
    truth_pid = obs_pid[inside]  # query keypoint k sees point truth_pid[k]
    assert inside[:n].sum() > 100 and inside[n:].sum() > 100

    i, j = mutual_ratio_matches(q_desc, obs_desc, max_ratio=0.8, max_distance=0.7)
    right = obs_pid[j] == truth_pid[i]
    assert right.sum() < 0.5 * len(kp) and (~right).sum() > 0.25 * len(i)  # matched whole: refused, or a guess

    def turned(metres: float, yaw_deg: float) -> np.ndarray:
        return invert_pose(_offset(np.eye(4), metres, yaw_deg))  # cam_from_world of the offset camera

    pair = guided_matches(kp, q_desc, obs_desc, obs_pid, xyz, turned(0.5, 1.0), camera, 40.0, 0.8, 0.7)
    assert len(pair) >= 0.9 * len(kp)
    np.testing.assert_array_equal(pair[:, 1], truth_pid[pair[:, 0]])
    assert len(np.unique(pair[:, 0])) == len(pair) == len(np.unique(pair[:, 1]))

    wide = guided_matches(kp, q_desc, obs_desc, obs_pid, xyz, turned(0.5, 1.0), camera, 400.0, 0.8, 0.7)
    assert len(wide) < 0.5 * len(pair)  # both look-alikes within reach: the ratio test refuses them ...
    np.testing.assert_array_equal(wide[:, 1], truth_pid[wide[:, 0]])  # ... rather than guess

    slid = guided_matches(kp, q_desc, obs_desc, obs_pid, xyz, turned(3.0, 0.0), camera, 40.0, 0.8, 0.7)
    assert len(slid) > 50 and not np.any(slid[:, 1] == truth_pid[slid[:, 0]])
    assert len(guided_matches(kp, q_desc, obs_desc, obs_pid, xyz, turned(0.0, 180.0), camera, 40.0, 0.8, 0.7)) == 0
    other = _unit512(rng.random((len(kp), 128)) ** 4)  # another scene's features where the points land
    assert len(guided_matches(kp, other, obs_desc, obs_pid, xyz, turned(0.5, 1.0), camera, 40.0, 0.8, 0.1)) == 0


def test_guided_matches_do_not_take_a_point_the_lens_distortion_folds_into_the_image():
    """A camera with strong barrel distortion (k1 = -0.11) folds a point 72 deg off its axis, far outside its
    field of view, back onto the image near the principal point, where a look-alike keypoint waits. Guided
    matching leaves it alone; a point in view, projected through the same distortion, is matched."""
    camera = pycolmap.Camera(model="OPENCV", width=640, height=480, params=[500, 500, 320, 240, -0.11, 0, 0, 0])
    outside, in_view = np.array([3.0, 0.0, 1.0]), np.array([0.1, 0.0, 1.0])
    folded = camera.img_from_cam(outside[None], check_cheirality=False)[0]
    assert 0 <= folded[0] < 640 and 0 <= folded[1] < 480  # what the camera model alone says
    kp = np.vstack([folded, camera.img_from_cam(in_view[None])[0]])
    desc = _unit512(np.random.default_rng(5).random((2, 128)) ** 4)
    xyz = {7: outside, 8: in_view}
    pair = guided_matches(kp, desc, desc, np.array([7, 8]), xyz, np.eye(4), camera, 10.0, 0.8, 0.7)
    np.testing.assert_array_equal(pair, [[1, 8]])


def test_a_query_whose_candidates_fail_registers_guided_from_its_neighbour(model, kitti_clip):
    """Frames 9, 10 and 11, none in the model, in sequence with their true odometry. Frame 10 has no candidates
    and its fallback lies 80 m off (a lost filter): alone it does not register. Guided
    from frame 9's registered pose moved by the odometry it registers within 0.25 m and 2 deg, and says so, and
    frame 11 then from frame 10; queries with nothing registered beside them keep their results; run backward,
    frame 9 registers from 10."""
    from mapkit.localization.localize import follow_neighbours

    folder, cam, poses = model
    frames = [9, 10, 11]
    images = [_image(kitti_clip, f) for f in frames]
    odometry = [None] + [invert_pose(poses[f - 1]) @ poses[f] for f in frames[1:]]
    lost = [_offset(poses[f], 80.0, 60.0) for f in frames]
    with SixDofLocalizer(folder) as loc:
        first = loc.localize(images[0], cam, ["000008.png", "000012.png"], lost[0], "9")
        assert first.accepted
        alone = loc.localize(images[1], cam, [], lost[1], "10")
        assert not alone.accepted
        unmatched = replace(alone, name="11", reason="not tried")
        out = follow_neighbours(loc, [first, alone, unmatched], images, [cam] * 3, ["9", "10", "11"], lost, odometry)
        assert out[0] is first
        for k in (1, 2):  # 10 from 9, then 11 from 10
            assert out[k].accepted and "from the previous query" in out[k].reason, out[k].reason
            assert "guided from a neighbour's pose moved by the odometry" in out[k].reason
            position_m, rotation_deg = _errors(out[k].world_from_cam, poses[frames[k]])
            assert position_m < 0.25 and rotation_deg < 2.0
        none = follow_neighbours(loc, [alone, unmatched], images[1:], [cam] * 2, ["10", "11"], lost[1:], odometry[1:])
        assert none[0] is alone and none[1] is unmatched  # nothing registered beside them
        back = follow_neighbours(
            loc, [replace(alone, name="9"), out[1]], images[:2], [cam] * 2, ["9", "10"], lost[:2], odometry[:2]
        )
    assert back[0].accepted and "from the next query" in back[0].reason
    position_m, rotation_deg = _errors(back[0].world_from_cam, poses[9])
    assert position_m < 0.25 and rotation_deg < 2.0


def test_a_guided_pose_beyond_its_guides_reach_is_refused(model, kitti_clip):
    """Frame 10 with no candidates, only its fallback pose as a guide. Turned 3 deg, within the 40 px reach
    (atan(40 / 707 px) = 3.2 deg), the guide finds the true pose. Turned 5 deg, the points land 60 px from their
    keypoints: within 40 px only wrong look-alikes are left, and RANSAC fits them a pose (measured: 10 inliers,
    1.8 m and 7 deg off) that turned farther from the guide than its matches allow. It is refused and the fallback
    stays, even with an inlier gate low enough to let it through."""
    folder, cam, poses = model
    cfg = SixDofConfig(min_inliers=8, guided_radii_px=[40.0, 10.0])
    image = _image(kitti_clip, 10)
    with SixDofLocalizer(folder, cfg) as loc:
        near = loc.localize(image, cam, [], _offset(poses[10], 0.0, 3.0))
        far = loc.localize(image, cam, [], _offset(poses[10], 0.0, 5.0))
    assert near.accepted and "guided from the fallback pose" in near.reason
    position_m, rotation_deg = _errors(near.world_from_cam, poses[10])
    assert position_m < 0.25 and rotation_deg < 2.0
    assert not far.accepted, far.reason
    np.testing.assert_array_equal(far.world_from_cam, _offset(poses[10], 0.0, 5.0))


def test_benchmark_poses_round_trip_and_read_as_colmap_quaternions(tmp_path):
    """``name qw qx qy qz tx ty tz`` of world-to-camera poses: written, read back to 1e-9, and each line's
    quaternion and translation are pycolmap's of the same pose (its quaternion is scalar-last)."""
    rng = np.random.default_rng(7)
    world_from_cam = np.tile(np.eye(4), (3, 1, 1))
    world_from_cam[:, :3, :3] = Rotation.random(3, random_state=7).as_matrix()
    world_from_cam[:, :3, 3] = rng.uniform(-500, 500, (3, 3))
    cam_from_world = invert_pose(world_from_cam)
    names = ["query/000010.png", "query/000016.png", "night/0001.jpg"]
    path = write_benchmark_poses(tmp_path / "poses.txt", names, cam_from_world)
    read_names, read_poses = read_benchmark_poses(path)
    assert read_names == names
    np.testing.assert_allclose(read_poses, cam_from_world, atol=1e-9)
    for line, T in zip(path.read_text().splitlines(), cam_from_world, strict=True):
        rigid = pycolmap.Rigid3d(T[:3])
        q_xyzw = np.asarray(rigid.rotation.quat)
        q_wxyz = np.array([float(v) for v in line.split()[1:5]])
        assert min(np.abs(q_wxyz - q_xyzw[[3, 0, 1, 2]]).max(), np.abs(q_wxyz + q_xyzw[[3, 0, 1, 2]]).max()) < 1e-9
        np.testing.assert_allclose([float(v) for v in line.split()[5:]], rigid.translation, atol=1e-9)
    bad = tmp_path / "bad.txt"
    bad.write_text("a.png 2 0 0 0 1 2 3\n")
    with pytest.raises(InputError, match="norm 2.0000") as err:
        read_benchmark_poses(bad)
    assert err.value.field == "line 1"
    with pytest.raises(ValueError, match="white space"):
        write_benchmark_poses(tmp_path / "x.txt", ["a b.png"], cam_from_world[:1])


def test_the_reach_check_measures_a_poses_drift_on_the_image_plane_not_through_a_folding_lens():
    """Points 10 m ahead to the left and right, near where a strong barrel distortion (k1 = -0.3) stops spreading
    rays apart and starts folding them back: a camera moved 0.25 m sideways shifts every one by f * 0.25 / 10 =
    10 px on the image plane, though through the lens they land within a pixel of where they were."""
    f, z, d = 400.0, 10.0, 0.25
    cam = pycolmap.Camera(model="OPENCV", width=640, height=480, params=[f, f, 320, 240, -0.3, 0, 0, 0])
    r = np.linspace(1.0, 1.1, 21)  # normalised radius about the fold at 1 / sqrt(3 * 0.3) = 1.054
    x = np.concatenate([r, -r]) * z
    points = np.stack([x, np.zeros_like(x), np.full_like(x, z)], axis=1)
    moved = np.eye(4)[:3]
    moved[0, 3] = d
    through_lens = np.linalg.norm(cam.img_from_cam(points) - cam.img_from_cam(points + [d, 0, 0]), axis=1)
    assert np.median(through_lens) < 1.5 and np.all(cam.img_from_cam(points)[:, 0] < 640)  # the trap, in view
    assert _drift_px(points, np.eye(4)[:3], moved, cam) == pytest.approx(f * d / z, rel=1e-9)


def test_queries_extracted_together_have_each_images_own_features(model, kitti_clip, tmp_path):
    """Many queries' features, extracted by COLMAP's pipeline two at a time, are each image's :meth:`extract`
    exactly (keypoints and descriptors): files from two folders, a file given twice, an array among them. A file
    that is gone is one error naming it."""
    folder, _, _ = model
    elsewhere = tmp_path / "elsewhere" / "q.png"
    elsewhere.parent.mkdir()
    shutil.copy(_image(kitti_clip, 16), elsewhere)
    array = cv2.imread(str(_image(kitti_clip, 10)), cv2.IMREAD_GRAYSCALE)
    images = [_image(kitti_clip, 10), elsewhere, array, _image(kitti_clip, 10), str(_image(kitti_clip, 11))]
    with SixDofLocalizer(folder, SixDofConfig()) as loc:
        together = loc.extract_many(images)
        assert len(together) == len(images)
        for image, (xy, desc) in zip(images, together, strict=True):
            one_xy, one_desc = loc.extract(image)
            assert len(xy) > 500
            np.testing.assert_array_equal(desc, one_desc)
            np.testing.assert_allclose(xy, one_xy, atol=1e-4)
        assert not np.array_equal(together[0][1], together[1][1])  # each image its own, not the first's
        with pytest.raises(InputError, match="gone.png"):
            loc.extract_many([_image(kitti_clip, 10), tmp_path / "gone.png"])


def test_a_features_database_that_is_not_colmaps_is_one_error_naming_it(model, tmp_path):
    """A database.db of other bytes, or a SQLite file without COLMAP's tables, is one error naming the file; the
    file is left as it was."""
    folder, _, _ = model
    for label, content in (("garbage", b"not a database at all" * 100), ("empty sqlite", None)):
        damaged = tmp_path / label.replace(" ", "_")
        shutil.copytree(folder, damaged)
        db = damaged / "database.db"
        db.unlink()
        if content is None:
            import sqlite3

            sqlite3.connect(db).execute("CREATE TABLE other (x INTEGER)").connection.close()
        else:
            db.write_bytes(content)
        before = db.read_bytes()
        with pytest.raises(InputError, match="not a readable COLMAP database") as err:
            SixDofLocalizer(damaged)
        assert err.value.path == db and err.value.field == "database"
        assert db.read_bytes() == before
