"""The synthetic town: layout, determinism, and ground truth checked against the mesh.

One ``tiny`` town is generated per test session (module fixture) and read back through mapkit's
own MCAP reader; determinism runs ``tiny`` a second time into another folder.
"""

from __future__ import annotations

import datetime as dt
import json
import os
import re
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from mapkit.core.errors import ConfigError, MapkitError
from mapkit.core.geodesy import LocalFrame
from mapkit.core.geometry import interpolate_poses
from mapkit.core.types import StreamKind
from mapkit.io.mcap_log import McapLog
from mapkit.synth import (
    GpsErrorModel,
    camera_poses,
    extrinsics,
    gt_poses,
    load_config,
    load_world,
    session_log,
    session_logs,
    street_coverage,
    synthesize,
)
from mapkit.synth.config import GpsConfig, presets_dir
from mapkit.synth.render import ground_truth_mesh_scene

TOPICS = {
    "/camera/front/image": "sensor_msgs/CompressedImage",
    "/camera/front/camera_info": "sensor_msgs/CameraInfo",
    "/lidar/points": "sensor_msgs/PointCloud2",
    "/gps/fix": "sensor_msgs/NavSatFix",
    "/imu/data": "sensor_msgs/Imu",
    "/tf_static": "tf2_msgs/TFMessage",
    "/ground_truth/odom": "nav_msgs/Odometry",
}


#: the tiny preset with its sessions cut to 24 m (a few seconds each, driven at speed throughout),
#: at the camera's own 10 Hz, with the HDL-32E sweep of 512 steps (a second layout besides the preset's
#: 64 x 512, and the one kiss-icp's own command line is checked on with its default config):
#: what these tests check of a log holds for any length, and the preset's own drives (long enough to
#: georeference, for the demo's every stage) are checked without rendering them, in
#: test_tiny_drives_can_be_georeferenced_aligned_and_localized
SHORT = {
    "sessions": [
        {**s, "length_m": 24.0, "camera_rate_hz": None} for s in load_config("tiny").model_dump(mode="json")["sessions"]
    ],
    "motion": {"start_from_rest": False},
    "lidar": {"beams": 32, "vertical_fov_deg": [-30.67, 10.67], "azimuth_steps": 512},
}


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    return synthesize(preset="tiny", out=tmp_path_factory.mktemp("synth") / "tiny", overrides=SHORT, progress=False)


@pytest.fixture(scope="module")
def world(tiny):
    return load_world(tiny)


def _images(mcap: Path) -> list[tuple[int, np.ndarray]]:
    log = McapLog(mcap)
    out = [(f.stamp_ns, f.image) for f in log.records(StreamKind.IMAGE)]
    log.close()
    return out


# --- configuration ---------------------------------------------------------------------------------


def test_presets_load_and_every_value_names_its_source():
    for name in ("tiny", "demo", "places", "benchmark"):
        cfg = load_config(name)
        assert cfg.preset == name
        text = (presets_dir() / f"{name}.yaml").read_text().splitlines()
        for lineno, line in enumerate(text, 1):
            body = line.split("#")[0]
            if re.match(r"^\s*[A-Za-z_]+:\s*\S", body) or body.strip().startswith("- {"):
                assert "#" in line, f"{name}.yaml line {lineno} has no source comment: {line!r}"
    demo = load_config("demo")
    assert len({s.weather for s in demo.sessions} | {"night"}) >= 5 and {s.role for s in demo.sessions} == {
        "train",
        "test",
    }
    bench = load_config("benchmark")
    assert bench.session_plan.n_train + len(bench.sessions) == 59  # MCVL: 59 vehicles


