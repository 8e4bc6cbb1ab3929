"""Trajectory stage: kiss-icp recovers a known motion; pose streams move to the base frame."""

import warnings
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from mapkit.core.errors import InputError, InputWarning
from mapkit.core.geometry import invert_pose, make_pose, rotation_angle_rad, yaw_rotation
from mapkit.core.types import FrameTransform, LidarScan, PoseSample
from mapkit.io.mcap_log import McapLog, McapWriter
from mapkit.mapping.trajectory import Trajectory, TrajectoryConfig, estimate_trajectory, trajectory_from_poses

T0 = 1_700_000_000_000_000_000
BASE_FROM_LIDAR = make_pose(yaw_rotation(0.05), [0.8, 0.0, 1.9])


def _street_scene() -> o3d.t.geometry.RaycastingScene:
    """A street 200 m long with buildings of different sizes on both sides, and the ground."""
    scene = o3d.t.geometry.RaycastingScene()
    rng = np.random.default_rng(3)
    ground = o3d.geometry.TriangleMesh.create_box(300, 80, 0.1).translate((-50, -40, -0.1))
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(ground))
    for side in (-1, 1):
        x = -40.0
        while x < 240:
            w, d, h = rng.uniform(6, 18), rng.uniform(6, 12), rng.uniform(5, 20)
            y = side * rng.uniform(8, 12) - (d if side < 0 else 0)
            box = o3d.geometry.TriangleMesh.create_box(w, d, h).translate((x, y, 0))
            scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(box))
            x += w + rng.uniform(1, 6)
        # poles and parked cars: what pins the motion along a street of parallel facades
        x = -40.0
        while x < 240:
            pole = o3d.geometry.TriangleMesh.create_box(0.3, 0.3, 5.0).translate((x, side * rng.uniform(5, 6.5), 0))
            scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(pole))
            if rng.random() < 0.5:
                car = o3d.geometry.TriangleMesh.create_box(4.2, 1.8, 1.5).translate((x + 2, side * 3.5 - 0.9, 0))
                scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(car))
            x += rng.uniform(6, 14)
    # rotated kiosks and shelters: surfaces at every heading, as a real street has
    for _ in range(40):
        kiosk = o3d.geometry.TriangleMesh.create_box(*rng.uniform(1.0, 3.0, size=3))
        kiosk.rotate(o3d.geometry.get_rotation_matrix_from_xyz((0, 0, rng.uniform(0, np.pi))), center=(0, 0, 0))
        kiosk.translate((rng.uniform(-40, 240), rng.choice([-1, 1]) * rng.uniform(4.5, 7.5), 0))
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(kiosk))
    return scene


def _scan(scene, world_from_lidar: np.ndarray) -> np.ndarray:
    el = np.radians(np.linspace(-20, 10, 32))
    az = np.radians(np.linspace(-180, 180, 900, endpoint=False))
    E, A = np.meshgrid(el, az, indexing="ij")
    d_lidar = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)
    d_world = d_lidar @ world_from_lidar[:3, :3].T
    o = np.broadcast_to(world_from_lidar[:3, 3], d_world.shape)
    rays = o3d.core.Tensor(np.hstack([o, d_world]).astype(np.float32))
    t = scene.cast_rays(rays)["t_hit"].numpy()
    ok = np.isfinite(t) & (t < 80)
    return (d_lidar[ok] * t[ok, None]).astype(np.float32)


def _truth(n=40):
    """Base poses: 1.5 m per scan along a gentle S-bend that stays in the street (10 Hz, 15 m/s)."""
    yaw = 0.08 * np.sin(np.linspace(0, 2 * np.pi, n))
    step = np.minimum(1.5, 0.15 * np.arange(1, n + 1))  # pulling away from a stop
    x = np.cumsum(np.r_[0, step[:-1] * np.cos(yaw[:-1])])
    y = np.cumsum(np.r_[0, step[:-1] * np.sin(yaw[:-1])])
    return np.stack([make_pose(yaw_rotation(a), [xi, yi, 0.0]) for a, xi, yi in zip(yaw, x, y, strict=True)])


@pytest.fixture(scope="module")
def lidar_log(tmp_path_factory):
    path = tmp_path_factory.mktemp("lidar") / "drive.mcap"
    scene = _street_scene()
    truth = _truth()
    with McapWriter(path) as w:
        w.write_transforms("/tf_static", [FrameTransform(0, "base_link", "lidar", BASE_FROM_LIDAR)])
        for i, world_from_base in enumerate(truth):
            pts = _scan(scene, world_from_base @ BASE_FROM_LIDAR)
            w.write("/lidar/points", LidarScan(T0 + i * 100_000_000, "lidar", pts))
    return path, truth


