"""Retrieval evaluation: recall@k on hand-built cases, self-retrieval, and the workspace protocol end to end."""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_index_vlad import FRAME, PLACES, make_workspace, small_config

from mapkit.core.errors import InputError
from mapkit.core.geodesy import LocalFrame
from mapkit.core.geometry import yaw_rotation
from mapkit.evaluation.retrieval import evaluate_retrieval, recall_at_k, rotation_error_deg, self_retrieval
from mapkit.io.trajectory import write_tum
from mapkit.retrieval.index_vlad import build_vlad_index, read_session_images


def test_recall_at_k_on_a_hand_built_case():
    db = np.array([[0, 0, 0], [100, 0, 0], [200, 0, 0], [30, 0, 0]], float)
    queries = np.array(
        [
            [0, 0, 0],  # right place at rank 2
            [100, 10, 0],  # rank 1
            [500, 0, 0],  # nothing within 25 m anywhere: unreachable
            [26, 0, 0],  # rank 1: db 3 is 4 m away (db 0 at 26 m is not)
            [125, 0, 0],  # db 1 exactly 25 m away at rank 3: the radius is inclusive
        ],
        float,
    )
    ids = np.array([[1, 0, 2], [1, 2, 0], [0, 1, 2], [3, 0, 1], [2, 0, 1]])
    r = recall_at_k(queries, db, ids, ks=(1, 2, 3), radius_m=25.0)
    assert r["recall"] == {1: 2 / 5, 2: 3 / 5, 3: 4 / 5}
    np.testing.assert_array_equal(r["first_hit_rank"], [2, 1, 0, 1, 3])
    np.testing.assert_allclose(r["curve"], [0.4, 0.6, 0.8])
    assert r["reachable"] == pytest.approx(4 / 5)
    # padding ids (-1: fewer database entries than k) never hit, even though db[0] would
    r = recall_at_k(queries[:1], db, np.array([[1, -1, -1]]), ks=(1, 3))
    assert r["recall"] == {1: 0.0, 3: 0.0}
    # k beyond the retrieved list counts what was retrieved
    assert recall_at_k(queries[:2], db, ids[:2, :1], ks=(1, 20))["recall"] == {1: 0.5, 20: 0.5}


def test_rotation_error_is_the_angle_between():
    np.testing.assert_allclose(rotation_error_deg(yaw_rotation(0.3), yaw_rotation(0.3 + np.radians(7))), 7.0, atol=1e-9)
    np.testing.assert_allclose(rotation_error_deg(np.eye(3), np.eye(3)), 0.0, atol=1e-6)


def test_self_retrieval_gaps_on_a_known_sequence():
    # points on an arc: the nearest allowed neighbour of frame i is i +- 3 ...
    t = np.linspace(0, 1, 30)
    v = np.stack([np.cos(t), np.sin(t), np.zeros_like(t)], 1)
    # ... except frames 25..29, which revisit frames 0..4 exactly (a loop closure: gap 25)
    v[25:] = v[:5]
    r = self_retrieval(v, exclude=2, positions=v * 10)
    gaps = np.asarray(r["gaps"])
    assert np.all(gaps[7:25] == 3)
    np.testing.assert_array_equal(gaps[5:7], [24, 23])  # frame 5's nearest allowed is the copy of frame 4
    np.testing.assert_array_equal(gaps[25:], 25)
    np.testing.assert_array_equal(gaps[:5], 25)
    assert r["median_gap"] == 3 and r["histogram"][25] == 10
    assert r["distances_m"][0] == 0.0
    with pytest.raises(InputError):
        self_retrieval(v[:5], exclude=2)


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    ws = make_workspace(tmp_path_factory.mktemp("evalws"))
    return ws, build_vlad_index(ws, config=small_config(), progress=False)


def make_town(root, ws) -> None:
    """A synthetic-town folder whose ENU origin is 10 m east of the workspace's, holding the true
    camera poses of the query session (its database poses moved 1.2 m: a known pose error)."""
    lat, lon, alt = FRAME.enu_to_geodetic(np.array([[10.0, 0.0, 0.0]]))
    town_frame = LocalFrame(float(lat[0]), float(lon[0]), float(alt[0]), FRAME.utm_epsg)
    (root / "world").mkdir(parents=True)
    (root / "sessions").mkdir()
    (root / "world" / "origin.json").write_text(json.dumps(town_frame.to_dict()))
    (root / "world" / "manifest.json").write_text(
        json.dumps({"sessions": [{"name": "test-c", "role": "test", "condition": "day-snowy", "weather": "snowy"}]})
    )
    s = read_session_images(ws, "test-c")
    true_ws = s.world_from_cam.copy()
    true_ws[:, 1, 3] += 1.2  # the session's recorded poses are 1.2 m off the truth
    town_from_ws = FRAME.to_frame(town_frame)
    write_tum(root / "sessions" / "test-c.camera.tum", s.table["stamp_ns"], town_from_ws @ true_ws)


def test_evaluate_retrieval_end_to_end(tmp_path, bundle):
    ws, out = bundle
    town = tmp_path / "town"
    make_town(town, ws)
    res = evaluate_retrieval(ws, out, ["test-c"], truth=town, out=tmp_path / "eval", progress=False)
    r = res["sessions"]["test-c"]
    assert r["queries"] == PLACES and r["condition"] == "day-snowy" and r["truth_source"] == "synthetic town"
    assert r["recall"] == {1: 1.0, 5: 1.0, 20: 1.0}
    assert r["reachable"] == 1.0
    # the measurement is the mean of the place's two database poses: (40 p + 0.5, 0.25, 1.5); truth
    # is (40 p + 0.5, -0.5 + 1.2, 1.5) -> 0.45 m off, whatever frame the town is in
    assert r["measurement"]["median_translation_m"] == pytest.approx(0.45, abs=0.01)
    assert r["measurement"]["median_rotation_deg"] < 0.1
    assert res["conditions"]["day-snowy"]["recall"][1] == 1.0
    for f in ("eval_retrieval.json", "eval_retrieval.md", "eval_retrieval.png", "eval_retrieval_queries.csv"):
        assert (tmp_path / "eval" / f).stat().st_size > 0
    assert "| test-c | day-snowy | 8 |" in (tmp_path / "eval" / "eval_retrieval.md").read_text()
    # without truth: the session's own poses (0.75 m from the measurement)
    res = evaluate_retrieval(ws, out, ["test-c"], ks=(1,), out=tmp_path / "eval2", progress=False)
    r = res["sessions"]["test-c"]
    assert r["truth_source"] == "session poses (imagedb)" and r["recall"] == {1: 1.0}
    assert r["measurement"]["median_translation_m"] == pytest.approx(0.75, abs=0.01)


def test_query_sessions_in_the_bundle_are_refused(tmp_path, bundle):
    ws, out = bundle
    with pytest.raises(InputError) as e:
        evaluate_retrieval(ws, out, ["test-c", "train-b"], out=tmp_path, progress=False)
    assert e.value.field == "sessions" and "train-b" in str(e.value)
    # a training-only session is refused too
    b = build_vlad_index(
        ws,
        tmp_path / "b",
        small_config(database_sessions=["train-a"], train_sessions=["train-a", "train-b"]),
        progress=False,
    )
    with pytest.raises(InputError, match="train-b"):
        evaluate_retrieval(ws, b, ["train-b"], out=tmp_path, progress=False)
