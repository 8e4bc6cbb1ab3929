"""``mapkit demo``: from nothing to deployable bundles and an HTML report, in one command.

The chain, each stage the library's own entry point (re-running resumes: every stage skips what
it already finished):

1. ``synth``: the synthetic town and its sessions (ROS 2 MCAP logs with exact truth)
2. ``build``: every session to a georeferenced semi-dense map and image database
   (``configs/build/demo.yaml``: the training drives' databases at MCVL's 2 Hz); eval build
3. ``align``: all sessions in one frame (ICP of submaps, pose graph); eval align
4. ``triplets``: the triplet patch dataset, with the true offsets of its positives
5. ``index vlad``: the image retrieval index of the training sessions
6. ``index structure``: NBLD and M2DP voting indexes of the training sessions (and the CNN when
   the learning extra is installed and ``train_cnn`` is set)
7. ``eval localize``: the Monte Carlo visual localizer on the test sessions
8. ``eval places``: precision/recall and AUC of every index on pairs mixing conditions
9. ``index export``: the deployable bundle; ``report.html``: every figure and picture above

A stage that does not apply to the chosen town (no test session, say) is reported as skipped,
with the reason; a stage that fails or would produce nothing (no verified pair, no triplet, no
keypoint, no image: the library raises a ``MapkitError``) is reported as failed, and the stages
that need it are skipped. Every preset runs every stage: ``tiny`` (configs/synth/tiny.yaml) is
the demo town scaled down to three drives on the same streets, about a minute on 2 cores.
Timings of every stage go into ``timings.md``, ``metrics.json`` and the report.
"""

from __future__ import annotations

import importlib.util
import json
import logging
import os
import time
import traceback
from collections.abc import Callable, Iterator
from contextlib import contextmanager, nullcontext
from pathlib import Path

import yaml

from mapkit import __version__
from mapkit.core.blas import openblas_kernels
from mapkit.core.config import deep_merge, load_config
from mapkit.core.errors import MapkitError
from mapkit.core.executor import default_executor, use_executor
from mapkit.core.presets import preset_path
from mapkit.core.runio import atomic_write_text, write_json, write_timings
from mapkit.core.workspace import Workspace
from mapkit.deploy.benchmark import export_benchmark
from mapkit.deploy.export import export_bundles, load_bundle
from mapkit.evaluation.evaluate import evaluate_align, evaluate_build
from mapkit.evaluation.localization import evaluate_localization, format_sixdof
from mapkit.evaluation.places import METHOD_LABELS, evaluate_places
from mapkit.evaluation.triplets import evaluate_triplets
from mapkit.evaluation.truth import town_sessions
from mapkit.localization.reference_model import build_reference_model
from mapkit.mapping.build import BuildConfig, build, format_build_summary
from mapkit.multisession.align import align_workspace
from mapkit.places.index_structure import build_structure_index
from mapkit.places.triplets import export_triplets
from mapkit.report.html import Section, write_report
from mapkit.report.view import render_top_view, write_recording
from mapkit.retrieval.index_vlad import build_vlad_index
from mapkit.synth import session_logs, synthesize

logger = logging.getLogger(__name__)


#: Each stage's wall time per preset on a quiet 2-core machine, from the runs behind the docs' figures
#: (docs/results/main-job.json, tiny.json, places.json: the median over their runs, rounded); the demo
#: prints it when a stage starts, so that a user knows what to expect (the places runs shared the machine
#: with other work: their times are upper bounds). tests/test_docs.py holds it to the records.
EXPECTED_SECONDS: dict[str, dict[str, int]] = {
    "tiny": {
        "synth": 33,
        "build": 60,
        "align": 6,
        "triplets": 4,
        "index_vlad": 10,
        "index_structure": 7,
        "localize": 4,
        "places": 5,
        "view": 3,
    },
    "demo": {
        "synth": 108,
        "build": 153,
        "align": 72,
        "triplets": 22,
        "index_vlad": 16,
        "index_structure": 30,
        "localize": 10,
        "sixdof": 123,  # with --sixdof: the median of its stage over the seeds of docs/results/main-job-6dof.json
        "places": 53,
        "view": 11,
    },
    "places": {
        "synth": 700,
        "build": 1115,
        "align": 211,
        "triplets": 139,
        "train_cnn": 540,
        "index_vlad": 81,
        "index_structure": 387,
        "localize": 59,
        "places": 230,
        "export": 1,
        "view": 13,
    },
}


def _duration(seconds: float) -> str:
    return f"{seconds:.0f} s" if seconds < 90 else f"{seconds / 60:.0f} min"


def _cpu_ticks() -> tuple[int, int] | None:
    """(busy, total) CPU ticks of the whole machine since boot, from /proc/stat; None elsewhere."""
    try:
        with open("/proc/stat") as f:
            v = [int(x) for x in f.readline().split()[1:]]
    except (OSError, ValueError):
        return None
    idle = v[3] + (v[4] if len(v) > 4 else 0)  # idle + iowait
    total = sum(v[:8])  # guest time is already inside user
    return total - idle, total


