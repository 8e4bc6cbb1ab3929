"""The structure voting index against known answers: a street of boxes mapped twice (two random
halves of its surfaces, different lanes and frame positions) must vote each query frame onto the
database frame at the same place; hand-built CSRs give hand-computed votes; rotating a session's
map about z changes nothing; a damaged bundle is refused."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from test_align import STREET_M, street  # the street of boxes: fronts, side walls, poles, ground

from mapkit.core.errors import ConfigError, InputError
from mapkit.core.geometry import make_pose, yaw_rotation
from mapkit.core.runio import read_timings, write_json
from mapkit.mapping.semidense import SemiDenseMap
from mapkit.places.index_structure import (
    _DESCRIBERS,
    POSE_INTERPOLATED,
    POSE_KEYFRAME,
    POSE_NONE,
    StructureIndex,
    StructureIndexConfig,
    build_structure_index,
    register_describer,
    session_frames,
    vote_counts,
    vote_many,
)

FAST = {"keypoint_fraction": 0.02}  # ~900 keypoints per session of the test street (the paper: 0.05)


def street_map(
    world: np.ndarray, rng: np.random.Generator, lane_y: float, x0: float, keep: float = 0.3
) -> SemiDenseMap:
    """One mapping of the street: a random ``keep`` of its surface samples with 3 cm noise, seen
    by a forward camera (+x) at 1 m spacing from ``x0``. Frame i sits at x0 + i; odd ids are
    keyframes (posed), even ids non-key neighbours. A point is observed by every frame 5-15 m
    behind it, like the few frames of a semi-dense mapper's window."""
    pts = world[rng.random(len(world)) < keep]
    pts = pts + rng.normal(0, 0.03, pts.shape)
    frame_x = np.arange(x0, STREET_M, 1.0)
    ids = np.arange(1, len(frame_x) + 1, dtype=np.int64)
    lo = np.searchsorted(frame_x, pts[:, 0] - 15.0)
    hi = np.searchsorted(frame_x, pts[:, 0] - 5.0, side="right")
    ok = hi - lo >= 2
    pts, lo, hi = pts[ok], lo[ok], hi[ok]
    counts = hi - lo
    indptr = np.r_[0, np.cumsum(counts)].astype(np.int64)
    obs = ids[np.repeat(lo - indptr[:-1], counts) + np.arange(indptr[-1])]
    kf = ids % 2 == 1
    poses = np.stack([make_pose(np.eye(3), [x, lane_y, 1.5]) for x in frame_x[kf]])
    return SemiDenseMap(
        points_world=pts,
        intensity=np.full(len(pts), 128, np.uint8),
        sigma_depth=np.full(len(pts), 0.05, np.float32),
        source_keyframe=obs[indptr[:-1]],
        obs_indptr=indptr,
        obs_frame_ids=obs,
        keyframe_ids=ids[kf],
        keyframe_stamps_ns=(1_000_000_000 + ids[kf] * 100_000_000).astype(np.int64),
        keyframe_world_from_cam=poses,
        K=np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]),
        image_size_wh=(640, 480),
    )


def rotated(smap: SemiDenseMap, yaw: float, shift) -> SemiDenseMap:
    """The same map in a frame turned by ``yaw`` about z and shifted."""
    T = make_pose(yaw_rotation(yaw), shift)
    return SemiDenseMap(
        points_world=smap.points_world @ T[:3, :3].T + T[:3, 3],
        intensity=smap.intensity,
        sigma_depth=smap.sigma_depth,
        source_keyframe=smap.source_keyframe,
        obs_indptr=smap.obs_indptr,
        obs_frame_ids=smap.obs_frame_ids,
        keyframe_ids=smap.keyframe_ids,
        keyframe_stamps_ns=smap.keyframe_stamps_ns,
        keyframe_world_from_cam=T @ smap.keyframe_world_from_cam,
        K=smap.K,
        image_size_wh=smap.image_size_wh,
    )


