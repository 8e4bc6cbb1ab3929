"""The retrieval measurement against known clusters, and the Euler convention against scipy."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mapkit.core.geometry import is_rotation, matrix_to_quat_wxyz, rotation_angle_rad, yaw_rotation
from mapkit.retrieval.measurement import (
    Measurement,
    euler_from_matrix,
    matrix_from_euler,
    mean_shift_measurement,
)


def _blob(rng, centre, n, sigma=1.0):
    return np.asarray(centre, float) + rng.normal(scale=sigma, size=(n, 3))


def test_euler_matches_scipy_and_round_trips():
    R = Rotation.random(500, random_state=7)
    e = euler_from_matrix(R.as_matrix())
    np.testing.assert_allclose(e, R.as_euler("XYZ"), atol=1e-9)  # intrinsic x-y'-z'', the filter's convention
    np.testing.assert_allclose(matrix_from_euler(e), R.as_matrix(), atol=1e-12)
    assert np.all(np.abs(e[:, 1]) <= np.pi / 2) and np.all(np.abs(e[:, [0, 2]]) <= np.pi)
    # R = Rx(a) Ry(b) Rz(c): with only c set, it is a yaw about z
    np.testing.assert_allclose(matrix_from_euler([0.0, 0.0, 0.4]), yaw_rotation(0.4), atol=1e-15)


@pytest.mark.parametrize("b", [np.pi / 2, -np.pi / 2])
def test_euler_round_trip_at_gimbal_lock(b):
    R = matrix_from_euler([0.3, b, -0.2])
    e = euler_from_matrix(R)
    assert np.all(np.isfinite(e)) and e[2] == 0.0
    np.testing.assert_allclose(matrix_from_euler(e), R, atol=1e-12)


def test_largest_cluster_wins_with_its_mean_and_members(rng):
    big, small = _blob(rng, [100, 50, 2], 12), _blob(rng, [160, 50, 2], 8)
    order = rng.permutation(20)  # interleave the two clusters in rank order
    X = np.concatenate([big, small])[order]
    R = np.stack([yaw_rotation(0.1)] * 12 + [yaw_rotation(2.0)] * 8)[order]
    z = mean_shift_measurement(X, R, bandwidth=5.0)
    expected_members = np.sort(np.flatnonzero(order < 12))
    np.testing.assert_array_equal(z.members, expected_members)
    assert (z.cluster_size, z.n_retrieved) == (12, 20)
    np.testing.assert_allclose(z.translation, big.mean(axis=0), atol=1e-12)
    np.testing.assert_allclose(z.rotation, yaw_rotation(0.1), atol=1e-12)
    np.testing.assert_allclose(z.euler, [0, 0, 0.1], atol=1e-12)
    rms = np.sqrt(np.mean(np.sum((big - big.mean(axis=0)) ** 2, axis=1)))
    assert z.spread_m == pytest.approx(rms, rel=1e-12)


def test_tie_goes_to_the_cluster_of_the_top_ranked_image(rng):
    a, b = _blob(rng, [0, 0, 0], 5, 0.5), _blob(rng, [40, 0, 0], 5, 0.5)
    R = np.broadcast_to(np.eye(3), (10, 3, 3))
    z = mean_shift_measurement(np.concatenate([b[:1], a, b[1:]]), R)
    np.testing.assert_array_equal(z.members, [0, 6, 7, 8, 9])
    z = mean_shift_measurement(np.concatenate([a, b]), R)
    np.testing.assert_array_equal(z.members, [0, 1, 2, 3, 4])


def test_weights_choose_the_heavier_cluster(rng):
    X = np.concatenate([_blob(rng, [0, 0, 0], 6, 0.5), _blob(rng, [30, 0, 0], 3, 0.5)])
    R = np.broadcast_to(np.eye(3), (9, 3, 3))
    assert mean_shift_measurement(X, R).cluster_size == 6
    w = np.array([1.0] * 6 + [5.0] * 3)
    z = mean_shift_measurement(X, R, weights=w)
    np.testing.assert_array_equal(z.members, [6, 7, 8])
    np.testing.assert_allclose(z.translation, X[6:].mean(axis=0), atol=1e-12)


def test_modes_closer_than_the_bandwidth_merge():
    # two tight groups 4 m apart converge to separate modes with a 3 m kernel but are one
    # cluster at 5 m: the mean of all six points
    X = np.array([[0, 0, 0], [0.2, 0, 0], [0, 0.2, 0], [4, 0, 0], [4.2, 0, 0], [4, 0.2, 0.0]])
    R = np.broadcast_to(np.eye(3), (6, 3, 3))
    assert mean_shift_measurement(X, R, bandwidth=3.0).cluster_size == 3
    z = mean_shift_measurement(X, R, bandwidth=5.0)
    assert z.cluster_size == 6
    np.testing.assert_allclose(z.translation, X.mean(axis=0), atol=1e-12)


def test_distinct_modes_within_the_bandwidth_are_merged():
    # along x: three points at 0, one at 4.9, three at 9.8; flat kernel of 5 m. The seeds converge
    # to three distinct modes, 1.225, 4.9 and 8.575; the middle one sees all seven points, is kept
    # first, and absorbs the other two (3.675 m away). Unmerged, the largest cluster would be 3.
    x = np.array([0, 0, 0, 4.9, 9.8, 9.8, 9.8])
    X = np.stack([x, np.zeros(7), np.zeros(7)], axis=1)
    z = mean_shift_measurement(X, np.broadcast_to(np.eye(3), (7, 3, 3)), bandwidth=5.0)
    assert z.cluster_size == 7
    np.testing.assert_allclose(z.translation, [4.9, 0, 0], atol=1e-12)


def test_rotation_average_is_sign_consistent_with_quaternions(rng):
    yaws = 2.5 + rng.normal(scale=0.05, size=10)
    R = yaw_rotation(yaws) @ Rotation.from_rotvec(rng.normal(scale=0.02, size=(10, 3))).as_matrix()
    q = matrix_to_quat_wxyz(R)
    q[::2] *= -1.0  # the same rotations, half of them with the other sign
    X = _blob(rng, [0, 0, 0], 10, 0.5)
    z_q = mean_shift_measurement(X, q * 3.0)  # unnormalised input is accepted
    z_R = mean_shift_measurement(X, R)
    assert is_rotation(z_q.rotation)
    np.testing.assert_allclose(z_q.rotation, z_R.rotation, atol=1e-12)
    # close to the mean yaw; a naive component-wise quaternion mean would be far off
    assert np.degrees(rotation_angle_rad(yaw_rotation(yaws.mean()).T @ z_q.rotation)) < 1.5
    naive = q.mean(axis=0)
    assert np.linalg.norm(naive) < 0.5


def test_single_retrieval_and_from_pose():
    z = mean_shift_measurement(np.array([[1.0, 2.0, 3.0]]), yaw_rotation(0.5)[None])
    assert z.cluster_size == 1 and z.spread_m == 0.0
    np.testing.assert_allclose(z.translation, [1, 2, 3])
    z2 = Measurement.from_pose([1, 2, 3], yaw_rotation(0.5))
    np.testing.assert_allclose(z2.euler, z.euler, atol=1e-12)


@pytest.mark.parametrize(
    "X, R, kw",
    [
        (np.zeros((4, 2)), np.zeros((4, 3, 3)), {}),
        (np.zeros((4, 3)), np.zeros((3, 3, 3)), {}),
        (np.zeros((4, 3)), np.broadcast_to(np.eye(3), (4, 3, 3)), {"weights": -np.ones(4)}),
        (np.zeros((4, 3)), np.broadcast_to(np.eye(3), (4, 3, 3)), {"bandwidth": 0.0}),
    ],
)
def test_bad_input_is_refused(X, R, kw):
    with pytest.raises(ValueError):
        mean_shift_measurement(X, R, **kw)


# --- beyond the paper: the retrieved poses as hypotheses ----------------------------------------------


def test_hit_weights_known_values():
    from mapkit.retrieval.measurement import hit_weights

    d = np.array([0.5, 0.6, 0.9, np.inf])  # the last one is padding (index smaller than k)
    np.testing.assert_allclose(hit_weights(d, "uniform"), [1 / 3, 1 / 3, 1 / 3, 0])
    r = np.exp(-np.arange(3) / 2.0)
    np.testing.assert_allclose(hit_weights(d, "rank", 2.0), np.append(r / r.sum(), 0))
    e = np.exp(-np.array([0.0, 0.1, 0.4]) / 0.1)
    np.testing.assert_allclose(hit_weights(d, "distance", 0.1), np.append(e / e.sum(), 0))
    with pytest.raises(ValueError):
        hit_weights(d, "rank", 0.0)
    with pytest.raises(ValueError):
        hit_weights(np.full(3, np.inf))


def test_pose_hypotheses_from_retrieval_drop_padding_and_read_quaternions():
    from mapkit.retrieval.measurement import PoseHypotheses

    X = np.array([[0.0, 0, 0], [10, 0, 0], [20, 0, 0]])
    R = yaw_rotation(np.array([0.0, 0.5, 1.0]))
    h = PoseHypotheses.from_retrieval(X, matrix_to_quat_wxyz(R), np.array([0.1, 0.2, np.inf]))
    assert len(h) == 2 and h.weights.sum() == pytest.approx(1.0)
    np.testing.assert_allclose(h.translations, X[:2])
    np.testing.assert_allclose(h.rotations, R[:2], atol=1e-12)
    one = PoseHypotheses.from_measurement(Measurement.from_pose([1.0, 2, 3], R[1]))
    assert len(one) == 1 and one.weights[0] == 1.0
    with pytest.raises(ValueError):
        PoseHypotheses.from_retrieval(X, R, weighting="distance")  # needs distances
    with pytest.raises(ValueError):
        PoseHypotheses(X, R[:2], np.ones(3) / 3)