def test_the_snowy_overlay_adds_a_snowy_test_drive_and_leaves_the_demos_drives_as_they_are():
    """configs/synth/demo-snowy.yaml over the demo preset: the demo's five sessions, planned along the same paths,
    and a snowy test drive on a training drive's streets."""
    from mapkit.synth.sessions import plan_sessions
    from mapkit.synth.world import build_town

    base = load_config("demo")
    snowy = load_config("demo", presets_dir() / "demo-snowy.yaml")
    assert [s.model_dump() for s in snowy.sessions[:-1]] == [s.model_dump() for s in base.sessions]
    extra = snowy.sessions[-1]
    assert extra.weather == "snowy" and extra.role == "test"
    assert extra.follow in {s.name for s in base.sessions if s.role == "train"}
    plans = plan_sessions(base, build_town(base, None), None)
    with_snow = plan_sessions(snowy, build_town(snowy, None), None)
    assert len(with_snow) == len(plans) + 1
    for a, b in zip(plans, with_snow, strict=False):
        assert a.name == b.name and np.array_equal(a.drive.path_xy, b.drive.path_xy)


def test_bad_preset_and_bad_field_raise_config_errors_naming_them(tmp_path):
    with pytest.raises(ConfigError, match="nonexistent"):
        load_config("nonexistent")
    bad = tmp_path / "bad.yaml"
    bad.write_text("camera:\n  widht: 100\n")
    with pytest.raises(ConfigError, match=r"camera\.widht"):
        load_config("tiny", bad)
    bad.write_text("lidar:\n  beams: -3\n")
    with pytest.raises(ConfigError, match=r"lidar\.beams"):
        load_config("tiny", bad)
    bad.write_text("sessions:\n  - {name: a, weather: sandstorm}\n")
    with pytest.raises(ConfigError, match=r"sessions\.0\.weather"):
        load_config("tiny", bad)


# --- layout and manifest ----------------------------------------------------------------------------


def test_output_layout_and_manifest(tiny, world):
    for f in (
        "world/mesh.ply",
        "world/roads.json",
        "world/origin.json",
        "world/manifest.json",
        "world/config.yaml",
        "metrics.json",
        "pictures/contact_sheet.png",
        "pictures/map.png",
        ".done",
        "world/.done",
    ):
        assert (tiny / f).is_file(), f
    assert not list(tiny.rglob("*.partial"))
    m = world.manifest
    assert m["format_version"] == 1 and m["preset"] == "tiny" and m["seed"] == 7 and len(m["config_hash"]) == 16
    assert world.frame == LocalFrame.from_dict(json.loads((tiny / "world/origin.json").read_text()))
    assert world.frame.utm_epsg == 32630  # Oxford is in UTM zone 30N
    roles = set()
    for s in m["sessions"]:
        for key in (
            "name",
            "file",
            "route_node_ids",
            "length_m",
            "duration_s",
            "start_time_ns",
            "time_of_day",
            "weather",
            "condition",
            "role",
            "camera_rate_hz",
            "lidar_rate_hz",
            "gps_noise",
        ):
            assert key in s, key
        roles.add(s["role"])
        # the log is a rosbag2 folder: metadata.yaml beside <name>_0.mcap
        assert (tiny / s["file"] / "metadata.yaml").is_file() and (tiny / s["file"] / f"{s['name']}_0.mcap").is_file()
        assert (tiny / s["file"]) == session_log(tiny, s["name"]) and (tiny / s["ground_truth"]).is_file()
        # a realistic epoch time on the session's date at its local time of day
        local = dt.datetime.fromisoformat(s["start_time_local"])
        assert abs(s["start_time_ns"] * 1e-9 - local.timestamp()) < 1.0
        assert local.strftime("%H:%M") == s["time_of_day"]
    assert roles == {"train", "test"}
    assert len({s["condition"] for s in m["sessions"]}) == 3
    streets = json.loads((tiny / "metrics.json").read_text())["streets"]
    assert (
        streets["distinct_m"] <= streets["driven_m"] == pytest.approx(sum(s["length_m"] for s in m["sessions"]), abs=10)
    )
    assert session_logs(tiny) == sorted(tiny / s["file"] for s in m["sessions"])
    # the mesh is readable by open3d and is what load_world gives
    import open3d as o3d

    mesh = o3d.io.read_triangle_mesh(str(tiny / "world/mesh.ply"))
    assert len(mesh.triangles) == len(world.mesh.triangles) == m["world"]["triangles"]


