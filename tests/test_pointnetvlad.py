"""PointNetVLAD layout of a triplet dataset: written, read back with pickle and numpy, and checked
against the triplet dataset it comes from (same patches, positions and split)."""

from __future__ import annotations

import csv
import pickle
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from test_triplets import make_aligned_street  # noqa: E402

from mapkit.patches import CNN_DOMAIN  # noqa: E402
from mapkit.pointnetvlad import PointNetVladConfig, export_pointnetvlad, query_dict  # noqa: E402
from mapkit.triplets import TripletDataset, export_triplets  # noqa: E402

CFG = {"n_triplets": 120, "tile_size_m": 40.0, "buffer_m": 8.0, "test_fraction": 0.3, "negative_min_distance_m": 40.0,
       "negative_pool": 40, "shard_patches": 64, "places_per_cell": 4, "keypoint_fraction": 0.02}
PNV = {"enabled": True, "positive_distance_m": 10.0, "negative_distance_m": 30.0, "points": 512, "max_negatives": 50}


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    ws = make_aligned_street(tmp_path_factory.mktemp("pnv") / "ws")
    out = export_triplets(ws, out=ws.parent / "t", overrides=dict(CFG, pointnetvlad=PNV), progress=False)
    return ws, out


def _queries(folder: Path, name: str) -> dict:
    with open(folder / name, "rb") as f:
        return pickle.load(f)


def test_round_trip_distances_split_and_clouds(exported):
    ws, out = exported
    pnv = out / "pointnetvlad"
    ds = TripletDataset(out)
    t = ds.table
    train, test = _queries(pnv, "training_queries_baseline.pickle"), _queries(pnv, "test_queries_baseline.pickle")
    assert len(train) and len(test)
    # every patch of the dataset is a query of its own split, under consecutive keys
    assert len(train) + len(test) == len(t["patch_id"])
    for queries, split in ((train, "train"), (test, "test")):
        assert sorted(queries) == list(range(len(queries)))
        ids = np.array([q["patch_id"] for q in queries.values()])
        assert np.all(t["split"][ids] == split)
        ne = np.array([[q["northing"], q["easting"]] for q in queries.values()])
        assert np.allclose(ne, t["utm"][ids][:, [1, 0]])  # the dataset's own UTM positions
        n_pos = 0
        for k, q in queries.items():
            d = np.linalg.norm(ne - ne[k], axis=1)
            assert k not in q["positives"] and np.all(d[q["positives"]] <= PNV["positive_distance_m"])
            assert np.all(d[q["negatives"]] > PNV["negative_distance_m"])
            assert len(q["negatives"]) == min(PNV["max_negatives"], int((d > PNV["negative_distance_m"]).sum()))
            # every patch within the distance is listed
            assert set(q["positives"]) == set(np.flatnonzero(d <= PNV["positive_distance_m"]).tolist()) - {k}
            n_pos += len(q["positives"])
        assert n_pos > 0
    # no test query has a training patch within the tiles' buffer
    ne_train = np.array([[q["northing"], q["easting"]] for q in train.values()])
    ne_test = np.array([[q["northing"], q["easting"]] for q in test.values()])
    assert np.linalg.norm(ne_test[:, None] - ne_train[None], axis=2).min() >= CFG["buffer_m"]
    # the members of one correspondence set are positives of each other
    q_of = {q["patch_id"]: (k, q) for k, q in train.items()}
    tr = ds.triplets("train")
    for a, p, _ in tr[:20]:
        assert q_of[int(p)][0] in q_of[int(a)][1]["positives"]
    # clouds: exactly the point count, float64, within [-1, 1], and inside the patch's occupied voxels
    g = ds.grid
    half = CNN_DOMAIN.half_size
    for q in list(train.values())[:25] + list(test.values())[:10]:
        raw = np.fromfile(pnv / q["query"], dtype=np.float64)
        assert raw.size == PNV["points"] * 3
        pc = raw.reshape(-1, 3)
        assert np.abs(pc).max() <= 1.0 and np.ptp(pc, axis=0).min() > 0.05
        occ = ds.grids([q["patch_id"]])[0]
        ijk = np.minimum(((pc * half + half) * (g / (2 * half))).astype(int), g - 1)
        assert occ[ijk[:, 0], ijk[:, 1], ijk[:, 2]].all()
    # the CSV of locations: one row per cloud, PointNetVLAD's columns
    rows = []
    for name in ds.manifest["sessions"]:
        f = pnv / name / "pointcloud_locations.csv"
        if f.is_file():
            with open(f) as fh:
                r = list(csv.DictReader(fh))
            assert list(r[0]) == ["timestamp", "northing", "easting"]
            assert all((pnv / name / "pointcloud_patches" / f"{x['timestamp']}.bin").is_file() for x in r)
            rows += r
    assert len(rows) == len(t["patch_id"])


def test_standalone_export_is_reproducible(exported, tmp_path):
    ws, out = exported
    again = export_pointnetvlad(out, ws, tmp_path / "pnv", PointNetVladConfig(**PNV))
    a, b = _queries(out / "pointnetvlad", "training_queries_baseline.pickle"), _queries(again, "training_queries_baseline.pickle")
    assert a == b
    q = a[0]["query"]
    assert (out / "pointnetvlad" / q).read_bytes() == (again / q).read_bytes()


def test_query_dict_on_a_known_line():
    # queries every 5 m along a line: positives within 10 m, negatives beyond 30 m, capped
    north = np.arange(20) * 5.0
    q = query_dict(north, np.zeros(20), 10.0, 30.0, None, np.random.default_rng(0))
    assert q[0]["positives"] == [1, 2] and q[10]["positives"] == [8, 9, 11, 12]
    assert q[0]["negatives"] == list(range(7, 20)) and q[10]["negatives"] == [0, 1, 2, 3, 17, 18, 19]
    capped = query_dict(north, np.zeros(20), 10.0, 30.0, 5, np.random.default_rng(0))
    assert len(capped[0]["negatives"]) == 5 and set(capped[0]["negatives"]) <= set(range(7, 20))
    with pytest.raises(ValueError):
        PointNetVladConfig(positive_distance_m=60.0, negative_distance_m=50.0)
