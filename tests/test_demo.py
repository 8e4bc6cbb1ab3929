"""`mapkit demo` on the tiny town, the deployment bundle it exports, and the HTML report."""

from __future__ import annotations

import json
import os
import re
import shutil
from pathlib import Path

import pycolmap
import pytest

from mapkit.cli import main
from mapkit.core.errors import InputError
from mapkit.core.runio import read_timings
from mapkit.core.workspace import Workspace
from mapkit.deploy.export import export_bundles, find_indexes, load_bundle
from mapkit.pipelines.demo import RUN_RECORDS, aucs_by_source, places_by_source, places_pairs, run_demo
from mapkit.report.html import Section, markdown_to_html, render
from mapkit.retrieval.index_vlad import VladIndex


def _differing_files(a: Path, b: Path) -> list[str]:
    """Files of run ``a`` and run ``b`` that are not the same to the byte (or exist in one only), run records aside."""

    def files(root: Path) -> dict[str, Path]:
        return {p.relative_to(root).as_posix(): p for p in root.rglob("*") if p.is_file() and p.name not in RUN_RECORDS}

    fa, fb = files(a), files(b)
    return sorted(set(fa) ^ set(fb)) + sorted(k for k in set(fa) & set(fb) if fa[k].read_bytes() != fb[k].read_bytes())


#: the whole tiny main job (every stage on a small town, the 6-DoF stage too), run twice into the same folder: the
#: first run is moved aside before the second starts, so that the paths the outputs record are the same
@pytest.fixture(scope="module")
def tiny_demo(tmp_path_factory):
    base = tmp_path_factory.mktemp("demo")
    out = base / "run"
    run_demo(out, preset="tiny", workers=2, log=lambda s: None, sixdof=True)
    out.rename(base / "first")
    metrics = run_demo(out, preset="tiny", workers=2, log=lambda s: None, sixdof=True)
    return out, metrics


def test_two_runs_of_the_tiny_chain_are_byte_identical(tiny_demo):
    out, _ = tiny_demo
    first = out.parent / "first"
    assert len(list(out.rglob("*.ply"))) > 10 and (out / "workspace" / "triplets" / "patches.npz").is_file()
    assert _differing_files(first, out) == []
    # the run records do differ (they hold wall-clock times), which is why they are kept apart
    assert (first / "timings.json").read_bytes() != (out / "timings.json").read_bytes()


def test_the_comparison_sees_a_changed_output(tmp_path):
    for run in ("a", "b"):
        (tmp_path / run / "map").mkdir(parents=True)
        (tmp_path / run / "map" / "points.ply").write_bytes(b"ply 1")
        (tmp_path / run / "timings.json").write_text(run)
    assert _differing_files(tmp_path / "a", tmp_path / "b") == []
    (tmp_path / "b" / "map" / "points.ply").write_bytes(b"ply 2")
    (tmp_path / "b" / "map" / "extra.csv").write_text("x")
    assert _differing_files(tmp_path / "a", tmp_path / "b") == ["map/extra.csv", "map/points.ply"]


