"""What decides that a finished build stage is reused: the resolved config with its defaults, the stage's
version, its input record and its outputs; and the one-time migration of markers written without a version."""

import json
import logging
import os
import shutil
import warnings

import numpy as np
import pytest

from mapkit.core.config import load_config
from mapkit.core.runio import (
    TIMINGS,
    config_hash,
    is_done,
    mark_done,
    read_marker,
    stage_digest,
    stage_hash,
    write_json,
)
from mapkit.core.workspace import Workspace
from mapkit.mapping.build import BuildConfig, _legacy_stage_hash, _stage_hash, _stage_version, build
from mapkit.mapping.semidense import SemiDenseConfig

N = 12
STAGES = ("trajectory", "georef", "map", "imagedb")  # the stages a camera-and-poses log without GPS runs
MIGRATED = "finished by an older mapkit"


@pytest.fixture(scope="module")
def clip12(clip12):
    """The clip12 fixture (tests/conftest.py) with old file times: a finished log, built without waiting for it."""
    for p in clip12.rglob("*"):
        os.utime(p, (1_000_000_000, 1_000_000_000))
    return clip12


@pytest.fixture(scope="module")
def built(clip12, tmp_path_factory):
    """A workspace with the clip built once; tests work on copies of it."""
    return build([clip12], tmp_path_factory.mktemp("built") / "ws", progress=False)


@pytest.fixture
def ws(built, tmp_path):
    return shutil.copytree(built, tmp_path / "ws")


def _runs(ws) -> dict[str, int]:
    """Per stage, the time its last run wrote its run record (a stage that is reused does not rewrite it)."""
    s = Workspace(ws).session("clip12")
    return {stage: (s.stage(stage) / TIMINGS).stat().st_mtime_ns for stage in STAGES}


def _rerun(clip12, ws, config=None) -> set[str]:
    """Build again (with ``config``); the stages that ran."""
    before = _runs(ws)
    build([clip12], ws, config, progress=False)
    after = _runs(ws)
    return {stage for stage in STAGES if after[stage] != before[stage]}


@pytest.fixture
def semidense_default(monkeypatch):
    """Set a default of the semi-dense config, as a change in code would; the model is rebuilt afterwards."""

    def set_default(field: str, value) -> None:
        monkeypatch.setattr(SemiDenseConfig.model_fields[field], "default", value)
        SemiDenseConfig.model_rebuild(force=True)

    yield set_default
    monkeypatch.undo()
    SemiDenseConfig.model_rebuild(force=True)


def test_a_changed_default_reruns_the_stages_it_affects_and_no_other(clip12, ws, semidense_default):
    map_hash = read_marker(Workspace(ws).session("clip12").map)["config_hash"]
    semidense_default("max_depth_m", 90.0)
    assert BuildConfig().semidense.max_depth_m == 90.0
    assert _rerun(clip12, ws) == {"map", "imagedb"}  # the image database hashes the semi-dense section too
    assert read_marker(Workspace(ws).session("clip12").map)["config_hash"] != map_hash


def test_a_bumped_stage_version_reruns_that_stage_and_its_downstream_stages_only(clip12, ws, monkeypatch):
    monkeypatch.setattr("mapkit.mapping.stages.georef.STAGE_VERSION", 2)
    assert _rerun(clip12, ws) == {"georef", "map", "imagedb"}
    assert read_marker(Workspace(ws).session("clip12").georef)["stage_version"] == 2
    assert read_marker(Workspace(ws).session("clip12").trajectory)["stage_version"] == _stage_version("trajectory")


@pytest.fixture
def first_versions(monkeypatch):
    """Every build stage at its first algorithm (version 1): what a marker without a version was made by."""
    for stage in STAGES:
        monkeypatch.setattr(f"mapkit.mapping.stages.{stage}.STAGE_VERSION", 1)