class _Skip(Exception):
    """A stage that does not apply to this town; the message says why."""


class Demo:
    """The state of one demo run: where things are, what each stage found, how long it took."""

    def __init__(
        self,
        out: Path,
        preset: str,
        seed: int | None,
        workers: int,
        train_cnn: bool,
        progress: bool,
        log: Callable[[str], None],
        record_rate_hz: float | None = None,
        synth_overrides: dict | None = None,
        lidar_maps: bool = True,
        sixdof: bool = False,
        synth_config: Path | None = None,
    ):
        self.out, self.preset, self.seed, self.workers = Path(out), preset, seed, workers
        self.lidar_maps, self.sixdof, self.synth_config = lidar_maps, sixdof, synth_config
        self.record_rate_hz, self.synth_overrides = record_rate_hz, synth_overrides
        self.train_cnn, self.progress, self.log = train_cnn, progress, log
        self.town = self.out / "town"
        self.ws = Workspace(self.out / "workspace")
        self.bundles = self.out / "bundles"
        self.metrics: dict = {
            "mapkit_version": __version__,
            "preset": preset,
            "seed": seed,
            "workers": workers,
            "record_rate_hz": record_rate_hz,
            "stages": {},
        }
        self.timings: dict = {"stages": {}}  # wall-clock figures: the run record (timings.json), apart from the metrics
        self.sections: list[Section] = []
        self.roles: dict[str, dict] = {}

    @contextmanager
    def stage(self, name: str, title: str) -> Iterator[Section]:
        sec = Section(title)
        expected = EXPECTED_SECONDS.get(self.preset, {}).get(name)
        self.log(f"[demo] {name} ..." + (f" (about {_duration(expected)} on 2 cores)" if expected else ""))
        t0, c0 = time.perf_counter(), _cpu_ticks()
        record: dict = {}
        try:
            yield sec
            record["status"] = "ok"
        except _Skip as why:
            record["status"] = "skipped"
            record["reason"] = str(why)
            sec.md(f"Skipped: {why}")
        except MapkitError as exc:  # bad input of a stage: reported, later stages that need it skip
            record["status"] = "failed"
            record["error"] = str(exc)
            sec.md(f"**Failed**: `{exc}`")
        sec.seconds = time.perf_counter() - t0
        timing: dict = {"seconds": round(sec.seconds, 1)}
        c1 = _cpu_ticks()
        if c0 is not None and c1 is not None and c1[1] > c0[1]:
            # how many of the machine's cores were busy on average (any process: a run sharing
            # the machine shows here), which says how far a stage is from using all of them
            timing["cores_busy"] = round((c1[0] - c0[0]) / (c1[1] - c0[1]) * (os.cpu_count() or 1), 2)
        self.metrics["stages"][name] = record
        self.timings["stages"][name] = timing
        self.sections.append(sec)
        self.log(
            f"[demo] {name}: {record['status']} in {sec.seconds:.0f} s"
            + (f" ({record.get('reason') or record.get('error')})" if record["status"] != "ok" else "")
        )

    def ok(self, *names: str) -> bool:
        return all(self.metrics["stages"].get(n, {}).get("status") == "ok" for n in names)

    def need(self, *names: str) -> None:
        bad = [n for n in names if not self.ok(n)]
        if bad:
            raise _Skip(f"needs the {', '.join(bad)} stage(s), which did not finish")

    @property
    def cnn_model(self) -> Path | None:
        """The trained CNN (``WORKSPACE/cnn``) when there is one."""
        p = self.ws.cnn_dir
        return p if (p / "model.onnx").is_file() else None

    def structure_kinds(self) -> list[str]:
        return ["nbld", "m2dp"] + (["cnn"] if self.cnn_model is not None else [])

    def structure_overrides(self, kind: str) -> dict | None:
        return {"cnn_model": str(self.cnn_model)} if kind == "cnn" else None

    def places_overrides(self) -> dict:
        # the localization stage's encodings, and the structure index stage's descriptors: nothing is described twice
        ov: dict = {
            "vlad_encodings_dir": str(_localize_cache(self.ws)),
            "descriptor_cache_dir": str(self.ws.descriptor_cache),
        }
        if self.cnn_model is not None:
            ov["structure"] = {"cnn_model": str(self.cnn_model)}
        return ov

    @property
    def train_sessions(self) -> list[str]:
        return sorted(n for n, s in self.roles.items() if s.get("role") == "train" and self.ws.session(n).root.is_dir())

    @property
    def test_sessions(self) -> list[str]:
        return sorted(n for n, s in self.roles.items() if s.get("role") == "test" and self.ws.session(n).root.is_dir())