def make_street_workspace(ws: Path, seed: int = 3) -> dict[str, SemiDenseMap]:
    """A workspace whose sessions "a" (database) and "b" (a re-mapping: other points, other lane,
    frames 0.5 m further on) drove the same street; written as aligned sessions."""
    world = street(np.random.default_rng(seed))
    maps = {
        "a": street_map(world, np.random.default_rng(10), -2.0, 0.0),
        "b": street_map(world, np.random.default_rng(11), -1.0, 0.5),
    }
    for name, m in maps.items():
        m.save(ws / "align" / "sessions" / name / "map")
    write_json(ws / "align" / ".done", {"config_hash": "test", "sessions": sorted(maps)})
    return maps


@pytest.fixture(scope="module")
def street_ws(tmp_path_factory):
    ws = tmp_path_factory.mktemp("ws")
    return ws, make_street_workspace(ws)


@pytest.fixture(scope="module")
def nbld_index(street_ws):
    ws, _ = street_ws
    return build_structure_index(ws, "nbld", sessions=["a"], overrides=FAST, cache_dir=ws / "cache")


# --------------------------------------------------------------------------- voting on hand-built CSRs


def test_vote_counts_equal_hand_computed_votes():
    # entry 0 was observed by frames 0, 1; entry 1 by 1, 2, 3; entry 2 by 3; frame 4 by none
    ref_indptr = np.array([0, 2, 5, 6])
    ref_frame = np.array([0, 1, 1, 2, 3, 3])
    # four query keypoints matched entries 0, 1, 1, 2: each match votes for every observer
    v = vote_counts(np.array([0, 1, 1, 2]), ref_indptr, ref_frame, 5)
    np.testing.assert_array_equal(v, [1, 3, 2, 3, 0])
    assert vote_counts(np.zeros(0, np.int64), ref_indptr, ref_frame, 5).tolist() == [0] * 5
    # two query frames at once: frame 0 matched entries 0, 1; frame 1 matched entries 1, 2, 2
    r, f, n = vote_many(np.array([0, 0, 1, 1, 1]), np.array([0, 1, 1, 2, 2]), ref_indptr, ref_frame, 5)
    got = {(int(a), int(b)): int(c) for a, b, c in zip(r, f, n, strict=True)}
    assert got == {(0, 0): 1, (0, 1): 2, (0, 2): 1, (0, 3): 1, (1, 1): 1, (1, 2): 1, (1, 3): 3}
    # sorted by row, then votes descending, then frame: the first triple of a row is its best frame
    assert list(zip(r.tolist(), f.tolist(), strict=True)) == [(0, 1), (0, 0), (0, 2), (0, 3), (1, 3), (1, 1), (1, 2)]


def test_session_frames_interpolates_non_key_frames():
    T = np.stack([make_pose(np.eye(3), [x, 0.0, 0.0]) for x in (0.0, 4.0)])
    smap = SemiDenseMap(
        points_world=np.zeros((2, 3)),
        intensity=np.zeros(2, np.uint8),
        sigma_depth=np.zeros(2, np.float32),
        source_keyframe=np.array([10, 12]),
        obs_indptr=np.array([0, 2, 4]),
        obs_frame_ids=np.array([10, 11, 12, 13]),
        keyframe_ids=np.array([10, 12]),
        keyframe_stamps_ns=np.array([1000, 3000]),
        keyframe_world_from_cam=T,
        K=np.eye(3),
        image_size_wh=(1, 1),
    )
    f = session_frames(smap)
    assert f["frame_id"].tolist() == [10, 11, 12, 13]
    assert f["pose_source"].tolist() == [POSE_KEYFRAME, POSE_INTERPOLATED, POSE_KEYFRAME, POSE_NONE]
    np.testing.assert_allclose(f["world_from_cam"][1, :3, 3], [2.0, 0.0, 0.0])
    assert f["stamp_ns"].tolist() == [1000, 2000, 3000, -1]
    assert np.all(np.isnan(f["world_from_cam"][3]))


