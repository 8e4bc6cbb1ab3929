"""Multi-session alignment against known answers: sessions of one street, each displaced by a
known GPS error, must come back into agreement; a session displaced by 30 m must not be merged."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mapkit.core.geodesy import LocalFrame
from mapkit.core.geometry import make_pose, yaw_rotation
from mapkit.core.runio import is_done, mark_done, write_json
from mapkit.mapping.imagedb import images_world_from_cam, read_images_csv, write_images_csv
from mapkit.mapping.semidense import SemiDenseMap
from mapkit.mapping.trajectory import Trajectory
from mapkit.multisession.align import AlignConfig, align_workspace
from mapkit.multisession.posegraph import Edge, PoseGraph, support_points
from mapkit.multisession.registration import register_clouds
from mapkit.multisession.submaps import SessionData, candidate_pairs, cut_submaps
from mapkit.multisession.tiles import load_tiles

FRAME = LocalFrame(48.1, 11.5, 520.0)
STREET_M = 160.0


def street(rng: np.random.Generator) -> np.ndarray:
    """Surface samples of a street: ground, building fronts of random widths and setbacks with
    gaps between them, and poles. Irregular along the street, so ICP is well posed."""
    parts = [np.c_[rng.uniform(-10, STREET_M + 10, 30000), rng.uniform(-12, 12, 30000), np.zeros(30000)]]
    for side in (-1, 1):
        x = -10.0
        while x < STREET_M + 10:
            w, gap = rng.uniform(6, 18), rng.uniform(2, 6)
            y0, h = side * rng.uniform(7, 12), rng.uniform(5, 14)
            n = int(w * h * 12)
            parts.append(np.c_[rng.uniform(x, x + w, n), np.full(n, y0), rng.uniform(0, h, n)])
            d = rng.uniform(4, 8)  # side walls give the along-street direction its constraint
            for xe in (x, x + w):
                m = int(d * h * 12)
                parts.append(np.c_[np.full(m, xe), y0 + side * rng.uniform(0, d, m), rng.uniform(0, h, m)])
            x += w + gap
    for px in rng.uniform(0, STREET_M, 14):
        py = rng.choice([-6.0, 6.0])
        a = rng.uniform(0, 2 * np.pi, 400)
        parts.append(np.c_[px + 0.15 * np.cos(a), py + 0.15 * np.sin(a), rng.uniform(0, 6, 400)])
    return np.concatenate(parts)


def write_session(
    ws: Path, name: str, world: np.ndarray, error: np.ndarray, rng: np.random.Generator, lane_y: float = -2.0
) -> None:
    """A built session that drove the street at 10 m/s, whose map and trajectory are displaced by
    ``error`` (true -> as built), as a GPS bias would displace them."""
    sdir = ws / "sessions" / name
    t = np.arange(0, STREET_M / 10.0, 0.1)
    stamps = (1_000_000_000 + t * 1e9).astype(np.int64)
    poses = np.stack([make_pose(np.eye(3), [10.0 * ti, lane_y, 0.0]) for ti in t])
    poses = error @ poses
    Trajectory(stamps, poses, "lidar", frame="enu").save(sdir / "georef" / "trajectory_enu")
    write_json(sdir / "georef" / "gps_alignment.json", {"session": name, "georeferenced": True, **FRAME.to_dict()})
    mark_done(sdir / "georef", "test")
    # a different random half of the surfaces per session, with noise, like two semi-dense maps
    pts = world[rng.random(len(world)) < 0.5]
    pts = pts + rng.normal(0, 0.03, pts.shape)
    pts = pts @ error[:3, :3].T + error[:3, 3]
    kf_x = np.arange(0.0, STREET_M, 1.0)
    kf_ids = np.arange(len(kf_x)) * 10
    kf_stamps = (1_000_000_000 + kf_x / 10.0 * 1e9).astype(np.int64)
    kf_poses = np.stack([error @ make_pose(np.eye(3), [x, lane_y, 1.5]) for x in kf_x])
    src = kf_ids[np.clip(np.searchsorted(kf_x, np.clip(world_x(pts, error), 0, STREET_M - 1)), 0, len(kf_x) - 1)]
    smap = SemiDenseMap(
        points_world=pts,
        intensity=np.full(len(pts), 128, np.uint8),
        sigma_depth=np.full(len(pts), 0.05, np.float32),
        source_keyframe=src,
        obs_indptr=np.arange(len(pts) + 1, dtype=np.int64),
        obs_frame_ids=src.copy(),
        keyframe_ids=kf_ids,
        keyframe_stamps_ns=kf_stamps,
        keyframe_world_from_cam=kf_poses,
        K=np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]),
        image_size_wh=(640, 480),
    )
    smap.save(sdir / "map")
    mark_done(sdir / "map", "test")
    # an image database: a camera 1.5 m above the base every 5 m
    img_t = np.arange(0.25, STREET_M / 10.0 - 0.25, 0.5)
    cams = np.stack([error @ make_pose(np.eye(3), [10.0 * ti, lane_y, 1.5]) for ti in img_t])
    write_images_csv(
        sdir / "imagedb" / "images.csv",
        np.arange(1, len(img_t) + 1),
        (1_000_000_000 + img_t * 1e9).astype(np.int64),
        ["cam"] * len(img_t),
        [f"images/cam/{i}.jpg" for i in range(len(img_t))],
        cams,
        FRAME,
    )


def world_x(pts: np.ndarray, error: np.ndarray) -> np.ndarray:
    return (np.linalg.inv(error)[:3, :3] @ pts.T).T[:, 0] + np.linalg.inv(error)[0, 3]


def gps_error(dx: float, dy: float, dz: float, yaw_deg: float = 0.0) -> np.ndarray:
    return make_pose(yaw_rotation(np.radians(yaw_deg)), [dx, dy, dz])


def misalignment(ws: Path, a: str, b: str, errors: dict, probe: np.ndarray) -> float:
    """Median distance between where sessions a and b (as aligned) put the same true points."""
    where = {}
    for name in (a, b):
        built = Trajectory.load(ws / "sessions" / name / "georef" / "trajectory_enu").world_from_base
        aligned = Trajectory.load(ws / "align" / "sessions" / name / "trajectory").world_from_base
        k = np.clip(np.searchsorted(built[:, 0, 3] - errors[name][0, 3], probe[:, 0]), 0, len(built) - 1)
        correction = aligned[k] @ np.linalg.inv(built[k])  # built -> aligned, at the nearest pose
        p = probe @ errors[name][:3, :3].T + errors[name][:3, 3]
        where[name] = np.einsum("nij,nj->ni", correction[:, :3, :3], p) + correction[:, :3, 3]
    return float(np.median(np.linalg.norm(where[a] - where[b], axis=1)))


@pytest.fixture(scope="module")
def street_world() -> np.ndarray:
    return street(np.random.default_rng(3))


def make_workspace(ws: Path, world: np.ndarray, errors: dict) -> None:
    ws.mkdir(parents=True, exist_ok=True)
    write_json(ws / "origin.json", FRAME.to_dict())
    for i, (name, E) in enumerate(errors.items()):
        write_session(ws, name, world, E, np.random.default_rng(100 + i), lane_y=-2.0 if i % 2 == 0 else 2.0)


def test_register_clouds_recovers_a_known_offset(street_world):
    rng = np.random.default_rng(0)
    a = street_world[(street_world[:, 0] > 20) & (street_world[:, 0] < 70) & (rng.random(len(street_world)) < 0.5)]
    b = street_world[(street_world[:, 0] > 10) & (street_world[:, 0] < 80) & (rng.random(len(street_world)) < 0.5)]
    true = gps_error(2.5, -1.8, 0.4, yaw_deg=0.5)
    r = register_clouds(a @ true[:3, :3].T + true[:3, 3], b, np.array([45.0, 0, 0]), AlignConfig().icp)
    # the registration undoes the offset: target_from_source ~ true^-1
    P = np.array([[45.0, 0, 0], [55.0, 8, 3], [35.0, -8, 3]])
    moved = P @ true[:3, :3].T + true[:3, 3]
    back = moved @ r.target_from_source[:3, :3].T + r.target_from_source[:3, 3]
    assert np.abs(back - P).max() < 0.1
    assert r.fitness > 0.5 and r.rmse_m < 0.2


def test_candidate_pairs_pairs_only_nearby_submaps_of_different_sessions():
    def sess(name, y):
        s = SessionData(
            name,
            np.arange(101, dtype=np.int64),
            np.stack([make_pose(np.eye(3), [x, y, 0]) for x in np.linspace(0, 200, 101)]),
            np.linspace(0, 200, 101),
            np.zeros((0, 3)),
            np.zeros(0),
            Path("."),
            "",
        )
        cut_submaps(s, 50.0)
        return s

    a, b, far = sess("a", 0.0), sess("b", 3.0), sess("far", 500.0)
    pairs = candidate_pairs([a, b, far], 35.0)
    assert a.n_submaps == 4
    assert pairs and all(sa != sb for sa, _, sb, _ in pairs)
    assert {(i, j) for _, i, _, j in pairs} == {(k, k) for k in range(4)}  # centres 50 m apart: only the facing ones
    assert not any(2 in (sa, sb) for sa, _, sb, _ in pairs)


def test_pose_graph_distributes_a_known_offset():
    # two sessions of 3 submaps; ICP says the second sits 2 m east of the first everywhere
    centres = np.array([[25.0, 0, 0], [75, 0, 0], [125, 0, 0]] * 2)
    g = PoseGraph(centres, AlignConfig().graph, session_of=np.repeat([0, 1], 3))
    edges = []
    for k in range(2):
        for s in (0, 3):
            edges.append(
                Edge(
                    "odometry",
                    s + k,
                    s + k + 1,
                    np.array([[50.0 * (k + 1), 0, 0], [50.0 * (k + 1) + 10, 0, 0], [50.0 * (k + 1), 10, 0]]),
                    np.eye(4),
                    0.1,
                )
            )
    T = make_pose(np.eye(3), [-2.0, 0, 0])  # maps the second session's points onto the first's
    for k in range(3):
        edges.append(Edge("icp", 3 + k, k, centres[k] + np.array([[0, 0, 0], [10.0, 0, 0], [0, 10.0, 0]]), T, 0.1))
    x = g.solve(edges)
    # the priors are equal, so each session moves half the way: +1 m and -1 m
    assert np.allclose(x[:3, 3], 1.0, atol=0.05) and np.allclose(x[3:, 3], -1.0, atol=0.05)
    assert np.abs(x[:, 4:]).max() < 0.05 and np.abs(x[:, :3]).max() < 1e-3
    assert g.edge_rms_sigmas(x, edges).max() < 0.5


def _mc_graph(rng, cfg, n_sessions=4, n_sub=3, outlier=False, isolated=0):
    """Sessions of ``n_sub`` submaps along x, each displaced by its GPS bias drawn from the graph's
    own prior; ICP edges between every pair of sessions at each place, exact, and odometry exact;
    the last ``isolated`` sessions touch no other."""
    centres = np.array([[25.0 + 50 * k, 0, 0] for k in range(n_sub)] * n_sessions)
    bias = rng.standard_normal((n_sessions, 3)) * np.asarray(cfg.gps_bias_sigma_m)
    true_t = -np.repeat(bias, n_sub, axis=0)  # the correction that undoes each session's bias
    x0 = np.zeros((len(centres), 6))
    x0[:, 3:] = true_t + bias.mean(axis=0)  # where align starts it: the sessions' relative offsets (session_offsets)
    g = PoseGraph(
        centres + np.repeat(bias, n_sub, axis=0), cfg, initial=x0, session_of=np.repeat(np.arange(n_sessions), n_sub)
    )
    for s in range(n_sessions):
        for k in range(n_sub - 1):
            g.add(
                Edge(
                    "odometry",
                    s * n_sub + k,
                    s * n_sub + k + 1,
                    support_points(np.array([50.0 * (k + 1), 0, 0]) + bias[s], np.array([1.0, 0, 0]), 10.0),
                    np.eye(4),
                    0.1,
                )
            )
    for sa in range(n_sessions - isolated):
        for sb in range(sa + 1, n_sessions - isolated):
            for k in range(n_sub):
                T = make_pose(np.eye(3), bias[sb] - bias[sa])  # session a's points onto session b's
                g.add(
                    Edge(
                        "icp",
                        sa * n_sub + k,
                        sb * n_sub + k,
                        support_points(g.centres[sa * n_sub + k], np.array([1.0, 0, 0]), 10.0),
                        T,
                        0.1,
                        0,
                    )
                )
    bad = None
    if outlier:  # one registration 3 m off, between the first two sessions
        bad = Edge(
            "icp",
            0,
            n_sub,
            support_points(g.centres[0], np.array([1.0, 0, 0]), 10.0),
            make_pose(np.eye(3), bias[1] - bias[0] + [3.0, 0, 0]),
            0.1,
            1,
        )
        g.add(bad)
    return g, true_t, bad


def test_pose_graph_covariances_are_consistent_with_its_gps_model():
    # Monte Carlo over the GPS bias model: the true corrections fall inside their 95% ellipsoids
    # about 95% of the time (the common offset of N sessions is known to sigma_b / sqrt(N), not better); the
    # registrations are exact, so their shared errors are not considered (tie_sigma_m 0): the GPS model alone
    cfg = AlignConfig().graph.model_copy(update={"tie_sigma_m": 0.0})
    rng = np.random.default_rng(4)
    d2, sig = [], []
    for _ in range(60):
        g, true_t, _ = _mc_graph(rng, cfg)
        x = g.solve()
        cov = g.covariances()
        e = x[:, 3:] - true_t
        d2 += [float(ei @ np.linalg.solve(c[3:, 3:], ei)) for ei, c in zip(e, cov, strict=True)]
        sig.append(np.sqrt(cov[0, 3, 3]))
    inside = np.mean(np.asarray(d2) <= 7.815)
    assert 0.90 <= inside <= 0.99, inside
    assert abs(np.median(sig) - 2.0 / np.sqrt(4)) < 0.15  # sigma_b / sqrt(N) east


def test_a_session_that_touches_no_other_keeps_its_gps_uncertainty():
    cfg = AlignConfig().graph.model_copy(update={"tie_sigma_m": 0.0})  # the GPS model alone, as above
    g, true_t, _ = _mc_graph(np.random.default_rng(2), cfg, n_sessions=4, isolated=1)
    g.solve()
    sig = np.sqrt(g.covariances()[:, [3, 4, 5], [3, 4, 5]])
    # three linked sessions: 2 m / sqrt(3) east; the lone one: its own bias prior and its 3 submaps'
    # 1 m ties to it, sqrt(2^2 + 1/3) m
    assert np.allclose(sig[:9, 0], 2.0 / np.sqrt(3), atol=0.1)
    assert np.allclose(sig[9:, 0], np.sqrt(4 + 1 / 3), atol=0.1)
    assert np.allclose(sig[9:, 2], np.sqrt(16 + 1 / 3), atol=0.15)  # vertical: 4 m bias prior


def test_pose_graph_removes_a_rejected_edge_as_if_never_added():
    cfg = AlignConfig().graph
    g, true_t, bad = _mc_graph(np.random.default_rng(1), cfg, n_sessions=3, outlier=True)
    x_all = g.solve()
    rms = g.edge_rms_sigmas(x_all, [bad])
    assert rms[0] > cfg.reject_sigmas  # the Cauchy kernel kept it from pulling the others far
    x_removed = g.remove([bad])
    clean, _, _ = _mc_graph(np.random.default_rng(1), cfg, n_sessions=3)
    x_clean = clean.solve()
    assert np.abs(x_removed - x_clean).max() < 1e-3
    assert np.abs(np.diff(x_removed[:, 3:] - true_t, axis=0)).max() < 1e-3  # sessions agree exactly


def test_align_brings_sessions_together_and_resumes(tmp_path, street_world):
    errors = {
        "s0": gps_error(1.5, -2.0, 0.3, 0.3),
        "s1": gps_error(-2.0, 1.0, -0.4, -0.2),
        "s2": gps_error(0.5, 2.5, 0.0, 0.0),
    }
    ws = tmp_path / "ws"
    make_workspace(ws, street_world, errors)
    cfg = {"graph": {"max_rounds": 2}}
    out = align_workspace(ws, overrides=cfg, progress=False)
    probe = street_world[np.random.default_rng(9).choice(len(street_world), 3000, replace=False)]
    probe = probe[(probe[:, 0] > 5) & (probe[:, 0] < STREET_M - 5)]
    for a, b in (("s0", "s1"), ("s0", "s2"), ("s1", "s2")):
        before = float(np.linalg.norm(errors[a][:3, 3] - errors[b][:3, 3]))
        after = misalignment(ws, a, b, errors, probe)
        assert before > 2.0 and after < 0.1, (a, b, before, after)
    m = json.loads((out / "metrics.json").read_text())
    assert m["pairs"]["accepted"] >= 6 and m["pairs"]["rejected"] == 0
    assert all(s["unverified"] == 0 for s in m["sessions"].values())
    pts, sid, idx, names = load_tiles(out / "tiles")
    assert names == ["s0", "s1", "s2"] and len(pts) == sum(s["points"] for s in m["sessions"].values())
    refined = SemiDenseMap.load(out / "sessions" / "s1" / "map")
    assert np.allclose(
        pts[(sid == 1)][np.argsort(idx[sid == 1])][:100], refined.points_world[np.sort(idx[sid == 1])][:100]
    )
    # the image databases moved with their sessions: every session's cameras are off the truth by
    # one common offset (the frame's gauge), not by their own GPS errors any more
    offsets = []
    for name in errors:
        tab = read_images_csv(out / "sessions" / name / "images.csv")
        lane = -2.0 if name in ("s0", "s2") else 2.0
        true = np.stack(
            [np.full(len(tab["x_m"]), 0.0), np.full(len(tab["x_m"]), lane), np.full(len(tab["x_m"]), 1.5)], axis=1
        )
        true[:, 0] = (tab["stamp_ns"] - 1_000_000_000) * 1e-8
        offsets.append(np.median(images_world_from_cam(tab)[:, :3, 3] - true, axis=0))
        assert tab["image"][0].endswith("imagedb/images/cam/0.jpg") and not tab["image"][0].startswith("/")
    assert np.ptp(np.array(offsets), axis=0).max() < 0.1, offsets
    for png in ("pairs_map.png", "icp_histograms.png"):
        assert (out / png).stat().st_size > 10_000
    # resuming: a finished run is not redone; adding a session registers only its own pairs
    stamp = (out / "metrics.json").stat().st_mtime_ns
    align_workspace(ws, overrides=cfg, progress=False)
    assert (out / "metrics.json").stat().st_mtime_ns == stamp
    before_s0 = (out / "sessions" / "s0" / "trajectory" / "poses_tum.txt").read_text()
    map_s0 = out / "sessions" / "s0" / "map" / "points.ply"
    stamp_s0 = map_s0.stat().st_mtime_ns
    table_s1 = out / "sessions" / "s1" / "images.csv"
    good_s1 = table_s1.read_bytes()
    table_s1.write_bytes(good_s1[:-10])  # damaged since the last run: s1 is written again, not kept
    errors["s3"] = gps_error(-1.0, -1.5, 0.2, 0.1)
    write_session(ws, "s3", street_world, errors["s3"], np.random.default_rng(200), lane_y=2.0)
    align_workspace(ws, overrides=cfg, progress=False)
    m2 = json.loads((out / "metrics.json").read_text())
    assert m2["registration"]["registered_this_run"] == m2["registration"]["pairs"] - m["registration"]["pairs"]
    assert (out / "sessions" / "s0" / "trajectory" / "poses_tum.txt").read_text() == before_s0  # frozen
    # a frozen session's files are those of the last run, kept, not written again; a damaged one is rewritten whole
    assert {n: s["outputs_kept"] for n, s in m2["sessions"].items()} == {
        "s0": True,
        "s1": False,
        "s2": True,
        "s3": False,
    }
    assert map_s0.stat().st_mtime_ns == stamp_s0 and table_s1.read_bytes() == good_s1
    assert is_done(out, verify=True)  # the marker records the kept files as they are
    assert misalignment(ws, "s0", "s3", errors, probe) < 0.1
    assert m2["graph"]["sessions_solved"] == 1  # only s3's submaps were variables of the graph
    # the frozen sessions keep their covariances and GPS biases; s3's are its own, and every
    # session's bias is estimated to what 3-4 sessions allow (2 m / sqrt(N) horizontally), widened by
    # what registrations wrong together at its 3 places could move it (tie_sigma_m), still below a
    # lone session's sqrt(2^2 + 1/3) m
    for name in ("s0", "s3"):
        sm = json.loads((out / "sessions" / name / "submaps.json").read_text())
        sig = np.array([k["position_sigma_enu_m"] for k in sm["submaps"]])
        assert np.all(sig[:, :2] > 0.5) and np.all(sig[:, :2] < 1.9), (name, sig)
        # the bias about as well as the submaps: each holds it to gps_submap_sigma_m (1 m), and a shift of
        # the registrations moves both
        assert 0.9 * sig[0, 0] < sm["gps_bias"]["sigma_enu_m"][0] < 2.0


def test_a_session_displaced_by_30m_is_not_merged(tmp_path, street_world):
    # s2's GPS alignment followed a 30 m multipath jump: its map sits 30 m north-east of the truth
    errors = {"s0": gps_error(1.0, -1.0, 0.0), "s1": gps_error(-1.0, 1.0, 0.0), "s2": gps_error(21.0, 21.0, 0.0)}
    ws = tmp_path / "ws"
    make_workspace(ws, street_world, errors)
    out = align_workspace(ws, overrides={"overlap_radius_m": 60.0}, progress=False)
    m = json.loads((out / "metrics.json").read_text())
    bad = m["sessions"]["s2"]
    assert bad["verified"] == 0 and bad["unverified"] > 0 and bad["points_merged"] == 0
    assert m["sessions"]["s0"]["verified"] > 0 and m["sessions"]["s0"]["points_merged"] == m["sessions"]["s0"]["points"]
    pairs = json.loads((out / "pairs.json").read_text())["pairs"]
    involving = [p for p in pairs if "s2" in (p["source"][0], p["target"][0])]
    assert involving and not any(p["accepted"] for p in involving)
    assert all(p["reason"] != "accepted" for p in involving)
    _, sid, _, names = load_tiles(out / "tiles")
    assert names.index("s2") not in set(sid.tolist())


def test_align_needs_two_georeferenced_sessions(tmp_path, street_world):
    from mapkit.core.errors import InputError

    ws = tmp_path / "ws"
    make_workspace(ws, street_world, {"only": gps_error(0, 0, 0)})
    with pytest.raises(InputError, match="at least two"):
        align_workspace(ws, progress=False)


def test_a_fused_trajectory_holds_its_submaps_together_more_tightly(tmp_path, street_world, monkeypatch):
    """A session whose trajectory is the factor graph's (georef/trajectory_fused) ties consecutive
    submaps with ``odometry_sigma_fused_m``; a rigid GPS fit of kiss-icp's keeps ``odometry_sigma_m``."""
    import shutil

    import mapkit.multisession.align as align_mod

    errors = {"s0": gps_error(1.0, -1.0, 0.2), "s1": gps_error(-1.0, 1.5, -0.3)}
    ws = tmp_path / "ws"
    make_workspace(ws, street_world, errors)
    georef = ws / "sessions" / "s1" / "georef"
    shutil.copytree(georef / "trajectory_enu", georef / "trajectory_fused")
    sigmas: dict[int, set] = {}
    real_edge = align_mod.Edge

    def edge(kind, a, b, *args):
        if kind == "odometry":
            sigmas.setdefault(a, set()).add(args[-1])
        return real_edge(kind, a, b, *args)

    monkeypatch.setattr(align_mod, "Edge", edge)
    cfg = {"graph": {"odometry_sigma_m": 0.1, "odometry_sigma_fused_m": 0.02}}
    out = align_workspace(ws, overrides=cfg, progress=False)
    n0 = len(json.loads((out / "sessions" / "s0" / "submaps.json").read_text())["submaps"])
    assert n0 >= 3 and len(sigmas) >= 2 * (n0 - 1)
    assert all(v == ({0.1} if a < n0 else {0.02}) for a, v in sigmas.items()), sigmas