def _make_old(ws) -> None:
    """Rewrite a workspace's markers as a mapkit without stage versions wrote them: the older rule's hash, no
    version, and the downstream stages' input records holding the digests of those markers."""
    s = Workspace(ws).session("clip12")
    cfg = load_config(BuildConfig, None)
    for stage in STAGES:  # upstream first: a stage's inputs hold the digest of its upstream's marker
        record = read_marker(s.stage(stage))
        record.pop("stage_version")
        record["config_hash"] = _legacy_stage_hash(cfg, stage)
        record["inputs"] = {k: v if k == "log" else stage_digest(s.stage(k)) for k, v in record["inputs"].items()}
        write_json(s.stage(stage) / ".done", record)


def test_an_older_workspace_is_migrated_once_and_nothing_runs_again(clip12, ws, first_versions):
    _make_old(ws)
    s = Workspace(ws).session("clip12")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert _rerun(clip12, ws) == set()
    migrated = sorted(str(w.message).split(":")[0] for w in caught if MIGRATED in str(w.message))
    assert migrated == sorted(str(s.stage(stage)) for stage in STAGES)  # one warning per stage, naming its folder
    cfg = load_config(BuildConfig, None)
    for stage in STAGES:
        record = read_marker(s.stage(stage))
        assert record["config_hash"] == _stage_hash(cfg, stage) and record["stage_version"] == 1
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert _rerun(clip12, ws) == set()
    assert not [w for w in caught if MIGRATED in str(w.message)]


def test_an_older_marker_of_another_config_is_not_migrated(clip12, ws, tmp_path, first_versions):
    """An older marker whose hash is not the older rule's hash of today's config is not reused: its stage runs."""
    _make_old(ws)
    cfg = tmp_path / "c.yaml"
    cfg.write_text("imagedb: {min_interval_s: 0.3}\n")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert _rerun(clip12, ws, cfg) == {"imagedb"}
    migrated = sorted(str(w.message).split(":")[0] for w in caught if MIGRATED in str(w.message))
    s = Workspace(ws).session("clip12")
    assert migrated == sorted(str(s.stage(stage)) for stage in ("trajectory", "georef", "map"))


def test_a_marker_without_its_input_record_reruns_its_stage(clip12, ws, caplog):
    s = Workspace(ws).session("clip12")
    record = read_marker(s.map)
    del record["inputs"]
    write_json(s.map / ".done", record)
    with caplog.at_level(logging.INFO, logger="mapkit.core.runio"):
        assert _rerun(clip12, ws) == {"map"}  # made again the same: the image database made from it stays
    assert f"{s.map}: its marker records no inputs" in caplog.text
    assert "inputs" in read_marker(s.map)


def test_an_older_marker_is_migrated_only_when_its_hash_inputs_and_outputs_still_match(tmp_path):
    folder = tmp_path / "stage"
    folder.mkdir()
    (folder / "out.txt").write_text("made")
    new, old = stage_hash("s", 1, {"a": 1}), config_hash({"a": 1})
    mark_done(folder, old, inputs={"log": 1}, outputs=True)
    digest = stage_digest(folder)
    assert not is_done(folder, new, inputs={"log": 1})  # without the older rule's hash: runs again
    assert not is_done(folder, new, inputs={"log": 1}, legacy_hash=config_hash({"a": 2}), version=1)
    assert not is_done(folder, new, inputs={"log": 2}, legacy_hash=old, version=1)
    (folder / "out.txt").write_text("changed")
    with pytest.warns(UserWarning, match="out.txt has"):
        assert not is_done(folder, new, inputs={"log": 1}, legacy_hash=old, version=1)
    (folder / "out.txt").write_text("made")
    assert not is_done(folder, new, inputs={"log": 1}, legacy_hash=old, version=2)  # the stage's algorithm changed
    with pytest.warns(UserWarning, match=MIGRATED):
        assert is_done(folder, new, inputs={"log": 1}, legacy_hash=old, version=1)
    record = read_marker(folder)
    assert record["config_hash"] == new and record["stage_version"] == 1
    assert stage_digest(folder) == digest  # what downstream stages recorded of it still matches
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert is_done(folder, new, inputs={"log": 1}, legacy_hash=old, version=1)  # migrated once
    assert not is_done(folder, stage_hash("s", 2, {"a": 1}), inputs={"log": 1}, legacy_hash=old, version=2)