# --------------------------------------------------------------------------- stages


def _synth(d: Demo) -> None:
    with d.stage("synth", "Synthetic town") as sec:
        overrides = dict(d.synth_overrides or {})
        if d.record_rate_hz is not None:
            overrides = deep_merge(overrides, {"camera": {"record_rate_hz": float(d.record_rate_hz)}})
        synthesize(preset=d.preset, out=d.town, config=d.synth_config, seed=d.seed, overrides=overrides or None)
        d.roles = town_sessions(d.town)
        rows = ["| session | role | condition | camera Hz (recorded / images) |", "|---|---|---|---|"]
        rows += [
            f"| {n} | {s.get('role', '')} | {_condition(s)} | {s.get('camera_rate_hz', '')} / "
            f"{s.get('image_rate_hz', s.get('camera_rate_hz', ''))} |"
            for n, s in sorted(d.roles.items())
        ]
        streets = json.loads((d.town / "metrics.json").read_text()).get("streets") or {}
        d.metrics["streets"] = streets
        if streets:
            rows.append(
                f"\nDriven {streets['driven_m'] / 1000:.1f} km; distinct streets {streets['distinct_m'] / 1000:.1f} "
                f"km, {streets['distinct_train_m'] / 1000:.1f} km of them by training drives (where held-out places "
                "can lie)."
            )
        sec.md("\n".join(rows))
        sec.picture(d.town / "pictures" / "map.png", "the town: streets, buildings and the drives", 560)
        sec.picture(d.town / "pictures" / "contact_sheet.png", "one camera frame per session", 560)


def _condition(s: dict) -> str:
    c = s.get("condition") or {}
    if isinstance(c, dict):
        return ", ".join(str(v) for k, v in c.items() if k in ("name", "time_of_day", "weather", "season") and v)
    return str(c)


def _build(d: Demo) -> None:
    with d.stage("build", "Session maps (mapkit build)") as sec:
        d.need("synth")
        logs = session_logs(d.town)
        config = demo_build_config(d.out, d.roles, d.lidar_maps)
        build(logs, d.ws.root, config=config, progress=d.progress)
        d.log(format_build_summary(d.ws.root))
        r = evaluate_build(d.ws, d.town)
        d.metrics["eval_build"] = r
        d.metrics["georeferenced"] = sorted(n for n, s in r["sessions"].items() if s.get("georeferenced"))
        sec.md_file(d.ws.eval_build_md)
        for n in sorted(r["sessions"]):
            sec.picture(d.ws.session(n).georef / "trajectory_over_gps.png", f"{n}: trajectory over GPS", 380)
        for n in sorted(r["sessions"]):
            sec.picture(d.ws.session(n).map / "top_view.png", f"{n}: semi-dense map, top view", 380)
        for n in sorted(r["sessions"]):
            lidar_view = d.ws.session(n).lidar_map / "top_view.png"
            if lidar_view.is_file():
                sec.picture(lidar_view, f"{n}: LiDAR map, top view", 380)


def demo_build_config(out: Path, roles: dict[str, dict], lidar_map: bool = True) -> Path:
    """``configs/build/demo.yaml``, or a copy of it in ``out`` where the run asks for more: where the town's
    cameras record faster than the sessions' own image rates (video, ``camera.record_rate_hz``), image databases
    that keep each session's own rate (``imagedb.min_interval_s``, never shorter than the demo's): the maps are
    made from every image, retrieval and the localizer see the images they would without video; without
    ``lidar_map``, no LiDAR maps (the preset builds them)."""
    base = preset_path("build", "demo")
    faster = {
        n: s for n, s in roles.items() if s.get("image_rate_hz") and s["camera_rate_hz"] > s["image_rate_hz"] * 1.001
    }
    if not faster and lidar_map:
        return base
    data = yaml.safe_load(base.read_text()) or {}
    cfg = load_config(BuildConfig, base)
    sessions = dict(data.get("sessions") or {})
    for name, s in sorted(faster.items()):
        interval = max(cfg.for_session(name).imagedb.min_interval_s, 1.0 / float(s["image_rate_hz"]))
        sessions[name] = deep_merge(sessions.get(name, {}), {"imagedb": {"min_interval_s": round(interval, 6)}})
    data["sessions"] = sessions
    notes = []
    if faster:
        notes.append(
            "# each session's image database at its own image rate: the town's cameras record faster\n"
            "# (camera.record_rate_hz) and the maps use every image"
        )
    if not lidar_map:
        data["lidar_map"] = {"enabled": False}
        notes.append("# no LiDAR maps (--no-lidar-maps)")
    path = out / ("build_config_video.yaml" if faster else "build_config.yaml")
    atomic_write_text(
        path,
        "# configs/build/demo.yaml as mapkit demo ran it, with:\n"
        + "\n".join(notes)
        + "\n"
        + yaml.safe_dump(data, sort_keys=False),
    )
    return path


