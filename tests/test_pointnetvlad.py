"""PointNetVLAD layout of a triplet dataset, read back the way PointNetVLAD's own scripts read it
(the run CSVs as pandas parses them, file names built from the parsed timestamps, clouds as
float64 (N, 3), the training and evaluation pickles) and checked against the triplet dataset it
comes from (same patches, positions and split)."""

from __future__ import annotations

import csv
import json
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from test_triplets import make_aligned_street

from mapkit.places.patches import PatchDomain
from mapkit.places.pointnetvlad import (
    PointNetVladConfig,
    export_pointnetvlad,
    export_triplets_pointnetvlad,
    normalise_cloud,
    query_dict,
    remove_ground,
    unique_stamps,
)
from mapkit.places.triplets import TripletDataset

CFG = {
    "n_triplets": 120,
    "tile_size_m": 40.0,
    "buffer_m": 8.0,
    "test_fraction": 0.3,
    "negative_min_distance_m": 40.0,
    "negative_pool": 40,
    "shard_patches": 64,
    "places_per_cell": 4,
    "keypoint_fraction": 0.02,
}
PNV = {
    "enabled": True,
    "positive_distance_m": 10.0,
    "negative_distance_m": 30.0,
    "evaluation_distance_m": 25.0,
    "points": 512,
    "max_negatives": 50,
}


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    ws = make_aligned_street(tmp_path_factory.mktemp("pnv") / "ws")
    out = export_triplets_pointnetvlad(ws, out=ws.parent / "t", overrides=dict(CFG, pointnetvlad=PNV), progress=False)
    return ws, out


def _queries(folder: Path, name: str):
    with open(folder / name, "rb") as f:
        return pickle.load(f)


def _pandas_value(text: str):
    """A CSV cell as pandas' default parser types its column when every cell looks the same: an
    integer literal (leading zeros dropped, "000003" -> 3), else a float, else the text."""
    try:
        return int(text)
    except ValueError:
        pass
    try:
        return float(text)
    except ValueError:
        return text


def read_csv_like_pandas(path: Path) -> list[dict]:
    """``pd.read_csv(path, sep=",")`` as rows (pandas itself when installed)."""
    try:
        import pandas as pd
    except ImportError:
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
        columns = {k: [_pandas_value(r[k]) for r in rows] for k in (rows[0] if rows else {})}
        for k, vals in columns.items():  # a column is int only when all its cells are
            if not all(isinstance(v, int) for v in vals) and all(isinstance(v, (int, float)) for v in vals):
                columns[k] = [float(v) for v in vals]
        return [{k: columns[k][i] for k in columns} for i in range(len(rows))]
    return pd.read_csv(path, sep=",").to_dict("records")


