"""LiDAR maps downstream of the build: ``mapkit align`` carries them into the common frame (and can register on
them), ``Workspace.session_map`` hands them out, and triplets and the structure index cut their patches from them.

The workspace is the test street of :mod:`test_align` (sessions displaced by known GPS errors), each session with a
semi-dense map and, but for one, a LiDAR map of the same surfaces voxelised at 0.25 m, each voxel stamped with the
time the car passed it."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).parent))
from test_align import FRAME, STREET_M, gps_error, make_workspace, street, write_session

from mapkit.cli import main
from mapkit.core.errors import InputError
from mapkit.core.runio import mark_done, write_json
from mapkit.core.workspace import Workspace
from mapkit.deploy.crs_export import ply_georef
from mapkit.mapping.lidar_map import load_voxel_stats, save_voxel_map
from mapkit.mapping.semidense import SemiDenseMap
from mapkit.mapping.trajectory import Trajectory
from mapkit.mapping.voxel_map import VoxelMap
from mapkit.multisession.align import AlignConfig, align_workspace, config_identity, pair_sources
from mapkit.multisession.submaps import candidate_pairs, load_session, voxel_arc_m
from mapkit.places.lidar_observations import lidar_observations
from mapkit.places.triplets import TripletConfig

T0_NS = 1_000_000_000  # the test street's trajectories start here, one pose every 0.1 s (1 m at 10 m/s)
VOXEL_M = 0.25
SEEN_S = 2.0  # a point is seen for this long before and after the car passes it
TRIPLETS = {
    "n_triplets": 60,
    "tile_size_m": 40.0,
    "buffer_m": 8.0,
    "test_fraction": 0.3,
    "negative_min_distance_m": 40.0,
    "negative_pool": 40,
    "shard_patches": 64,
    "places_per_cell": 4,
    "keypoint_fraction": 0.01,
}


def write_lidar_map(ws: Path, name: str, world: np.ndarray, error: np.ndarray, seed: int) -> None:
    """A built LiDAR map of session ``name``: a random 60 % of the street's surface samples with 2 cm noise,
    displaced by ``error`` like the session's trajectory, voxelised at VOXEL_M. A point is seen from SEEN_S before
    the car passes it (the pose nearest to it) until SEEN_S after, as a scanner sees a facade while it drives by."""
    rng = np.random.default_rng(seed)
    pts = world[rng.random(len(world)) < 0.6]
    pts = pts + rng.normal(0, 0.02, pts.shape)
    passed = nearest_pose(pts)
    pts = pts @ error[:3, :3].T + error[:3, 3]
    vm = VoxelMap(VOXEL_M)
    for k in np.unique(passed):
        sel = passed == k
        for dt_ns in (-SEEN_S * 1e9, SEEN_S * 1e9):
            vm.add(pts[sel], np.full(int(sel.sum()), 30.0), T0_NS + int(k) * 100_000_000 + int(dt_ns))
    folder = ws / "sessions" / name / "lidar_map"
    save_voxel_map(folder, vm.stats(), FRAME)
    mark_done(folder, "test")


def nearest_pose(true_points: np.ndarray) -> np.ndarray:
    """The index of the test street's pose nearest to each true point: poses lie on a line along x, 1 m apart."""
    return np.clip(np.rint(true_points[:, 0]), 0, STREET_M - 1).astype(int)


ERRORS = {"s0": gps_error(1.5, -2.0, 0.3, 0.3), "s1": gps_error(-2.0, 1.0, -0.4, -0.2), "s2": gps_error(0.5, 2.5, 0.0)}


@pytest.fixture(scope="module")
def world() -> np.ndarray:
    return street(np.random.default_rng(3))


