"""Geometry against known answers: known Sim3s, known interpolants, known associations."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mapkit.core import geometry as g


def _random_pose(rng):
    return g.make_pose(Rotation.random(random_state=rng.integers(1 << 31)).as_matrix(), rng.normal(size=3) * 10)


def test_quaternion_round_trip_and_sign(rng):
    R = Rotation.random(50, random_state=1).as_matrix()
    q = g.matrix_to_quat_wxyz(R)
    assert np.all(q[:, 0] >= 0)
    np.testing.assert_allclose(g.quat_wxyz_to_matrix(q), R, atol=1e-12)
    # a 90 degree turn about z is (cos 45, 0, 0, sin 45) in wxyz
    np.testing.assert_allclose(
        g.matrix_to_quat_wxyz(g.yaw_rotation(np.pi / 2)), [np.sqrt(0.5), 0, 0, np.sqrt(0.5)], atol=1e-12
    )


def test_skew_is_the_cross_product_for_one_vector_and_a_stack(rng):
    u, v = rng.normal(size=(2, 7, 3))
    np.testing.assert_allclose(g.skew(u[0]) @ v[0], np.cross(u[0], v[0]), atol=1e-12)
    S = g.skew(u)
    assert S.shape == (7, 3, 3)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", S, v), np.cross(u, v), atol=1e-12)


def test_invert_pose_is_inverse(rng):
    T = np.stack([_random_pose(rng) for _ in range(5)])
    np.testing.assert_allclose(g.invert_pose(T) @ T, np.broadcast_to(np.eye(4), T.shape), atol=1e-12)


@pytest.mark.parametrize("with_scale", [True, False])
def test_umeyama_recovers_known_similarity(rng, with_scale):
    scale = 2.5 if with_scale else 1.0
    R = Rotation.from_euler("zyx", [40, -10, 5], degrees=True).as_matrix()
    t = np.array([100.0, -20.0, 3.0])
    S_true = g.make_sim3(scale, R, t)
    src = rng.uniform(-50, 50, size=(200, 3))
    dst = g.transform_points(S_true, src) + rng.normal(scale=0.01, size=src.shape)
    S = g.umeyama(src, dst, with_scale=with_scale)
    assert g.sim3_scale(S) == pytest.approx(scale, rel=1e-4)
    np.testing.assert_allclose(S[:3, :3] / g.sim3_scale(S), R, atol=1e-4)
    np.testing.assert_allclose(S[:3, 3], t, atol=0.01)


def test_umeyama_handles_reflection_case():
    # planar points: the SVD may propose a reflection, the result must stay a rotation
    src = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float)
    R = g.yaw_rotation(0.3)
    dst = src @ R.T
    S = g.umeyama(src, dst, with_scale=False)
    assert g.is_rotation(S[:3, :3])
    np.testing.assert_allclose(S[:3, :3], R, atol=1e-9)


def test_umeyama_rejects_bad_shapes():
    with pytest.raises(ValueError):
        g.umeyama(np.zeros((2, 3)), np.zeros((2, 3)))


def test_interpolate_poses_midpoint_and_no_extrapolation():
    stamps = np.array([1_000_000_000, 2_000_000_000], dtype=np.int64)
    T0 = g.make_pose(np.eye(3), [0, 0, 0])
    T1 = g.make_pose(g.yaw_rotation(np.pi / 2), [10, 0, 0])
    query = np.array([500_000_000, 1_500_000_000, 2_000_000_000, 2_000_000_001], dtype=np.int64)
    poses, mask = g.interpolate_poses(stamps, np.stack([T0, T1]), query)
    assert mask.tolist() == [False, True, True, False]
    np.testing.assert_allclose(poses[0][:3, 3], [5, 0, 0])
    np.testing.assert_allclose(poses[0][:3, :3], g.yaw_rotation(np.pi / 4), atol=1e-12)
    np.testing.assert_allclose(poses[1], T1, atol=1e-12)


def test_interpolate_keeps_nanosecond_resolution_at_epoch_times():
    # 2026 epoch stamps: float64 seconds since 1970 would lose the sub-microsecond part
    t0 = 1_790_000_000_000_000_000
    stamps = np.array([t0, t0 + 1000], dtype=np.int64)
    poses = np.stack([g.make_pose(np.eye(3), [0, 0, 0]), g.make_pose(np.eye(3), [1000.0, 0, 0])])
    out, _ = g.interpolate_poses(stamps, poses, np.array([t0 + 1], dtype=np.int64))
    assert out[0, 0, 3] == pytest.approx(1.0, abs=1e-6)


def test_associate_is_one_to_one_and_respects_max_dt():
    a = np.array([0, 100, 200, 300, 1000], dtype=np.int64)
    b = np.array([98, 104, 305, 2000], dtype=np.int64)
    ia, ib = g.associate(a, b, max_dt_ns=10)
    pairs = set(zip(ia.tolist(), ib.tolist(), strict=True))
    # 100 -> 98 (2 ns) wins over 104; 300 -> 305; 0, 200, 1000 have nothing within 10 ns
    assert pairs == {(1, 0), (3, 2)}


def test_average_rotations_of_symmetric_spread_is_centre():
    centre = g.yaw_rotation(1.0)
    Rs = np.stack(
        [centre @ Rotation.from_rotvec(v).as_matrix() for v in ([0.1, 0, 0], [-0.1, 0, 0], [0, 0.2, 0], [0, -0.2, 0])]
    )
    np.testing.assert_allclose(g.average_rotations(Rs), centre, atol=1e-9)
    assert g.rotation_angle_rad(g.average_rotations(Rs).T @ centre) < 1e-9


def test_transform_poses_by_a_similarity_keeps_rotations_rigid():
    """A Sim(3) moves poses: positions as points, rotations turned (not scaled), and its inverse undoes it."""
    from mapkit.core.geometry import is_rotation, make_pose, make_sim3, transform_points, transform_poses

    rng = np.random.default_rng(4)
    poses = np.stack(
        [make_pose(Rotation.from_rotvec(rng.normal(size=3)).as_matrix(), rng.normal(size=3) * 10) for _ in range(5)]
    )
    R = Rotation.from_rotvec([0.3, -0.2, 1.1]).as_matrix()
    S = make_sim3(7.5, R, [1.0, -2.0, 3.0])
    moved = transform_poses(S, poses)
    assert is_rotation(moved[:, :3, :3], atol=1e-9)
    np.testing.assert_allclose(moved[:, :3, 3], transform_points(S, poses[:, :3, 3]), atol=1e-12)
    np.testing.assert_allclose(moved[:, :3, :3], R @ poses[:, :3, :3], atol=1e-12)
    np.testing.assert_allclose(transform_poses(np.linalg.inv(S), moved), poses, atol=1e-9)
