"""Accuracy measures against ground truth: trajectory error, map-to-surface distance, consistency.

``trajectory_errors`` is pure numpy; ``distances_to_mesh`` uses open3d's RaycastingScene (exact
point-to-triangle distances, vectorised in C++).
"""

from __future__ import annotations

import numpy as np

from mapkit.core.geometry import interpolate_poses, rotation_angle_rad


def trajectory_errors(
    est_stamps_ns: np.ndarray, est_poses: np.ndarray, gt_stamps_ns: np.ndarray, gt_poses: np.ndarray
) -> dict:
    """Absolute errors of georeferenced estimates against ground truth interpolated at their stamps.

    No alignment is applied: both are in the same georeferenced frame, so this is the error a user
    of the map sees (the absolute trajectory error of the papers' evaluations).
    """
    gt, ok = interpolate_poses(gt_stamps_ns, gt_poses, est_stamps_ns)
    est = np.asarray(est_poses)[ok]
    err = est[:, :3, 3] - gt[:, :3, 3]
    dt = np.linalg.norm(err, axis=1)
    dr = np.degrees(rotation_angle_rad(np.swapaxes(gt[:, :3, :3], 1, 2) @ est[:, :3, :3]))
    return {
        "poses_compared": int(ok.sum()),
        "ate_rmse_m": float(np.sqrt(np.mean(dt**2))) if len(dt) else None,
        "horizontal_rmse_m": float(np.sqrt(np.mean(np.sum(err[:, :2] ** 2, axis=1)))) if len(dt) else None,
        "vertical_rmse_m": float(np.sqrt(np.mean(err[:, 2] ** 2))) if len(dt) else None,
        "translation_median_m": float(np.median(dt)) if len(dt) else None,
        "translation_max_m": float(dt.max()) if len(dt) else None,
        "rotation_mean_deg": float(dr.mean()) if len(dr) else None,
        "rotation_median_deg": float(np.median(dr)) if len(dr) else None,
        "per_pose_translation_m": dt,
    }


def distances_to_mesh(points: np.ndarray, mesh) -> np.ndarray:
    """Unsigned distance of every point to a triangle mesh.

    ``mesh`` is an open3d legacy mesh or a (vertices (V, 3), triangles (T, 3)) pair. open3d works
    in float32, so everything is moved next to the mesh's centroid first (UTM-sized coordinates
    would otherwise lose centimetres).
    """
    import open3d as o3d

    if isinstance(mesh, o3d.geometry.TriangleMesh):
        V, F = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.triangles)
    else:
        V, F = np.asarray(mesh[0], np.float64), np.asarray(mesh[1])
    origin = V.mean(axis=0) if len(V) else np.zeros(3)
    scene = o3d.t.geometry.RaycastingScene()
    # open3d's stub gives Tensor(np_array, dtype, device) no defaults; its binding defaults both (the
    # array's dtype, the CPU)
    vertices = o3d.core.Tensor((V - origin).astype(np.float32))  # type: ignore[call-overload]
    scene.add_triangles(vertices, o3d.core.Tensor(F.astype(np.uint32)))  # type: ignore[call-overload]
    out = np.empty(len(points), np.float64)
    step = 1_000_000
    for i in range(0, len(points), step):
        q = o3d.core.Tensor(  # type: ignore[call-overload]  # defaults the stub lacks, as above
            (np.asarray(points[i : i + step], np.float64) - origin).astype(np.float32)
        )
        out[i : i + step] = scene.compute_distance(q).numpy()
    return out


def map_accuracy(points: np.ndarray, mesh, road_length_m: float | None = None) -> dict:
    """The map-accuracy figures of the map-construction goals."""
    d = distances_to_mesh(points, mesh)
    out = {
        "points": int(len(points)),
        "median_distance_m": float(np.median(d)) if len(d) else None,
        "fraction_within_0.5m": float(np.mean(d < 0.5)) if len(d) else None,
        "fraction_within_0.15m": float(np.mean(d < 0.15)) if len(d) else None,
        "fraction_within_0.25m": float(np.mean(d < 0.25)) if len(d) else None,
        "p50_p90_p99_m": [float(x) for x in np.percentile(d, [50, 90, 99])] if len(d) else None,
    }
    if road_length_m:
        out["points_per_100m"] = float(len(points) / road_length_m * 100.0)
    return out