@pytest.fixture(scope="module")
def aligned(world, tmp_path_factory) -> Path:
    """Three sessions, s0 and s1 with LiDAR maps, s2 without; aligned with map_source auto."""
    ws = tmp_path_factory.mktemp("lidar_consumers") / "ws"
    make_workspace(ws, world, ERRORS)
    for i, name in enumerate(("s0", "s1")):
        write_lidar_map(ws, name, world, ERRORS[name], 50 + i)
    align_workspace(ws, overrides={"map_source": "auto", "graph": {"max_rounds": 2}}, progress=False)
    return ws


# --- align ---------------------------------------------------------------------------------------------------


def test_aligned_lidar_map_is_the_built_one_under_the_sessions_correction(aligned):
    """Each aligned voxel is the built one moved by the session's correction at the pose that passed it (the
    aligned trajectory's pose there times the built one's inverse), its normal turned by the same rotation; the
    file states its frame; and the two sessions' aligned LiDAR maps put the true surfaces in one place, as their
    built ones did not (2-3 m apart)."""
    ws = Workspace(aligned)
    gauge = {}
    for name in ("s0", "s1"):
        built = load_voxel_stats(ws.session(name).lidar_map)
        out = load_voxel_stats(ws.aligned(name).lidar_map)
        T_built = Trajectory.load(ws.session(name).georef_trajectory)
        T_aligned = Trajectory.load(ws.aligned(name).trajectory)
        # built = error @ truth: each voxel moves with the correction at the pose nearest to its true centroid
        E = ERRORS[name]
        truth = (built.centroid - E[:3, 3]) @ E[:3, :3]
        k = nearest_pose(truth)
        assert (built.last_ns - built.first_ns >= 2 * SEEN_S * 1e9).all()  # seen for 40 poses: the nearest decides
        C = T_aligned.world_from_base[k] @ np.linalg.inv(T_built.world_from_base[k])  # built -> aligned, per voxel
        want = np.einsum("nij,nj->ni", C[:, :3, :3], built.centroid) + C[:, :3, 3]
        clear = np.abs(truth[:, 0] - np.rint(truth[:, 0])) < 0.49  # not half-way between two poses
        assert len(out) == len(built) and clear.mean() > 0.9 and np.abs(out.centroid - want)[clear].max() < 1e-6
        assert np.abs(out.centroid - built.centroid).max() > 1e-3  # the correction moved it
        n_want = np.einsum("nij,nj->ni", C[:, :3, :3], built.normal)
        ok = np.isfinite(built.normal[:, 0])
        assert ok.sum() > 1000 and np.abs(np.abs(np.einsum("ij,ij->i", out.normal[ok], n_want[ok])) - 1).max() < 1e-9
        assert (out.normal[ok, 2] >= 0).all()
        for f in ("count", "intensity", "planarity", "first_ns", "last_ns"):
            np.testing.assert_array_equal(getattr(out, f), getattr(built, f))
        assert ply_georef(ws.aligned(name).lidar_map / "points.ply")[0] == FRAME
        # the offset of aligned from true positions is the frame's gauge, common to sessions
        gauge[name] = np.median(out.centroid - truth, axis=0)
        assert np.percentile(np.linalg.norm(out.centroid - truth - gauge[name], axis=1), 95) < 0.1
    assert np.linalg.norm(ERRORS["s0"][:3, 3] - ERRORS["s1"][:3, 3]) > 2.0
    assert np.linalg.norm(gauge["s0"] - gauge["s1"]) < 0.1, gauge
    assert not ws.aligned("s2").lidar_map.exists()


def test_auto_registers_on_lidar_maps_only_where_both_sessions_have_one_and_says_so(aligned):
    pairs = json.loads((aligned / "align" / "pairs.json").read_text())["pairs"]
    for p in pairs:
        both = {p["source"][0], p["target"][0]} <= {"s0", "s1"}
        assert p["map_source"] == ("lidar" if both else "semidense"), p
    m = json.loads((aligned / "align" / "metrics.json").read_text())["map_source"]
    assert m["config"] == "auto" and m["sessions_without_lidar_map"] == ["s2"]
    assert m["pairs"]["lidar"] >= 2 and m["pairs"]["semidense"] >= 4
    qa = (aligned / "align" / "qa.md").read_text()
    assert "Registered on (map_source auto)" in qa and "no LiDAR map (s2)" in qa