def test_road_graph_is_a_town_not_a_grid():
    """On the demo town (geometry only): 3-, 4- and 5-way junctions, dead ends, curves, a long
    straight, many buildings in repeated styles, and parked cars that differ between sessions."""
    from mapkit.synth.sessions import session_parked_cars
    from mapkit.synth.world import Mat, build_town, longest_straight_m

    town = build_town(load_config("places"))
    deg = town.roads.degree()
    assert {1, 3, 4, 5} <= set(deg.tolist()) and deg.max() <= 5
    assert sum(len(r.polyline) > 2 for r in town.roads.roads) >= 10
    assert longest_straight_m(town.roads) > 800
    g = town.geometry
    walls = g.material == Mat.WALL
    style_of_building = {int(o): int(s) for o, s in zip(g.object_id[walls], g.style[walls], strict=True)}
    assert len(style_of_building) > 500
    counts = np.bincount(list(style_of_building.values()))
    assert (counts > 10).sum() >= 8  # every style appears on many buildings (and so on many streets)
    a = session_parked_cars(town, 1)
    b = session_parked_cars(town, 2)
    assert a.n_triangles and (a.n_triangles != b.n_triangles or not np.allclose(a.vertices, b.vertices))


def test_tiny_drives_can_be_georeferenced_aligned_and_localized():
    """The tiny preset's own sessions (planned, not rendered): two or more training drives and a
    test drive, each long and bent enough for GPS to fix its heading (the extent check of
    mapkit.mapping.gps_align, with margin), all on the same streets (alignment, triplets, localization)."""
    from mapkit.mapping.gps_align import planarity
    from mapkit.synth.sessions import plan_sessions
    from mapkit.synth.world import build_town

    cfg = load_config("tiny")
    plans = plan_sessions(cfg, build_town(cfg))
    roles = [p.config.role for p in plans]
    assert roles.count("train") >= 2 and roles.count("test") >= 1
    xy = {p.name: p.drive.world_from_base[:, :2, 3] for p in plans}
    for p in plans:
        extent, ratio = planarity(xy[p.name])
        assert p.drive.length_m > 150 and extent > 5 * 20.0 and ratio > 0.05, (p.name, p.drive.length_m, extent, ratio)
        assert p.drive.duration_s < 40.0  # seconds of driving: what synth and build cost
    from scipy.spatial import cKDTree

    first = cKDTree(xy[plans[0].name])
    for p in plans[1:]:
        near = first.query(xy[p.name])[0] < 5.0
        assert near.mean() > 0.5, (p.name, near.mean())  # most of every drive retraces the first one


def test_new_road_weight_spreads_planned_routes_over_more_streets():
    """session_plan.new_road_weight: later planned routes steer away from roads earlier ones took
    (more distinct streets for held-out places); at 0 the routes are the ones planned
    without the option (the presets' drives do not move)."""
    from mapkit.synth.sessions import plan_sessions
    from mapkit.synth.world import build_town

    base = load_config("tiny").model_dump(mode="json")
    four = [{**base["sessions"][0], "name": f"d{k}", "follow": None, "length_m": 250.0} for k in range(4)]
    cfg0 = load_config("tiny", overrides={"sessions": four})
    town = build_town(cfg0)

    def plans(weight: float) -> list:
        return plan_sessions(
            load_config("tiny", overrides={"sessions": four, "session_plan": {"new_road_weight": weight}}), town
        )

    independent, weighted = plans(0.0), plans(4.0)
    assert [p.drive.route_roads for p in independent] == [p.drive.route_roads for p in plan_sessions(cfg0, town)]

    def distinct(ps):
        return len(set().union(*(set(p.drive.route_roads) for p in ps)))

    assert distinct(weighted) > distinct(independent), (distinct(weighted), distinct(independent))
    assert all(town.anchor["road"] in p.drive.route_roads for p in weighted)  # every route still drives the anchor road
    # the street length synth reports (metrics.json "streets"): 4 drives of 250 m, more of it distinct when spread
    a, b = street_coverage(independent), street_coverage(weighted)
    assert a["driven_m"] == pytest.approx(1000, abs=8) and b["driven_m"] == pytest.approx(1000, abs=8)
    assert 250 <= a["distinct_m"] < b["distinct_m"] <= b["driven_m"], (a, b)