def check_against_the_towns_truth(m: dict) -> None:
    """What the tiny run's metrics say against the synthetic town's truth, with a margin over what it
    measures (seed 7, in brackets): a chain that breaks a stage's geometry fails here, not only one
    that leaves a stage empty."""
    # maps on the true surfaces and trajectories on the true path, once the GPS offset no drive can
    # see is removed (median 0.08-0.15 m, 74-87% within 0.5 m; ATE 0.03-0.08 m)
    for name, s in m["eval_build"]["sessions"].items():
        assert s["map_local"]["median_distance_m"] < 0.3 and s["map_local"]["fraction_within_0.5m"] > 0.6, (name, s)
        assert s["trajectory_local"]["ate_rmse_m"] < 0.3, (name, s["trajectory_local"])
    # alignment brings the sessions together: metres apart on GPS alone (5.4 m), centimetres after
    # (0.053 m; every pair at most 0.08 m), with no accepted registration a metre off, and the frame
    # within the goal's 1.2x of what the drives' common GPS bias allows (0.99x)
    a = m["eval_align"]
    assert a["pairs_evaluated"] == 3 and a["before_median_m"] > 2.0 and a["after_median_m"] < 0.1, a
    assert all(p["after_median_m"] < 0.15 for p in a["pairs"].values()), a["pairs"]
    assert a["accepted_pairs"] > 0 and a["accepted_pairs_true_error_above_1m"] == 0, a
    assert a["gps_bias_bound"]["ratio_median"] <= 1.2, a["gps_bias_bound"]
    # triplet positives show the same true place (99.6% of the pairs within 0.5 m, median 0.11 m)
    t = m["triplets"]["truth"]
    assert t["positive_pairs"] == sum(m["triplets"]["export"]["triplets"].values()), t
    assert t["fraction_below_0.5m"] > 0.9 and t["offset_median_m"] < 0.3, t
    # localization of the night drive against the day drives: the odometry-driven multi-hypothesis
    # filter stays on it (median 2.7 m, 0.35 deg) where retrieval alone is tens of metres off
    night = m["localize"]["odometry-multihypothesis"]["tiny-night"]["filter"]
    assert night["frames"] > 0 and night["median_translation_m"] < 10.0 and night["median_rotation_deg"] < 3.0, night


def test_tiny_main_job_runs_every_stage_with_non_empty_outputs(tiny_demo):
    out, m = tiny_demo
    status = {n: s["status"] for n, s in m["stages"].items()}
    assert status.pop("train_cnn") == "skipped"  # only with --train-cnn
    assert set(status.values()) == {"ok"}, m["stages"]
    ws = out / "workspace"
    # synth and build: every session georeferenced; align: at least two sessions in one frame
    assert len(m["georeferenced"]) == len(m["eval_build"]["sessions"]) >= 3
    # the demo's maps are made on the factor graph's trajectory (configs/build/demo.yaml: georef.fuse)
    used = {n: s.get("trajectory_used") for n, s in m["eval_build"]["sessions"].items()}
    assert set(used.values()) == {"factor graph"}, used
    assert len(Workspace(ws).aligned_sessions()) >= 2
    assert m["eval_align"]["pairs_evaluated"] > 0
    # triplets, and the three indexes the demo builds
    assert sum(m["triplets"]["export"]["triplets"].values()) > 0
    assert m["index_vlad"]["database_images"] > 0
    for kind in ("nbld", "m2dp"):
        counts = json.loads((ws / "indexes" / f"structure-{kind}" / "manifest.json").read_text())["counts"]
        assert counts["entries"] > 0 and counts["frames"] > 0, (kind, counts)
    # localization and place recognition tables with rows
    for name, run in m["localize"].items():
        assert run and all(s["queries"] > 0 for s in run.values()), run
        for session in run:  # the estimates, as TUM files evo and mapkit view read
            assert (ws / "localize" / name / session / "poses_tum.txt").stat().st_size > 0
    # the recording of the workspace, within its budget, and its top view in the report
    assert (ws / "view.rrd").stat().st_size > 100_000 and 0 < m["view"]["points"] <= 1_000_000
    # 6-DoF: every test query scored; a query without an accepted pose keeps the filter's, so the share within
    # 5 m is never below the filter's; the benchmark export opens in pycolmap
    for session, r in m["sixdof"].items():
        assert r["6dof"]["queries"] == r["filter"]["queries"] > 0, session
        assert r["6dof"]["recall"]["5m_10deg"] >= r["filter"]["recall"]["5m_10deg"], (session, r)
        assert r["sequence"]["queries"] == r["6dof"]["queries"], session  # the drive's pose graph scored too
    bench = pycolmap.Reconstruction(str(out / "benchmark" / "sfm"))
    assert bench.num_points3D() > 0 and (out / "benchmark" / "queries_with_intrinsics.txt").stat().st_size > 0
    assert m["places"] and all(len(v) >= 3 for v in m["places"].values()), m["places"]
    assert "| " in (ws / "eval" / "places" / "places.md").read_text()
    assert {"vlad", "structure-nbld", "structure-m2dp"} <= set(m["bundles"]["indexes"])
    assert json.loads((out / "metrics.json").read_text())["stages"] == m["stages"]
    check_against_the_towns_truth(m)
    timings = read_timings(out)  # the run record, apart from the metrics
    assert set(timings["stages"]) == set(m["stages"])
    assert timings["seconds_total"] >= sum(s["seconds"] for s in timings["stages"].values()) - 1.0
    # how many cores each stage kept busy, read from the machine's counters (Linux)
    busy = [s["cores_busy"] for s in timings["stages"].values() if "cores_busy" in s]
    assert busy and all(0.0 <= b <= os.cpu_count() + 0.05 for b in busy), busy
    assert f"cores busy (of {os.cpu_count()})" in (out / "timings.md").read_text()