def test_semidense_and_lidar_takes_the_lidar_maps_where_the_semidense_ones_are_too_sparse(aligned):
    """The default map source registers a pair on the LiDAR maps where its semi-dense maps hold fewer than min_points
    about it and both sessions have a LiDAR map: none on the test street's dense maps; with min_points above every
    pair's points, exactly the pairs of the sessions with LiDAR maps (s0, s1)."""
    ws = Workspace(aligned)
    data = [load_session(ws.session(n), ws.frame(), AlignConfig().submap_length_m) for n in ("s0", "s1", "s2")]
    cands = candidate_pairs(data, AlignConfig().overlap_radius_m)
    assert AlignConfig().map_source == "semidense+lidar"
    assert pair_sources(data, cands, AlignConfig()) == ["semidense"] * len(cands)
    starved = AlignConfig(min_points=10**9)
    with_lidar = ["lidar" if data[ia].lidar and data[ib].lidar else "semidense" for ia, _, ib, _ in cands]
    assert "lidar" in with_lidar and "semidense" in with_lidar
    assert pair_sources(data, cands, starved) == with_lidar


def test_semidense_stays_out_of_the_alignments_identity():
    """An alignment made before map_source existed is still the same alignment (its hashes do not move)."""
    assert "map_source" not in config_identity(AlignConfig(map_source="semidense"))
    assert config_identity(AlignConfig(map_source="lidar"))["map_source"] == "lidar"
    assert config_identity(AlignConfig())["map_source"] == "semidense+lidar"


def test_voxel_arc_is_the_nearest_pose_within_the_time_it_was_seen():
    stamps = np.arange(10, dtype=np.int64) * 100
    positions = np.c_[np.arange(10.0), np.zeros(10), np.zeros(10)]
    arc = np.arange(10.0) * 2  # any increasing distance driven
    centroids = np.array([[3.2, 5.0, 0.0], [3.2, 5.0, 0.0], [8.9, -1.0, 2.0]])
    first = np.array([0, 600, 0])
    last = np.array([900, 700, 900])
    got = voxel_arc_m(centroids, first, last, positions, stamps, arc)
    # nearest pose 3; seen only at 600-700: clamped to 600 (pose 6); nearest pose 9
    np.testing.assert_allclose(got, [6.0, 12.0, 18.0])


@pytest.mark.parametrize("source", ["lidar", None])
def test_registering_on_lidar_maps_recovers_a_known_offset_that_the_semidense_maps_cannot(
    world, tmp_path, capsys, source
):
    """Two sessions whose semi-dense maps are too sparse to register (a few hundred points a submap, under
    min_points): on them align finds no pair; on the LiDAR maps (map_source lidar, or the default semidense+lidar,
    which takes them for exactly such pairs) it brings together what GPS left 3.2 m apart."""
    errors = {"a": gps_error(1.0, -1.5, 0.2, 0.2), "b": gps_error(-1.0, 1.0, -0.2, -0.1)}
    ws = tmp_path / "ws"
    ws.mkdir()
    write_json(ws / "origin.json", FRAME.to_dict())
    sparse = world[np.random.default_rng(0).random(len(world)) < 0.02]
    for i, (name, E) in enumerate(errors.items()):
        write_session(ws, name, sparse, E, np.random.default_rng(300 + i), lane_y=-2.0 if i == 0 else 2.0)
        write_lidar_map(ws, name, world, E, 60 + i)
    with pytest.raises(InputError, match="0 of .* candidate submap pairs verified"):
        align_workspace(ws, overrides={"map_source": "semidense"}, progress=False)
    assert main(["align", str(ws), *(["--map-source", source] if source else [])]) == 0
    said = "lidar" if source else "semidense+lidar"
    assert f"Registered on (map_source {said}): 3 on lidar maps." in capsys.readouterr().out
    out = ws / "align"
    pairs = json.loads((out / "pairs.json").read_text())["pairs"]
    assert pairs and all(p["map_source"] == "lidar" for p in pairs) and any(p["accepted"] for p in pairs)
    gauge = []
    for name, E in errors.items():
        built = load_voxel_stats(ws / "sessions" / name / "lidar_map")
        moved = load_voxel_stats(out / "sessions" / name / "lidar_map")
        gauge.append(np.median(moved.centroid - (built.centroid - E[:3, 3]) @ E[:3, :3], axis=0))
    assert np.linalg.norm(errors["a"][:3, 3] - errors["b"][:3, 3]) > 3.0
    assert np.linalg.norm(gauge[0] - gauge[1]) < 0.1, gauge


