"""A registration's covariance in the pose graph's convention (mapkit.localization.sixdof.world_from_cam_covariance),
held against the spread of COLMAP's own registrations of one camera from keypoints with one pixel of noise."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mapkit.core.geometry import invert_pose, make_pose
from mapkit.localization.sixdof import world_from_cam_covariance

pycolmap = pytest.importorskip("pycolmap")


def _log_right(T_true: np.ndarray, T_est: np.ndarray) -> np.ndarray:
    """gtsam's Pose3 tangent (rotation, translation) of ``T_est`` about ``T_true``, to first order."""
    D = invert_pose(T_true) @ T_est
    return np.r_[Rotation.from_matrix(D[:3, :3]).as_rotvec(), D[:3, 3]]


def test_covariance_matches_the_spread_of_registrations():
    rng = np.random.default_rng(5)
    camera = pycolmap.Camera(model="PINHOLE", width=1024, height=768, params=[700.0, 700.0, 512.0, 384.0])
    # a camera 300 m from the world's origin, so the cross term between rotation and position counts; points
    # 20 to 60 m ahead fix the position along the view worse than across it
    world_from_cam = make_pose(Rotation.from_rotvec([0.3, -1.2, 0.2]).as_matrix(), np.array([250.0, -160.0, 30.0]))
    X_cam = np.c_[rng.uniform(-8, 8, 60), rng.uniform(-3, 3, 60), rng.uniform(20, 60, 60)]
    X_world = X_cam @ world_from_cam[:3, :3].T + world_from_cam[:3, 3]
    uv = X_cam[:, :2] / X_cam[:, 2:] * 700.0 + [512.0, 384.0]
    errors, predicted = [], []
    for _ in range(300):
        out = pycolmap.estimate_and_refine_absolute_pose(
            uv + rng.normal(0.0, 1.0, uv.shape), X_world, camera, return_covariance=True
        )
        cam_from_world = np.eye(4)
        cam_from_world[:3] = out["cam_from_world"].matrix()
        errors.append(_log_right(world_from_cam, invert_pose(cam_from_world)))
        predicted.append(world_from_cam_covariance(cam_from_world, out["covariance"]))
    empirical = np.cov(np.array(errors).T)
    C = np.mean(predicted, axis=0)
    ratio = np.sqrt(np.diag(C) / np.diag(empirical))
    assert np.all((ratio > 0.7) & (ratio < 1.5)), ratio  # COLMAP's is about 1.25x the spread: conservative
    # the position's uncertainty lies along the view, as the spread's does
    along = np.linalg.eigh(C[3:, 3:])[1][:, -1]
    assert abs(along[2]) > 0.9
    corr = C / np.sqrt(np.outer(np.diag(C), np.diag(C)))
    corr_emp = empirical / np.sqrt(np.outer(np.diag(empirical), np.diag(empirical)))
    assert np.max(np.abs(corr - corr_emp)) < 0.2
