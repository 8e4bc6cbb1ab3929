"""Loop closures (mapkit.mapping.loop_closure and the factor graph's loop factors) against known answers.

- The graph: the rounded-rectangle loop of tests/test_factor_graph.py driven a lap and 80 m on, its
  odometry drifting by a known yaw-rate bias and a height ramp, GPS with a bias; a loop edge equal
  to the true relative pose of two poses a lap apart, or the same edge moved metres across the road.
- ICP on real geometry: LiDAR sweeps ray cast in the synthetic town (the tiny preset's world and a
  short drive through it), a second pass of one place rendered from poses moved by a known rigid
  transform that the estimate does not know of, and a pass of another place the estimate puts there.
- End to end: a synthetic town built around a closed route driven a lap and 45 m on from rest,
  built with ``georef: {fuse: true}`` with and without loop closures, measured against the town's truth.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_factor_graph import LOOSE, gps_fixes, true_drive

from mapkit.core.geometry import interpolate_poses, invert_pose, make_pose, rotation_angle_rad, yaw_rotation
from mapkit.core.runio import read_timings
from mapkit.core.types import LidarScan
from mapkit.mapping.factor_graph import FactorGraphConfig, LoopClosures, LoopEdge, fuse_session
from mapkit.mapping.loop_closure import (
    LoopCandidate,
    LoopReason,
    loop_closures,
    propose_loops,
    read_scans,
    scans_needed,
    verify_loop,
)

pytest.importorskip("gtsam")
pytest.importorskip("open3d")

LAP_M = 340.0  # true_drive's loop: its heading turns once every 340 m


# --- the graph ---------------------------------------------------------------------------------------


def drifting_odometry(truth: np.ndarray, yaw_rad_per_m: float, climb_m_per_m: float) -> np.ndarray:
    """The truth's steps, each turned by ``yaw_rad_per_m`` and raised by ``climb_m_per_m`` per metre of its length
    (a gyro-like yaw-rate bias and a height ramp), chained from the identity."""
    steps = invert_pose(truth[:-1]) @ truth[1:]
    d = np.linalg.norm(steps[:, :3, 3], axis=1)
    drift = make_pose(
        Rotation.from_rotvec(np.outer(d * yaw_rad_per_m, [0.0, 0.0, 1.0])).as_matrix(),
        np.outer(d * climb_m_per_m, [0.0, 0.0, 1.0]),
    )
    out = [np.eye(4)]
    for step in steps @ drift:
        out.append(out[-1] @ step)
    return np.stack(out)


@pytest.fixture(scope="module")
def loop_drive():
    """(stamps, truth, odometry, GPS, a, b): a lap and 80 m of the loop at 1 m a pose; poses a and b are a lap
    apart. The odometry turns 0.005 deg/m too much and climbs 1 cm/m (2.1 deg and 4.2 m over the drive), within
    LOOSE's model."""
    stamps, truth = true_drive(length_m=LAP_M + 80.0)
    odom = drifting_odometry(truth, np.radians(0.005), 0.01)
    gps, _ = gps_fixes(stamps, truth, np.random.default_rng(5), bias=np.array([0.8, -0.6, 0.5]))
    a = 30
    b = a + int(LAP_M)
    return stamps, truth, odom, gps, a, b


def relative(P: np.ndarray, a: int, b: int) -> np.ndarray:
    return invert_pose(P[a]) @ P[b]


def end_to_start_error_m(P: np.ndarray, truth: np.ndarray, a: int, b: int) -> float:
    return float(np.linalg.norm((invert_pose(relative(truth, a, b)) @ relative(P, a, b))[:3, 3]))


EDGE_COVARIANCE = np.diag(
    np.repeat([FactorGraphConfig().loop_floor_rotation_rad, FactorGraphConfig().loop_floor_translation_m], 3) ** 2
)