def _align(d: Demo) -> None:
    with d.stage("align", "Multi-session map (mapkit align)") as sec:
        d.need("build")
        if len(d.metrics.get("georeferenced", [])) < 2:
            raise _Skip(
                f"{len(d.metrics.get('georeferenced', []))} georeferenced session(s); alignment needs two "
                "(a drive too short or too straight for GPS to fix its heading is not georeferenced: see eval_build)"
            )
        out = align_workspace(d.ws.root, progress=d.progress)
        d.metrics["eval_align"] = evaluate_align(d.ws, d.town)
        sec.md_file(out / "qa.md")
        sec.md_file(out / "eval_align.md")
        sec.picture(out / "pairs_map.png", "registered submap pairs", 560)
        sec.picture(out / "icp_histograms.png", "ICP fitness and residuals", 560)


def _triplets(d: Demo) -> None:
    with d.stage("triplets", "Triplet patch dataset (mapkit triplets)") as sec:
        d.need("align")
        folder = export_triplets(d.ws.root, overrides=DEMO_TRIPLETS.get(d.preset), progress=d.progress)
        m = json.loads((folder / "metrics.json").read_text())
        ev = evaluate_triplets(folder, d.ws, d.town)
        d.metrics["triplets"] = {"export": m, "truth": ev}
        sec.md(_figures(("", m), ("true offset: ", ev)))
        sec.picture(folder / "examples.png", "positive and negative patches side by side", 900)


def _figures(*groups: tuple[str, dict]) -> str:
    """A two-column Markdown table of the scalar figures of metric dicts, each key with its prefix."""
    rows = ["| figure | value |", "|---|---|"]
    for prefix, m in groups:
        rows += [
            f"| {prefix}{k} | {f'{v:.4g}' if isinstance(v, float) else v} |"
            for k, v in m.items()
            if not isinstance(v, (dict, list))
        ]
    return "\n".join(rows)


#: the demo's VLAD encoder: dense SIFT on the image halved first, the MCVL authors' released code's
#: practice, where the paper's text (the library default) extracts at full resolution. A quarter of
#: the descriptors: on the demo town, the index build and the localization stage take 33 s and 32 s
#: instead of 124 s and 117 s (both cores); retrieval medians move by -25 to +26 m, and the
#: multi-hypothesis filter still beats retrieval alone on every test session.
DEMO_VLAD = {"dsift": {"half_resolution": True}}

#: Triplet settings per preset. The places town's drives are 0.8-1 km, so the library's 200 m tiles
#: with a quarter held out leave few held-out queries per place-recognition pair; 100 m tiles with 40%
#: held out leave more. The split is the paper's geographic one (semi-dense paper Sec. 5.1), only
#: finer; the CNN trains on its train tiles. The tiny and demo towns keep the library's tiles: their
#: 250-400 m drives have no negative 100 m away inside such small tiles.
#: The demo town exports 2,000 triplets, enough to show the dataset (the paper's set of 20,000, the
#: library default, takes a minute more); a CNN trained on the demo (--train-cnn) takes its budget's 2,000.
DEMO_TRIPLETS: dict[str, dict] = {"places": {"tile_size_m": 100.0, "test_fraction": 0.4}, "demo": {"n_triplets": 2000}}


def _index_vlad(d: Demo) -> None:
    with d.stage("index_vlad", "Image retrieval index (mapkit index vlad)") as sec:
        d.need("build")
        train = d.train_sessions
        if not train:
            raise _Skip("the town has no training session")
        out = build_vlad_index(
            d.ws.root,
            overrides={"train_sessions": train, "database_sessions": train, "workers": d.workers, "vlad": DEMO_VLAD},
            progress=d.progress,
        )
        m = json.loads((out / "metrics.json").read_text())
        d.metrics["index_vlad"] = m
        sec.md(
            f"Database and training sessions: {', '.join(train)}. Dense SIFT on images halved first, as the MCVL "
            "authors' released code does (the library's default is the paper's text, full resolution).\n\n"
            + _figures(("", m))
        )


def _index_structure(d: Demo) -> None:
    with d.stage("index_structure", "Structure indexes (mapkit index structure)") as sec:
        d.need("align")
        train = d.train_sessions
        rows = ["| descriptor | entries | frames | dim | seconds |", "|---|---|---|---|---|"]
        for kind in d.structure_kinds():
            t0 = time.perf_counter()
            out = build_structure_index(
                d.ws.root,
                kind,
                sessions=train,
                overrides=d.structure_overrides(kind),
                cache_dir=d.ws.descriptor_cache,
                progress=d.progress,
            )
            man = json.loads((out / "manifest.json").read_text())
            c = man["counts"]
            rows.append(f"| {kind} | {c['entries']} | {c['frames']} | {c['dim']} | {time.perf_counter() - t0:.0f} |")
        sec.md(f"Database sessions: {', '.join(train)}.\n\n" + "\n".join(rows))


