"""A stage that would produce nothing fails, in one line that says why and what to change, and
leaves no finished marker behind (a later run must not take it as done): ``mapkit align`` with no
verified submap pair, ``mapkit index structure`` with no keypoint, ``mapkit index vlad`` with no
image. The demo reports such a stage as failed, not skipped."""

from __future__ import annotations

import numpy as np
import pytest
from test_align import FRAME, gps_error, make_workspace, street  # the synthetic street of boxes
from test_index_structure import street_map

from mapkit.core.errors import InputError, MapkitError
from mapkit.core.runio import write_json
from mapkit.mapping.imagedb import write_images_csv
from mapkit.mapping.semidense import SemiDenseMap
from mapkit.multisession.align import align_workspace
from mapkit.pipelines.demo import Demo, _index_vlad
from mapkit.places.index_structure import build_structure_index
from mapkit.retrieval.index_vlad import build_vlad_index


def _one_line(exc: BaseException) -> str:
    msg = str(exc)
    assert isinstance(exc, MapkitError) and "\n" not in msg
    return msg


def test_align_with_no_verified_pair_fails_before_any_output(tmp_path):
    # the second session's map sits 30 m off the first: every candidate pair is rejected
    ws = tmp_path / "ws"
    make_workspace(
        ws, street(np.random.default_rng(3)), {"s0": gps_error(1.0, -1.0, 0.0), "s2": gps_error(21.0, 21.0, 0.0)}
    )
    with pytest.raises(InputError, match=r"0 of \d+ candidate submap pairs verified") as e:
        align_workspace(ws, overrides={"overlap_radius_m": 60.0}, progress=False)
    msg = _one_line(e.value)
    assert "drive the same streets" in msg  # what to change
    out = ws / "align"
    assert not (out / ".done").exists() and not (out / "tiles").exists() and not (out / "sessions").exists()


def _empty_map(like: SemiDenseMap) -> SemiDenseMap:
    return SemiDenseMap(
        points_world=like.points_world[:0],
        intensity=like.intensity[:0],
        sigma_depth=like.sigma_depth[:0],
        source_keyframe=like.source_keyframe[:0],
        obs_indptr=np.zeros(1, np.int64),
        obs_frame_ids=like.obs_frame_ids[:0],
        keyframe_ids=like.keyframe_ids,
        keyframe_stamps_ns=like.keyframe_stamps_ns,
        keyframe_world_from_cam=like.keyframe_world_from_cam,
        K=like.K,
        image_size_wh=like.image_size_wh,
    )


def test_structure_index_of_an_empty_map_fails_without_a_bundle(tmp_path):
    ws = tmp_path / "ws"
    full = street_map(street(np.random.default_rng(3)), np.random.default_rng(10), -2.0, 0.0)
    _empty_map(full).save(ws / "align" / "sessions" / "a" / "map")
    write_json(ws / "align" / ".done", {"config_hash": "test", "sessions": ["a"]})
    for kind in ("nbld", "m2dp"):
        with pytest.raises(InputError, match="0 keypoints") as e:
            build_structure_index(ws, kind, sessions=["a"])
        assert "database_sessions" in _one_line(e.value)
        out = ws / "indexes" / f"structure-{kind}"
        assert not out.exists() or not any(out.iterdir())


def _workspace_without_images(ws) -> None:
    write_json(ws / "origin.json", FRAME.to_dict())
    for name in ("a", "b"):
        write_images_csv(ws / "sessions" / name / "imagedb" / "images.csv", [], [], [], [], np.zeros((0, 4, 4)), FRAME)


def test_vlad_index_with_no_image_fails_without_a_bundle(tmp_path):
    ws = tmp_path / "ws"
    _workspace_without_images(ws)
    with pytest.raises(InputError, match=r"0 image\(s\)") as e:
        build_vlad_index(ws, overrides={"train_sessions": ["a", "b"], "database_sessions": ["a", "b"]}, progress=False)
    assert "rebuild" in _one_line(e.value)
    out = ws / "indexes" / "vlad"
    assert not out.exists() or not any(out.iterdir())


def test_demo_reports_a_stage_that_made_nothing_as_failed(tmp_path):
    d = Demo(tmp_path / "run", "tiny", None, 1, False, False, log=lambda s: None)
    _workspace_without_images(d.ws.root)
    d.roles = {"a": {"role": "train"}, "b": {"role": "test"}}
    d.metrics["stages"]["build"] = {"status": "ok"}
    _index_vlad(d)
    rec = d.metrics["stages"]["index_vlad"]
    assert rec["status"] == "failed" and "0 image(s)" in rec["error"]
