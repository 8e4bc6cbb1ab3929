"""Place-recognition scoring against hand-computed answers (Table 1, PR curve, AUC), the held-out
query selection against hand-placed tiles and against a triplet dataset's split (Sec. 5.1), and the
whole evaluation on the street of boxes mapped twice, with a stand-in appearance method of known answer."""

from __future__ import annotations

import csv
import json
import warnings

import numpy as np
import pytest
from test_index_structure import make_street_workspace
from test_triplets import CFG as TRIPLETS_CFG
from test_triplets import make_aligned_street

from mapkit.core.config import dump_config
from mapkit.core.errors import InputError, InputWarning
from mapkit.core.geodesy import LocalFrame
from mapkit.core.runio import write_json
from mapkit.core.workspace import Workspace
from mapkit.evaluation.places import (
    PlacesEvalConfig,
    best_f1,
    evaluate_places,
    nearest_l2,
    nearest_stamp,
    pr_auc,
    pr_curve,
    resolve_split,
    score_queries,
    split_from_dataset,
    tiles_split_of_workspace,
)
from mapkit.places.triplets import TripletConfig, TripletDataset, export_triplets


def table1_counts(accepted: np.ndarray, correct: np.ndarray, reachable: np.ndarray) -> tuple[int, int, int]:
    """(tp, fp, fn) of Table 1 at one threshold, query by query, for boolean arrays over queries:
    match accepted, matched place within r_e, some database place within r_e. The reference that
    ``pr_curve``'s cumulative counts over every threshold are held against."""
    tp = int(np.sum(accepted & correct))
    fp = int(np.sum(accepted & ~correct))
    fn = int(np.sum(accepted & ~correct & reachable) + np.sum(~accepted & reachable))
    return tp, fp, fn


def test_table1_rows():
    # one query per row of Table 1: right match; wrong match, reachable; wrong match, unreachable;
    # no match, reachable; no match, unreachable
    accepted = np.array([1, 1, 1, 0, 0], bool)
    correct = np.array([1, 0, 0, 0, 0], bool)
    reachable = np.array([1, 1, 0, 1, 0], bool)
    for i, expected in enumerate([(1, 0, 0), (0, 1, 1), (0, 1, 0), (0, 0, 1), (0, 0, 0)]):
        assert table1_counts(accepted[i : i + 1], correct[i : i + 1], reachable[i : i + 1]) == expected
    assert table1_counts(accepted, correct, reachable) == (1, 2, 2)


def test_pr_curve_and_auc_of_a_hand_built_case():
    # scores with a tie and a query without any match (-inf); reachable: q0, q1, q2, q4 (4)
    scores = np.array([5.0, 4.0, 4.0, 2.0, -np.inf])
    correct = np.array([1, 0, 1, 0, 0], bool)
    reachable = np.array([1, 1, 1, 0, 1], bool)
    c = pr_curve(scores, correct, reachable)
    # t = 5: q0 right -> P 1, R 1/4; t = 4: + q1 wrong, q2 right -> P 2/3, R 2/4; t = 2: + q3 wrong -> P 2/4, R 2/4
    np.testing.assert_array_equal(c["thresholds"], [5.0, 4.0, 2.0])
    np.testing.assert_allclose(c["precision"], [1.0, 2 / 3, 0.5])
    np.testing.assert_allclose(c["recall"], [0.25, 0.5, 0.5])
    np.testing.assert_array_equal(c["fn"], [3, 2, 2])
    for k, t in enumerate(c["thresholds"]):  # every point agrees with Table 1 at its threshold
        assert table1_counts(scores >= t, correct, reachable) == (c["tp"][k], c["fp"][k], c["fn"][k])
    assert pr_auc(c["recall"], c["precision"]) == pytest.approx(0.25 * 1.0 + 0.25 * 2 / 3)
    b = best_f1(c)
    assert b["threshold"] == 4.0 and b["f1"] == pytest.approx(2 * (2 / 3) * 0.5 / (2 / 3 + 0.5))
    # a perfect method: every reachable query right, ranked above the rest
    perfect = pr_curve(np.array([3.0, 2.0, 1.0]), np.array([1, 1, 0], bool), np.array([1, 1, 0], bool))
    assert pr_auc(perfect["recall"], perfect["precision"]) == pytest.approx(1.0)
    assert pr_auc(np.zeros(0), np.zeros(0)) == 0.0
    with pytest.raises(InputError):
        pr_curve(np.array([1.0]), np.array([True]), np.array([False]))
    # no reachable query: recall is 0/0, so the AUC is undefined (None, said why), not 0
    from mapkit.evaluation.places import _summary

    r = _summary(np.array([3.0, 1.0]), np.zeros(2, bool), np.zeros(2, bool), np.array([50.0, 60.0]), 20)
    assert r["auc"] is None and r["auc_ci90"] is None and "2 queries" in r["auc_undefined"] and r["reachable"] == 0
    assert _summary(scores, correct, reachable, np.zeros(5), 0)["auc_undefined"] is None


