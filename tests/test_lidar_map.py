"""The LiDAR map (``lidar_map/`` of a session): voxel statistics, deskewing against known surfaces, the real
KITTI clip's road, the PLY and its CRS, streaming memory, and the build's config and input errors."""

from __future__ import annotations

import dataclasses
import json
import tracemalloc
import warnings

import numpy as np
import open3d as o3d
import pytest
from conftest import SHARED_DATA
from scipy.spatial.transform import Rotation

from mapkit.core.errors import InputError, InputWarning
from mapkit.core.geodesy import LocalFrame
from mapkit.core.geometry import make_pose
from mapkit.core.types import FrameTransform, LidarScan, PoseSample, StreamKind
from mapkit.core.workspace import Workspace
from mapkit.deploy.crs_export import ply_georef
from mapkit.evaluation.metrics import distances_to_mesh
from mapkit.io import open_log
from mapkit.io.mcap_log import McapWriter
from mapkit.io.plots import raster_top_view
from mapkit.mapping.build import BuildConfig, build
from mapkit.mapping.lidar_map import LidarMapConfig, build_lidar_map, load_voxel_stats, save_voxel_map
from mapkit.mapping.trajectory import Trajectory
from mapkit.mapping.voxel_map import _OUTER_I, _OUTER_J, VoxelMap, symmetric3_eigen

T0 = 1_700_000_000_000_000_000
SPEED_MPS, YAW_RATE = 8.0, np.pi / 2  # a fast turn: 9 degrees and 0.8 m during one 0.1 s sweep
BASE_FROM_LIDAR = make_pose(Rotation.from_euler("xyz", [2.0, -1.0, 3.0], degrees=True).as_matrix(), [0.4, 0.1, 1.8])


# --- a synthetic drive: a ground slab and four buildings, scanned by a turning car ----------------------------


def _scene() -> o3d.geometry.TriangleMesh:
    boxes = [((-40, -40, -0.2), (80, 80, 0.2)), ((8, -6, 0), (4, 12, 5)), ((-12, 4, 0), (6, 3, 4))]
    boxes += [((-3, 14, 0), (10, 2, 6)), ((2, -16, 0), (3, 3, 2.5))]
    mesh = o3d.geometry.TriangleMesh()
    for corner, size in boxes:
        box = o3d.geometry.TriangleMesh.create_box(*size)
        box.translate(corner)
        mesh += box
    return mesh


def _world_from_base(t_s: np.ndarray) -> np.ndarray:
    """A circle at SPEED_MPS turning at YAW_RATE, from the origin heading +x."""
    yaw = YAW_RATE * t_s
    r = SPEED_MPS / YAW_RATE
    return make_pose(
        Rotation.from_euler("z", yaw[:, None]).as_matrix(),
        np.stack([r * np.sin(yaw), r * (1 - np.cos(yaw)), 0 * yaw], 1),
    )