def test_report_is_one_self_contained_page_with_every_stage(tiny_demo):
    out, m = tiny_demo
    page = (out / "report.html").read_text()
    titles = re.findall(r"<h2 id=\"[^\"]+\">([^<]+)", page)
    assert len(titles) == len(m["stages"])
    assert page.count("data:image/png;base64,") >= 3  # town map, contact sheet, trajectories...
    assert not re.search(r"(src|href)=\"https?:", page)  # nothing fetched from a network
    assert "Whole run" in page and "eval_build" not in page.split("<body>")[0]
    assert "Documentation: " in page and "rerun " in page  # where to read on, and how to open the recording


def test_exported_bundle_loads_and_finds_a_database_image(tiny_demo):
    out, m = tiny_demo
    bundle = load_bundle(out / "bundles")
    vlad = bundle["vlad"]
    assert isinstance(vlad, VladIndex) and len(vlad) > 0
    assert vlad.encoder.cfg.dsift.half_resolution  # the demo's encoder: the MCVL authors' code's practice
    top = bundle.manifest["indexes"]["vlad"]
    assert top["source_sessions"] == vlad.database_sessions and top["entries"] == len(vlad)
    origin = json.loads((out / "workspace" / "origin.json").read_text())
    assert top["crs"]["utm_crs_epsg"] == origin["utm_crs_epsg"] == 32630  # Oxford: UTM zone 30N
    assert top["crs"]["origin_wgs84"] == origin["origin_wgs84"]


def test_bundle_loader_refuses_a_changed_file_and_an_unknown_version(tiny_demo, tmp_path):
    out, _ = tiny_demo
    copy = tmp_path / "bundle"
    shutil.copytree(out / "bundles", copy)  # a real copy: the fixture's files stay intact
    victim = copy / "vlad" / "database.csv"
    victim.write_text(victim.read_text() + "\n")
    with pytest.raises(InputError, match="checksum mismatch") as e:
        load_bundle(copy)
    assert "database.csv" in str(e.value)

    shutil.rmtree(copy)
    shutil.copytree(out / "bundles", copy)
    man = json.loads((copy / "manifest.json").read_text())
    man["format_version"] = 99
    (copy / "manifest.json").write_text(json.dumps(man))
    with pytest.raises(InputError, match="unknown bundle format version 99") as e:
        load_bundle(copy)
    assert "manifest.json" in str(e.value) and "format_version" in str(e.value)


def test_a_bundle_whose_manifest_lists_fewer_indexes_than_it_holds_is_refused(tiny_demo, tmp_path):
    """A manifest edited (or an export mixed with another) so that it lists no index while an index folder is
    there: one error naming the manifest and the unlisted folders, never an empty bundle."""
    out, _ = tiny_demo
    copy = tmp_path / "bundle"
    shutil.copytree(out / "bundles", copy)
    man = json.loads((copy / "manifest.json").read_text())
    held = sorted(man["indexes"])
    man["indexes"] = {}
    (copy / "manifest.json").write_text(json.dumps(man))
    with pytest.raises(InputError, match="lists 0 index") as e:
        load_bundle(copy)
    assert "manifest.json" in str(e.value) and all(name in str(e.value) for name in held)
    # one of its index folders, loaded alone (`mapkit localize EXPORT/vlad`), is refused as well
    with pytest.raises(InputError, match="does not list the index 'vlad'") as e:
        VladIndex.load(copy / "vlad")
    assert str(copy / "manifest.json") in str(e.value)