def test_kiss_icp_trajectory_matches_known_motion(lidar_log):
    path, truth = lidar_log
    with McapLog(path) as log:
        traj = estimate_trajectory(log, TrajectoryConfig())
    assert traj.source == "lidar:/lidar/points" and len(traj) == len(truth)
    assert np.all(np.diff(traj.stamps_ns) > 0)
    # the odometry frame is the base at the first scan: compare with truth expressed the same way
    expected = invert_pose(truth[0]) @ truth
    err_t = np.linalg.norm(traj.world_from_base[:, :3, 3] - expected[:, :3, 3], axis=1)
    err_r = rotation_angle_rad(np.swapaxes(traj.world_from_base[:, :3, :3], 1, 2) @ expected[:, :3, :3])
    # this street of parallel facades pins motion along it only through poles and cars, so
    # kiss-icp drifts ~1.4% here; a wrong extrinsic or frame convention gives metres at once
    travelled = np.linalg.norm(np.diff(expected[:, :3, 3], axis=0), axis=1).sum()
    assert err_t.max() < 0.02 * travelled, f"max translation error {err_t.max():.3f} m over {travelled:.0f} m"
    assert np.degrees(err_r.max()) < 2.0  # kiss-icp drifts ~1.5 deg in pitch on this flat toy street


def test_lidar_trajectory_without_a_base_in_the_calibration_is_the_scanners(tmp_path):
    """KITTI raw's calibration names imu, velodyne and cameras but no base_link: the trajectory is the
    scanner's own (body_frame 'lidar'), so that the GPS antenna ('imu') is found from it, with no
    'no extrinsic' warning and no identity assumed between base_link and the scanner."""
    path = tmp_path / "raw.mcap"
    scene = _street_scene()
    truth = _truth()
    with McapWriter(path) as w:
        w.write_transforms("/tf_static", [FrameTransform(0, "imu", "lidar", BASE_FROM_LIDAR)])
        for i, world_from_base in enumerate(truth):
            w.write(
                "/lidar/points",
                LidarScan(T0 + i * 100_000_000, "lidar", _scan(scene, world_from_base @ BASE_FROM_LIDAR)),
            )
    with McapLog(path) as log, warnings.catch_warnings():
        warnings.simplefilter("error", InputWarning)
        traj = estimate_trajectory(log, TrajectoryConfig())
    assert traj.body_frame == "lidar"
    lidar = truth @ BASE_FROM_LIDAR
    expected = invert_pose(lidar[0]) @ lidar  # the scanner's poses from its first
    err_t = np.linalg.norm(traj.world_from_base[:, :3, 3] - expected[:, :3, 3], axis=1)
    travelled = np.linalg.norm(np.diff(expected[:, :3, 3], axis=0), axis=1).sum()
    assert err_t.max() < 0.02 * travelled, (
        f"max translation error {err_t.max():.3f} m over {travelled:.0f} m"
    )  # as the base's


def test_pose_stream_of_a_camera_is_moved_to_the_base(tmp_path):
    base_from_cam = make_pose(np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float), [1.5, 0.0, 1.4])
    truth = _truth(10)
    with McapWriter(tmp_path / "p.mcap") as w:
        w.write_transforms("/tf_static", [FrameTransform(0, "base_link", "camera", base_from_cam)])
        for i, world_from_base in enumerate(truth):
            w.write("/gt", PoseSample(T0 + i * 10**8, "world", "camera", world_from_base @ base_from_cam))
    with McapLog(tmp_path / "p.mcap") as log:
        traj = trajectory_from_poses(log, "/gt", "base_link")
    np.testing.assert_allclose(traj.world_from_base, truth, atol=1e-9)
    assert traj.frame == "world"


def test_trajectory_files_round_trip(tmp_path):
    truth = _truth(7)
    stamps = T0 + np.arange(7, dtype=np.int64) * 123_456_789
    Trajectory(stamps, truth, "test").save(tmp_path / "t")
    back = Trajectory.load(tmp_path / "t")
    np.testing.assert_array_equal(back.stamps_ns, stamps)
    np.testing.assert_array_equal(back.world_from_base, truth)
    from mapkit.io.trajectory import read_kitti_poses, read_tum

    s2, p2 = read_tum(tmp_path / "t" / "poses_tum.txt")
    np.testing.assert_array_equal(s2, stamps)
    np.testing.assert_allclose(p2, truth, atol=1e-6)
    np.testing.assert_allclose(read_kitti_poses(tmp_path / "t" / "poses_kitti.txt"), truth, atol=1e-8)