def test_session_frames_interpolate_over_time_when_frames_are_unevenly_spaced():
    # keyframes 10 (t = 1000 ns, x = 0) and 14 (t = 2000 ns, x = 4, turned 90 deg); the camera
    # delivered frames 11-13 at 1100, 1200 and 1900 ns: over time they sit at x = 0.4, 0.8, 3.6
    # (frame ids would put them at 1, 2, 3). Frame 15 is past the last keyframe; frame 16 is not
    # in the stamp table.
    T = np.stack([make_pose(np.eye(3), [0.0, 0.0, 0.0]), make_pose(yaw_rotation(np.pi / 2), [4.0, 0.0, 0.0])])
    smap = SemiDenseMap(
        points_world=np.zeros((2, 3)),
        intensity=np.zeros(2, np.uint8),
        sigma_depth=np.zeros(2, np.float32),
        source_keyframe=np.array([10, 14]),
        obs_indptr=np.array([0, 3, 6]),
        obs_frame_ids=np.array([10, 11, 12, 13, 14, 15]),
        keyframe_ids=np.array([10, 14]),
        keyframe_stamps_ns=np.array([1000, 2000]),
        keyframe_world_from_cam=T,
        K=np.eye(3),
        image_size_wh=(1, 1),
    )
    stamps = (np.array([15, 13, 12, 11, 10, 14]), np.array([2500, 1900, 1200, 1100, 1000, 2000]))  # any order
    f = session_frames(smap, stamps)
    assert f["frame_id"].tolist() == [10, 11, 12, 13, 14, 15]
    assert f["pose_source"].tolist() == [
        POSE_KEYFRAME,
        POSE_INTERPOLATED,
        POSE_INTERPOLATED,
        POSE_INTERPOLATED,
        POSE_KEYFRAME,
        POSE_NONE,
    ]
    assert f["stamp_ns"].tolist() == [1000, 1100, 1200, 1900, 2000, -1]
    np.testing.assert_allclose(f["world_from_cam"][1:4, :3, 3], [[0.4, 0, 0], [0.8, 0, 0], [3.6, 0, 0]], atol=1e-12)
    np.testing.assert_allclose(
        f["world_from_cam"][3, :3, :3], yaw_rotation(0.9 * np.pi / 2), atol=1e-12
    )  # slerp, 90 % of the turn
    assert np.all(np.isnan(f["world_from_cam"][5]))
    # without the stamp table: over frame ids, as a constant camera rate would have it
    g = session_frames(smap)
    np.testing.assert_allclose(g["world_from_cam"][1:4, :3, 3], [[1, 0, 0], [2, 0, 0], [3, 0, 0]], atol=1e-12)
    assert g["stamp_ns"].tolist() == [1000, 1250, 1500, 1750, 2000, -1]
    # a table that lacks a frame: that frame falls back to its frame id
    h = session_frames(smap, (np.array([11]), np.array([1100])))
    np.testing.assert_allclose(h["world_from_cam"][1:4, :3, 3], [[0.4, 0, 0], [2, 0, 0], [3, 0, 0]], atol=1e-12)


# --------------------------------------------------------------------------- the chain on the street


def _true_x(query: SemiDenseMap, frame_ids: np.ndarray) -> np.ndarray:
    pos = np.searchsorted(query.keyframe_ids, frame_ids)
    return query.keyframe_world_from_cam[pos, 0, 3]