def test_an_index_of_an_export_is_checked_against_the_export_and_the_export_is_not_an_index(tiny_demo, tmp_path):
    """`mapkit localize EXPORT/vlad` loads one index of an export: it must be the one the export lists (an index
    replaced by another is refused); `mapkit localize EXPORT` says to pass one of its index folders."""
    out, _ = tiny_demo
    copy = tmp_path / "bundle"
    shutil.copytree(out / "bundles", copy)
    assert len(VladIndex.load(copy / "vlad")) > 0
    man = json.loads((copy / "manifest.json").read_text())
    man["indexes"]["vlad"]["manifest_sha256"] = "0" * 64
    (copy / "manifest.json").write_text(json.dumps(man))
    with pytest.raises(InputError, match="differs from the one"):
        VladIndex.load(copy / "vlad")
    with pytest.raises(InputError, match="pass one of its index folders"):
        VladIndex.load(copy)


def test_export_of_one_named_index_and_of_a_missing_one(tiny_demo, tmp_path, capsys):
    out, _ = tiny_demo
    ws = out / "workspace"
    path = export_bundles(ws, tmp_path / "b", names=["vlad"])
    assert sorted(json.loads((path / "manifest.json").read_text())["indexes"]) == ["vlad"]
    with pytest.raises(InputError, match="no finished index named"):
        export_bundles(ws, tmp_path / "c", names=["structure-cnn"])
    assert not (tmp_path / "c").exists()
    assert main(["index", "export", str(ws), "--out", str(tmp_path / "d")]) == 0
    assert "verified" in capsys.readouterr().out


def test_rerun_resumes_without_rebuilding(tiny_demo):
    out, _ = tiny_demo
    manifest = out / "workspace" / "indexes" / "vlad" / "manifest.json"
    before = manifest.stat().st_mtime_ns
    again = run_demo(out, preset="tiny", workers=2, log=lambda s: None)
    assert manifest.stat().st_mtime_ns == before  # the index was not written again
    assert {n: s["status"] for n, s in again["stages"].items()}["export"] == "ok"


def test_video_rate_build_config_keeps_each_sessions_image_rate(tmp_path):
    """With cameras recording faster than the sessions' own rates, the demo's build config keeps
    every image database at its session's rate (never denser than configs/build/demo.yaml's)."""
    from mapkit.core.config import load_config
    from mapkit.core.presets import preset_path
    from mapkit.mapping.build import BuildConfig
    from mapkit.pipelines.demo import demo_build_config

    same = {"train-a": {"camera_rate_hz": 4.0, "image_rate_hz": 4.0}, "test-b": {"camera_rate_hz": 4.0}}
    assert demo_build_config(tmp_path, same) == preset_path("build", "demo")  # LiDAR maps as the preset's: on
    roles = {
        "train-a": {"camera_rate_hz": 16.0, "image_rate_hz": 4.0},
        "test-b": {"camera_rate_hz": 16.0, "image_rate_hz": 4.0},
        "test-c": {"camera_rate_hz": 16.0, "image_rate_hz": 16.0},
    }
    path = demo_build_config(tmp_path, roles)
    assert path.parent == tmp_path and path.is_file()
    cfg, base = load_config(BuildConfig, path), load_config(BuildConfig, preset_path("build", "demo"))
    assert base.for_session("train-a").imagedb.min_interval_s == 0.5  # MCVL's 2 Hz training databases
    assert cfg.for_session("train-a").imagedb.min_interval_s == 0.5  # kept: sparser than 4 Hz
    assert cfg.for_session("test-b").imagedb.min_interval_s == 0.25  # the session's own 4 Hz, not the 16 Hz video
    assert cfg.for_session("test-c").imagedb.min_interval_s == base.for_session("test-c").imagedb.min_interval_s
    assert (
        cfg.georef.fuse == base.georef.fuse and cfg.semidense == base.semidense
    )  # the maps: every image, as the demo's
    assert base.lidar_map.enabled == "auto" and cfg.lidar_map.enabled == "auto"
    camera_only = load_config(BuildConfig, demo_build_config(tmp_path / "camera", same, lidar_map=False))
    assert camera_only.lidar_map.enabled is False and camera_only.for_session("train-a").imagedb.min_interval_s == 0.5


