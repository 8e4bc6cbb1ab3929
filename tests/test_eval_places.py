"""Place-recognition scoring against hand-computed answers (Table 1, PR curve, AUC), and the whole
evaluation on the street of boxes mapped twice, with a stand-in appearance method of known answer."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
from test_index_structure import make_street_workspace  # noqa: E402

from mapkit.core.errors import InputError, InputWarning
from mapkit.evaluation.places import (
    best_f1,
    evaluate_places,
    nearest_l2,
    nearest_stamp,
    pr_auc,
    pr_curve,
    score_queries,
    table1_counts,
)


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
    overrides = {"structure": {"keypoint_fraction": 0.02}, "query_stride": 3}
    res = evaluate_places(ws, [("a", "b"), ("b", "a")], methods=["nbld", "vlad"], out=out, overrides=overrides,
                          appearance=PositionAppearance(maps))
    for p in res["pairs"]:
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
    assert json.loads((out / "places.json").read_text())["pairs"][0]["methods"]["nbld"]["curve"]["recall"]
    n_rows = len((out / "queries.csv").read_text().splitlines()) - 1
    assert n_rows == 2 * sum(p["queries"] for p in res["pairs"])

    # an appearance method trained on the query session cannot score it: left out with a note
    trained = PositionAppearance(maps)
    trained.train_sessions = ["b"]
    with pytest.warns(InputWarning, match="trained the VLAD encoder"):
        res3 = evaluate_places(ws, [("a", "b")], methods=["nbld", "vlad"], out=out, overrides=overrides, appearance=trained)
    assert res3["pairs"][0]["methods"]["vlad"]["available"] is False
    assert "trained the VLAD encoder" in (out / "places.md").read_text()

    # no VLAD bundle: the column is left empty with a warning, structure is still evaluated
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res2 = evaluate_places(ws, [("a", "b")], methods=["nbld", "vlad"], out=tmp_path / "eval2", overrides=overrides)
    assert any(issubclass(w.category, InputWarning) for w in caught)
    assert res2["pairs"][0]["methods"]["vlad"]["available"] is False
    assert res2["pairs"][0]["methods"]["nbld"]["auc"] == pytest.approx(res["pairs"][0]["methods"]["nbld"]["auc"])
    assert "n/a" in (tmp_path / "eval2" / "places.md").read_text()