def test_their_scripts_find_every_file_and_the_pickles_hold(exported):
    ws, out = exported
    pnv = out / "pointnetvlad"
    ds = TripletDataset(out)
    t = ds.table
    m = json.loads((pnv / "manifest.json").read_text())
    with open(pnv / "pointcloud_locations.csv", newline="") as f:
        listing = {r["file"]: r for r in csv.DictReader(f)}
    # generate_training_tuples_baseline.py: per run, read the CSV and build run/folder/ + str(timestamp) + .bin
    files, ne, split = [], [], []
    per_run = {}
    for run in m["runs"]:
        rows = read_csv_like_pandas(pnv / run / "pointcloud_locations.csv")
        assert list(rows[0]) == ["timestamp", "northing", "easting"]
        run_files = [f"{run}/pointcloud_patches/" + str(r["timestamp"]) + ".bin" for r in rows]
        assert [r["timestamp"] for r in rows] == sorted(r["timestamp"] for r in rows)  # unique, sortable names
        assert len(set(run_files)) == len(run_files)
        per_run[run] = (run_files, np.array([[r["northing"], r["easting"]] for r in rows]))
        files += run_files
        ne += [[r["northing"], r["easting"]] for r in rows]
        split += [listing[f]["split"] for f in run_files]
    ne, split = np.array(ne), np.array(split)
    assert len(files) == len(t["patch_id"]) - m["patches_left_out"] and m["patches_left_out"] < 0.2 * len(t["patch_id"])
    # every named file is a float64 (points, 3) cloud, zero-mean, within [-1, 1], spread as PointNetVLAD's (0.5)
    g, box = ds.grid, np.asarray(PatchDomain(**ds.manifest["domain"]).box_half_extents, np.float64)
    for k, f in enumerate(files):
        pc = np.fromfile(pnv / f, dtype=np.float64)
        assert pc.shape[0] == PNV["points"] * 3
        pc = pc.reshape(-1, 3)
        assert np.abs(pc).max() <= 1.0 and np.allclose(pc.mean(axis=0), 0.0, atol=1e-9)
        assert 0.3 < np.linalg.norm(pc, axis=1).mean() <= 0.5 + 1e-9
        if k % 7 == 0:  # back to metres in the patch frame: inside the patch's occupied voxels
            row = listing[f]
            metric = pc / float(row["scale"]) + np.array(
                [float(row[c]) for c in ("centroid_x_m", "centroid_y_m", "centroid_z_m")]
            )
            occ = ds.grids([int(row["patch_id"])])[0]
            ijk = np.clip(((metric + box) / (2 * box) * g).astype(int), 0, g - 1)
            # (a point on a voxel face may land on either side after the round trip through the scale)
            assert occ[ijk[:, 0], ijk[:, 1], ijk[:, 2]].mean() > 0.99
    # the training and test pickles: keys over the runs' CSV rows in order, as their script numbers them
    for split_name, name in (("train", "training_queries_baseline.pickle"), ("test", "test_queries_baseline.pickle")):
        queries = _queries(pnv, name)
        sel = np.flatnonzero(split == split_name)
        assert len(sel) > 0
        assert sorted(queries) == list(range(len(sel)))
        assert [queries[k]["query"] for k in range(len(sel))] == [files[i] for i in sel]
        pos = ne[sel]
        n_pos = 0
        for k, q in queries.items():
            assert (pnv / q["query"]).is_file()
            d = np.linalg.norm(pos - pos[k], axis=1)
            assert k not in q["positives"] and np.all(d[q["positives"]] <= PNV["positive_distance_m"])
            assert set(q["positives"]) == set(np.flatnonzero(d <= PNV["positive_distance_m"]).tolist()) - {k}
            assert np.all(d[q["negatives"]] > PNV["negative_distance_m"])
            assert len(q["negatives"]) == min(PNV["max_negatives"], int((d > PNV["negative_distance_m"]).sum()))
            assert all((pnv / queries[j]["query"]).is_file() for j in q["positives"][:3] + q["negatives"][:3])
            n_pos += len(q["positives"])
        assert n_pos > 0
        assert np.all(t["split"][[q["patch_id"] for q in queries.values()]] == split_name)
    # the members of one correspondence set are positives of each other
    train = _queries(pnv, "training_queries_baseline.pickle")
    q_of = {q["patch_id"]: (k, q) for k, q in train.items()}
    for a, p, _ in ds.triplets("train")[:20]:
        if int(a) in q_of and int(p) in q_of:
            assert q_of[int(p)][0] in q_of[int(a)][1]["positives"]
    # no test query has a training patch within the tiles' buffer
    assert np.linalg.norm(ne[split == "test"][:, None] - ne[split == "train"][None], axis=2).min() >= CFG["buffer_m"]
    # generate_test_sets.py's pickles: per run, the database (all its clouds) and the queries (its test clouds)
    database, query = (
        _queries(pnv, "mapkit_evaluation_database.pickle"),
        _queries(pnv, "mapkit_evaluation_query.pickle"),
    )
    assert len(database) == len(query) == len(m["runs"]) >= 2
    n_true = 0
    for i, run in enumerate(m["runs"]):
        run_files, run_ne = per_run[run]
        assert [database[i][k]["query"] for k in range(len(database[i]))] == run_files
        assert np.allclose([[e["northing"], e["easting"]] for e in database[i].values()], run_ne)
        tests = [f for f in run_files if listing[f]["split"] == "test"]
        assert [query[i][k]["query"] for k in range(len(query[i]))] == tests
    for j, qs in enumerate(query):
        for q in qs.values():
            assert (pnv / q["query"]).is_file() and j not in q
            for i in range(len(database)):
                if i == j:
                    continue
                d = np.linalg.norm(per_run[m["runs"][i]][1] - [q["northing"], q["easting"]], axis=1)
                assert q[i] == np.flatnonzero(d <= PNV["evaluation_distance_m"]).tolist()
                n_true += len(q[i])
    assert n_true > 0 and m["evaluation_queries"] == sum(len(q) for q in query)


def test_triplets_does_not_import_pointnetvlad():
    code = (
        "import sys, mapkit.places.triplets; assert 'mapkit.places.pointnetvlad' not in sys.modules; "
        "import mapkit.places.pointnetvlad"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_unique_stamps_sort_by_time():
    u = unique_stamps(np.array([5, 9, 5, 5, 6, 100]), np.array([3, 0, 1, 2, 0, 0]))
    assert u.tolist() == [7, 9, 5, 6, 8, 100]  # 5, 5, 5, 6 -> 5, 6, 7, 8 in tie-break order
    assert len(set(u.tolist())) == 6 and str(int(u[0])) == "7"


def test_ground_removal_and_normalisation():
    rng = np.random.default_rng(0)
    ground = np.c_[rng.uniform(-10, 10, (3000, 2)), rng.normal(-1.5, 0.05, 3000)]
    wall = np.c_[rng.uniform(-10, 10, 1500), np.full(1500, 6.0) + rng.normal(0, 0.05, 1500), rng.uniform(-1.5, 8, 1500)]
    kept = remove_ground(np.r_[ground, wall], 0.5, 15.0, np.random.default_rng(1))
    assert len(kept) < 1500 * 1.05 and kept[:, 2].min() > -1.5 + 0.4  # the wall stays, the ground goes
    assert len(remove_ground(wall, 0.5, 15.0, np.random.default_rng(1))) == len(
        wall
    )  # no horizontal plane: nothing removed
    pc, c, s = normalise_cloud(kept, 4096, np.random.default_rng(2))
    assert pc.shape == (4096, 3) and np.abs(pc).max() <= 1.0 and np.allclose(pc.mean(axis=0), 0, atol=1e-12)
    assert 0.4 < np.linalg.norm(pc, axis=1).mean() <= 0.5 + 1e-12
    metric = pc / s + c
    assert np.isin(metric.round(9).view([("", metric.dtype)] * 3), kept.round(9).view([("", kept.dtype)] * 3)).all()


def test_standalone_export_is_reproducible(exported, tmp_path):
    ws, out = exported
    again = export_pointnetvlad(out, ws, tmp_path / "pnv", PointNetVladConfig(**PNV))
    a, b = (
        _queries(out / "pointnetvlad", "training_queries_baseline.pickle"),
        _queries(again, "training_queries_baseline.pickle"),
    )
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
