"""The reference 6-DoF localizer: real KITTI frames held out of the reference model register to a few
centimetres of their ground-truth poses, a query that does not register keeps its fallback pose and
says why, a damaged model is one error naming the file, and benchmark pose files round-trip and read
as COLMAP's quaternions."""

from __future__ import annotations

import shutil
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
        assert f"2D-3D matches, fewer than min_inliers {loc.cfg.min_inliers}" in r.reason
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
