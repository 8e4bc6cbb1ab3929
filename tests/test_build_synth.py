"""`mapkit build` on a small synthetic town: georeferencing and map accuracy against exact truth."""

import json

import pytest

from mapkit.evaluation.evaluate import evaluate_build
from mapkit.mapping.build import build
from mapkit.synth import session_log, synthesize

# one 80 m drive; GPS with white noise and multipath jumps but no bias, so that what is measured is
# the alignment itself (a session's bias moves the whole map, see eval_build's mean offset)
OVERRIDES = {
    "sessions": [
        {
            "name": "drive",
            "role": "train",
            "date": "2014-06-26",
            "time": "11:00",
            "weather": "overcast",
            "length_m": 80.0,
            "speed_mps": 8.0,
            "lane_offset_m": 0.0,
        },
    ],
    # the demo's HDL-64E beam layout: with tiny's HDL-32E, kiss-icp drifts in pitch
    "lidar": {"beams": 64, "vertical_fov_deg": [-24.9, 2.0], "azimuth_steps": 512},
    "motion": {"start_from_rest": False},  # what these figures were measured with (the tiny preset starts from rest)
    "gps": {
        "rate_hz": 5.0,
        "bias_sigma_m": 0.0,
        "white_sigma_m": 1.5,
        "multipath_rate_hz": 0.1,
        "multipath_sigma_m": 8.0,
        "dropout_rate_hz": 0.0,
    },
}


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    root = tmp_path_factory.mktemp("synth-build")
    town = synthesize(preset="tiny", out=root / "town", overrides=OVERRIDES, progress=False)
    ws = build([session_log(town, "drive")], root / "ws", progress=False)
    return town, ws, evaluate_build(ws, town)["sessions"]["drive"]


def test_session_is_georeferenced_in_the_declared_utm_zone(built):
    town, ws, _ = built
    ga = json.loads((ws / "sessions" / "drive" / "georef" / "gps_alignment.json").read_text())
    assert ga["georeferenced"] and ga["utm_crs_epsg"] == 32630  # Oxford
    assert ga["alignment"]["mode"] == "yaw"  # 'auto': LiDAR odometry is metric and keeps its scale
    assert ga["alignment"]["scale"] == pytest.approx(1.0, abs=1e-12)
    assert abs(ga["alignment"]["scale_if_estimated"] - 1.0) < 0.02  # GPS agrees, roughly