def test_a_true_loop_edge_closes_the_drift(loop_drive):
    """Without the loop the GPS-held solution is still metres off where the drive comes back (the height ramp: GPS's
    vertical is weak); with the true relative pose as a loop edge the end-to-start error falls to millimetres, the edge
    is satisfied at the solution and the stats count it."""
    stamps, truth, odom, gps, a, b = loop_drive
    assert end_to_start_error_m(odom, truth, a, b) > 3.0  # the drift the loop has to remove
    plain = fuse_session(stamps, odom, gps, None, LOOSE)
    assert end_to_start_error_m(plain.enu_from_base, truth, a, b) > 1.5
    assert "loop_candidates" not in plain.stats
    edge = LoopEdge(int(stamps[a]), int(stamps[b]), relative(truth, a, b), EDGE_COVARIANCE)
    fused = fuse_session(stamps, odom, gps, None, LOOSE, loops=LoopClosures([edge], ["fitness", "fitness", "RMSE"]))
    assert end_to_start_error_m(fused.enu_from_base, truth, a, b) < 0.02
    s = fused.stats
    assert (
        s["loop_candidates"] == 4
        and s["loop_accepted"] == 1
        and s["loop_rejected_by_reason"] == {"fitness": 2, "RMSE": 1}
    )
    (r,) = s["loop_residuals"]
    assert r["stamps_ns"] == [int(stamps[a]), int(stamps[b])] and r["translation_m"] < 0.02 and r["sigmas"] < 1.0
    assert s["loop_downweighted"] == 0
    # the height ramp is gone along the whole drive, not only at the two poses
    assert np.max(np.abs(fused.enu_from_base[:, 2, 3] - truth[:, 2, 3])) < 0.5 * np.max(
        np.abs(plain.enu_from_base[:, 2, 3] - truth[:, 2, 3])
    )


def test_a_loop_edge_metres_off_gives_way(loop_drive):
    """The same edge moved 12 m across the road (a wrong place that passed ICP): the GPS-held rest of the graph
    contradicts it, the Cauchy loss lets it go, the solution moves less than a tenth of that from the one without loops
    and the stats show the edge metres off its solution and down-weighted. (ICP's correction gate keeps out loops more
    than loop_max_correction_m off the estimate; nearer than about 2 loop_robust_k of the graph's own sigmas, which
    GPS's bias random walk makes about a metre across the 34 s between the passes, a loop holds.)"""
    stamps, truth, odom, gps, a, b = loop_drive
    plain = fuse_session(stamps, odom, gps, None, LOOSE)
    wrong = relative(truth, a, b) @ make_pose(np.eye(3), [0.0, 12.0, 0.0])
    fused = fuse_session(
        stamps,
        odom,
        gps,
        None,
        LOOSE,
        loops=LoopClosures([LoopEdge(int(stamps[a]), int(stamps[b]), wrong, EDGE_COVARIANCE)]),
    )
    moved = np.linalg.norm(fused.enu_from_base[:, :3, 3] - plain.enu_from_base[:, :3, 3], axis=1)
    assert np.max(moved) < 1.2, np.max(moved)
    (r,) = fused.stats["loop_residuals"]
    assert r["translation_m"] > 10.0 and fused.stats["loop_downweighted"] == 1


def test_loops_off_and_bad_stamps(loop_drive):
    stamps, truth, odom, gps, a, b = loop_drive
    edge = LoopEdge(int(stamps[a]), int(stamps[b]), relative(truth, a, b), EDGE_COVARIANCE)
    off = fuse_session(
        stamps[:60],
        odom[:60],
        None,
        None,
        LOOSE.model_copy(update={"loop_closures": False}),
        loops=LoopClosures([LoopEdge(int(stamps[5]), int(stamps[55]), edge.a_from_b, EDGE_COVARIANCE)]),
    )
    assert off.stats["loops"] == "not used: loop_closures is off" and off.stats["loop_residuals"] == []
    from mapkit.core.errors import InputError

    with pytest.raises(InputError, match="loops.*not a pose"):
        fuse_session(
            stamps[:60],
            odom[:60],
            None,
            None,
            LOOSE,
            loops=LoopClosures([LoopEdge(int(stamps[5]) + 1, int(stamps[55]), edge.a_from_b, EDGE_COVARIANCE)]),
        )