def test_places_pairs_mix_conditions_and_skip_empty_maps():
    roles = {
        "a": {"role": "train"},
        "b": {"role": "train"},
        "c": {"role": "train"},
        "x": {"role": "test"},
        "y": {"role": "test"},
    }
    pts = {"a": 10, "b": 30, "c": 20, "x": 5, "y": 0}
    # the two fullest training maps (b, c) against each test session with a map, then test to test
    assert places_pairs(roles, pts) == [("b", "x"), ("c", "x")]
    pts["y"] = 7
    assert places_pairs(roles, pts) == [("b", "x"), ("c", "x"), ("b", "y"), ("c", "y"), ("x", "y")]
    # a test drive that retraces a training drive's streets is scored against that one first
    roles["y"]["follows"] = "a"
    assert places_pairs(roles, pts) == [("b", "x"), ("c", "x"), ("a", "y"), ("b", "y"), ("x", "y")]
    pts["a"] = 0  # ... when it has a map
    assert places_pairs(roles, pts) == [("b", "x"), ("c", "x"), ("b", "y"), ("c", "y"), ("x", "y")]


def test_places_by_source_puts_each_pairs_two_aucs_side_by_side():
    """Each pair's row holds its semi-dense AUC then its LiDAR AUC per structure method (the VLAD column, not in the
    LiDAR run, is left out), matched by pair, not by order, over the held-out queries or over all; a method without
    an AUC says n/a; metrics.json's form holds the same figures."""

    def run(headline, pairs):
        def scope(aucs, n):
            return {"queries": n, "methods": {m: {"auc": a} for m, a in aucs.items()}}

        return {
            "headline": headline,
            "methods": ["nbld", "m2dp"] + (["vlad"] if headline else []),
            "pairs": [
                {"database": db, "query": q, **scope(held, n), "all_places": scope(every, 2 * n)}
                for db, q, n, held, every in pairs
            ],
        }

    semi = run(
        "held_out",
        [
            ("a", "x", 40, {"nbld": 0.5, "m2dp": 0.25, "vlad": 0.9}, {"nbld": 0.4, "m2dp": 0.3, "vlad": 0.8}),
            ("b", "x", 40, {"nbld": 0.75}, {"nbld": 0.7}),
        ],
    )
    lidar = run(
        None,
        [
            ("b", "x", 31, {"nbld": 0.125, "m2dp": None}, {"nbld": 0.2, "m2dp": None}),
            ("a", "x", 30, {"nbld": 0.625, "m2dp": 1.0}, {"nbld": 0.6, "m2dp": 0.9}),
        ],
    )
    lines = places_by_source(semi, lidar).splitlines()
    assert lines[0].split(" | ")[2:] == ["NBLD: semi-dense / LiDAR", "M2DP: semi-dense / LiDAR |"]
    assert lines[2] == "| x to a | 40 / 30 | 0.500 / 0.625 | 0.250 / 1.000 |"
    assert lines[3] == "| x to b | 40 / 31 | 0.750 / 0.125 | n/a / n/a |"
    assert "AUC over held-out queries" in lines[5]
    every = places_by_source(semi, lidar, "all_places").splitlines()
    assert every[2] == "| x to a | 80 / 60 | 0.400 / 0.600 | 0.300 / 0.900 |"
    assert "AUC over all queries" in every[5]
    m = aucs_by_source(semi, lidar)
    assert list(m) == [("a", "x"), ("b", "x")]  # the semi-dense run's order
    assert m[("a", "x")]["lidar"]["auc"]["m2dp"] == {"held_out": 1.0, "all_places": 0.9}
    assert m[("b", "x")]["semidense"]["queries"] == {"held_out": 40, "all_places": 80}
    assert set(m[("a", "x")]["semidense"]["auc"]) == {"nbld", "m2dp"}