def test_a_sparse_session_is_kept_with_its_reason_and_one_without_gps_is_skipped(tmp_path, street_world):
    """Degenerate sessions: a foggy one whose map is too sparse to register (every pair it is in is
    rejected as "too few points"; it stays in the alignment on its GPS, its submaps unverified, out of the
    merged map), and one whose GPS never fixed (not georeferenced: skipped with a warning naming it)."""
    errors = {"s0": gps_error(1.5, -2.0, 0.3), "s1": gps_error(-2.0, 1.0, -0.4), "fog": gps_error(0.5, 2.5, 0.0)}
    ws = tmp_path / "ws"
    make_workspace(ws, street_world, errors)
    fog = SemiDenseMap.load(ws / "sessions" / "fog" / "map")
    keep = (
        np.random.default_rng(5).random(len(fog.points_world)) < 0.005
    )  # ~0.5% of the points: a few hundred per submap
    sparse = SemiDenseMap(
        fog.points_world[keep],
        fog.intensity[keep],
        fog.sigma_depth[keep],
        fog.source_keyframe[keep],
        np.arange(int(keep.sum()) + 1, dtype=np.int64),
        fog.source_keyframe[keep],
        fog.keyframe_ids,
        fog.keyframe_stamps_ns,
        fog.keyframe_world_from_cam,
        fog.K,
        fog.image_size_wh,
    )
    sparse.save(ws / "sessions" / "fog" / "map")
    mark_done(ws / "sessions" / "fog" / "map", "test")
    write_session(ws, "nogps", street_world, np.eye(4), np.random.default_rng(300))
    write_json(
        ws / "sessions" / "nogps" / "georef" / "gps_alignment.json",
        {"session": "nogps", "georeferenced": False, "reason": "no GPS fix in the log"},
    )
    mark_done(ws / "sessions" / "nogps" / "georef", "test")
    with pytest.warns(UserWarning, match="nogps.*not georeferenced \\(no GPS fix in the log\\); skipped"):
        out = align_workspace(ws, overrides={"graph": {"max_rounds": 2}}, progress=False)
    m = json.loads((out / "metrics.json").read_text())
    assert sorted(m["sessions"]) == ["fog", "s0", "s1"]
    pairs = json.loads((out / "pairs.json").read_text())["pairs"]
    fog_pairs = [p for p in pairs if "fog" in (p["source"][0], p["target"][0])]
    assert fog_pairs and all(not p["accepted"] and "too few points" in p["reason"] for p in fog_pairs), fog_pairs[0][
        "reason"
    ]
    assert m["sessions"]["fog"]["verified"] == 0 and not m["sessions"]["fog"]["merged"]
    assert m["sessions"]["s0"]["verified"] > 0 and m["sessions"]["s0"]["merged"]