def _scans(mesh, n: int = 10, columns: int = 720, beams: int = 32, noise_m: float = 0.01):
    """Scans of a 10 Hz spinning scanner mounted at BASE_FROM_LIDAR, each column fired at its own time (clockwise
    from the rear, as mapkit.synth's), points in the sensor frame at their firing time, stamped at the sweep's
    start with per-point times."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    el = np.radians(np.linspace(-25.0, 2.0, beams))
    az = np.pi - 2 * np.pi * np.arange(columns) / columns
    dirs = np.stack(
        [
            np.cos(el)[None] * np.cos(az)[:, None],
            np.cos(el)[None] * np.sin(az)[:, None],
            np.tile(np.sin(el), (columns, 1)),
        ],
        -1,
    )
    rng = np.random.default_rng(7)
    for k in range(n):
        col_s = np.arange(columns) / columns * 0.1
        W = _world_from_base(k * 0.1 + col_s) @ BASE_FROM_LIDAR
        dirs_w = np.einsum("aij,abj->abi", W[:, :3, :3], dirs)
        origins = np.broadcast_to(W[:, None, :3, 3], dirs_w.shape)
        rays = np.concatenate([origins, dirs_w], -1).reshape(-1, 6).astype(np.float32)
        hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(np.float64)
        ok = np.isfinite(hit) & (hit < 60)
        r = hit[ok] + rng.normal(0.0, noise_m, int(ok.sum()))
        xyz = (dirs.reshape(-1, 3)[ok] * r[:, None]).astype(np.float32)
        times = np.repeat(col_s, beams)[ok].astype(np.float32)
        ring = np.tile(np.arange(beams, dtype=np.uint16), columns)[ok]
        yield LidarScan(T0 + k * 100_000_000, "lidar", xyz, np.full(len(xyz), 40.0, np.float32), times, ring)


def _synthetic_log(path, mesh, times: bool = True):
    """The drive as a log: the LiDAR's mount on /tf_static, the true poses of base_link at 100 Hz, the scans
    (``times``: with their per-point times; else with a zero time field, which cannot be used)."""
    stamps_s = np.arange(0.0, 1.1, 0.01)
    poses = _world_from_base(stamps_s)
    scans = {s.stamp_ns: s for s in _scans(mesh)}
    with McapWriter(path) as w:
        w.write_transforms("/tf_static", [FrameTransform(T0, "base_link", "lidar", BASE_FROM_LIDAR)])
        for t_s, T in zip(stamps_s, poses, strict=True):
            stamp = T0 + round(t_s * 1e9)
            w.write("/ins/pose", PoseSample(stamp, "world", "base_link", T))
            if stamp in scans:
                scan = scans[stamp]
                if not times:
                    scan.point_time_s = np.zeros(len(scan), np.float32)
                w.write("/lidar/points", scan)
    return path


def _build(log, ws, lidar_map: dict | bool | str = True):
    cfg = BuildConfig.model_validate({"trajectory": {"source": "poses"}, "lidar_map": lidar_map})
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", "no GPS stream", InputWarning)
        warnings.filterwarnings("ignore", ".*skipped: the log has no image stream", InputWarning)
        return Workspace(build([log], ws, config=cfg, progress=False)).session(log.stem.split(".")[0])


@pytest.fixture(scope="module")
def mesh():
    return _scene()


@pytest.fixture(scope="module")
def drive(mesh, tmp_path_factory):
    return _synthetic_log(tmp_path_factory.mktemp("lidar") / "turn.mcap", mesh)


def test_deskewed_map_on_true_poses_lies_on_the_true_surfaces_and_is_worse_without_deskew(drive, mesh, tmp_path):
    """Built by ``mapkit build`` on the true poses: the voxel centroids lie on the scene's surfaces (median <= 5 cm,
    >= 95 % within 25 cm). Without deskewing, the 9 degree turn during a sweep smears the walls."""
    s = _build(drive, tmp_path / "on")
    d_on = distances_to_mesh(load_voxel_stats(s.lidar_map).centroid, mesh)
    m = json.loads((s.lidar_map / "metrics.json").read_text())
    assert m["deskew"] and m["deskew_times"] == {"field": 10} and m["scans_used"] == 10
    assert np.median(d_on) <= 0.05 and np.mean(d_on < 0.25) >= 0.95, np.percentile(d_on, [50, 90, 99])
    off = _build(drive, tmp_path / "off", {"deskew": False})
    d_off = distances_to_mesh(load_voxel_stats(off.lidar_map).centroid, mesh)
    assert json.loads((off.lidar_map / "metrics.json").read_text())["deskew_times"] == {"off": 10}
    assert np.mean(d_off < 0.25) < 0.95 and np.percentile(d_off, 99) > 5 * np.percentile(d_on, 99)


def test_a_zero_time_field_is_one_warning_and_those_scans_are_placed_undeskewed(mesh, tmp_path):
    log = _synthetic_log(tmp_path / "notimes.mcap", mesh, times=False)
    with pytest.warns(InputWarning, match="10 LiDAR scans have a time field that cannot be used.*deskew is off"):
        s = _build(log, tmp_path / "ws")
    assert json.loads((s.lidar_map / "metrics.json").read_text())["deskew_times"] == {"unusable": 10}


def test_scans_without_a_time_field_are_deskewed_from_their_azimuth(mesh):
    """Times from the azimuth (kiss-icp's rule, the sweep ending at the stamp) place a scan without a time field
    as well as its own times do, once its stamp is the sweep's end."""
    scans = list(_scans(mesh, n=3))
    for scan in scans:
        scan.point_time_s, scan.stamp_ns = None, scan.stamp_ns + 100_000_000
    stamps_s = np.arange(0.0, 0.5, 0.01)
    traj = Trajectory(T0 + np.round(stamps_s * 1e9).astype(np.int64), _world_from_base(stamps_s), "truth")
    cfg = LidarMapConfig(max_range_m=60.0)
    result = build_lidar_map(iter(scans), traj, BASE_FROM_LIDAR, cfg)
    d = distances_to_mesh(result.voxels.stats().centroid, mesh)
    assert result.times == {"azimuth": 3} and np.mean(d < 0.25) >= 0.95, np.percentile(d, [50, 90, 99])


# --- the voxel statistics ----------------------------------------------------------------------------------------


def test_voxel_statistics_of_a_plane_and_a_line_and_merging_in_chunks_is_exact(rng, monkeypatch):
    """Points on a known tilted plane give its normal and planarity ~1, on a line planarity ~0; the centroid,
    count, mean intensity and first/last stamp are exact, and merging in small chunks changes nothing."""
    n_up = np.array([0.3, -0.2, 1.0]) / np.linalg.norm([0.3, -0.2, 1.0])
    u = np.cross(n_up, [1.0, 0, 0])
    u /= np.linalg.norm(u)
    v = np.cross(n_up, u)
    centre = np.array([10.25, -3.25, 2.25])  # the centre of one 0.5 m voxel
    ab = rng.uniform(-0.1, 0.1, (400, 2))
    plane = centre + ab[:, :1] * u + ab[:, 1:] * v
    line = np.array([10.75, -3.25, 2.25]) + rng.uniform(-0.2, 0.2, (300, 1)) * np.array([[1.0, 0, 0]])
    maps = [VoxelMap(0.5, chunk_points=chunk) for chunk in (10_000, 50)]
    for vm in maps:
        for k in range(4):  # four scans, 100 points of the plane each, then the line at the last one
            vm.add(plane[k * 100 : (k + 1) * 100], np.full(100, 10.0 * k), T0 + k)
        vm.add(line, None, T0 + 9)
    a, b = (vm.stats() for vm in maps)
    assert len(a) == 2 and a.count.tolist() == [400, 300]
    np.testing.assert_allclose(a.centroid, [plane.mean(0), line.mean(0)], atol=1e-12)
    assert abs(a.normal[0] @ n_up) > 1 - 1e-9 and a.normal[0, 2] > 0
    l3, l2, l1 = np.linalg.eigvalsh(np.cov(plane.T, bias=True))
    assert a.planarity[0] == pytest.approx((l2 - l3) / l1, rel=1e-9) and a.planarity[0] > 0.75
    assert a.planarity[1] < 0.01
    assert a.intensity[0] == pytest.approx(15.0) and np.isnan(a.intensity[1])
    assert a.first_ns.tolist() == [T0, T0 + 9] and a.last_ns.tolist() == [T0 + 3, T0 + 9]
    monkeypatch.setattr("mapkit.mapping.voxel_map.STATS_BLOCK", 1)  # the normals computed one voxel at a time
    c = maps[0].stats()
    for field in ("centroid", "count", "intensity", "normal", "planarity", "first_ns", "last_ns"):
        np.testing.assert_allclose(getattr(a, field), getattr(b, field), rtol=1e-12, atol=1e-12, err_msg=field)
        np.testing.assert_array_equal(getattr(a, field), getattr(c, field), err_msg=field)


def test_closed_form_eigen_gives_the_known_eigenvalues_and_smallest_eigenvector(rng):
    """Matrices built as R diag(l) R^T with known l and R, over the shapes a voxel takes (plane, thin plane, line,
    ball, plane with exactly zero thickness, one repeated point): the eigenvalues to 2e-8 of the largest (about the
    square root of the machine epsilon where two coincide, as the cubic's roots are there), and
    where the smallest is simple the eigenvector is R's first column (up to sign)."""
    shapes = {
        "plane": [1e-6, 4e-4, 9e-4],
        "thin plane": [1e-12, 1e-4, 2e-3],
        "flat": [0.0, 1e-4, 2e-3],
        "line": [1e-8, 1e-8, 2e-3],
        "ball": [4e-4, 4e-4, 4e-4],
        "point": [0.0, 0.0, 0.0],
    }
    for name, lam in shapes.items():
        rot = Rotation.random(500, random_state=rng.integers(1 << 31)).as_matrix()
        full = np.einsum("vij,j,vkj->vik", rot, np.array(lam), rot)
        evals, vec = symmetric3_eigen(full[:, _OUTER_I, _OUTER_J])
        np.testing.assert_allclose(
            evals, np.broadcast_to(lam, evals.shape), atol=2e-8 * max(max(lam), 1e-12), err_msg=name
        )
        residual = np.einsum("vij,vj->vi", full, vec) - evals[:, :1] * vec
        assert np.abs(np.linalg.norm(vec, axis=1) - 1).max() < 1e-9, name
        assert np.abs(residual).max() <= 2e-8 * max(max(lam), 1e-12), name
        if lam[0] < lam[1]:  # a simple smallest eigenvalue: a unique normal
            assert np.abs(np.einsum("vi,vi->v", vec, rot[:, :, 0])).min() > 1 - 1e-6, name


def test_raster_top_view_puts_each_point_in_its_pixel_with_its_height_colour(tmp_path):
    """Two clusters at known places and heights: the low one is drawn dark blue (viridis' start) and the high one
    yellow (its end) where they are, the rest of the map white; north is up."""
    from PIL import Image

    low = np.column_stack([np.full(50, 10.0), np.full(50, 10.0), np.zeros(50)])
    high = np.column_stack([np.full(50, 90.0), np.full(50, 90.0), np.full(50, 5.0)])
    path = raster_top_view(tmp_path / "top.png", np.vstack([low, high]), None, "two clusters", max_side_px=200)
    img = np.asarray(Image.open(path).convert("RGB")).astype(int)[52:]  # below the caption
    h, w, _ = img.shape
    lo, px = 10.0 - 0.03 * 80, 80 * 1.06 / 200  # the padded extent and metres per pixel

    def at(x, y):
        return img[int((90.0 + 0.03 * 80 - y) / px), int((x - lo) / px)]

    assert (at(10.0, 10.0) == [68, 1, 84]).all()  # viridis(0)
    assert (at(90.0, 90.0) == [253, 231, 36]).all()  # viridis(1)
    assert (at(50.0, 80.0) == 255).all() and (at(80.0, 20.0) == 255).all()
    assert (img == 255).all(axis=2).mean() > 0.9


def test_memory_is_bounded_by_the_map_not_by_the_log(mesh):
    """Four passes over the same scans make the same voxels with four times the counts, at the same peak memory
    (within 20 %): the scans are merged chunk by chunk, never held. (Dynamic removal off: it needs scans at
    different times; its own window is bounded in the next test.)"""
    scans = list(_scans(mesh, n=4))
    traj = Trajectory(T0 + np.arange(0, 60) * 10_000_000, _world_from_base(np.arange(0, 60) * 0.01), "truth")
    cfg = LidarMapConfig(max_range_m=60.0, chunk_points=40_000, dynamic={"enabled": False})
    peaks, results = [], []
    for repeats in (1, 4):
        tracemalloc.start()
        results.append(build_lidar_map((s for _ in range(repeats) for s in scans), traj, BASE_FROM_LIDAR, cfg))
        peaks.append(tracemalloc.get_traced_memory()[1])
        tracemalloc.stop()
    one, four = (r.voxels.stats() for r in results)
    assert len(four) == len(one) and (four.count == 4 * one.count).all()
    assert peaks[1] <= 1.2 * peaks[0], peaks


def test_dynamic_removal_holds_a_time_window_not_the_log(mesh):
    """Two and four turns of the circle (8 and 16 s, each turn's scans those of the first, four seconds later, so
    the map stays the same) peak at the same memory within 2 %: once the filter's window (3 s of scans, 6 s of
    range images) is full, memory follows the map, not the log (range images kept for the whole log: +4 %)."""
    turn = list(_scans(mesh, n=40))  # 4 s: the circle's period at YAW_RATE
    scans = [dataclasses.replace(s, stamp_ns=s.stamp_ns + k * 4_000_000_000) for k in range(4) for s in turn]
    stamps_s = np.arange(0.0, 16.2, 0.01)
    traj = Trajectory(T0 + np.round(stamps_s * 1e9).astype(np.int64), _world_from_base(stamps_s), "truth")
    cfg = LidarMapConfig(max_range_m=60.0, chunk_points=40_000)
    peaks, results = [], []
    for n in (80, 160):
        tracemalloc.start()
        results.append(build_lidar_map(iter(scans[:n]), traj, BASE_FROM_LIDAR, cfg))
        peaks.append(tracemalloc.get_traced_memory()[1])
        tracemalloc.stop()
    assert results[1].scans_used == 160 and abs(len(results[1].voxels) - len(results[0].voxels)) <= 10
    assert peaks[1] <= 1.02 * peaks[0], peaks


def test_a_pitch_error_between_scans_does_not_carve_the_road_with_the_height_tolerance(mesh):
    """The static scene placed by poses that pitch +-0.5 deg (as a build's own might): without the height
    tolerance near the ground, beams meeting the road at a grazing angle look seen through and the road loses
    points; with it (the default) ten times fewer go, and almost nothing of the scene at all."""
    scans = list(_scans(mesh, n=40))
    stamps_s = np.arange(0.0, 4.2, 0.01)
    pitch = Rotation.from_euler("y", 0.5 * np.sin(2 * np.pi * stamps_s / 1.5)[:, None], degrees=True).as_matrix()
    poses = _world_from_base(stamps_s) @ make_pose(pitch, np.zeros((len(stamps_s), 3)))
    traj = Trajectory(T0 + np.round(stamps_s * 1e9).astype(np.int64), poses, "truth")
    road = {}
    for tolerance in (0.0, LidarMapConfig().dynamic.margin_vertical_m):
        result = build_lidar_map(
            iter(scans),
            traj,
            BASE_FROM_LIDAR,
            LidarMapConfig(max_range_m=60.0, dynamic={"margin_vertical_m": tolerance}),
        )
        gone = result.removed.stats()
        road[tolerance] = int(gone.count[np.abs(gone.centroid[:, 2]) < 0.3].sum())
        if tolerance:
            assert result.metrics(LidarMapConfig())["dynamic"]["fraction_removed"] < 5e-4
    assert road[0.0] > 10 * road[LidarMapConfig().dynamic.margin_vertical_m] and road[0.0] > 300, road


# --- files, config and errors -----------------------------------------------------------------------------------


def test_points_ply_opens_in_open3d_and_states_its_frame_like_the_semidense_map(drive, tmp_path):
    s = _build(drive, tmp_path / "ws")
    stats = load_voxel_stats(s.lidar_map)
    ply = s.lidar_map / "points.ply"
    pts = np.asarray(o3d.io.read_point_cloud(str(ply)).points)
    assert len(pts) == len(stats) == json.loads((s.lidar_map / "metrics.json").read_text())["voxels"]
    np.testing.assert_allclose(pts, stats.centroid)
    assert ply_georef(ply)[2]["frame"] == "unspecified"  # no GPS: the trajectory's own frame
    frame = LocalFrame(49.0, 8.4, 110.0)
    save_voxel_map(tmp_path / "enu", stats, frame)
    got_frame, epsg, kv = ply_georef(tmp_path / "enu" / "points.ply")
    assert got_frame == frame and epsg is None and kv["frame"] == "local_enu"


def test_config_switches_and_a_lidar_map_asked_of_a_log_without_lidar(tmp_path):
    assert BuildConfig().lidar_map.enabled == "auto"
    assert BuildConfig.model_validate({"lidar_map": False}).lidar_map.enabled is False
    assert BuildConfig.model_validate({"lidar_map": "auto"}).lidar_map.enabled == "auto"
    assert BuildConfig.model_validate({"lidar_map": {"voxel_size_m": 0.2}}).lidar_map.voxel_size_m == 0.2
    with pytest.raises(ValueError, match="min_range_m"):
        BuildConfig.model_validate({"lidar_map": {"min_range_m": 50, "max_range_m": 40}})
    log = tmp_path / "poses_only.mcap"
    with McapWriter(log) as w:
        for i in range(20):
            w.write(
                "/odom", PoseSample(T0 + i * 100_000_000, "map", "base_link", make_pose(np.eye(3), [0.5 * i, 0, 0]))
            )
    with pytest.raises(InputError, match=r"poses_only\.mcap.*lidar_map\.enabled.*no LiDAR stream"):
        build([log], tmp_path / "ws", config=BuildConfig.model_validate({"lidar_map": True}), progress=False)
    assert not (tmp_path / "ws").exists()


def test_lidar_map_false_skips_the_stage_without_a_warning(drive, tmp_path):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        s = _build(drive, tmp_path / "ws", False)
    assert not s.lidar_map.exists() and not [w for w in caught if "lidar_map" in str(w.message)]
    st = json.loads((tmp_path / "ws" / "metrics.json").read_text())["sessions"]["turn"]["stages"]
    assert st["lidar_map"] == {"skipped": "lidar_map: false in the config"}


def test_a_lidar_that_tf_does_not_link_is_the_mounts_error(mesh, tmp_path):
    log = tmp_path / "unlinked.mcap"
    with McapWriter(log) as w:
        w.write_transforms("/tf_static", [FrameTransform(T0, "base_link", "gps", np.eye(4))])
        for i, scan in enumerate(_scans(mesh, n=3)):
            w.write(
                "/ins/pose", PoseSample(scan.stamp_ns, "world", "base_link", _world_from_base(np.array([i * 0.1]))[0])
            )
            w.write("/lidar/points", scan)
    with pytest.raises(InputError, match=r"tf does not link the LiDAR frame 'lidar' to 'base_link'.*assume_identity"):
        _build(log, tmp_path / "ws")


# --- the real KITTI clip ----------------------------------------------------------------------------------------

KITTI_VELODYNE = SHARED_DATA / "kitti-raw-velodyne-clip"


@pytest.fixture(scope="module")
def kitti_velodyne(tmp_path_factory):
    if not (KITTI_VELODYNE / "velodyne").is_dir():
        pytest.skip(f"real data not found at {KITTI_VELODYNE} (30 HDL-64 scans as a KITTI odometry folder)")
    ws = tmp_path_factory.mktemp("kitti") / "ws"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputWarning)  # no GPS, no images
        build([KITTI_VELODYNE], ws, progress=False)
    return Workspace(ws).session(KITTI_VELODYNE.name)