# --- the workspace -------------------------------------------------------------------------------------------


def test_session_map_hands_out_lidar_maps_and_names_a_session_without_one(aligned):
    ws = Workspace(aligned)
    assert ws.sessions_with_maps("lidar") == ["s0", "s1"] and ws.sessions_with_maps() == ["s0", "s1", "s2"]
    assert ws.session_map("s0", source="lidar") == (ws.aligned("s0").lidar_map, "align")
    assert ws.session_map("s0", prefer_aligned=False, source="lidar") == (ws.session("s0").lidar_map, "build")
    assert ws.session_map("s2") == (ws.aligned("s2").map, "align")  # the default: the semi-dense map, as before
    with pytest.raises(
        InputError, match=r"session 's2' has no LiDAR map \(map source 'lidar'\); it has semi-dense map"
    ):
        ws.session_map("s2", source="lidar")


# --- triplets and the structure index ------------------------------------------------------------------------


def test_triplets_from_lidar_maps_cut_their_patches_from_the_lidar_voxels(aligned, tmp_path, capsys):
    """``mapkit triplets --map-source lidar``: a dataset of its own (triplets-lidar/) whose config and metrics say
    lidar, drawn from the s0 and s1 LiDAR maps only; a negative patch is centred on a merged LiDAR voxel of its
    session and holds exactly the voxels of its cylinder (not the semi-dense map's points); its frame is a pose of
    the session's trajectory."""
    cfg = tmp_path / "triplets.yaml"
    cfg.write_text(json.dumps(TRIPLETS))
    assert main(["triplets", str(aligned), "--config", str(cfg), "--map-source", "lidar"]) == 0
    capsys.readouterr()
    ws = Workspace(aligned)
    out = ws.triplets_folder("lidar")
    assert out == aligned / "triplets-lidar" and not ws.triplets_dir.exists()
    man = json.loads((out / "manifest.json").read_text())
    assert man["map_source"] == "lidar" and man["sessions"] == ["s0", "s1"]
    assert json.loads((out / "metrics.json").read_text())["map_source"] == "lidar"
    assert "map_source: lidar" in (out / "config.yaml").read_text()
    tab = dict(np.load(out / "patches.npz", allow_pickle=False))
    neg = np.flatnonzero(tab["role"] == "negative")
    assert len(neg) >= 10 and (tab["role"] == "positive").sum() >= 2
    domain = TripletConfig().domain
    for si, name in enumerate(man["sessions"]):
        folder = ws.aligned(name).lidar_map
        merged = load_voxel_stats(folder).centroid[np.load(folder / "voxel_submaps.npz")["merged"]]
        semi = SemiDenseMap.load(ws.aligned(name).map).points_world
        mine = neg[tab["session"][neg] == si]
        assert len(mine)
        d_lidar, _ = cKDTree(merged).query(tab["enu"][mine])
        d_semi, _ = cKDTree(semi).query(tab["enu"][mine])
        assert d_lidar.max() < 1e-9 and d_semi.min() > 1e-6
        for j in mine:
            rel = merged - tab["enu"][j]
            inside = (np.hypot(rel[:, 0], rel[:, 1]) <= domain.patch_radius) & (
                np.abs(rel[:, 2]) <= domain.patch_half_height
            )
            assert tab["points"][j] == inside.sum()
        n_poses = len(Trajectory.load(ws.aligned(name).trajectory).stamps_ns)
        frames = tab["frame"][tab["session"] == si]
        assert frames.min() >= 0 and frames.max() < n_poses