def _localize(d: Demo) -> None:
    with d.stage("localize", "Monte Carlo visual localization (mapkit eval localize)") as sec:
        d.need("index_vlad")
        if not d.test_sessions:
            raise _Skip("the town has no test session")
        cache = _localize_cache(d.ws)  # test images are encoded once, for both runs and for places
        runs = {"paper": None, "odometry-multihypothesis": preset_path("localize", "odometry-multihypothesis")}
        d.metrics["localize"] = {}
        for name, cfg in runs.items():
            out = d.ws.localize_dir / name
            r = evaluate_localization(
                d.ws, d.town, bundle=d.ws.vlad_index, config=cfg, out=out, cache_dir=cache, progress=d.progress
            )
            d.metrics["localize"][name] = {
                n: {k: s.get(k) for k in ("retrieval", "filter", "queries")} for n, s in r["sessions"].items()
            }
            label = (
                "the paper's defaults (MCVL Sec. IV-A)"
                if cfg is None
                else f"preset `configs/localize/{cfg.name}` (beyond the paper)"
            )
            sec.md(f"#### Filter with {label}")
            sec.md_file(out / "eval_localize.md", drop_title=False)
            for n in d.test_sessions:
                sec.picture(out / f"{n}.png", f"{n}, {name}: localized track against truth", 420)


def _sixdof(d: Demo) -> None:
    title = "6-DoF localization on a reference model (mapkit model, eval localize --refine 6dof, export benchmark)"
    with d.stage("sixdof", title) as sec:
        if not d.sixdof:
            raise _Skip("not asked for (`mapkit demo --sixdof`: about 2 more minutes on the demo town)")
        d.need("align", "index_vlad")
        if not d.train_sessions or not d.test_sessions:
            raise _Skip("the town needs training and test sessions")
        model = build_reference_model(d.ws, sessions=d.train_sessions)
        m = json.loads((model / "metrics.json").read_text())
        depth = {k: v for k, v in (m.get("depth_check") or {}).items() if isinstance(v, dict)}
        checks = "; ".join(
            f"{src}: median {100 * v['median_relative_difference']:.1f} % of the depth, "
            f"{100 * v['fraction_compared']:.0f} % of the observations compared"
            for src, v in depth.items()
            if v.get("median_relative_difference") is not None
        )
        sec.md(
            f"Reference model of {', '.join(d.train_sessions)} in the aligned frame (`{model}`): {m['points']:,} "
            f"points seen by {m['images_with_points']} of {m['images']} images, median track length "
            f"{m['track_length_median']:g}, median reprojection error {m['reprojection_error_median_px']:.2f} px."
            + (f" Depth check against the maps: {checks}." if checks else "")
        )
        sec.picture(model / "statistics.png", "points per image, track lengths, reprojection errors", 700)
        out = d.ws.localize_dir / "6dof"
        r = evaluate_localization(  # the filter that localizes best on the demo gives the prior and the fallback
            d.ws,
            d.town,
            bundle=d.ws.vlad_index,
            config=preset_path("localize", "odometry-multihypothesis"),
            overrides={"refine": "6dof"},
            out=out,
            cache_dir=_localize_cache(d.ws),
            progress=d.progress,
        )
        d.metrics["sixdof"] = {n: s["sixdof"] for n, s in r["sessions"].items() if "sixdof" in s}
        fit = r["model_from_truth"]
        sec.md(
            "#### Each test drive's queries: 6-DoF, MCVL's filter and retrieval alone\n\n"
            "The filter is preset `configs/localize/odometry-multihypothesis.yaml`; its pose is the 6-DoF localizer's "
            "prior and the estimate of a query it does not register. Every estimate is scored against the truth in "
            f"the model's frame, fitted on its {fit['fit_images']} database images (the aligned frame sits "
            f"{fit['offset_m']:.2f} m off the truth; fit residual {fit['residual_rmse_m']:.2f} m RMSE)."
        )
        sec.md(format_sixdof(r))
        bench = export_benchmark(
            d.ws,
            d.out / "benchmark",
            queries=d.test_sessions,
            truth=d.town,
            progress=d.progress,
            cache_dir=_localize_cache(d.ws),
        )
        sec.md(
            f"Benchmark export for outside localizers: `{bench}` (the model, `queries_with_intrinsics.txt`, the "
            "ground truth and retrieval pairs; its README says what each file is)."
        )


#: the voxel the demo's LiDAR maps are merged to for place recognition (m); mapkit choice: on the demo town 0.45 m
#: leaves 0.59 M LiDAR points over its four evaluated drives against their 0.61 M semi-dense points (0.25 m, as
#: built: 6.4 M, ten times as long to describe), so both sources are compared at about the same density
LIDAR_PLACES_VOXEL_M = 0.45