def road_thickness_m(centroids: np.ndarray) -> float:
    """RMS distance to a plane of the road ahead: the voxel centroids in a box 3 to 11 m ahead of the first pose
    (the stretch the car then drives over) and 2 m either side, 1.5 to 2.1 m below the sensor (1.73 m above the
    road; this leaves out cars and kerbs), in the trajectory's frame (velodyne at the first scan: x forward, z up);
    a least-squares plane, refitted twice to the centroids within 3 RMS of it."""
    x, y, z = centroids.T
    road = centroids[(x > 3) & (x < 11) & (np.abs(y) < 2) & (z > -2.1) & (z < -1.5)]
    keep = np.ones(len(road), bool)
    for _ in range(3):
        c = road[keep].mean(axis=0)
        normal = np.linalg.svd(road[keep] - c, full_matrices=False)[2][2]
        d = (road - c) @ normal
        rms = float(np.sqrt(np.mean(d[keep] ** 2)))
        keep = np.abs(d) < 3 * rms
    assert keep.mean() > 0.9 and len(road) > 2000, (keep.mean(), len(road))
    return rms


def test_real_clip_road_is_thin(kitti_velodyne):
    """The road in front of the car on the real HDL-64 clip (times from each point's azimuth, the KITTI reader's):
    RMS thickness <= 3 cm with deskewing; the figure without it is printed beside it."""
    stats = load_voxel_stats(kitti_velodyne.lidar_map)
    on = road_thickness_m(stats.centroid)
    traj = Trajectory.load(kitti_velodyne.enu_trajectory)
    log = open_log(KITTI_VELODYNE)
    try:
        off = build_lidar_map(log.records(StreamKind.LIDAR), traj, np.eye(4), LidarMapConfig(deskew=False))
    finally:
        log.close()
    off_rms = road_thickness_m(off.voxels.stats().centroid)
    print(f"KITTI road RMS thickness: {on * 100:.2f} cm deskewed, {off_rms * 100:.2f} cm without deskewing")
    assert on <= 0.03