def test_score_queries_and_matching_helpers():
    q = np.array([[0.0, 0, 0], [100, 0, 0], [200, 0, 0], [300, 0, 0]])
    db = np.array([[10.0, 0, 0], [110, 0, 0], [400, 0, 0]])
    matched = np.array([[10.0, 0, 0], [10, 0, 0], [400, 0, 0], [np.nan, np.nan, np.nan]])
    correct, reachable, err = score_queries(q, matched, np.array([1, 1, 1, 0], bool), db, 25.0)
    assert correct.tolist() == [True, False, False, False]
    assert reachable.tolist() == [True, True, False, False]
    np.testing.assert_allclose(err[:3], [10.0, 90.0, 200.0])
    assert np.isnan(err[3])
    rows, gap = nearest_stamp(np.array([30, 10, 20]), np.array([9, 14, 16, 100]))
    assert rows.tolist() == [1, 1, 2, 0] and gap.tolist() == [1, 4, 4, 70]
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(7, 5)), rng.normal(size=(40, 5))
    j, d2 = nearest_l2(a, b)
    full = ((a[:, None] - b[None]) ** 2).sum(-1)
    assert j.tolist() == full.argmin(1).tolist()
    np.testing.assert_allclose(d2, full.min(1), rtol=1e-9)


class PositionAppearance:
    """A stand-in image method whose descriptor is the camera position itself: its top-1 is the
    nearest database keyframe, so every reachable query is right, i.e. AUC 1 at r_e = 25 m."""

    def __init__(self, maps):
        self.maps = maps

    def database(self, session):
        m = self.maps[session]
        return m.keyframe_world_from_cam[:, :3, 3], m.keyframe_stamps_ns, m.keyframe_world_from_cam[:, :3, 3]

    def query_rows(self, session, stamps_ns):
        rows, gap = nearest_stamp(self.maps[session].keyframe_stamps_ns, stamps_ns)
        return rows, gap * 1e-9

    def encode(self, session, rows):
        return self.maps[session].keyframe_world_from_cam[rows, :3, 3]