def test_proposal_finds_the_revisit_once_per_stretch(loop_drive):
    """On the drifted odometry (4 m off after a lap) the proposal finds the pairs a lap apart, each pair at least
    loop_min_travel_m apart along the route, at most one per loop_min_separation_m, nearest first; the 80 m driven again
    give about 8 of them. On the true poses every proposed pair is within the radius."""
    stamps, truth, odom, _, _, _ = loop_drive
    cfg = FactorGraphConfig()
    kf = np.arange(len(stamps))
    for poses in (odom, truth):
        c = propose_loops(poses, kf, cfg)
        assert 5 <= len(c) <= 10, len(c)
        assert all(abs(x.travel_m - LAP_M) < 10 for x in c)  # only the revisit: 340 m driven between
        d = [x.distance_m for x in c]
        assert d == sorted(d)
        at = np.array([[x.a, x.b] for x in c], float)
        gaps = np.abs(at[:, None] - at[None]) + np.eye(len(c))[:, :, None] * 1e9
        assert gaps.min() >= cfg.loop_min_separation_m - 1  # 1 m a pose
    assert max(d) <= cfg.loop_radius_m
    need = scans_needed(c, len(stamps), cfg)
    want = {x.a + k for x in c for k in range(-2, 3)} | {x.b + k for x in c for k in range(-2, 3)}
    assert set(need) == {i for i in want if 0 <= i < len(stamps)}


# --- ICP on the synthetic town -----------------------------------------------------------------------


@pytest.fixture(scope="module")
def street(tmp_path_factory):
    """The tiny preset's world with one 60 m drive through it (the truth this test renders sweeps along), its renderer
    and the LiDAR's mount."""
    from mapkit.synth import gt_poses, load_world, synthesize
    from mapkit.synth.sensors import FRAME_LIDAR, extrinsics

    out = synthesize(
        preset="tiny",
        out=tmp_path_factory.mktemp("loop-street") / "town",
        progress=False,
        overrides={
            "sessions": [
                {
                    "name": "street",
                    "role": "train",
                    "time": "12:00",
                    "weather": "sunny",
                    "length_m": 60.0,
                    "speed_mps": 8.0,
                    "camera_rate_hz": 0.5,
                }
            ],
            "camera": {"width": 64, "height": 48},
            "motion": {"start_from_rest": False},
        },
    )
    world = load_world(out)
    stamps, truth = gt_poses(out, "street")
    return world.renderer("street"), stamps, truth, extrinsics(world.config)[FRAME_LIDAR]


def render_pass(
    street, first_ns: int, n: int, move: np.ndarray, stamp0_ns: int
) -> tuple[list[LidarScan], np.ndarray, np.ndarray]:
    """``n`` sweeps at 10 Hz along the truth from ``first_ns``, the vehicle moved by ``move`` (world frame), stamped
    from ``stamp0_ns``: (scans as a log holds them, the pose stamps kiss-icp would give them (each sweep's last
    point), the unmoved true poses there, which is where an estimate that does not know of ``move`` puts them)."""
    renderer, gt_stamps, truth, base_from_lidar = street
    col_ns = np.round(renderer.lidar_col_time_s * 1e9).astype(np.int64)
    sweep_ns = 100_000_000
    starts = first_ns + np.arange(n, dtype=np.int64) * sweep_ns
    scans, poses = [], []
    for k, t in enumerate(starts):
        at, _ = interpolate_poses(gt_stamps, truth, t + col_ns)
        sweep = renderer.scan_lidar(move @ at @ base_from_lidar, np.random.default_rng(k))
        scans.append(
            LidarScan(
                int(stamp0_ns + k * sweep_ns), "lidar", sweep.points_xyz, sweep.intensity, sweep.time_s, sweep.ring
            )
        )
        poses.append(interpolate_poses(gt_stamps, truth, np.array([t + col_ns[-1]]))[0][0])
    return scans, stamp0_ns + np.arange(n, dtype=np.int64) * sweep_ns + col_ns[-1], np.stack(poses)