def test_real_clip_the_removal_of_moving_objects_leaves_the_road(kitti_velodyne):
    """On the real clip the removal takes under 1 % of the points near the ground (the road, where no moving object
    stands but a small pitch error between scans looks like free space), and more than 1.5 % without the height
    tolerance near the ground that keeps it."""
    m = json.loads((kitti_velodyne.lidar_map / "metrics.json").read_text())["dynamic"]
    assert m["enabled"] and 0 < m["near_ground_fraction_removed"] < 0.01 and m["fraction_removed"] < 0.1, m
    traj = Trajectory.load(kitti_velodyne.enu_trajectory)
    log = open_log(KITTI_VELODYNE)
    try:
        bare = build_lidar_map(
            log.records(StreamKind.LIDAR), traj, np.eye(4), LidarMapConfig(dynamic={"margin_vertical_m": 0.0})
        )
    finally:
        log.close()
    assert bare.metrics(LidarMapConfig())["dynamic"]["near_ground_fraction_removed"] > 0.015


def test_the_trajectory_the_map_is_placed_by_agrees_with_kiss_icps_own_pipeline(kitti_velodyne, tmp_path):
    """kiss-icp's ``OdometryPipeline`` on the same scans, read by its own KITTI reader with its own azimuth times
    (``KITTIRawDataset.get_timestamps``) and mapkit's default settings: every pose within 1 cm of mapkit's."""
    import yaml
    from kiss_icp.datasets.generic import GenericDataset
    from kiss_icp.datasets.kitti_raw import KITTIRawDataset
    from kiss_icp.pipeline import OdometryPipeline

    class WithAzimuthTimes(GenericDataset):
        def __getitem__(self, idx):
            points, _ = super().__getitem__(idx)
            return points, KITTIRawDataset.get_timestamps(points)

    o = BuildConfig().trajectory.kiss_icp
    cfg = {
        "out_dir": str(tmp_path / "kiss"),
        "data": {"max_range": o.max_range_m, "min_range": o.min_range_m, "deskew": o.deskew},
        "mapping": {"voxel_size": o.max_range_m / 100.0, "max_points_per_voxel": o.max_points_per_voxel},
        "registration": {"max_num_threads": o.max_threads},
    }
    (tmp_path / "kiss.yaml").write_text(yaml.safe_dump(cfg))
    pipeline = OdometryPipeline(WithAzimuthTimes(KITTI_VELODYNE / "velodyne"), config=tmp_path / "kiss.yaml")
    pipeline._run_pipeline()  # run() would also write its results folder
    ours = Trajectory.load(kitti_velodyne.trajectory)
    assert ours.body_frame == "velodyne" and len(ours) == len(pipeline.poses) == 30
    gap = np.linalg.norm(ours.world_from_base[:, :3, 3] - pipeline.poses[:, :3, 3], axis=1)
    print(f"mapkit vs kiss-icp's pipeline: largest position gap {gap.max() * 1000:.3f} mm")
    assert gap.max() <= 0.01