def test_build_load_query_finds_the_same_place(street_ws, nbld_index):
    ws, maps = street_ws
    idx = StructureIndex.load(nbld_index)
    m = idx.manifest
    assert m["counts"]["dim"] == 25 and m["counts"]["raw_dim"] == 576 and m["descriptor"] == "nbld"
    assert m["sessions"]["a"]["map_source"] == "align" and m["sessions"]["a"]["frames_interpolated"] > 0
    n_a = len(maps["a"].points_world)
    assert len(idx) == round(0.02 * n_a)
    # every reference of an entry is a frame that observed its keypoint (global frame rows)
    e = 7
    refs = idx.entries["ref_frame"][idx.entries["ref_indptr"][e] : idx.entries["ref_indptr"][e + 1]]
    p = idx.entries["point_index"][e]
    assert idx.frames["frame_id"][refs].tolist() == maps["a"].observations(p).tolist()

    query = maps["b"]
    q_ids = query.keyframe_ids[5:-5]  # the ends see little of the street
    res = idx.query_session_frames(query, q_ids, name="b")
    assert len(res) == len(q_ids) and np.all(res.best_frame >= 0)
    err = np.abs(idx.frame_positions()[res.best_frame, 0] - _true_x(query, q_ids))
    # frames are 1 m apart and a keypoint's observers span 10 m: most votes land within a few metres
    # (a random frame of the 160 m street would be within 10 m one time in eight)
    assert np.mean(err <= 10.0) >= 0.9 and np.median(err) <= 2.0, np.round(err, 1)
    assert np.all(res.top_votes[:, 0] == res.best_votes) and np.all(np.diff(res.top_votes, axis=1) <= 0)
    assert np.all(res.accepted(0.0)) and not np.any(res.accepted(float(res.best_votes.max())))

    # one frame through query_frame (describe the keypoints it observed; bincount voting) = the batch
    prep = idx.prepare_query(query, "b")
    k = len(q_ids) // 2
    kp = prep.keypoints
    seen = np.flatnonzero(np.add.reduceat(kp.obs_frame_ids == q_ids[k], kp.obs_indptr[:-1]) > 0)
    one = idx.query_frame(query.points_world, kp.positions[seen], kp.observer_positions[seen])
    assert one.frame == res.best_frame[k] and one.votes == res.best_votes[k] and one.n_keypoints == res.n_keypoints[k]
    assert one.session == "a" and one.accepted
    np.testing.assert_array_equal(one.top_votes, res.top_votes[k][: len(one.top_votes)])


def test_rebuild_with_same_inputs_skips_and_config_change_rebuilds(street_ws, nbld_index):
    ws, _ = street_ws
    before = (nbld_index / "manifest.json").stat().st_mtime_ns
    assert (
        build_structure_index(ws, "nbld", sessions=["a"], overrides={**FAST, "lambda_v": 3.0}) == nbld_index
    )  # query-time only
    assert (nbld_index / "manifest.json").stat().st_mtime_ns == before
    other = build_structure_index(
        ws, "nbld", out=ws / "idx-pca10", sessions=["a"], overrides={**FAST, "pca_dim": 10}, cache_dir=ws / "cache"
    )
    assert StructureIndex.load(other).manifest["counts"]["dim"] == 10
    assert read_timings(other)["sessions"]["a"]["cached"]  # descriptors reused, only the PCA is new
    assert not list(ws.glob(".*partial*")) and not list((ws / "indexes").glob(".*partial*"))
    (ws / ".idx-pca12.partial-999999999-dead").mkdir()  # an interrupted build, its process gone
    build_structure_index(
        ws, "nbld", out=ws / "idx-pca12", sessions=["a"], overrides={**FAST, "pca_dim": 12}, cache_dir=ws / "cache"
    )
    assert not list(ws.glob(".*partial*"))