def test_structure_index_of_lidar_maps_has_its_own_folder_and_lidar_keypoints(aligned, capsys):
    """``mapkit index structure --map-source lidar``: indexes/structure-nbld-lidar beside the semi-dense bundle,
    every entry a voxel centroid of its session's LiDAR map, every frame a pose of its aligned trajectory; and the
    place a query frame of s1 votes for is the s0 frame at the same place."""
    from mapkit.places.index_structure import StructureIndex, session_frames

    cfg = aligned / "index.yaml"
    cfg.write_text(json.dumps({"keypoint_fraction": 0.03}))
    for extra in ([], ["--map-source", "lidar"]):
        assert main(["index", "structure", str(aligned), "-s", "s0", "--config", str(cfg), *extra]) == 0
    capsys.readouterr()
    assert main(["index", "structure", str(aligned), "-s", "s2", "--map-source", "lidar"]) == 2
    assert "no LiDAR map for session(s) ['s2'] (map_source lidar)" in capsys.readouterr().err
    ws = Workspace(aligned)
    semi, lidar = ws.structure_index("nbld"), ws.structure_index("nbld", "lidar")
    assert lidar == aligned / "indexes" / "structure-nbld-lidar" and semi.is_dir() and lidar.is_dir()
    man = json.loads((lidar / "manifest.json").read_text())
    assert man["config"]["map_source"] == "lidar" and man["sessions"]["s0"]["map_kind"] == "lidar"
    assert json.loads((lidar / "metrics.json").read_text())["map_source"] == "lidar"
    voxels = load_voxel_stats(ws.aligned("s0").lidar_map)
    assert man["sessions"]["s0"]["map_points"] == len(voxels)
    assert json.loads((semi / "manifest.json").read_text())["sessions"]["s0"]["map_points"] != len(voxels)
    entries = np.load(lidar / "entries.npz")
    np.testing.assert_array_equal(entries["position"], voxels.centroid[entries["point_index"]])
    traj = Trajectory.load(ws.aligned("s0").trajectory)
    frames = np.load(lidar / "frames.npz")
    np.testing.assert_allclose(frames["world_from_cam"], traj.world_from_base[frames["frame_id"]])
    # a query from s1's LiDAR map, frames in the middle of the street: each votes for the s0 frame at its place
    idx = StructureIndex.load(lidar)
    q = lidar_observations(load_voxel_stats(ws.aligned("s1").lidar_map), Trajectory.load(ws.aligned("s1").trajectory))
    table = session_frames(q)
    mid = table["frame_id"][np.abs(table["world_from_cam"][:, 0, 3] - STREET_M / 2) < 30][::2]
    res = idx.query_session_frames(q, mid.tolist(), name="s1")
    q_x = Trajectory.load(ws.aligned("s1").trajectory).world_from_base[mid, 0, 3]
    err = np.abs(idx.frame_positions()[res.best_frame, 0] - q_x)
    # frames 2 m apart, a voxel observed by those within 15 m: the votes peak at the place (a random frame of the
    # 160 m street would lie within 10 m one time in eight)
    assert len(mid) >= 10 and np.all(res.best_frame >= 0)
    print("lidar index place error m:", np.round(err, 1))
    assert np.mean(err <= 10.0) >= 0.8 and np.median(err) <= 4.0, np.round(err, 1)