def test_no_source_is_a_clear_error(tmp_path):
    from mapkit.core.types import GpsFix

    with McapWriter(tmp_path / "g.mcap") as w:
        w.write("/gps", GpsFix(T0, 49.0, 8.4, 100.0))
    with McapLog(tmp_path / "g.mcap") as log:
        with pytest.raises(InputError, match="no LiDAR, pose or image stream"):
            estimate_trajectory(log, TrajectoryConfig())
        with pytest.raises(InputError, match="no LiDAR stream"):
            estimate_trajectory(log, TrajectoryConfig(source="lidar"))


@pytest.mark.realdata
def test_camera_only_trajectory_of_the_real_clip_matches_truth_up_to_similarity(kitti_clip):
    """pycolmap on 20 real frames: after a Sim3 fit the path lies on KITTI's ground truth."""
    from mapkit.core.geometry import transform_points, umeyama
    from mapkit.io.kitti import KittiOdometry
    from mapkit.mapping.trajectory import trajectory_from_camera

    cfg = TrajectoryConfig(source="camera")
    cfg.camera.max_images = 20
    with pytest.warns(Warning):  # the clip has no times.txt: nominal 10 Hz stamps
        log = KittiOdometry(kitti_clip)
    with log:
        traj = trajectory_from_camera(log, "/kitti/camera_0/image", cfg)
        gt = {p.stamp_ns: p.parent_from_child for p in log.records("pose")}
    assert len(traj) >= 15
    truth = np.stack([gt[int(s)][:3, 3] for s in traj.stamps_ns])
    est = traj.world_from_base[:, :3, 3]
    S = umeyama(est, truth, with_scale=True)
    err = np.linalg.norm(transform_points(S, est) - truth, axis=1)
    travelled = np.linalg.norm(np.diff(truth, axis=0), axis=1).sum()
    assert err.max() < 0.01 * travelled, f"max error {err.max():.2f} m over {travelled:.0f} m"


# --- the synthetic LiDAR's sweep resolution: why the presets sweep 512 columns, not 256 -------------------

#: the tiny preset's rainy drive cut to its first 40 m, from a standing start as the preset drives,
#: with a thumbnail camera (the LiDAR is what is measured)
STANDING_START_STEPS = (256, 512)


@pytest.fixture(scope="module")
def standing_start_towns(tmp_path_factory) -> dict[int, Path]:
    from mapkit.synth import synthesize
    from mapkit.synth.config import load_config

    rainy = next(s for s in load_config("tiny").model_dump(mode="json")["sessions"] if s["name"] == "tiny-rainy")
    session = {**rainy, "length_m": 40.0, "follow": None, "follow_shift_m": 0.0, "camera_rate_hz": 0.5}
    root = tmp_path_factory.mktemp("standing-start")
    return {
        steps: synthesize(
            preset="tiny",
            out=root / f"sweep{steps}",
            progress=False,
            overrides={"sessions": [session], "camera": {"width": 64, "height": 48}, "lidar": {"azimuth_steps": steps}},
        )
        for steps in STANDING_START_STEPS
    }


def test_kiss_icp_keeps_the_distance_of_a_standing_start_on_a_fine_enough_sweep(standing_start_towns):
    """Known answer: the town's true distance over the first 40 m of a drive from rest.

    On a sweep of 64 x 256 columns (1.4 deg apart: 0.5 m between neighbours at 20 m, eight times
    coarser than the HDL-64E it models) the sensor-fixed pattern of rings on the flat road and
    columns on flat facades outweighs the real structure, and kiss-icp stays near zero motion while
    the car pulls away (it finds under 60% of the distance); 64 x 512 columns keep over 90%.
    """
    from mapkit.core.geometry import interpolate_poses
    from mapkit.io import open_log
    from mapkit.mapping.trajectory import trajectory_from_lidar
    from mapkit.synth import gt_poses, session_log

    kept = {}
    for steps, town in standing_start_towns.items():
        log = open_log(session_log(town, "tiny-rainy"))
        try:
            traj = trajectory_from_lidar(log, "/lidar/points", TrajectoryConfig())
        finally:
            log.close()
        gt, ok = interpolate_poses(*gt_poses(town, "tiny-rainy"), traj.stamps_ns)
        true_m = np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1).sum()
        est_m = np.linalg.norm(np.diff(traj.world_from_base[ok, :3, 3], axis=0), axis=1).sum()
        assert true_m == pytest.approx(40.0, abs=1.0)
        kept[steps] = est_m / true_m
    assert kept[512] > 0.9, f"64 x 512 sweep: kiss-icp found {kept[512]:.0%} of the distance from a standing start"
    assert kept[256] < 0.6, f"64 x 256 sweep: kiss-icp found {kept[256]:.0%}; the slip this test documents is gone"
