"""Evaluation measures against known answers."""

import numpy as np
import open3d as o3d
import pytest

from mapkit.core.geometry import make_pose, yaw_rotation
from mapkit.evaluation.metrics import distances_to_mesh, map_accuracy, trajectory_errors


def test_distances_to_a_known_box(rng):
    box = o3d.geometry.TriangleMesh.create_box(10, 10, 10)  # [0, 10]^3
    on_face = np.c_[rng.uniform(1, 9, 500), rng.uniform(1, 9, 500), np.full(500, 10.0)]
    offsets = rng.uniform(-0.3, 0.3, 500)
    pts = on_face + np.c_[np.zeros(500), np.zeros(500), offsets]
    d = distances_to_mesh(pts, box)
    np.testing.assert_allclose(d, np.abs(offsets), atol=1e-5)
    acc = map_accuracy(pts, box, road_length_m=50.0)
    assert acc["fraction_within_0.5m"] == 1.0
    assert acc["median_distance_m"] == pytest.approx(np.median(np.abs(offsets)), abs=1e-5)
    assert acc["points_per_100m"] == pytest.approx(1000.0)


def test_trajectory_errors_of_a_known_offset():
    stamps = np.arange(0, 11, dtype=np.int64) * 10**9
    gt = np.stack([make_pose(yaw_rotation(0.1 * i), [i, 0.0, 0.0]) for i in range(11)])
    est = gt.copy()
    est[:, 1, 3] += 0.5  # half a metre to the left everywhere
    est[:, :3, :3] = est[:, :3, :3] @ yaw_rotation(np.radians(2.0))
    r = trajectory_errors(
        stamps[:-1] + 5 * 10**8, np.stack([(a + b) / 2 for a, b in zip(est[:-1], est[1:], strict=True)]), stamps, gt
    )
    # mid-way poses: compare against interpolated truth (the averaged rotations are close enough)
    assert r["poses_compared"] == 10
    assert r["ate_rmse_m"] == pytest.approx(0.5, abs=1e-6)
    assert r["horizontal_rmse_m"] == pytest.approx(0.5, abs=1e-6) and r["vertical_rmse_m"] == pytest.approx(
        0.0, abs=1e-9
    )
    up = est.copy()
    up[:, 2, 3] += 1.2  # and 1.2 m up: 1.3 m in all
    r_up = trajectory_errors(stamps, up, stamps, gt)
    assert r_up["vertical_rmse_m"] == pytest.approx(1.2) and r_up["ate_rmse_m"] == pytest.approx(1.3)
    assert r["rotation_median_deg"] == pytest.approx(2.0, abs=0.05)
    # estimates outside the truth's time span are not compared (no extrapolation)
    r2 = trajectory_errors(np.array([-1, 5 * 10**9], np.int64), est[[0, 5]], stamps, gt)
    assert r2["poses_compared"] == 1