# --- determinism ------------------------------------------------------------------------------------


def test_tiny_is_deterministic_whatever_the_worker_count(tiny, tmp_path):
    """The same town again, its sessions rendered by two worker processes instead of one: the same files (the
    worker count is not in the manifest's hash)."""
    again = synthesize(preset="tiny", out=tmp_path / "again", overrides={**SHORT, "workers": 2}, progress=False)
    for f in ("world/mesh.ply", "world/roads.json", "world/manifest.json"):
        assert (tiny / f).read_bytes() == (again / f).read_bytes(), f
    for s in load_world(tiny).sessions:
        name = s["name"]
        for suffix in (".gt.tum", ".camera.tum", ".parked_cars.ply"):
            assert (tiny / "sessions" / f"{name}{suffix}").read_bytes() == (
                again / "sessions" / f"{name}{suffix}"
            ).read_bytes()
        a, b = _images(tiny / s["file"]), _images(again / s["file"])
        assert len(a) == len(b) > 10
        for (sa, ia), (sb, ib) in zip(a, b, strict=True):
            assert sa == sb and np.array_equal(ia, ib)


def test_resume_skips_finished_sessions_and_overwrite_redoes_them(tmp_path):
    cfg = tmp_path / "one.yaml"
    cfg.write_text(
        "sessions:\n  - {name: only, role: train, time: '12:00', weather: cloudy, length_m: 8.0, speed_mps: 8.0}\n"
        "camera: {width: 96, height: 72}\nlidar: {azimuth_steps: 128}\n"
    )
    out = synthesize(preset="tiny", out=tmp_path / "t", config=cfg, progress=False)
    mcap = session_log(out, "only") / "only_0.mcap"
    t0 = mcap.stat().st_mtime_ns
    synthesize(preset="tiny", out=out, config=cfg, progress=False)
    assert mcap.stat().st_mtime_ns == t0
    assert json.loads((out / "metrics.json").read_text())["sessions"][0]["skipped"]
    synthesize(preset="tiny", out=out, config=cfg, overwrite=True, progress=False)
    assert mcap.stat().st_mtime_ns != t0
    assert not list(out.rglob("*.partial"))


# --- the logs ---------------------------------------------------------------------------------------


def test_video_rate_records_every_session_faster_and_keeps_its_own_image_rate(tmp_path):
    """camera.record_rate_hz: the camera records at that rate whatever the session's own rate,
    which the manifest keeps as image_rate_hz (what `mapkit demo --record-rate-hz` maps from and
    sub-samples its image databases to)."""
    one = {**SHORT, "sessions": SHORT["sessions"][:1], "lidar": {"enabled": False}}
    own = load_config("tiny", overrides=one).camera.rate_hz
    out = synthesize(
        preset="tiny", out=tmp_path / "video", overrides={**one, "camera": {"record_rate_hz": 2 * own}}, progress=False
    )
    s = load_world(out).sessions[0]
    assert s["camera_rate_hz"] == 2 * own and s["image_rate_hz"] == own
    stamps = np.array([st for st, _ in _images(out / s["file"])])
    assert len(stamps) == pytest.approx(s["duration_s"] * 2 * own, abs=2)
    assert np.median(np.diff(stamps)) * 1e-9 == pytest.approx(1 / (2 * own), rel=1e-3)
    assert load_world(out).config.camera.record_rate_hz == 2 * own  # the resolved config records it