def two_passes(street, move: np.ndarray, other_place_s: float = 0.0):
    """A place seen on a first pass (7 sweeps from 2 s into the drive) and again, 100 s later, from the vehicle moved by
    ``move`` (or at the place ``other_place_s`` seconds further along the drive): the scans read back as local maps
    placed with an estimate that puts both passes where the first one was. Returns (scans, estimate, the true
    a_from_b of the two middle sweeps, the candidate)."""
    _, gt_stamps, truth, base_from_lidar = street
    t0 = int(gt_stamps[0]) + 2_000_000_000
    scans_a, stamps_a, est_a = render_pass(street, t0, 7, np.eye(4), t0)
    first_b = t0 + int(other_place_s * 1e9)
    scans_b, stamps_b, true_b = render_pass(street, first_b, 7, move, t0 + 100_000_000_000)
    stamps = np.concatenate([stamps_a, stamps_b])
    estimate = np.concatenate([est_a, est_a])  # the estimate puts the second pass on the first
    a, b = 3, 10
    truth_b = move @ true_b[3]
    cfg = FactorGraphConfig()
    cand = LoopCandidate(a, b, 0.0, 400.0)
    scans = read_scans(
        scans_a + scans_b, stamps, estimate, scans_needed([cand], len(stamps), cfg), lambda frame: base_from_lidar, cfg
    )
    return scans, estimate, invert_pose(est_a[3]) @ truth_b, cand


def test_icp_recovers_a_known_offset_between_two_passes(street):
    """The second pass 1.8 m further along, 1.2 m to the right and turned 2 deg (moved about the first pass's middle
    pose): ICP of the two local maps recovers the relative pose within 2 cm and 0.05 deg, from an estimate that thought
    them one place, and accepts it with a covariance that is the floor and a little more."""
    _, gt_stamps, truth, _ = street
    pivot = interpolate_poses(gt_stamps, truth, np.array([int(gt_stamps[0]) + 2_300_000_000 + 99_800_000]))[0][0]
    move = pivot @ make_pose(yaw_rotation(np.radians(2.0)), [1.8, -1.2, 0.0]) @ invert_pose(pivot)
    scans, estimate, true_a_from_b, cand = two_passes(street, move)
    check = verify_loop(cand, scans, estimate, FactorGraphConfig())
    assert check.accepted, check.text
    err = invert_pose(true_a_from_b) @ check.a_from_b
    assert np.linalg.norm(err[:3, 3]) < 0.02 and np.degrees(rotation_angle_rad(err[:3, :3])) < 0.05, err
    assert check.correction_m == pytest.approx(np.linalg.norm(true_a_from_b[:3, 3]), abs=0.05)
    assert check.fitness > 0.8 and check.rmse_m < 0.05 and check.constraint > 0.05
    sig = np.sqrt(np.diag(check.covariance))
    floor = np.sqrt(np.diag(EDGE_COVARIANCE))
    assert np.all(sig >= floor) and np.all(sig < 1.5 * floor)
    closures = loop_closures([check], np.arange(14) * 1000)
    assert (
        len(closures.edges) == 1 and closures.rejected == [] and np.allclose(closures.edges[0].a_from_b, check.a_from_b)
    )