@pytest.mark.parametrize("kind", ["nbld", "m2dp"])
def test_votes_invariant_to_rotating_a_session_map_about_z(street_ws, kind, tmp_path):
    ws, maps = street_ws
    # a sparser draw keeps M2DP (~10x slower per patch than NBLD) quick; the query is described twice
    idx = StructureIndex.load(
        build_structure_index(ws, kind, out=tmp_path / kind, sessions=["a"], overrides={"keypoint_fraction": 0.01})
    )
    query = maps["b"]
    q_ids = query.keyframe_ids[10:-10:3]
    turned = rotated(query, 2.2, [310.0, -75.0, 4.0])
    a = idx.query_session_frames(query, q_ids, name="b")
    b = idx.query_session_frames(turned, q_ids, name="b")
    np.testing.assert_array_equal(b.n_keypoints, a.n_keypoints)
    # same top frame and votes; a point on a cell edge may flip one NBLD bit or move an M2DP
    # coefficient by float32 noise, so allow one frame in twenty to differ by a vote
    assert np.mean(b.best_frame == a.best_frame) >= 0.95
    assert np.mean(np.abs(b.best_votes - a.best_votes) <= 1) >= 0.95


# --------------------------------------------------------------------------- damaged bundles and hooks


def test_bad_manifest_version_and_checksum_are_refused(nbld_index, tmp_path):
    bad = tmp_path / "bad"
    shutil.copytree(nbld_index, bad)
    m = json.loads((bad / "manifest.json").read_text())
    m["format_version"] = 99
    (bad / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(InputError) as e:
        StructureIndex.load(bad)
    assert e.value.field == "format_version"

    shutil.rmtree(bad)
    shutil.copytree(nbld_index, bad)
    with open(bad / "entries.npz", "r+b") as f:
        f.seek(200)
        b = f.read(1)
        f.seek(200)
        f.write(bytes([b[0] ^ 0xFF]))
    with pytest.raises(InputError) as e:
        StructureIndex.load(bad)
    assert e.value.path == bad / "entries.npz" and "checksum" in str(e.value)

    with pytest.raises(InputError):
        StructureIndex.load(tmp_path / "nothing-here")


def test_cnn_hook_needs_a_registered_describer(street_ws, tmp_path):
    ws, _ = street_ws
    with pytest.raises(ConfigError):
        build_structure_index(ws, "cnn", out=tmp_path / "cnn", sessions=["a"], overrides=FAST)

    def fake_cnn(points, keypoints, observer_dirs, cfg, tree):  # height and a direction: any (M, D) descriptor
        return np.c_[keypoints[:, 2:], observer_dirs[:, :2], np.zeros((len(keypoints), 29))].astype(np.float32)

    register_describer("cnn", fake_cnn)
    try:
        idx = StructureIndex.load(
            build_structure_index(ws, "cnn", out=tmp_path / "cnn", sessions=["a"], overrides=FAST)
        )
        assert idx.manifest["counts"]["raw_dim"] == 32 and idx.kind == "cnn"
    finally:
        _DESCRIBERS.pop("cnn", None)


def test_unknown_session_is_an_input_error(street_ws, tmp_path):
    ws, _ = street_ws
    with pytest.raises(InputError) as e:
        build_structure_index(ws, "nbld", out=tmp_path / "x", sessions=["nope"])
    assert e.value.field == "database_sessions"
    assert StructureIndexConfig().pca_dim == 25 and StructureIndexConfig().keypoint_fraction == 0.05


@pytest.mark.parametrize("kind", ["nbld", "m2dp"])
def test_descriptors_are_identical_on_a_process_pool(street_ws, kind, monkeypatch):
    """Patch description goes through the run's executor: two spawned workers give the serial bits."""
    import mapkit.places.index_structure as ix
    from mapkit.core.executor import ProcessExecutor, use_executor

    monkeypatch.setattr(ix, "_DESCRIBE_CHUNK", 100)  # several chunks, so that their order matters
    _, maps = street_ws
    cfg = ix.StructureIndexConfig(**FAST)
    kps, serial, _ = ix.session_descriptors(maps["a"], "a", kind, cfg)
    assert len(kps) > 4 * 100 and serial.shape[0] == len(kps)
    with use_executor(ProcessExecutor(2)):
        kps2, pooled, _ = ix.session_descriptors(maps["a"], "a", kind, cfg)
    np.testing.assert_array_equal(kps2.positions, kps.positions)
    np.testing.assert_array_equal(pooled, serial)