def test_topics_types_and_stamps(tiny, world):
    s = world.sessions[0]
    log = McapLog(tiny / s["file"])
    types = {st.topic: st.msgtype for st in log.streams()}
    assert types == TOPICS
    last: dict[str, int] = {}
    n = {t: 0 for t in TOPICS}
    for msg in log.messages():
        assert isinstance(msg.stamp_ns, int)
        assert msg.stamp_ns >= s["start_time_ns"]
        key = msg.topic + getattr(msg.record, "child_frame", "")
        assert msg.stamp_ns > last.get(key, -1) or msg.topic == "/tf_static"
        last[key] = msg.stamp_ns
        n[msg.topic] += 1
    log.close()
    dur = s["duration_s"]
    assert n["/camera/front/image"] == pytest.approx(dur * s["camera_rate_hz"], abs=2)
    assert n["/lidar/points"] == pytest.approx(dur * s["lidar_rate_hz"], abs=2)
    assert n["/gps/fix"] == pytest.approx(dur * s["gps_rate_hz"], abs=1)
    assert n["/gps/fix"] < n["/camera/front/image"]
    assert n["/ground_truth/odom"] == len(gt_poses(tiny, s["name"])[0])
    log = McapLog(tiny / s["file"])
    scan = next(log.records(StreamKind.LIDAR))
    assert (
        scan.frame_id == "lidar"
        and scan.point_time_s is not None
        and scan.ring is not None
        and scan.intensity is not None
    )
    assert scan.point_time_s.min() >= 0 and scan.point_time_s.max() < 1.0 / s["lidar_rate_hz"]
    assert scan.ring.max() == world.config.lidar.beams - 1
    gt = next(log.records(StreamKind.POSE))
    assert (gt.parent_frame, gt.child_frame) == ("world", "base_link")
    log.close()


def test_tf_static_equals_configured_extrinsics(tiny, world):
    log = McapLog(tiny / world.sessions[0]["file"])
    tf = {t.child_frame: t for t in log.transforms()}
    log.close()
    want = extrinsics(world.config)
    assert set(tf) == set(want) == {"camera_front", "lidar", "gps", "imu"}
    for child, T in want.items():
        assert tf[child].parent_frame == "base_link"
        np.testing.assert_allclose(tf[child].parent_from_child, T, atol=1e-9)
    # the camera frame is an optical frame: z forward (base x), x right (base -y), y down (base -z)
    R = tf["camera_front"].parent_from_child[:3, :3]
    assert R[:, 2] @ [1, 0, 0] > 0.99 and R[:, 0] @ [0, -1, 0] > 0.99 and R[:, 1] @ [0, 0, -1] > 0.99


def test_lidar_points_undistorted_with_their_time_lie_on_the_mesh(tiny, world):
    s = world.sessions[0]["name"]
    V, T = world.session_mesh_arrays(s)
    scene = ground_truth_mesh_scene(V, T)
    import open3d as o3d

    gs, world_from_base = gt_poses(tiny, s)
    log = McapLog(session_log(tiny, s))
    base_from_lidar = {t.child_frame: t.parent_from_child for t in log.transforms()}["lidar"]
    scans = [sc for k, sc in enumerate(log.records(StreamKind.LIDAR)) if k in (2, 12)]
    log.close()
    sigma = world.config.lidar.range_noise_m
    for scan in scans:
        t_ns = scan.stamp_ns + np.round(scan.point_time_s.astype(np.float64) * 1e9).astype(np.int64)
        wfb, ok = interpolate_poses(gs, world_from_base, t_ns)
        assert ok.all()
        wfl = wfb @ base_from_lidar
        p = np.einsum("nij,nj->ni", wfl[:, :3, :3], scan.points_xyz.astype(np.float64)) + wfl[:, :3, 3]
        dist = scene.compute_distance(o3d.core.Tensor(p.astype(np.float32))).numpy()
        assert np.median(dist) < 0.01 and np.percentile(dist, 99) < 0.02 and dist.max() < 5 * sigma + 0.002
        # motion distortion is there: the pose at the stamp for every point is centimetres to metres off
        w0 = interpolate_poses(gs, world_from_base, np.array([scan.stamp_ns]))[0][0] @ base_from_lidar
        raw = scene.compute_distance(
            o3d.core.Tensor((scan.points_xyz @ w0[:3, :3].T + w0[:3, 3]).astype(np.float32))
        ).numpy()
        assert np.percentile(raw, 99) > 0.2