def test_evaluate_places_on_the_street(tmp_path):
    ws = tmp_path / "ws"
    maps = make_street_workspace(ws)
    out = tmp_path / "eval"
    overrides = {"structure": {"keypoint_fraction": 0.02}, "query_stride": 3, "split": "none"}
    res = evaluate_places(
        ws,
        [("a", "b"), ("b", "a")],
        methods=["nbld", "vlad"],
        out=out,
        overrides=overrides,
        appearance=PositionAppearance(maps),
    )
    assert res["headline"] == "all_places" and res["split"]["source"] == "none"
    for p in res["pairs"]:
        assert p["held_out_queries"] is None and p["all_places"]["methods"]["nbld"] == p["methods"]["nbld"]
        nb, va = p["methods"]["nbld"], p["methods"]["vlad"]
        assert p["queries"] == len(maps[p["query"]].keyframe_ids[::3])
        assert nb["reachable"] == p["queries"]  # one street: every query has a database frame nearby
        # the street's last ~15 m are seen by few keypoints: some end frames vote wrong
        assert nb["auc"] > 0.7 and nb["top1_correct_of_reachable"] > 0.75, nb
        assert va["auc"] == pytest.approx(1.0) and va["median_error_m"] < 1.5
    for f in ("places.json", "places.md", "pr_curves.png", "queries.csv", "config.yaml"):
        assert (out / f).is_file()
    md = (out / "places.md").read_text()
    assert "| b to a |" in md and "| a to b |" in md and "NBLD" in md and "VLAD" in md
    # both maps' densities, side by side: the maps the pairs used, counted from their own points and keyframes
    for name in ("a", "b"):
        m, d = maps[name], res["maps"][name]
        path = np.linalg.norm(np.diff(m.keyframe_world_from_cam[:, :3, 3], axis=0), axis=1).sum()
        assert d["points"] == len(m) and d["keyframes"] == len(m.keyframe_ids)
        assert d["points_per_100m"] == pytest.approx(100 * len(m) / path)
    ratio = res["maps"]["b"]["points_per_100m"] / res["maps"]["a"]["points_per_100m"]
    assert "## Map densities" in md and f"| {ratio:.2f} |" in md
    assert json.loads((out / "places.json").read_text())["pairs"][0]["methods"]["nbld"]["curve"]["recall"]
    n_rows = len((out / "queries.csv").read_text().splitlines()) - 1
    assert n_rows == 2 * sum(p["queries"] for p in res["pairs"])

    # an appearance method trained on the query session cannot score it: left out with a note
    trained = PositionAppearance(maps)
    trained.train_sessions = ["b"]
    with pytest.warns(InputWarning, match="trained the VLAD encoder"):
        res3 = evaluate_places(
            ws, [("a", "b")], methods=["nbld", "vlad"], out=out, overrides=overrides, appearance=trained
        )
    assert res3["pairs"][0]["methods"]["vlad"]["available"] is False
    assert "trained the VLAD encoder" in (out / "places.md").read_text()

    # no VLAD bundle: the column is left empty with a warning, structure is still evaluated; the
    # default split needs UTM tiles, which a workspace without a geographic frame has not: all places, said so
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res2 = evaluate_places(
            ws,
            [("a", "b")],
            methods=["nbld", "vlad"],
            out=tmp_path / "eval2",
            overrides={k: v for k, v in overrides.items() if k != "split"},
        )
    said = [str(w.message) for w in caught if issubclass(w.category, InputWarning)]
    assert any("no VLAD bundle" in m for m in said) and any("no geographic frame" in m for m in said)
    assert res2["headline"] == "all_places" and "no geographic frame" in res2["split"]["notes"][0]
    assert res2["pairs"][0]["methods"]["vlad"]["available"] is False
    assert res2["pairs"][0]["methods"]["nbld"]["auc"] == pytest.approx(res["pairs"][0]["methods"]["nbld"]["auc"])
    assert "n/a" in (tmp_path / "eval2" / "places.md").read_text()


# --------------------------------------------------------------------------- held-out queries (Sec. 5.1)

FRAME = LocalFrame(47.37, 8.54, 400.0)


def enu_at_utm(frame: LocalFrame, utm_xy: np.ndarray) -> np.ndarray:
    """Local ENU positions of UTM points (inverse projection, then the tangent plane)."""
    lat, lon = frame.utm.inverse(utm_xy[:, 0], utm_xy[:, 1])
    return frame.geodetic_to_enu(lat, lon, np.full(len(utm_xy), frame.alt0_m))