def places_pairs(roles: dict[str, dict], map_points: dict[str, int]) -> list[tuple[str, str]]:
    """Session pairs (database, query) mixing conditions: each test session against two training
    sessions with maps, the one whose streets it retraces (its ``follows``) first, then the fullest
    maps; and each later test session against the first."""
    train = sorted(
        (n for n, s in roles.items() if s.get("role") == "train" and map_points.get(n, 0) > 0),
        key=lambda n: (-map_points[n], n),
    )
    tests = sorted(n for n, s in roles.items() if s.get("role") == "test" and map_points.get(n, 0) > 0)
    pairs = []
    for q in tests:
        leader = roles[q].get("follows")
        dbs = ([leader] if leader in train else []) + [n for n in train if n != leader]
        pairs += [(db, q) for db in dbs[:2]]
    if tests:
        pairs += [(tests[0], q) for q in tests[1:]]
    return pairs


def _places(d: Demo) -> None:
    with d.stage("places", "Place recognition (mapkit eval places)") as sec:
        d.need("align", "index_vlad")
        pairs = places_pairs(d.roles, _map_points(d.ws))
        if not pairs:
            raise _Skip("no pair of a training and a test session with maps")
        methods = list(d.structure_kinds()) + ["vlad"]
        out = d.ws.places_eval_dir
        r = evaluate_places(
            d.ws,
            pairs,
            methods,
            out=out,
            truth=d.town,
            vlad_bundle=d.ws.vlad_index,
            overrides=d.places_overrides(),
            progress=d.progress,
        )
        d.metrics["places"] = {
            f"{p['database']}:{p['query']}": {m: v.get("auc") for m, v in p["methods"].items()} for p in r["pairs"]
        }
        sec.md_file(out / "places.md")
        sec.picture(out / "pr_curves.png", "precision-recall curves", 1000)
        if d.lidar_maps:
            structure = [m for m in methods if m != "vlad"]
            ov = d.places_overrides()
            ov["structure"] = {**ov.get("structure", {}), "map_source": "lidar", "lidar_voxel_m": LIDAR_PLACES_VOXEL_M}
            lidar = evaluate_places(
                d.ws,
                pairs,
                structure,
                out=d.ws.places_eval_folder("lidar"),
                truth=d.town,
                overrides=ov,
                progress=d.progress,
            )
            d.metrics["places_by_source"] = {f"{db}:{q}": e for (db, q), e in aucs_by_source(r, lidar).items()}
            sec.md(
                "#### Structure from images against structure from LiDAR\n\n"
                f"The LiDAR maps' voxels merged to {LIDAR_PLACES_VOXEL_M:g} m, about the semi-dense maps' point count. "
                "Held-out places:\n\n"
                + places_by_source(r, lidar)
                + "\n\nAll places:\n\n"
                + places_by_source(r, lidar, "all_places")
                + "\n\nThe LiDAR run's own tables: `workspace/eval/places-lidar/places.md`."
            )


def places_by_source(semidense: dict, lidar: dict, scope: str = "held_out") -> str:
    """Each pair's AUC per structure method on the semi-dense maps and on the LiDAR maps, side by side, over one
    scope of queries (``held_out``, the headline where there is a split, or ``all_places``), with each run's query
    count: :func:`aucs_by_source` as a table."""
    methods = [m for m in lidar["methods"] if m in semidense["methods"]]
    head = ["pair (query to database)", "queries (semi-dense / LiDAR)"] + [
        f"{METHOD_LABELS.get(m, m)}: semi-dense / LiDAR" for m in methods
    ]
    rows = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]

    def auc(entry: dict, m: str) -> str:
        v = entry["auc"].get(m, {}).get(scope)
        return "n/a" if v is None else f"{v:.3f}"

    for (db, query), e in aucs_by_source(semidense, lidar).items():
        semi, lid = e["semidense"], e["lidar"]
        cells = [f"{semi['queries'][scope]} / {lid['queries'][scope]}"] + [
            f"{auc(semi, m)} / {auc(lid, m)}" for m in methods
        ]
        rows.append(f"| {query} to {db} | " + " | ".join(cells) + " |")
    what = "all queries" if scope == "all_places" or semidense.get("headline") != "held_out" else "held-out queries"
    return (
        "\n".join(rows)
        + f"\n\nAUC over {what}, the same pairs and split; queries are the semi-dense maps' keyframes and the LiDAR "
        "maps' frames (one every 2 m), so their counts differ."
    )