def test_markdown_subset_to_html():
    md = "# Title\n\nSome **bold** and `code` <tag>.\n\n| a | b |\n|---|---|\n| 1 | 2 |\n| 3 | 4 |\n\n- one\n- two\n"
    h = markdown_to_html(md)
    assert "<h3>Title</h3>" in h
    assert "<b>bold</b>" in h and "<code>code</code>" in h and "&lt;tag&gt;" in h
    assert h.count("<tr>") == 3 and "<th>a</th>" in h and "<td>4</td>" in h and "---" not in h
    assert "<ul><li>one</li><li>two</li></ul>" in h
    page = render("T", "intro", [Section("A stage", ["x"], seconds=12.3)])
    assert 'id="a-stage"' in page and "12 s" in page and 'href="#a-stage"' in page


def test_the_docs_figures_read_a_run_as_it_is_written(tiny_demo):
    """docs/figures.py extracts a run's figures from the files the run wrote (what the docs' tables come from)."""
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "docs"))
    try:
        import figures
    finally:
        sys.path.pop(0)
    out, m = tiny_demo
    r = figures.extract_run(out)
    assert r["preset"] == "tiny" and r["seed"] == 7
    assert set(r["stages_s"]) == set(m["stages"]) and r["total_s"] >= sum(r["stages_s"].values()) - 1.0
    assert set(r["maps"]) == {"tiny-sunny", "tiny-rainy", "tiny-night"}
    assert all(0 < v["median_m"] < 1.0 and 0 < v["within_0.5m"] <= 1 for v in r["maps"].values()), r["maps"]
    assert (
        set(r["localize"]) == {"paper", "odometry-multihypothesis"}
        and r["localize"]["paper"]["tiny-night"]["queries"] > 0
    )
    assert {k.split(" > ")[0] for k in r["places"]} == {"tiny-night"}
    assert r["units"]["scans"] > 800 and r["units"]["trajectory_s"] > 0 and r["units"]["keyframes"] > 0


def test_figures_spread_and_verdicts():
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "docs"))
    try:
        import figures
    finally:
        sys.path.pop(0)
    assert figures.spread([0.5, 0.7, 0.6]) == "0.600 (0.500-0.700)"
    assert figures.spread([0.5, None]) == "0.500" and figures.spread([None]) == "n/a"
    assert figures.verdict([0.1, 0.2, 0.01]) == "yes, in 3 of 3 runs"
    assert figures.verdict([0.1, -0.2, 0.3]) == "not beyond the spread (2 of 3 runs)"
    assert figures.verdict([-0.1, -0.2]) == "no, in 2 of 2 runs"


def _functions_taking_a_workspace() -> dict[str, object]:
    """Every public function and class of mapkit (the CLI aside) with a parameter that is a workspace or a folder of
    one: named ``workspace`` or ``ws``, or typed ``Workspace`` or ``SessionDirs``. By qualified name."""
    import importlib
    import inspect
    import pkgutil

    import mapkit

    found: dict[str, object] = {}
    for info in pkgutil.walk_packages(mapkit.__path__, "mapkit."):
        if info.name in ("mapkit.cli", "mapkit.__main__"):
            continue
        module = importlib.import_module(info.name)
        for attr, obj in vars(module).items():
            if attr.startswith("_") or not (inspect.isfunction(obj) or inspect.isclass(obj)):
                continue
            if obj.__module__ != info.name:
                continue
            params = inspect.signature(obj.__init__ if inspect.isclass(obj) else obj).parameters.values()
            if any(
                p.name in ("workspace", "ws") or re.search(r"\b(Workspace|SessionDirs)\b", str(p.annotation))
                for p in params
            ):
                found[f"{info.name}.{attr}"] = obj
    return found