def write_triplet_manifest(folder, frame: LocalFrame, tiles: dict, tile_m: float, buffer_m: float) -> None:
    """The two files of a triplet dataset the split is read from: manifest.json and config.yaml."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "config.yaml").write_text(dump_config(TripletConfig(tile_size_m=tile_m, buffer_m=buffer_m)))
    write_json(
        folder / "manifest.json",
        {
            "format_version": 2,
            "seed": 0,
            "config_hash": "hand",
            "frame": frame.to_dict(),
            "tiles": [{"utm_min": [i * tile_m, j * tile_m], "split": v} for (i, j), v in tiles.items()],
        },
    )


def test_held_out_queries_of_hand_placed_tiles(tmp_path):
    # tiles of 100 m, buffer 10 m: (i0, j0) test, its east neighbour and its north-east diagonal train,
    # everything else unlabelled (a tile without a label counts as training, never as test)
    i0, j0 = (np.floor(FRAME.enu_to_utm(np.zeros((1, 3)))[0, :2] / 100.0)).astype(int)
    x0, y0 = i0 * 100.0, j0 * 100.0
    tiles = {(int(i0), int(j0)): "test", (int(i0) + 1, int(j0)): "train", (int(i0) + 1, int(j0) + 1): "train"}
    write_triplet_manifest(tmp_path / "ds", FRAME, tiles, 100.0, 10.0)
    cases = [  # UTM offset from the test tile's corner, expected label
        ((50.0, 50.0), "test"),  # middle of the test tile
        ((95.0, 50.0), "buffer"),  # 5 m from the training tile to the east
        ((89.0, 50.0), "test"),  # 11 m from it
        ((105.0, 50.0), "buffer"),  # in the training tile, 5 m from the test tile
        ((150.0, 50.0), "train"),  # middle of the training tile
        ((5.0, 50.0), "test"),  # 5 m from an unlabelled tile: no buffer towards it
        (
            (94.0, 94.0),
            "buffer",
        ),  # 6 m and 6 m from the diagonal training tile's corner: 8.5 m (and 6 m from the east one)
        ((-50.0, 50.0), "train"),  # an unlabelled tile
    ]
    utm = np.array([[x0 + dx, y0 + dy] for (dx, dy), _ in cases])
    enu = enu_at_utm(FRAME, utm)
    np.testing.assert_allclose(FRAME.enu_to_utm(enu)[:, :2], utm, atol=1e-6)
    split = split_from_dataset(tmp_path / "ds", FRAME)
    assert split.source == "triplets" and split.tiles == tiles and (split.tile_size_m, split.buffer_m) == (100.0, 10.0)
    assert split.labels(enu).tolist() == [label for _, label in cases]
    assert split.held_out(enu).tolist() == [label == "test" for _, label in cases]
    # the diagonal alone: 8.5 m from its corner is in the buffer, 11.3 m is not
    diag = {(int(i0), int(j0)): "test", (int(i0) + 1, int(j0) + 1): "train"}
    write_triplet_manifest(tmp_path / "diag", FRAME, diag, 100.0, 10.0)
    d = split_from_dataset(tmp_path / "diag", FRAME)
    assert d.labels(enu_at_utm(FRAME, np.array([[x0 + 94.0, y0 + 94.0], [x0 + 92.0, y0 + 92.0]]))).tolist() == [
        "buffer",
        "test",
    ]
    # a dataset in another UTM zone, or tiles off the config's grid, are refused
    with pytest.raises(InputError, match="EPSG"):
        split_from_dataset(tmp_path / "ds", LocalFrame(47.37, 14.0, 400.0))
    write_triplet_manifest(tmp_path / "odd", FRAME, tiles, 100.0, 10.0)
    (tmp_path / "odd" / "config.yaml").write_text(dump_config(TripletConfig(tile_size_m=30.0)))
    with pytest.raises(InputError, match="tile"):
        split_from_dataset(tmp_path / "odd", FRAME)


@pytest.fixture(scope="module")
def street_with_triplets(tmp_path_factory):
    """The aligned three-session street of the triplet tests, with its triplet dataset where the workspace keeps it."""
    ws = make_aligned_street(tmp_path_factory.mktemp("held") / "ws")
    export_triplets(ws, out=Workspace(ws).triplets_dir, overrides=TRIPLETS_CFG, progress=False)
    return ws


def test_the_split_is_the_triplet_datasets(street_with_triplets):
    ws = Workspace(street_with_triplets)
    ds = TripletDataset(ws.triplets_dir)
    split = resolve_split(ws, PlacesEvalConfig())
    assert split.source == "triplets" and split.dataset == str(ws.triplets_dir.resolve())
    assert split.to_dict()["tiles"] == sorted(ds.manifest["tiles"], key=lambda t: t["utm_min"])
    # every patch of the dataset, taken as a query place, lands in the split the dataset gave it
    tab = ds.table
    assert set(tab["split"]) == {"train", "test"}
    assert split.labels(tab["enu"]).tolist() == tab["split"].tolist()
    # drawn afresh with the dataset's parameters, the tiles are the dataset's (same function, same points)
    frame = ws.require_frame()
    assert tiles_split_of_workspace(ws, frame, TripletConfig(**TRIPLETS_CFG)).tiles == split.tiles
    # split = tiles: TripletConfig's defaults
    t = resolve_split(ws, PlacesEvalConfig(split="tiles"))
    assert t.source == "tiles" and (t.tile_size_m, t.buffer_m, t.test_fraction, t.seed) == (200.0, 30.0, 0.25, 0)
    assert resolve_split(ws, PlacesEvalConfig(split="none")).labels(tab["enu"][:3]).tolist() == ["", "", ""]


def _csv_rows(path, method: str) -> list[dict]:
    with open(path, newline="") as f:
        return [r for r in csv.DictReader(f) if r["method"] == method]


def test_evaluate_places_scores_held_out_queries(street_with_triplets, tmp_path):
    ws = Workspace(street_with_triplets)
    frame = ws.require_frame()
    man = json.loads((ws.triplets_dir / "manifest.json").read_text())
    tile, buf = TRIPLETS_CFG["tile_size_m"], TRIPLETS_CFG["buffer_m"]
    # the dataset's random tiles put the street along a boundary between a test and a training
    # row of tiles (its queries all in buffer strips); the same tiles split by columns instead
    keys = sorted(tuple(int(round(v / tile)) for v in t["utm_min"]) for t in man["tiles"])
    i_test = sorted({i for i, _ in keys})[1:3]
    tiles = {k: "test" if k[0] in i_test else "train" for k in keys}
    columns = tmp_path / "columns"
    write_triplet_manifest(columns, frame, tiles, tile, buf)
    ov = {"structure": {"keypoint_fraction": 0.05}, "query_stride": 2, "bootstrap": 50, "triplets_dir": str(columns)}
    out = tmp_path / "eval"
    res = evaluate_places(ws, [("s0", "s1")], methods=["nbld"], out=out, overrides=ov)
    assert res["headline"] == "held_out" and res["split"]["source"] == "triplets"
    p = res["pairs"][0]
    rows = _csv_rows(out / "queries.csv", "nbld")
    pos = np.array([[float(r[k]) for k in ("x_m", "y_m", "z_m")] for r in rows])

    # the known answer, worked out here: a query's own tile gives its split (a tile without a label
    # trains), unless it lies within the buffer of a labelled tile of the other split
    def distance_to_tile(u, key):
        lo = np.array(key) * tile
        return float(np.hypot(*np.maximum(np.maximum(lo - u, u - (lo + tile)), 0.0)))

    expected = []
    for u in frame.enu_to_utm(pos)[:, :2]:
        own = tiles.get(tuple(int(i) for i in np.floor(u / tile)), "train")
        near_other = any(distance_to_tile(u, k) < buf for k, v in tiles.items() if v != own)
        expected.append("buffer" if near_other else own)
    expected = np.array(expected)
    assert [r["split"] for r in rows] == expected.tolist()
    n_test = int(np.sum(expected == "test"))
    assert 0 < n_test < len(rows) and p["held_out_queries"] == p["queries"] == n_test
    assert p["query_split"] == {s: int(np.sum(expected == s)) for s in ("test", "train", "buffer")}
    assert p["all_places"]["queries"] == len(rows) and p["all_places"]["methods"]["nbld"]["queries"] == len(rows)

    # the headline AUC is the AUC of the held-out rows alone, the all-places AUC of all rows
    def auc_of(rs):
        c = pr_curve(
            np.array([float(r["score"]) for r in rs]),
            np.array([r["correct"] == "1" for r in rs]),
            np.array([r["reachable"] == "1" for r in rs]),
        )
        return pr_auc(c["recall"], c["precision"])

    held, every = p["methods"]["nbld"], p["all_places"]["methods"]["nbld"]
    assert held["auc"] == pytest.approx(auc_of([r for r in rows if r["held_out"] == "1"]))
    assert every["auc"] == pytest.approx(auc_of(rows))
    assert held["queries"] == n_test and held["reachable"] <= n_test
    kp = np.array([int(r["keypoints"]) for r in rows])
    assert held["keypoints_per_query_mean"] == pytest.approx(kp[expected == "test"].mean())
    assert every["keypoints_per_query_median"] == pytest.approx(np.median(kp)) and every["keypoints_per_query_mean"] > 0
    md = (out / "places.md").read_text()
    assert (
        md.index("## Held-out places") < md.index("## All places") and "Sec. 5.1" in md and str(columns.resolve()) in md
    )

    # a split without a test tile where the query drove: no held-out figures, said (and warned), all-places kept
    empty = tmp_path / "all-train"
    write_triplet_manifest(empty, frame, {k: "train" for k in tiles}, tile, buf)
    with pytest.warns(InputWarning, match="no held-out query"):
        res2 = evaluate_places(
            ws, [("s0", "s1")], methods=["nbld"], out=tmp_path / "eval2", overrides={**ov, "triplets_dir": str(empty)}
        )
    p2 = res2["pairs"][0]
    assert p2["held_out_queries"] == 0 and "no held-out query" in p2["held_out_note"]
    assert p2["methods"]["nbld"]["available"] is False and p2["methods"]["nbld"].get("auc") is None
    assert p2["all_places"]["methods"]["nbld"]["auc"] == pytest.approx(every["auc"])
    md2 = (tmp_path / "eval2" / "places.md").read_text()
    assert "no held-out query" in md2 and "| s1 to s0 |  | n/a | 0 |" in md2