def test_gps_alignment_beats_gps_alone(built):
    _, ws, r = built
    t, g = r["trajectory"], r["gps_alone"]
    assert t["ate_rmse_m"] < 1.0, t  # the map-construction goal, reached when the GPS has no bias
    assert t["horizontal_rmse_m"] < 0.5 * g["horizontal_rmse_m"], (t, g)
    assert t["rotation_median_deg"] < 1.0
    # with no bias to remove, the offset-removed error is no larger than the absolute one, and the
    # table a person reads shows both
    loc = r["trajectory_local"]["ate_rmse_m"]
    assert loc <= t["ate_rmse_m"] + 1e-9
    row = next(line for line in (ws / "eval_build.md").read_text().splitlines() if line.startswith("| drive |"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[2] == f"{t['ate_rmse_m']:.2f}" and cells[5] == f"{loc:.2f}", cells


def test_map_lies_on_the_true_surfaces(built):
    _, _, r = built
    m = r["map_local"]
    assert m["points"] > 2000
    assert m["median_distance_m"] < 0.25 and m["fraction_within_0.5m"] > 0.65, m


def test_lidar_map_on_the_builds_own_poses_lies_on_the_true_surfaces_beside_the_semidense_map(built):
    """The LiDAR map built on the session's own (GPS-aligned) trajectory, its offset removed: median distance to
    the true surfaces at most 0.10 m, at least 95 % of its voxels within 0.25 m; eval_build.md puts both maps of
    the session side by side."""
    _, ws, r = built
    lm = r["lidar_map_local"]
    assert lm["points"] > 10 * r["map_local"]["points"]  # the LiDAR sees far more of the street than the images
    assert lm["median_distance_m"] <= 0.10 and lm["fraction_within_0.25m"] >= 0.95, lm
    rows = [line for line in (ws / "eval_build.md").read_text().splitlines() if line.startswith("| drive | LiDAR |")]
    assert len(rows) == 1 and f"| {lm['median_distance_m']:.3f} |" in rows[0], rows


def test_image_database_records_the_camera_mount(built):
    """The build keeps the camera's mount on the vehicle beside its image table, and a VLAD bundle
    made from it carries it, so that the localizer's filter runs on the vehicle pose as recorded."""
    import warnings

    import numpy as np

    from mapkit.core.workspace import Workspace
    from mapkit.localization.localize import LocalizeConfig
    from mapkit.retrieval.index_vlad import VladIndex, VladIndexConfig, build_vlad_index
    from mapkit.synth import load_world
    from mapkit.synth.sensors import FRAME_CAMERA, extrinsics

    town, ws, _ = built
    rec = json.loads(Workspace(ws).session("drive").camera_mount.read_text())
    truth = extrinsics(load_world(town).config)[FRAME_CAMERA]
    assert rec["camera"] == FRAME_CAMERA and rec["base_frame"] == "base_link"
    np.testing.assert_allclose(rec["base_from_camera"], truth, atol=1e-9)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a short drive: the PCA is capped
        cfg = VladIndexConfig(
            database_sessions=["drive"],
            train_sessions=["drive"],
            vlad={"num_words": 8, "pca_dim": 12, "kmeans_iterations": 10, "dsift": {"half_resolution": True}},
        )
        index = VladIndex.load(build_vlad_index(ws, config=cfg, progress=False))
    np.testing.assert_allclose(index.base_from_camera, truth, atol=1e-9)
    np.testing.assert_allclose(LocalizeConfig().camera_mount(index).base_from_camera, truth, atol=1e-9)
    pinned = np.eye(4)[[2, 0, 1, 3]].T  # an explicit mount in the config wins over the bundle's
    assert not np.allclose(
        LocalizeConfig(base_from_camera=tuple(map(tuple, pinned))).camera_mount(index).base_from_camera, truth
    )


def test_fused_georeferencing_writes_poses_with_covariances_and_the_map_uses_them(built, tmp_path):
    """``georef: {fuse: true}``: the factor graph over kiss-icp, GPS and the preintegrated
    IMU writes its trajectory and per-pose covariances beside the rigid fit's; the trajectory stage
    is kept, the georef and map stages redone on the fused poses. Against the truth, the fused
    frame-to-frame motion is better than kiss-icp's (the IMU is exact over a tenth of a second);
    its absolute attitude is not (on this straight drive the accelerometer's bias and the tilt are
    one unknown: measured 0.37 deg of pitch, which is why ``fuse`` is off by default)."""
    import shutil

    import numpy as np

    from mapkit.core.geometry import interpolate_poses, invert_pose
    from mapkit.core.runio import is_done
    from mapkit.core.workspace import Workspace
    from mapkit.evaluation.truth import session_truth, ws_from_town
    from mapkit.mapping.trajectory import Trajectory

    town, ws, _ = built
    ws2 = tmp_path / "ws"
    shutil.copytree(ws, ws2)
    cfg = tmp_path / "fuse.yaml"
    cfg.write_text("georef:\n  fuse: true\nimagedb: false\nlidar_map: false\n")
    s, s2 = Workspace(ws).session("drive"), Workspace(ws2).session("drive")
    traj_marker = (s2.trajectory / ".done").read_text()
    map_marker = (s2.map / ".done").read_text()
    build([session_log(town, "drive")], ws2, config=cfg, progress=False)
    assert (s2.trajectory / ".done").read_text() == traj_marker  # kiss-icp not run again
    assert (
        is_done(s2.georef) and is_done(s2.map) and (s2.map / ".done").read_text() != map_marker
    )  # the map follows the fused poses
    fused = Trajectory.load(s2.fused_trajectory)
    cov = np.load(s2.fused_covariances)
    assert cov["covariances"].shape == (len(fused.stamps_ns), 6, 6) and cov["georef_covariance"].shape == (6, 6)
    sig = np.sqrt(np.einsum("nii->ni", cov["covariances"][:, 3:, 3:]))
    assert np.all(np.isfinite(sig)) and np.all(sig > 0) and np.median(sig) < 5.0
    stats = json.loads(s2.gps_alignment.read_text())["fused"]
    assert stats["imu"] == "preintegrated" and stats["imu_factors"] > 0

    stamps, truth = session_truth(town, "drive")
    truth = ws_from_town(town, Workspace(ws).frame()) @ truth

    def step_errors_mm(traj: Trajectory) -> np.ndarray:
        gt, ok = interpolate_poses(stamps, truth, traj.stamps_ns)
        est = traj.world_from_base[ok]

        def rel(T):
            return invert_pose(T[:-1]) @ T[1:]

        return 1000 * np.linalg.norm((invert_pose(rel(gt)) @ rel(est))[:, :3, 3], axis=1)

    rigid_mm, fused_mm = step_errors_mm(Trajectory.load(s.georef_trajectory)), step_errors_mm(fused)
    assert np.median(fused_mm) < 0.5 * np.median(rigid_mm), (np.median(fused_mm), np.median(rigid_mm))
    assert np.median(fused_mm) < 5.0
    # what reads a session's trajectory after the build reads the one its map was made with
    assert s2.enu_trajectory == s2.fused_trajectory and s.enu_trajectory == s.georef_trajectory
    fused_fit = Trajectory(fused.stamps_ns, fused.world_from_base, fused.source, frame="enu")
    assert evaluate_build(ws2, town)["sessions"]["drive"]["trajectory_used"] == "factor graph"
    assert evaluate_build(ws, town)["sessions"]["drive"]["trajectory_used"] == "rigid GPS fit"
    tum = tmp_path / "truth.tum"  # one session against a trajectory file: the fused poses are the estimate
    fused_fit.save(tmp_path / "as-truth")
    tum.write_text((tmp_path / "as-truth" / "poses_tum.txt").read_text())
    r = evaluate_build(ws2, tum, session="drive")["sessions"]["drive"]
    assert r["estimate"]["folder"] == str(s2.fused_trajectory) and "factor graph" in r["estimate"]["trajectory"]
    assert r["ate"]["rmse_m"] < 1e-6  # compared with itself