def test_pixel_rays_hit_the_mesh_at_the_rendered_depth(tiny, world):
    """Re-render a logged frame from its ground-truth camera pose: the image is the logged one, and
    an independent ray through a pixel (from the logged intrinsics) hits the mesh at its depth."""
    import open3d as o3d

    from mapkit.core.threads import single_thread_blas
    from mapkit.synth.sessions import TOPIC_IMAGE

    s = world.sessions[2]  # night: lamps, headlights, noise
    name = s["name"]
    stamps, world_from_cam = camera_poses(tiny, name)
    k = len(stamps) // 2
    log = McapLog(tiny / s["file"])
    info = next(iter(log.camera_infos().values()))
    logged = [f for f in log.records(StreamKind.IMAGE, TOPIC_IMAGE)][k]
    log.close()
    assert logged.stamp_ns == stamps[k]
    renderer = world.renderer(name)
    gs, gp = gt_poses(tiny, name)
    wfb = interpolate_poses(gs, gp, stamps[k : k + 1])[0][0]
    with single_thread_blas():
        frame = renderer.render_camera(
            world_from_cam[k], world.conditions(name), np.random.default_rng([s["seed"], 5, k]), wfb
        )
    ok, buf = cv2.imencode(".jpg", frame.rgb[..., ::-1])
    diff = np.abs(cv2.imdecode(buf, cv2.IMREAD_COLOR).astype(int) - logged.image.astype(int))
    # the pose file rounds to 1 um and 1e-9: a few pixels on edges may change, nothing else
    assert diff.mean() < 0.5 and (diff == 0).mean() > 0.95
    V, T = world.session_mesh_arrays(name)
    scene = ground_truth_mesh_scene(V, T)
    rng = np.random.default_rng(0)
    v, u = rng.integers(0, info.height, 400), rng.integers(0, info.width, 400)
    d_cam = np.stack([(u - info.cx) / info.fx, (v - info.cy) / info.fy, np.ones(len(u))], 1)
    d_cam /= np.linalg.norm(d_cam, axis=1, keepdims=True)
    d_w = d_cam @ world_from_cam[k][:3, :3].T
    rays = np.hstack([np.broadcast_to(world_from_cam[k][:3, 3], d_w.shape), d_w]).astype(np.float32)
    t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    depth = frame.depth_m[v, u]
    hit = np.isfinite(depth)
    assert hit.mean() > 0.5
    np.testing.assert_array_equal(np.isfinite(t), hit)
    np.testing.assert_allclose(t[hit] * d_cam[hit, 2], depth[hit], rtol=1e-4, atol=2e-3)


def test_gps_error_statistics_match_the_configuration():
    cfg = GpsConfig(
        rate_hz=1.0,
        white_sigma_m=2.0,
        bias_sigma_m=3.0,
        bias_tau_s=120.0,
        multipath_rate_hz=0.01,
        multipath_duration_s=10.0,
        multipath_sigma_m=8.0,
        dropout_rate_hz=0.005,
        dropout_duration_s=6.0,
        vertical_factor=2.0,
    )
    model = GpsErrorModel(cfg)
    n = 400_000
    e = model.simulate(n, np.random.default_rng(3))
    assert e.white_enu[:, :2].std() == pytest.approx(2.0, rel=0.02)
    assert e.white_enu[:, 2].std() == pytest.approx(4.0, rel=0.02)
    b = e.bias_enu[:, 0]
    assert b.std() == pytest.approx(3.0, rel=0.08)
    lag = int(cfg.bias_tau_s * cfg.rate_hz)
    assert np.corrcoef(b[:-lag], b[lag:])[0, 1] == pytest.approx(np.exp(-1), abs=0.05)
    assert np.corrcoef(b[:-1], b[1:])[0, 1] == pytest.approx(np.exp(-1 / 120), abs=0.002)
    assert e.n_multipath_events / (n / cfg.rate_hz) == pytest.approx(0.01, rel=0.05)
    jumps = e.multipath_enu[:, :2]
    assert jumps[np.any(jumps != 0, axis=1)].std() == pytest.approx(8.0, rel=0.1)
    assert (~e.valid).mean() == pytest.approx(model.expected_dropout_fraction, rel=0.1)
    assert model.covariance_enu_m2[0, 0] == pytest.approx(4.0 + 9.0)