def test_icp_rejects_another_place_with_its_reason(street):
    """The second pass 4 s (32 m) further along the street, which the estimate puts on the first: not accepted, and
    the verdict names the gate with its figures; the graph's stats count it by that reason."""
    scans, estimate, _, cand = two_passes(street, np.eye(4), other_place_s=4.0)
    check = verify_loop(cand, scans, estimate, FactorGraphConfig())
    assert not check.accepted and check.reason in (
        LoopReason.FITNESS,
        LoopReason.RMSE,
        LoopReason.DEGENERATE,
        LoopReason.CORRECTION,
    ), check.text
    assert check.detail and any(ch.isdigit() for ch in check.detail)
    assert loop_closures([check], np.arange(14)).rejected == [check.reason.value]


def test_a_missing_scan_is_a_warning_and_a_reason(street):
    """A local map's keyframe scan absent from the log: read_scans warns naming the stamp, the check says why."""
    from mapkit.core.errors import InputWarning

    _, gt_stamps, truth, base_from_lidar = street
    t0 = int(gt_stamps[0]) + 2_000_000_000
    scans, stamps, est = render_pass(street, t0, 7, np.eye(4), t0)
    cfg = FactorGraphConfig()
    cand = LoopCandidate(1, 5, 0.0, 400.0)
    with pytest.warns(InputWarning, match=f"no LiDAR scan found for 1 of the 7 poses.*stamp {int(stamps[5])}"):
        got = read_scans(
            scans[:5] + scans[6:], stamps, est, scans_needed([cand], len(stamps), cfg), lambda f: base_from_lidar, cfg
        )
    check = verify_loop(cand, got, est, cfg)
    assert check.reason is LoopReason.SCANS_MISSING and "keyframe b" in check.text


# --- end to end --------------------------------------------------------------------------------------


def loop_route(
    path, size_m: tuple[float, float, float] = (90.0, 70.0, 12.0), lap_extra_m: float = 40.0, speed: float = 9.0
) -> None:
    """A TUM file of a rounded rectangle (width, height, corner radius) driven from rest a lap and ``lap_extra_m`` on,
    at ``speed`` (accelerating at 1.5 m/s^2, braking at 2 m/s^2 to a stop)."""
    from mapkit.io.trajectory import write_tum

    w, h, r = size_m
    corners = [(w / 2 - r, h / 2 - r), (-w / 2 + r, h / 2 - r), (-w / 2 + r, -h / 2 + r), (w / 2 - r, -h / 2 + r)]
    arcs = [
        np.stack([cx + r * np.cos(th), cy + r * np.sin(th)], 1)
        for k, (cx, cy) in enumerate(corners)
        for th in [np.linspace(k * np.pi / 2, (k + 1) * np.pi / 2, 60)]
    ]
    ring = np.vstack(arcs + [arcs[0][:1]])
    s_ring = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(ring, axis=0), axis=1))])
    total = s_ring[-1] + lap_extra_m
    acc, dec = 1.5, 2.0
    t_cruise = (total - speed**2 / (2 * acc) - speed**2 / (2 * dec)) / speed
    t_end = speed / acc + t_cruise + speed / dec
    t = np.arange(0.0, t_end, 0.01)
    s = (
        np.where(
            t < speed / acc,
            0.5 * acc * t**2,
            np.where(
                t < speed / acc + t_cruise,
                speed**2 / (2 * acc) + speed * (t - speed / acc),
                total - 0.5 * dec * np.maximum(t_end - t, 0.0) ** 2,
            ),
        )
        % s_ring[-1]
    )
    x, y = np.interp(s, s_ring, ring[:, 0]), np.interp(s, s_ring, ring[:, 1])
    yaw = np.unwrap(np.arctan2(np.gradient(y), np.gradient(x)))
    write_tum(
        path,
        np.round((1_400_000_000 + t) * 1e9).astype(np.int64),
        make_pose(yaw_rotation(yaw), np.stack([x, y, 0 * x], 1)),
    )