def test_eval_places_on_lidar_maps_scores_lidar_frames_beside_the_semidense_run(aligned, capsys):
    """``mapkit eval places --map-source lidar``: its own folder (eval/places-lidar) beside the semi-dense run's, the
    queries the frames of the query drive's LiDAR map, the database index cut from the database drive's LiDAR
    voxels; on the test street a query frame finds its place (both drives pass the same facades); a pair whose drive
    has no LiDAR map is one error naming it."""
    from mapkit.places.index_structure import session_frames

    cfg = aligned / "places.yaml"
    cfg.write_text(json.dumps({"structure": {"keypoint_fraction": 0.03}, "split": "none", "bootstrap": 0}))
    ws = Workspace(aligned)
    args = ["eval", "places", str(aligned), "-p", "s0:s1", "-m", "nbld", "-c", str(cfg)]
    assert main([*args, "--map-source", "lidar"]) == 0
    out = aligned / "eval" / "places-lidar"
    assert ws.places_eval_folder("lidar") == out and not ws.places_eval_dir.exists()
    r = json.loads((out / "places.json").read_text())
    assert r["map_source"] == "lidar" and r["config"]["structure"]["map_source"] == "lidar"
    pair = r["pairs"][0]
    q = lidar_observations(load_voxel_stats(ws.aligned("s1").lidar_map), Trajectory.load(ws.aligned("s1").trajectory))
    assert pair["all_places"]["queries"] == len(session_frames(q)["frame_id"][:: r["query_stride"]])
    assert r["maps"]["s0"]["points"] == len(load_voxel_stats(ws.aligned("s0").lidar_map))
    index = Path(pair["methods"]["nbld"]["index"])
    assert json.loads((index / "manifest.json").read_text())["config"]["map_source"] == "lidar"
    assert pair["all_places"]["methods"]["nbld"]["auc"] >= 0.8, pair["all_places"]["methods"]["nbld"]
    assert "from the LiDAR maps" in (out / "places.md").read_text()
    before = (out / "places.json").read_bytes()
    capsys.readouterr()
    assert main([*args[:4], "s0:s2", *args[5:], "--map-source", "lidar"]) == 2
    assert "session 's2' has no LiDAR" in capsys.readouterr().err
    assert (out / "places.json").read_bytes() == before  # the earlier run's results stand


def test_coarsen_merges_voxels_by_count_and_keeps_the_times_they_were_seen():
    """Three 0.25 m voxels, two of them in one 1 m cell: the merged centroid is their count-weighted mean, the counts
    add, the intensity is the count-weighted mean of the voxels that had one, the stamps span both; the third voxel
    stays as it was; a voxel size not above the map's is refused."""
    from mapkit.mapping.voxel_map import VoxelStats
    from mapkit.places.lidar_observations import coarsen

    fine = VoxelStats(
        0.25,
        np.array([[0.1, 0.1, 0.1], [0.6, 0.1, 0.1], [1.5, 0.2, 0.3]]),
        np.array([1, 3, 2]),
        np.array([10.0, np.nan, 7.0]),
        np.full((3, 3), 0.5),
        np.full(3, 0.9),
        np.array([50, 20, 5]),
        np.array([60, 90, 8]),
    )
    c = coarsen(fine, 1.0)
    assert len(c) == 2 and c.voxel_size_m == 1.0
    np.testing.assert_allclose(c.centroid, [[0.475, 0.1, 0.1], [1.5, 0.2, 0.3]])
    np.testing.assert_array_equal(c.count, [4, 2])
    np.testing.assert_allclose(c.intensity, [10.0, 7.0])
    np.testing.assert_array_equal(c.first_ns, [20, 5])
    np.testing.assert_array_equal(c.last_ns, [90, 8])
    assert np.all(np.isnan(c.normal)) and np.all(np.isnan(c.planarity))
    with pytest.raises(ValueError, match="not larger"):
        coarsen(fine, 0.25)