def test_gps_fixes_in_the_log_are_the_antenna_plus_bounded_error(tiny, world):
    s = world.sessions[0]
    log = McapLog(tiny / s["file"])
    fixes = list(log.records(StreamKind.GPS))
    log.close()
    ok = [f for f in fixes if f.has_fix]
    assert ok and all(f.covariance_enu_m2 is not None for f in ok)
    gs, gp = gt_poses(tiny, s["name"])
    wfb, _ = interpolate_poses(gs, gp, np.array([f.stamp_ns for f in ok]))
    antenna = (wfb @ extrinsics(world.config)["gps"])[:, :3, 3]
    enu = world.frame.geodetic_to_enu(
        np.array([f.lat_deg for f in ok]), np.array([f.lon_deg for f in ok]), np.array([f.alt_m for f in ok])
    )
    err = np.linalg.norm((enu - antenna)[:, :2], axis=1)
    assert err.max() < 40.0 and err.mean() > 0.1


def test_imu_measures_gravity_and_the_turn_rate(tiny, world):
    s = world.sessions[0]["name"]
    log = McapLog(session_log(tiny, s))
    imu = list(log.records(StreamKind.IMU))
    log.close()
    acc = np.array([m.linear_acceleration_m_s2 for m in imu])
    gyro = np.array([m.angular_velocity_rad_s for m in imu])
    assert acc[:, 2].mean() == pytest.approx(9.81, abs=0.2)
    gs, gp = gt_poses(tiny, s)
    yaw = np.unwrap(np.arctan2(gp[:, 1, 0], gp[:, 0, 0]))
    t = (np.array([m.stamp_ns for m in imu]) - imu[0].stamp_ns) * 1e-9
    assert np.trapezoid(gyro[:, 2], t) == pytest.approx(yaw[-1] - yaw[0], abs=0.02)