def revisit_error_m(ws, town, fused: bool = True) -> float:
    """Median error (m) of the estimated motion between the two passes of the revisit, against the truth: from each pose
    of the second pass (200 m or more driven) to the first pass's pose nearest to it in truth."""
    from mapkit.core.workspace import Workspace
    from mapkit.evaluation.truth import session_truth, ws_from_town
    from mapkit.mapping.trajectory import Trajectory

    w = Workspace(ws)
    s = w.session("loop")
    traj = Trajectory.load(s.fused_trajectory if fused else s.georef_trajectory)
    gst, gt = session_truth(town, "loop")
    gt, ok = interpolate_poses(gst, ws_from_town(town, w.frame()) @ gt, traj.stamps_ns)
    est = traj.world_from_base[ok]
    travel = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1))])
    first = np.nonzero(travel < 100.0)[0]
    errors = []
    for j in np.nonzero(travel > 200.0)[0]:
        d = np.linalg.norm(gt[first, :2, 3] - gt[j, :2, 3], axis=1)
        if d.min() < 2.0:
            i = int(first[np.argmin(d)])
            errors.append(np.linalg.norm((invert_pose(relative(gt, i, j)) @ relative(est, i, j))[:3, 3]))
    return float(np.median(errors))


@pytest.fixture(scope="module")
def loop_builds(tmp_path_factory):
    import shutil

    from mapkit.mapping.build import build
    from mapkit.synth import session_log, synthesize

    root = tmp_path_factory.mktemp("loop-e2e")
    loop_route(root / "loop.tum")
    cfg = root / "synth.yaml"
    # LiDAR at 5 Hz: half the sweeps for kiss-icp (the test's time), which keeps its track from rest here
    cfg.write_text(
        "seed: 3\nsessions:\n  - {name: loop, role: train, time: '12:00', weather: sunny, length_m: 360.0, "
        "camera_rate_hz: 0.2}\ncamera: {width: 64, height: 48}\nlidar: {rate_hz: 5.0}\n"
    )
    town = synthesize(preset="tiny", out=root / "town", config=cfg, trajectory=root / "loop.tum", progress=False)
    log = session_log(town, "loop")
    off, on = root / "off.yaml", root / "on.yaml"
    maps_off = "map: false\nlidar_map: false\nimagedb: false\n"  # the loop closure is in the trajectory alone
    off.write_text("georef: {fuse: true, factor_graph: {loop_closures: false}}\n" + maps_off)
    on.write_text("georef: {fuse: true}\n" + maps_off)
    build([log], root / "ws-off", config=off, progress=False)
    shutil.copytree(root / "ws-off", root / "ws-on")  # kiss-icp once: the trajectory stage is kept, georef redone
    build([log], root / "ws-on", config=on, progress=False)
    return town, root / "ws-off", root / "ws-on"


def test_a_drive_that_comes_back_closes_its_loop(loop_builds):
    """Built with loop closures the revisit is found and verified (at least one loop accepted where the drive comes
    back), and the fused motion between the two passes is closer to the truth than without them (measured 1.46 ->
    0.09 m, median); the georef stage's metrics carry the loop step's stats, its run record the step's time."""
    town, ws_off, ws_on = loop_builds
    stats = json.loads((ws_on / "sessions" / "loop" / "georef" / "gps_alignment.json").read_text())["fused"]
    assert stats["loop_accepted"] >= 1, stats.get("loop_checks")
    assert all(c["travel_m"] > 250 for c in stats["loop_checks"])  # the revisit, a lap on
    assert len(stats["loop_residuals"]) == stats["loop_accepted"] and "loop_seconds" not in stats
    assert read_timings(ws_on / "sessions" / "loop" / "georef")["fused_loop_seconds"] > 0
    off = json.loads((ws_off / "sessions" / "loop" / "georef" / "gps_alignment.json").read_text())["fused"]
    assert "loop_candidates" not in off
    e_off, e_on = revisit_error_m(ws_off, town), revisit_error_m(ws_on, town)
    assert e_on < 0.5 * e_off, (e_on, e_off)
