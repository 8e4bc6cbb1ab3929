"""Triplet export on an aligned synthetic street: positives are one place seen by two sessions,
negatives are far away, train and test places are kept apart, and the loader round-trips."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from test_align import gps_error, make_workspace, street

from mapkit.core.errors import InputError, MapkitError
from mapkit.core.runio import DONE_MARKER, sha256_file
from mapkit.multisession.align import align_workspace
from mapkit.multisession.registration import Registration
from mapkit.places.triplets import (
    ChunkSets,
    GridIndex,
    NoTripletsError,
    TripletConfig,
    TripletDataset,
    export_triplets,
    load_aligned_sessions,
    make_patches,
    mapped_patches,
    place_chunks,
    read_shard,
    split_of,
    tile_split,
    write_shard_hdf5,
)

CFG = {
    "n_triplets": 150,
    "tile_size_m": 40.0,
    "buffer_m": 8.0,
    "test_fraction": 0.3,
    "negative_min_distance_m": 40.0,
    "negative_pool": 60,
    "shard_patches": 64,
    "places_per_cell": 4,
    "keypoint_fraction": 0.02,
}


def make_aligned_street(ws: Path) -> Path:
    """Three sessions of the test street, a few decimetres to metres apart by GPS, then aligned."""
    make_workspace(
        ws,
        street(np.random.default_rng(3)),
        {"s0": gps_error(1.0, -1.0, 0.2), "s1": gps_error(-1.0, 1.5, -0.2), "s2": gps_error(0.5, 0.5, 0.0)},
    )
    align_workspace(ws, progress=False)
    return ws


@pytest.fixture(scope="module")
def aligned(tmp_path_factory):
    return make_aligned_street(tmp_path_factory.mktemp("trip") / "ws")


def test_tiles_and_buffer_keep_train_and_test_apart():
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 400, (20000, 2))
    tiles = tile_split(xy, 100.0, 0.3, seed=1)
    assert set(tiles.values()) == {"train", "test"}
    split = split_of(xy, tiles, 100.0, 15.0)
    train, test = xy[split == "train"], xy[split == "test"]
    assert len(train) and len(test) and (split == "").sum() > 0
    from scipy.spatial import cKDTree

    d, _ = cKDTree(train).query(test)
    assert d.min() >= 15.0
    # the same seed gives the same tiles
    assert tile_split(xy, 100.0, 0.3, seed=1) == tiles


def test_grid_index_finds_what_a_kd_tree_finds():
    rng = np.random.default_rng(1)
    xy = rng.uniform(-50, 50, (5000, 2))
    g = GridIndex(xy, 5.0)
    centres = rng.uniform(-40, 40, (20, 2))
    indptr, indices = g.candidates_many(centres, 7.0)
    for k, c in enumerate(centres):
        cand = g.candidates(c, 7.0)
        inside = np.flatnonzero(np.hypot(*(xy - c).T) <= 7.0)
        assert set(inside) <= set(cand.tolist())
        assert np.array_equal(indices[indptr[k] : indptr[k + 1]], cand)  # the batched query, in the same order


def test_batched_patches_are_the_per_place_patches(aligned):
    """The export cuts a chunk's patches from each session's cell cloud in one batch, and the
    negatives' patches per session: the grids are those of the per-place procedure
    (make_patches on each member's local cloud moved by its transform)."""
    cfg = TripletConfig(**CFG)
    sessions, _ = load_aligned_sessions(aligned)
    rng = np.random.default_rng(0)
    kp_session = np.concatenate([np.full(len(s.points) // 50, si) for si, s in enumerate(sessions)])
    kp_index = np.concatenate([rng.choice(len(s.points), len(s.points) // 50, replace=False) for s in sessions])
    order, chunk = place_chunks(
        kp_session, kp_index, np.full(len(kp_session), "train", dtype=object), sessions, cfg, rng
    )
    # negatives: patches as mapped
    pick = order[:30]
    centres = np.array([sessions[kp_session[j]].points[kp_index[j]] for j in pick])
    obs = np.array([sessions[kp_session[j]].observer_pos[kp_index[j]] for j in pick])
    pts, indptr = mapped_patches(sessions, kp_session[pick], centres, cfg.domain)
    clouds = [sessions[kp_session[j]].around(c, cfg.domain.patch_radius) for j, c in zip(pick, centres, strict=True)]
    ref = make_patches(clouds, centres, obs, cfg)
    assert np.array_equal(np.diff(indptr), ref[3]) and ref[3].min() > 0
    from mapkit.places.triplets import make_patches_csr

    got = make_patches_csr(pts, indptr, centres, obs, cfg)
    assert all(np.array_equal(a, b) for a, b in zip(got, ref, strict=True))
    # correspondence sets: a chunk's members, moved by known transforms
    shift = {si: np.eye(4) for si in range(len(sessions))}
    for si in shift:
        shift[si][:3, 3] = [0.05 * si, -0.03 * si, 0.0]

    def icp_of(si, a, centre, reach, n_src, n_tgt):
        return Registration(shift[si] @ np.linalg.inv(shift[a]), 1.0, 0.1, 1.0, 0.1)

    n_sets = 0
    for c in np.unique(chunk)[:6]:
        places = order[chunk == c]
        sets = ChunkSets(places, sessions, kp_session, kp_index, cfg, icp_of)
        for j in places:
            res, rejected = sets.get(j)
            assert rejected == 0
            if res is None:
                continue
            n_sets += 1
            p = sessions[kp_session[j]].points[kp_index[j]]
            clouds, obs = [], []
            for si, T, f in zip(res["session"], res["transform"], res["frame"], strict=True):
                s = sessions[si]
                clouds.append(s.around(p, cfg.domain.patch_radius + 2.0) @ T[:3, :3].T + T[:3, 3])
                pi = kp_index[j] if si == kp_session[j] else s.tree3.query(p)[1]
                assert s.observer_frame[pi] == f
                obs.append(T[:3, :3] @ s.observer_pos[pi] + T[:3, 3])
            occ, dcg, yaw, npts = make_patches(clouds, np.repeat(p[None], len(clouds), axis=0), np.array(obs), cfg)
            assert res["session"][0] == kp_session[j] and len(res["session"]) >= 2
            assert np.array_equal(npts, res["points"]) and np.allclose(yaw, res["yaw"])
            assert np.array_equal(occ, res["occ"]) and np.array_equal(dcg, res["dcg"])
    assert n_sets > 0


def test_export_positives_negatives_split_and_loader(aligned, tmp_path):
    out = export_triplets(aligned, out=tmp_path / "t", overrides=CFG, progress=False)
    ds = TripletDataset(out, verify=True)
    t = np.concatenate([ds.triplets("train"), ds.triplets("test")])
    assert len(t) == CFG["n_triplets"]
    tab = ds.table
    # anchor and positive: one place (same set), two sessions; negative: far from the anchor
    assert np.all(tab["set_id"][t[:, 0]] == tab["set_id"][t[:, 1]]) and np.all(tab["set_id"][t[:, 0]] >= 0)
    assert np.all(tab["session"][t[:, 0]] != tab["session"][t[:, 1]])
    assert np.all(np.linalg.norm(tab["enu"][t[:, 0], :2] - tab["enu"][t[:, 1], :2], axis=1) < 1e-9)
    assert np.all(tab["role"][t[:, 2]] == "negative")
    assert (
        np.linalg.norm(tab["enu"][t[:, 0], :2] - tab["enu"][t[:, 2], :2], axis=1).min() > CFG["negative_min_distance_m"]
    )
    # no train patch within the buffer of a test patch
    tr, te = tab["utm"][tab["split"] == "train"], tab["utm"][tab["split"] == "test"]
    if len(tr) and len(te):
        d = np.linalg.norm(tr[:, None, :2] - te[None, :, :2], axis=2)
        assert d.min() >= CFG["buffer_m"]
    # the aligned sessions need little ICP: small transforms, low RMSE
    pos = tab["role"] == "positive"
    assert np.abs(tab["transform"][pos][:, :3, 3]).max() < 0.5 and tab["icp_rmse_m"][pos].max() <= 0.4
    # loader: unpacked grids, occupied where the street is, identical on a second read
    x1, x2, x3 = next(ds.batches(8, split="train" if len(ds.triplets("train")) else "test", shuffle=False))
    assert x1.shape == (8, 32, 32, 32) and x1.dtype == np.uint8 and set(np.unique(x1)) <= {0, 1}
    assert x1.sum() > 100 and x2.sum() > 100
    # the same place from two sessions overlaps far more than an anchor and its negative

    def inter(a, b):
        return (a & b).sum() / max(1, (a | b).sum())

    assert (
        np.mean([inter(a, b) for a, b in zip(x1, x2, strict=True)])
        > np.mean([inter(a, c) for a, c in zip(x1, x3, strict=True)]) + 0.1
    )
    dcg = ds.grids(t[:2, 0], "density_comparison")
    assert dcg.shape == (2, 3, 32, 32, 32)
    m = json.loads((out / "manifest.json").read_text())
    assert m["seed"] == 0 and m["patches"] == len(tab["patch_id"]) and (out / "examples.png").stat().st_size > 5000
    # reproducible: the same seed and inputs give the same triplets
    out2 = export_triplets(aligned, out=tmp_path / "t2", overrides=CFG, progress=False)
    assert np.array_equal(np.load(out / "triplets_train.npy"), np.load(out2 / "triplets_train.npy"))
    # a damaged shard is named
    shard = out / m["shards"][0]["file"]
    shard.write_bytes(shard.read_bytes()[:-10] + b"0123456789")
    with pytest.raises(InputError, match=m["shards"][0]["file"]):
        TripletDataset(out, verify=True)


def test_export_needs_an_alignment(tmp_path):
    (tmp_path / "ws").mkdir()
    with pytest.raises(InputError, match="mapkit align"):
        export_triplets(tmp_path / "ws", progress=False)


def test_a_failed_export_keeps_the_earlier_dataset(aligned, tmp_path, monkeypatch):
    import mapkit.places.triplets as tr

    out = export_triplets(aligned, out=tmp_path / "t", overrides=CFG, progress=False)
    before = (out / "manifest.json").read_text()

    def crash(*args, **kwargs):
        raise RuntimeError("killed half-way")

    monkeypatch.setattr(tr, "make_patches_csr", crash)
    with pytest.raises(RuntimeError, match="half-way"):
        export_triplets(aligned, out=out, overrides=dict(CFG, n_triplets=40), progress=False)
    assert (out / "manifest.json").read_text() == before
    TripletDataset(out, verify=True)  # every file as the manifest lists it
    assert not list(tmp_path.glob(".t.partial-*"))


def test_hdf5_shard_round_trip_with_plain_h5py(tmp_path):
    import h5py

    from mapkit.places.patches import pack_bits

    rng = np.random.default_rng(0)
    occ = pack_bits((rng.random((37, 32, 32, 32)) < 0.05).astype(np.uint8))
    dcg = pack_bits((rng.random((37, 3, 32, 32, 32)) < 0.05).astype(np.uint8))
    write_shard_hdf5(tmp_path / "s.h5", occ, dcg, first_id=100, grid=32)
    with h5py.File(tmp_path / "s.h5", "r") as f:
        assert np.array_equal(f["occupancy"][()], occ) and np.array_equal(f["density_comparison"][()], dcg)
        assert f["occupancy"].chunks == (16, 32, 32, 4) and f["density_comparison"].chunks == (16, 3, 32, 32, 4)
        assert f["occupancy"].compression == "gzip" and f.attrs["first_id"] == 100 and f.attrs["grid"] == 32
        assert f.attrs["patches"] == 37 and "packbits" in f.attrs["packing"]
        # a plain reader gets the grids back with np.unpackbits
        assert np.unpackbits(f["occupancy"][3], axis=-1, count=32).shape == (32, 32, 32)
    got = read_shard(tmp_path / "s.h5")
    assert (
        np.array_equal(got["occupancy"], occ)
        and np.array_equal(got["density_comparison"], dcg)
        and got["first_id"] == 100
    )
    np.savez(tmp_path / "s.npz", occupancy=occ, density_comparison=dcg, first_id=np.int64(100))
    old = read_shard(tmp_path / "s.npz")
    assert all(np.array_equal(old[k], got[k]) for k in got)
    (tmp_path / "bad.h5").write_bytes(b"not hdf5")
    with pytest.raises(InputError, match="bad.h5"):
        read_shard(tmp_path / "bad.h5")


def test_loader_reads_hdf5_npz_and_version_1_datasets(aligned, tmp_path):
    cfg = dict(CFG, n_triplets=40)
    h5 = export_triplets(aligned, out=tmp_path / "h5", overrides=cfg, progress=False)
    npz = export_triplets(aligned, out=tmp_path / "npz", overrides=dict(cfg, shard_format="npz"), progress=False)
    for folder, fmt, suffix in ((h5, "hdf5", ".h5"), (npz, "npz", ".npz")):
        m = json.loads((folder / "manifest.json").read_text())
        assert m["shard_format"] == fmt and m["shards"]
        for s in m["shards"]:
            assert s["file"].endswith(suffix) and s["bytes"] == (folder / s["file"]).stat().st_size
            assert s["sha256"] == sha256_file(folder / s["file"])
    a, b = TripletDataset(h5, verify=True), TripletDataset(npz, verify=True)
    ids = np.arange(a.manifest["patches"])
    assert np.array_equal(a.grids(ids), b.grids(ids)) and np.array_equal(
        a.grids(ids, "density_comparison"), b.grids(ids, "density_comparison")
    )
    # a dataset of the first format (version 1: npz shards, no shard_format) still reads
    m = json.loads((npz / "manifest.json").read_text())
    m["format_version"] = 1
    del m["shard_format"]
    (npz / "manifest.json").write_text(json.dumps(m))
    old = TripletDataset(npz)
    assert old.shard_format == "npz" and np.array_equal(old.grids(ids), a.grids(ids))
    x = next(old.batches(4, split="train" if len(old.triplets("train")) else "test"))
    assert x[0].shape == (4, 32, 32, 32)


def test_no_triplets_is_an_error_and_leaves_nothing_finished(aligned, tmp_path, capsys):
    out = tmp_path / "t"
    impossible = dict(CFG, min_patch_points=10**9)
    with pytest.raises(NoTripletsError) as err:
        export_triplets(aligned, out=out, overrides=impossible, progress=False)
    assert isinstance(err.value, MapkitError)
    msg = str(err.value)
    assert "no triplets" in msg and "min_patch_points" in msg and "\n" not in msg
    assert not out.exists() and not list(tmp_path.glob(".t.*"))  # no folder, no done-marker, no partial left
    # nothing far enough for a negative: the message names the setting
    with pytest.raises(NoTripletsError, match="negative_min_distance_m"):
        export_triplets(
            aligned, out=out, overrides=dict(CFG, negative_min_distance_m=1e5, n_triplets=10), progress=False
        )
    # an earlier finished dataset survives a run that makes nothing
    good = export_triplets(aligned, out=out, overrides=dict(CFG, n_triplets=20), progress=False)
    done = (good / DONE_MARKER).read_text()
    with pytest.raises(NoTripletsError):
        export_triplets(aligned, out=out, overrides=impossible, progress=False)
    assert (good / DONE_MARKER).read_text() == done
    TripletDataset(good, verify=True)
    # the CLI: one line on stderr, non-zero exit
    from mapkit.cli import main

    (tmp_path / "c.yaml").write_text("".join(f"{k}: {v}\n" for k, v in impossible.items()))
    capsys.readouterr()
    code = main(["triplets", str(aligned), "--out", str(tmp_path / "cli"), "--config", str(tmp_path / "c.yaml")])
    err_text = capsys.readouterr().err.strip()
    assert code != 0 and err_text.startswith("error:") and "no triplets" in err_text and len(err_text.splitlines()) == 1
    assert not (tmp_path / "cli").exists()