def test_coarsen_sorts_packed_voxel_keys_as_it_sorts_their_rows(monkeypatch):
    """Merging 20,000 random voxels either side of the origin through one packed int64 key per voxel gives exactly
    the merge through np.unique of the (i, j, k) rows (every field, bit for bit); a map beyond the packed keys'
    range (a voxel 2,000 km out at 1 m) takes the rows' way and still merges."""
    from mapkit.mapping.voxel_map import VoxelStats
    from mapkit.places import lidar_observations

    rng = np.random.default_rng(3)
    n = 20_000
    centroid = rng.uniform(-60.0, 60.0, (n, 3))
    fine = VoxelStats(
        0.25,
        centroid,
        rng.integers(1, 9, n),
        np.where(rng.random(n) < 0.2, np.nan, rng.uniform(0, 100, n)),
        np.full((n, 3), 0.5),
        np.full(n, 0.9),
        rng.integers(0, 10**9, n),
        rng.integers(10**9, 2 * 10**9, n),
    )
    packed = lidar_observations.coarsen(fine, 1.5)
    monkeypatch.setattr(lidar_observations, "packable", lambda keys: False)
    rows = lidar_observations.coarsen(fine, 1.5)
    monkeypatch.undo()
    assert 1000 < len(packed) < n
    for field in ("centroid", "count", "intensity", "first_ns", "last_ns"):
        np.testing.assert_array_equal(getattr(packed, field), getattr(rows, field))
    far = VoxelStats(
        0.25,
        centroid + [2.0e6, 0.0, 0.0],
        *[getattr(fine, f) for f in ("count", "intensity", "normal", "planarity", "first_ns", "last_ns")],
    )
    moved = lidar_observations.coarsen(far, 1.0)
    assert len(moved) == len(lidar_observations.coarsen(fine, 1.0))


def test_a_lidar_map_read_again_unchanged_is_read_once(aligned, tmp_path, monkeypatch):
    """Loading a session's LiDAR map twice with the same merge reads it once (the same object); another merge, or
    the map's trajectory changed on disk, reads it again."""
    import shutil

    from mapkit.places import index_structure

    ws = Workspace(shutil.copytree(aligned, tmp_path / "ws", symlinks=True))
    reads = []
    real = index_structure.load_lidar_observations
    monkeypatch.setattr(index_structure, "load_lidar_observations", lambda *a: reads.append(a) or real(*a))
    folder, where = ws.session_map("s0", True, "lidar")
    first = index_structure.load_session_map(ws, "s0", folder, where, "lidar", 0.5)
    assert index_structure.load_session_map(ws, "s0", folder, where, "lidar", 0.5) is first
    assert len(reads) == 1
    other = index_structure.load_session_map(ws, "s0", folder, where, "lidar", 1.0)
    assert len(reads) == 2 and len(other.points_world) < len(first.points_world)
    trajectory = sorted(ws.map_trajectory("s0", where).glob("*.npz"))[0]
    with np.load(trajectory) as z:
        arrays = {k: z[k] for k in z.files}
    np.savez(trajectory, **{k: (v + 1.0 if v.dtype.kind == "f" else v) for k, v in arrays.items()})
    again = index_structure.load_session_map(ws, "s0", folder, where, "lidar", 0.5)
    assert len(reads) == 3 and again is not first


def test_a_merge_voxel_not_above_the_maps_own_is_a_warning_and_the_map_as_built(aligned):
    """lidar_voxel_m at or below the built 0.25 m voxels has nothing to merge: one warning naming the folder, and
    every voxel of the map; above it, fewer points than voxels."""
    from mapkit.core.errors import InputWarning
    from mapkit.places.lidar_observations import load_lidar_observations

    ws = Workspace(aligned)
    folder, traj = ws.aligned("s0").lidar_map, ws.aligned("s0").trajectory
    voxels = len(load_voxel_stats(folder))
    with pytest.warns(InputWarning, match=r"lidar_voxel_m 0.2 is not above the map's 0.25 m voxels"):
        assert len(load_lidar_observations(folder, traj, 0.2)) == voxels
    assert len(load_lidar_observations(folder, traj, 1.0)) < voxels / 4