def aucs_by_source(semidense: dict, lidar: dict) -> dict:
    """Per pair (``(database, query)``, the semi-dense run's order) and structure method, the AUC on each map source
    over the held-out queries and over all, with the query counts (``metrics.json``'s ``places_by_source``, keyed
    ``DATABASE:QUERY``)."""
    out: dict = {}
    by_pair = {(p["database"], p["query"]): p for p in lidar["pairs"]}
    for p in semidense["pairs"]:
        q = by_pair.get((p["database"], p["query"]))
        if q is None:
            continue
        entry: dict = {}
        for src, e in (("semidense", p), ("lidar", q)):
            entry[src] = {
                "queries": {"held_out": e["queries"], "all_places": e["all_places"]["queries"]},
                "auc": {
                    m: {"held_out": e["methods"][m].get("auc"), "all_places": e["all_places"]["methods"][m].get("auc")}
                    for m in lidar["methods"]
                    if m in e["methods"]
                },
            }
        out[(p["database"], p["query"])] = entry
    return out


def _map_points(ws: Workspace) -> dict[str, int]:
    """Points of each built session's semi-dense map, from its build metrics."""
    points = {}
    for name in ws.session_names():
        m = ws.session(name).metrics
        if m.is_file():
            points[name] = int((json.loads(m.read_text()).get("stages", {}).get("semidense") or {}).get("points", 0))
    return points


def _localize_cache(ws: Workspace) -> Path:
    """Where the demo keeps the localization stage's retrieved hits and encodings (shared with places)."""
    return ws.localize_cache


def _export(d: Demo) -> None:
    with d.stage("export", "Deployable bundle (mapkit index export)") as sec:
        d.need("index_vlad")
        out = export_bundles(d.ws.root, d.bundles)
        b = load_bundle(out, verify=False)  # export_bundles checked every file's checksum; this loads every index
        rows = ["| index | kind | entries | source sessions |", "|---|---|---|---|"]
        for name, e in b.manifest["indexes"].items():
            rows.append(f"| {name} | {e['descriptor']} | {e['entries']} | {', '.join(e['source_sessions'])} |")
        sec.md(f"Written to `{out}` (every file's checksum verified) and loaded back.\n\n" + "\n".join(rows))
        d.metrics["bundles"] = {"path": str(out), "indexes": sorted(b.indexes)}


def _view(d: Demo) -> None:
    with d.stage("view", "Fly through it (mapkit view)") as sec:
        d.need("build")
        if importlib.util.find_spec("rerun") is None:
            raise _Skip("the viewer extra (rerun-sdk) is not installed")
        s = write_recording(d.ws, budget_points=VIEW_BUDGET_POINTS, progress=d.progress)
        png = render_top_view(s.path, d.out / "view_top.png")
        sec.md(
            f"`{s.path}` ({s.bytes / 1e6:.1f} MB, {s.seconds:.0f} s): open it with `rerun {s.path}` (the viewer "
            f"extra). {s.points:,} of {sum(s.map_points_total.values()):,} map points in {len(s.map_points)} maps, "
            f"{sum(s.images.values())} thumbnails at their poses, {sum(s.gps_fixes.values())} GPS fixes, the "
            "localizer's estimates over time. Its top view, drawn from the recording:"
        )
        sec.picture(png, "the recording from above", 900)
        d.metrics["view"] = {"path": str(s.path), "points": s.points}


#: map points in the demo's recording (mapkit view's default budget is 2 M)
VIEW_BUDGET_POINTS = 1_000_000

#: the demo's training budget (a few minutes on 2 cores); the paper's full schedule (20,000 triplets,
#: several hard-negative cycles) is `mapkit train` with its defaults
CNN_DEMO_BUDGET = {"triplet_set": 2000, "epochs": 5}


def _train_cnn(d: Demo) -> None:
    with d.stage("train_cnn", "Learned patch descriptor (mapkit train)") as sec:
        if not d.train_cnn:
            raise _Skip("not asked for (`mapkit demo --train-cnn`, needs the learning extra)")
        d.need("triplets")
        from mapkit.learning.train import train_cnn

        out = train_cnn(d.ws.triplets_dir, d.ws.cnn_dir, overrides=CNN_DEMO_BUDGET, progress=d.progress)
        sec.picture(out / "training_curve.png", "training curve", 640)
        d.metrics["train_cnn"] = (
            json.loads((out / "metrics.json").read_text()) if (out / "metrics.json").is_file() else {}
        )


#: Files of a run that are records of the run itself, not results: they differ between two runs of the
#: same inputs. Every other file of a run is the same to the byte on the same machine (the reference model's nearly
#: always: COLMAP's SIFT has once given one image other keypoint orientations, docs/concepts.md).
RUN_RECORDS = {
    "timings.json": "wall-clock figures of the stage that wrote the folder",
    "timings.md": "the run's stage times",
    "report.html": "shows the stage times",
    "view.rrd": "Rerun stamps every row it records with a time-based id",
}