#: the public functions that take a workspace and only read it, each called here on the tiny chain's workspace
def _readers(ws: Path) -> dict[str, object]:
    from mapkit.evaluation.places import PlacesEvalConfig, VladBaseline, resolve_split, tiles_split_of_workspace
    from mapkit.localization.localize import LocalizeConfig, open_reference_model, reference_model_folder
    from mapkit.localization.reference_model import session_maps, workspace_images
    from mapkit.mapping.build import format_build_summary
    from mapkit.multisession.submaps import load_session
    from mapkit.places.index_structure import load_session_map, session_map_checksum, session_map_dir, session_names
    from mapkit.places.triplets import load_aligned_sessions
    from mapkit.retrieval.vlad_bundle import read_camera_mount, read_session_images, workspace_sessions

    w = Workspace(ws)
    name = w.session_names()[0]
    frame = w.require_frame()
    return {
        "mapkit.deploy.export.find_indexes": lambda: find_indexes(ws),
        "mapkit.evaluation.places.tiles_split_of_workspace": lambda: tiles_split_of_workspace(w, frame),
        "mapkit.evaluation.places.resolve_split": lambda: resolve_split(w, PlacesEvalConfig()),
        "mapkit.evaluation.places.VladBaseline": lambda: VladBaseline(ws / "indexes" / "vlad", ws).images(name),
        "mapkit.mapping.build.format_build_summary": lambda: format_build_summary(ws),
        "mapkit.multisession.submaps.load_session": lambda: load_session(w.session(name), frame, 20.0),
        "mapkit.places.index_structure.session_names": lambda: session_names(ws),
        "mapkit.places.index_structure.session_map_dir": lambda: session_map_dir(ws, name),
        "mapkit.places.index_structure.load_session_map": lambda: load_session_map(
            w, name, *w.session_map(name), "semidense"
        ),
        "mapkit.places.index_structure.session_map_checksum": lambda: session_map_checksum(
            w, name, *w.session_map(name), "semidense"
        ),
        "mapkit.places.triplets.load_aligned_sessions": lambda: load_aligned_sessions(ws),
        "mapkit.localization.reference_model.session_maps": lambda: session_maps(w, None),
        "mapkit.retrieval.vlad_bundle.workspace_sessions": lambda: workspace_sessions(ws),
        "mapkit.retrieval.vlad_bundle.read_session_images": lambda: read_session_images(ws, name),
        "mapkit.retrieval.vlad_bundle.read_camera_mount": lambda: read_camera_mount(ws, name),
        "mapkit.localization.localize.reference_model_folder": lambda: reference_model_folder(LocalizeConfig(), ws),
        "mapkit.localization.reference_model.workspace_images": lambda: workspace_images(w, [name]),
        # the tiny chain's reference model, opened and its features read: COLMAP's own database reader would
        # rewrite the database's header
        "mapkit.localization.localize.open_reference_model": lambda: _read_features(
            open_reference_model(LocalizeConfig(refine="6dof"), ws)
        ),
    }


def _read_features(loc) -> None:
    with loc:
        assert loc.image_names
        for n in loc.image_names:  # a descriptor per keypoint of the model's image
            assert len(loc._database_features(n)[0]) == loc.rec.find_image_with_name(n).num_points2D()


#: public classes that take a workspace: each method that writes takes the lock itself (tests/faults/test_lock.py)
LOCKING_CLASSES = {
    "mapkit.core.workspace.Workspace",  # paths only; Workspace.lock() is the lock
    "mapkit.mapping.build.SessionBuilder",  # every stage runs under the lock (test_lock: a held workspace)
    "mapkit.mapping.stages.georef.Georeference",  # run() takes the lock
}