def test_an_older_alignment_is_migrated_and_a_migrated_map_keeps_it(tmp_path, monkeypatch):
    """The alignment's marker of an older mapkit is migrated once; a session map whose marker was migrated is the
    same map to it (the hash it was made with), so nothing is registered or written again."""
    from test_align import gps_error, make_workspace, street

    import mapkit.multisession.align as align

    ws = tmp_path / "ws"
    make_workspace(
        ws, street(np.random.default_rng(3)), {"s0": gps_error(1.0, -1.0, 0.0), "s1": gps_error(-1.0, 1.0, 0.0)}
    )
    cfg = {"graph": {"max_rounds": 2}}
    with monkeypatch.context() as m:  # the older rule: the config's hash alone
        m.setattr(align, "stage_hash", lambda stage, version, config: config_hash(config))
        out = align.align_workspace(ws, overrides=cfg, progress=False)
    record = read_marker(out)
    del record["stage_version"]
    write_json(out / ".done", record)
    stamp = (out / "metrics.json").stat().st_mtime_ns
    with pytest.warns(UserWarning, match=MIGRATED) as caught:
        align.align_workspace(ws, overrides=cfg, progress=False)
    assert [str(w.message).split(":")[0] for w in caught if MIGRATED in str(w.message)] == [str(out)]
    assert read_marker(out)["stage_version"] == align.STAGE_VERSION
    for name in ("s0", "s1"):  # the maps' markers migrated by a build
        marker = ws / "sessions" / name / "map" / ".done"
        write_json(marker, {**read_marker(marker.parent), "config_hash": "new", "legacy_config_hash": "test"})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        align.align_workspace(ws, overrides=cfg, progress=False)
    assert (out / "metrics.json").stat().st_mtime_ns == stamp
    monkeypatch.setattr(align, "STAGE_VERSION", align.STAGE_VERSION + 1)
    align.align_workspace(ws, overrides=cfg, progress=False)
    metrics = json.loads((out / "metrics.json").read_text())
    assert (out / "metrics.json").stat().st_mtime_ns != stamp
    assert metrics["registration"]["registered_this_run"] == 0  # the maps are the same: registrations are reused


def test_the_pointnetvlad_layout_is_made_again_from_a_dataset_made_again(tmp_path):
    """The PointNetVLAD stage records the triplet dataset it read (its marker's digest): the same dataset reuses
    it; a dataset made again with the same config (from another alignment) does not."""
    from test_pointnetvlad import CFG, PNV
    from test_triplets import make_aligned_street

    from mapkit.places.pointnetvlad import PointNetVladConfig, export_pointnetvlad, export_triplets_pointnetvlad
    from mapkit.places.triplets import TripletConfig

    ws = make_aligned_street(tmp_path / "ws")
    out = export_triplets_pointnetvlad(ws, out=tmp_path / "t", overrides=dict(CFG, pointnetvlad=PNV), progress=False)
    pnv, cfg, seed = out / "pointnetvlad", PointNetVladConfig(**PNV), load_config(TripletConfig, None, CFG).seed
    stamp = (pnv / "manifest.json").stat().st_mtime_ns
    assert read_marker(pnv)["inputs"] == {"dataset": stage_digest(out)}
    export_pointnetvlad(out, ws, pnv, cfg, seed=seed)
    assert (pnv / "manifest.json").stat().st_mtime_ns == stamp
    write_json(out / ".done", {**read_marker(out), "inputs": {"align": "another alignment"}})
    export_pointnetvlad(out, ws, pnv, cfg, seed=seed)
    assert (pnv / "manifest.json").stat().st_mtime_ns != stamp