STAGES = (
    _synth,
    _build,
    _align,
    _triplets,
    _train_cnn,
    _index_vlad,
    _index_structure,
    _localize,
    _sixdof,
    _places,
    _export,
    _view,
)


def run_demo(
    out: str | Path = "mapkit-demo",
    preset: str = "demo",
    seed: int | None = None,
    workers: int = 2,
    train_cnn: bool = False,
    progress: bool = False,
    log: Callable[[str], None] = logger.info,
    record_rate_hz: float | None = None,
    synth_overrides: dict | None = None,
    lidar_maps: bool = True,
    sixdof: bool = False,
    synth_config: str | Path | None = None,
) -> dict:
    """Run the whole chain into ``out``; returns the metrics (also in ``out/metrics.json``), with
    the paths of the report and the bundle. ``log`` takes the stage lines ("[demo] build: ok in
    12 s"); by default they go to this module's logger at INFO (the CLI shows them on stderr).

    ``record_rate_hz``: the town's cameras record video at this rate and the maps are made from
    every image, as the semi-dense paper's DSO maps are (Sec. 3); image databases and queries keep
    the preset's rates (:func:`demo_build_config`). ``synth_config``: a YAML file over the town's preset, as
    ``mapkit synth --config`` takes it (``configs/synth/demo-snowy.yaml`` adds a snowy test drive);
    ``synth_overrides``: a mapping merged over both. ``lidar_maps`` (on by default): each session's LiDAR
    map too (the report shows them beside the semi-dense maps, align registers on them, place recognition scores
    them beside the semi-dense maps and the reference model's depth check uses them; triplets and the structure
    indexes read the semi-dense maps). ``sixdof``: the reference model of the training drives, the 6-DoF
    localization of the test drives on it and the localization benchmark export (the ``sixdof`` stage)."""

    d = Demo(
        Path(out),
        preset,
        seed,
        workers,
        train_cnn,
        progress,
        log,
        record_rate_hz,
        synth_overrides,
        lidar_maps,
        sixdof,
        None if synth_config is None else Path(synth_config),
    )
    d.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    ex = default_executor()  # `mapkit --executor ray demo` set one; else a local pool of `workers`
    with (
        d.ws.lock(command="mapkit demo"),
        nullcontext(ex) if ex is not None else use_executor("local", workers=workers) as ex,
    ):
        d.metrics["executor"] = {"kind": ex.kind, "workers": ex.workers}
        for stage in STAGES:
            try:
                stage(d)
            except Exception:  # a bug in one stage: keep its traceback in the report, stop the chain
                d.metrics.setdefault("stages", {})[stage.__name__.strip("_")] = {
                    "status": "crashed",
                    "traceback": traceback.format_exc(),
                }
                _finish(d, time.perf_counter() - t0)
                raise
    return _finish(d, time.perf_counter() - t0)


def _docs_line(d: Demo) -> str:
    """Where to read on: the documentation (the checkout's docs/, when mapkit runs from one) and the recording."""
    docs = Path(__file__).resolve().parents[2] / "docs" / "index.md"
    parts = [
        f"Documentation: `{docs}` (a site with `mkdocs build --strict`)"
        if docs.is_file()
        else "Documentation: the docs/ folder of mapkit's source"
    ]
    if d.ok("view"):
        parts.append(f"3D: `rerun {d.ws.recording}`")
    return "; ".join(parts) + "."


def _finish(d: Demo, seconds: float) -> dict:
    d.timings["seconds_total"] = round(seconds, 1)
    d.metrics["report"] = str(d.out / "report.html")
    d.metrics["openblas"] = openblas_kernels()  # the kernel each OpenBLAS ran: the bits of every product
    rows = [f"| stage | status | seconds | cores busy (of {os.cpu_count()}) |", "|---|---|---|---|"]
    rows += [
        f"| {n} | {s['status']}{' (' + s['reason'] + ')' if s.get('reason') else ''} | {t.get('seconds', '')} "
        f"| {t.get('cores_busy', '')} |"
        for n, s in d.metrics["stages"].items()
        for t in [d.timings["stages"].get(n, {})]
    ]
    ex = d.metrics.get("executor", {})
    intro = (
        f"mapkit {__version__}, synthetic town preset `{d.preset}`, executor {ex.get('kind', 'local')} with "
        f"{ex.get('workers', d.workers)} worker(s). "
        f"Whole run: **{seconds / 60:.1f} min** wall time. {_docs_line(d)}\n\n" + "\n".join(rows)
    )
    write_report(d.out / "report.html", f"mapkit demo: {d.preset} town", intro, d.sections)
    atomic_write_text(d.out / "timings.md", "\n".join(rows) + "\n")
    write_json(d.out / "metrics.json", d.metrics)
    write_timings(d.out, **d.timings)
    return d.metrics


__all__ = ["RUN_RECORDS", "STAGES", "demo_build_config", "places_pairs", "run_demo"]