def test_every_function_that_takes_a_workspace_locks_it_or_writes_nothing(tiny_demo):
    """The walk over the library: a public function that takes a workspace is a registered writer (it takes the
    lock: tests/faults/test_lock.py calls each while another process holds it), or it writes nothing there: each of
    the others is called on the tiny chain's workspace, whose files (names, sizes, times) must not change. A new
    function that takes a workspace fails here until it is one or the other."""
    from mapkit.core.writers import WRITERS

    out, _ = tiny_demo
    ws = out / "workspace"
    found = _functions_taking_a_workspace()
    writers = {f"{fn.__module__}.{fn.__name__}" for fn in WRITERS}  # every module is imported by now
    readers = _readers(ws)
    unlocked = sorted(set(found) - writers - set(readers) - LOCKING_CLASSES)
    assert unlocked == []
    assert set(readers) <= set(found)  # no stale entry

    def state() -> dict[str, tuple[int, int]]:
        return {
            p.relative_to(ws).as_posix(): (p.stat().st_size, p.stat().st_mtime_ns)
            for p in ws.rglob("*")
            if p.name != ".lock"
        }

    before = state()
    for name, call in readers.items():
        call()
        assert state() == before, name


def test_the_demo_commands_hand_their_synth_config_to_the_town(tmp_path, monkeypatch):
    """`mapkit demo --synth-config` and pipelines/main.py's give the file to run_demo, which synthesizes the town
    from the preset with it (an overlay's extra drive is among the town's sessions)."""
    import importlib.util

    from mapkit.core.presets import preset_path

    overlay = preset_path("synth", "demo-snowy")
    seen: list = []

    def fake_run_demo(out, *args, **kw):
        seen.append(kw["synth_config"])
        Path(out).mkdir(parents=True, exist_ok=True)
        (Path(out) / "timings.md").write_text("")
        return {"stages": {}, "report": str(Path(out) / "report.html")}

    monkeypatch.setattr("mapkit.pipelines.demo.run_demo", fake_run_demo)
    assert main(["demo", "-o", str(tmp_path / "a"), "--synth-config", str(overlay)]) == 0
    spec = importlib.util.spec_from_file_location("main_job", Path(__file__).parents[1] / "pipelines" / "main.py")
    job = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(job)
    assert job.main(["--out", str(tmp_path / "b"), "--synth-config", str(overlay)]) == 0
    assert [Path(p) for p in seen] == [overlay, overlay]

    captured: dict = {}
    monkeypatch.setattr(
        "mapkit.pipelines.demo.synthesize", lambda **kw: captured.update(kw) or (_ for _ in ()).throw(RuntimeError)
    )
    from mapkit.pipelines.demo import Demo, _synth

    d = Demo(tmp_path / "c", "demo", None, 1, False, False, lambda s: None, synth_config=overlay)
    with pytest.raises(RuntimeError):
        _synth(d)
    assert captured["config"] == overlay and captured["preset"] == "demo"


def test_a_town_that_fails_skips_every_stage_after_it_and_says_why(tmp_path, monkeypatch):
    """A failed synth is one failed stage: the build and everything after it are skipped for want of it, not
    reported failed on a town that is not there."""
    from mapkit.core.errors import InputError
    from mapkit.pipelines.demo import run_demo

    def broken(**kw):
        raise InputError(kw.get("config"), "the town's preset cannot be read")

    monkeypatch.setattr("mapkit.pipelines.demo.synthesize", broken)
    stages = run_demo(tmp_path / "run", preset="tiny", workers=1, log=lambda s: None)["stages"]
    assert stages["synth"]["status"] == "failed"
    assert "cannot be read" in stages["synth"]["error"]
    assert stages["build"] == {"status": "skipped", "reason": "needs the synth stage(s), which did not finish"}
    assert {s["status"] for n, s in stages.items() if n != "synth"} == {"skipped"}