def test_conditions_change_appearance_but_not_geometry(tiny, world):
    """Same place, sessions under different conditions: images differ strongly; the static scene is
    identical (depth differs at most where parked cars moved)."""
    from mapkit.core.threads import single_thread_blas

    town = world.town()
    names = [s["name"] for s in world.sessions]
    _, wfc = camera_poses(tiny, names[0])
    pose = wfc[len(wfc) // 2]
    frames = []
    with single_thread_blas():
        for n in names:
            frames.append(world.renderer(n, town).render_camera(pose, world.conditions(n), np.random.default_rng(0)))
    grey = [cv2.cvtColor(f.rgb, cv2.COLOR_RGB2GRAY).astype(float) for f in frames]
    for i in range(len(grey)):
        for j in range(i + 1, len(grey)):
            assert np.abs(grey[i] - grey[j]).mean() > 20
            same = frames[i].material == frames[j].material
            static = same & (frames[i].material < 14)  # not a car
            a, b = frames[i].depth_m[static], frames[j].depth_m[static]
            assert np.array_equal(np.isinf(a), np.isinf(b))
            np.testing.assert_allclose(a[np.isfinite(a)], b[np.isfinite(b)], atol=1e-4)


# --- external trajectories ----------------------------------------------------------------------------


def _curve(n=60, dt_s=0.1):
    t = np.arange(n) * dt_s
    x = 8.0 * t
    y = 10.0 * np.sin(t / 3.0)
    return t, x, y


def test_external_trajectory_drives_a_session_with_the_town_around_it(tmp_path):
    from mapkit.core.geometry import make_pose, yaw_rotation
    from mapkit.io.trajectory import write_tum

    t, x, y = _curve()
    yaw = np.arctan2(np.gradient(y), np.gradient(x))
    stamps = (1_400_000_000 + t) * 1e9
    traj = tmp_path / "drive.tum"
    write_tum(
        traj, np.round(stamps).astype(np.int64), make_pose(yaw_rotation(yaw), np.stack([x, y, np.zeros_like(x)], 1))
    )
    cfg = tmp_path / "ext.yaml"
    cfg.write_text(
        "sessions:\n  - {name: ext, role: train, time: '12:00', weather: sunny, length_m: 30.0, max_duration_s: 2.0}\n"
        "camera: {width: 96, height: 72, rate_hz: 5.0}\nlidar: {azimuth_steps: 128}\n"
    )
    out = synthesize(preset="tiny", out=tmp_path / "ext", config=cfg, trajectory=traj, progress=False)
    world = load_world(out)
    assert world.session("ext")["trajectory_source"] == "tum:drive.tum"
    gs, gp = gt_poses(out, "ext")
    assert (gs[-1] - gs[0]) * 1e-9 == pytest.approx(2.0, abs=0.011)
    # the session follows the file's path (shifted to be centred in the town)
    rel = gp[:, :2, 3] - gp[0, :2, 3]
    want = np.stack([np.interp((gs - gs[0]) * 1e-9, t, x) - x[0], np.interp((gs - gs[0]) * 1e-9, t, y) - y[0]], 1)
    np.testing.assert_allclose(rel, want, atol=1e-3)
    assert any(r.kind == "track" for r in world.roads.roads)
    assert world.manifest["world"]["buildings"] > 10


def test_external_trajectory_readers(tmp_path):
    from mapkit.synth.sessions import read_external_trajectory

    t, x, y = _curve(20)
    kitti = tmp_path / "poses.txt"
    # KITTI camera frame: x right, y down, z forward; ground motion in x-z
    rows = [f"1 0 0 {-yy:.6f} 0 1 0 0 0 0 1 {xx:.6f}" for xx, yy in zip(x, y, strict=True)]
    kitti.write_text("\n".join(rows) + "\n")
    e = read_external_trajectory(kitti)
    np.testing.assert_allclose(e.xy, np.stack([x, y], 1), atol=1e-6)
    assert e.stamps_ns[1] == 100_000_000
    csv = tmp_path / "ins.csv"
    lines = ["timestamp,ins_status,latitude,longitude,altitude,northing,easting,down,utm_zone,roll,pitch,yaw"]
    for k, (xx, yy) in enumerate(zip(x, y, strict=True)):
        lines.append(
            f"{1418131260000000 + k * 100000},INS_SOLUTION_GOOD,51.7601,-1.2610,110.0,"
            f"{5735000 + yy:.4f},{620000 + xx:.4f},-110.0,30U,0,0,0"
        )
    csv.write_text("\n".join(lines) + "\n")
    e = read_external_trajectory(csv)
    assert e.origin_latlon == (51.7601, -1.2610)
    np.testing.assert_allclose(e.xy, np.stack([x - x[0], y - y[0]], 1), atol=1e-3)
    assert e.stamps_ns[1] == 100_000_000
    bad = tmp_path / "bad.txt"
    bad.write_text("1 2 3\n")
    with pytest.raises(MapkitError):
        read_external_trajectory(bad)


def test_load_world_rejects_a_folder_that_is_not_a_town(tmp_path):
    with pytest.raises(MapkitError, match="not a synthesized town"):
        load_world(tmp_path)
    with pytest.raises(MapkitError, match="no ground truth"):
        gt_poses(tmp_path, "x")


def test_kiss_icp_command_line_reads_the_lidar_topic_and_tracks_the_ground_truth(tiny, world, tmp_path, monkeypatch):
    """An outside tool: kiss-icp's own pipeline (MCAP dataloader) on a session's /lidar/points."""
    import shutil

    # the command beside this interpreter (a virtual environment's bin/ need not be on PATH)
    monkeypatch.setenv("PATH", os.pathsep.join([str(Path(sys.executable).parent), os.environ.get("PATH", "")]))
    assert shutil.which("kiss_icp_pipeline"), "kiss-icp's command line is a dependency of mapkit"
    from bench.kiss_icp_on_synth import evaluate, run_kiss_icp

    name = world.sessions[2]["name"]
    mcap = tiny / world.session(name)["file"]
    poses, _ = run_kiss_icp(mcap, tmp_path)
    row = evaluate(tiny, name, poses, mcap)
    assert row["scans"] >= 20
    assert row["ate_rmse_m"] < 0.5  # after a rigid alignment; kiss-icp needs a few scans to pick up speed
