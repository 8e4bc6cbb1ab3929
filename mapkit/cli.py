"""The ``mapkit`` command line. It only parses arguments and calls the library.

A ``MapkitError`` (bad input, bad config) becomes one line on stderr and exit code 2; anything
else is a bug and keeps its traceback.
"""

from __future__ import annotations

import functools
import logging
import sys
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, TypeGuard

import typer

from mapkit import __version__
from mapkit.core.errors import ConfigError, InputWarning, MapkitError

if TYPE_CHECKING:
    from mapkit.core.config import MapkitConfig
    from mapkit.deploy.crs_export import Source

app = typer.Typer(
    name="mapkit",
    help="Drive logs to semi-dense maps, georeferenced image databases, triplet patches and localization indexes.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
index_app = typer.Typer(help="Build, extend and export deployable indexes.", no_args_is_help=True)
eval_app = typer.Typer(help="Evaluate maps, indexes and localizers against ground truth.", no_args_is_help=True)
app.add_typer(index_app, name="index")
app.add_typer(eval_app, name="eval")
export_app = typer.Typer(help="Export a workspace for other tools.", no_args_is_help=True)
app.add_typer(export_app, name="export")


def _writes(arg: str):
    """Hold the write lock of the workspace named by the command's argument ``arg`` for the whole
    command (:mod:`mapkit.core.lock`): a second writer refuses, naming the first, or waits ``--wait``."""

    def wrap(fn):
        @functools.wraps(fn)
        def run(*args, **kwargs):
            from mapkit.core.lock import workspace_lock
            from mapkit.core.writers import lock_wait

            if arg == "workspace" and not Path(kwargs[arg]).is_dir():
                return fn(*args, **kwargs)  # no workspace to protect: the command says what is missing
            with workspace_lock(kwargs[arg], command=f"mapkit {fn.__name__.replace('_', ' ')}", wait_s=lock_wait()):
                return fn(*args, **kwargs)

        return run

    return wrap


def _version(value: bool) -> None:
    if value:
        typer.echo(f"mapkit {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: bool = typer.Option(
        False, "--version", callback=_version, is_eager=True, help="Print the version and exit."
    ),
    executor: str = typer.Option(
        "local", "--executor", help="Where per-frame, per-patch and per-pair work runs: local (processes) or ray."
    ),
    workers: int | None = typer.Option(
        None,
        "--workers",
        help="Local processes or CPUs of a local Ray instance (default: one, or the stage's own setting).",
    ),
    ray_address: str | None = typer.Option(
        None, "--ray-address", help="A running Ray cluster ('auto' or HOST:PORT); default: start a local instance."
    ),
    wait: float = typer.Option(
        0.0,
        "--wait",
        help="Seconds to wait for another mapkit command writing the same workspace (default: refuse at once).",
    ),
) -> None:
    """mapkit: dataset building and mapping for visual localization."""
    from mapkit.core.writers import set_lock_wait

    set_lock_wait(wait)
    if executor not in ("local", "ray"):
        raise MapkitError(f"--executor {executor!r}: expected local or ray")
    if executor == "ray" or workers is not None or ray_address is not None:
        from mapkit.core.executor import set_default_executor

        set_default_executor(executor, workers, ray_address)


@app.command()
def info(
    log: Path = typer.Argument(..., help="An MCAP file or a KITTI / RobotCar / generic folder."),
    format: str | None = typer.Option(None, "--format", "-f", help="Reader name; guessed from the path if omitted."),
    json_out: Path | None = typer.Option(None, "--json", help="Also write the summary as JSON here."),
) -> None:
    """Per stream: topic, type, count, rate, time span; for GPS the distance covered and fix quality."""
    from mapkit.core.runio import write_json
    from mapkit.io.info import format_summary, summarize

    summary = summarize(log, format=format, progress=sys.stderr.isatty())
    typer.echo(format_summary(summary))
    if json_out is not None:
        write_json(json_out, summary)
    if summary["messages_read"] == 0:
        raise MapkitError(f"{log}: no usable message could be read")


config_app = typer.Typer(help="Show configuration defaults.", no_args_is_help=True)
app.add_typer(config_app, name="config")

#: name -> "module:Model" of every stage's config, for ``mapkit config defaults NAME``; resolved
#: lazily so that listing them imports no stage (here, at the top, because it names every rung)
CONFIGS: dict[str, str] = {
    "topics": "mapkit.core.config:TopicConfig",
    "build": "mapkit.mapping.build:BuildConfig",
    "semidense": "mapkit.mapping.semidense:SemiDenseConfig",
    "align": "mapkit.multisession.align:AlignConfig",
    "mcl": "mapkit.localization.mcl:MclConfig",
    "vlad": "mapkit.retrieval.vlad:VladConfig",
    "triplets": "mapkit.places.triplets:TripletConfig",
    "reference_model": "mapkit.localization.reference_model:ReferenceModelConfig",
    "sixdof": "mapkit.localization.sixdof:SixDofConfig",
    "colmap_registrator": "mapkit.localization.colmap_registrator:ColmapRegistratorConfig",
    "benchmark_export": "mapkit.deploy.benchmark:BenchmarkExportConfig",
    "index_vlad": "mapkit.retrieval.index_vlad:VladIndexConfig",
    "localize": "mapkit.localization.localize:LocalizeConfig",
    "structure_index": "mapkit.places.index_structure:StructureIndexConfig",
    "places": "mapkit.evaluation.places:PlacesEvalConfig",
    "train": "mapkit.learning.train:TrainConfig",
    "executor": "mapkit.core.executor:ExecutorConfig",
}


def config_model(name: str) -> type[MapkitConfig]:
    """The config model registered as ``name``."""
    from mapkit.core.registry import load_entry

    if name not in CONFIGS:
        raise ConfigError(f"no configuration named {name!r}; known: {', '.join(sorted(CONFIGS))}")
    return load_entry(CONFIGS[name])


@config_app.command("defaults")
def config_defaults(name: str = typer.Argument(..., help="Config name, e.g. topics.")) -> None:
    """Print the defaults of a configuration as commented YAML."""
    from mapkit.core.config import defaults_yaml

    typer.echo(defaults_yaml(config_model(name)), nl=False)


@app.command()
def synth(
    preset: str = typer.Option(
        "tiny",
        help="tiny (tests), demo, places or benchmark: configs/synth/NAME.yaml, installed as mapkit/configs/synth/.",
    ),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder for the world and session logs."),
    seed: int | None = typer.Option(None, help="Seed of the town and sessions (the preset's if omitted)."),
    config: Path | None = typer.Option(
        None, "--config", "-c", help="YAML overriding the preset (e.g. configs/synth/benchmark-camera.yaml)."
    ),
    trajectory: Path | None = typer.Option(None, help="Drive one session along this TUM / KITTI / RobotCar INS file."),
    overwrite: bool = typer.Option(False, help="Regenerate outputs that already exist."),
    record_rate_hz: float | None = typer.Option(
        None,
        help="Cameras record video at this rate (camera.record_rate_hz); "
        "each session's own rate stays its image rate (manifest: image_rate_hz).",
    ),
) -> None:
    """Generate the synthetic town: georeferenced multi-session drive logs with ground truth."""
    from mapkit.synth import synthesize

    overrides = {"camera": {"record_rate_hz": record_rate_hz}} if record_rate_hz is not None else None
    path = synthesize(
        preset=preset,
        out=out,
        seed=seed,
        config=config,
        trajectory=trajectory,
        overwrite=overwrite,
        overrides=overrides,
    )
    typer.echo(f"synthetic town written to {path}")


@app.command()
@_writes("out")
def build(
    logs: list[Path] = typer.Argument(..., help="One or more drive logs; each becomes a session."),
    out: Path = typer.Option(..., "--out", "-o", help="Workspace folder."),
    config: Path | None = typer.Option(
        None,
        "--config",
        "-c",
        help="YAML overriding `mapkit config defaults build` (e.g. configs/build/mcvl-database.yaml).",
    ),
) -> None:
    """Build georeferenced session maps (trajectory, GPS alignment, semi-dense map, image database)."""
    from mapkit.mapping.build import build as run_build
    from mapkit.mapping.build import format_build_summary

    ws = run_build(logs, out, config, progress=sys.stderr.isatty())
    typer.echo(format_build_summary(ws))


@app.command()
@_writes("workspace")
def align(
    workspace: Path = typer.Argument(
        ..., help="A workspace made by `mapkit build` (two or more georeferenced sessions)."
    ),
    config: Path | None = typer.Option(None, "--config", "-c", help="YAML overriding `mapkit config defaults align`."),
    map_source: str | None = typer.Option(
        None,
        "--map-source",
        help="Register submap pairs on semidense, lidar, auto (LiDAR maps where both sessions have one) or "
        "semidense+lidar (LiDAR maps where the semi-dense ones are too sparse to register); default: the config's "
        "map_source (semidense+lidar).",
    ),
) -> None:
    """Align the sessions of a workspace into one georeferenced frame (GPS, then ICP and a pose graph)."""
    from mapkit.multisession.align import align_workspace

    overrides = None if map_source is None else {"map_source": map_source}
    out = align_workspace(workspace, config, overrides, progress=sys.stderr.isatty())
    typer.echo((out / "qa.md").read_text(), nl=False)
    typer.echo(f"written to {out}: refined sessions, tiles/, pairs.json, qa.md, pictures")


@app.command("export-crs")
@_writes("workspace")
def export_crs(
    workspace: Path = typer.Argument(..., help="A georeferenced workspace (mapkit build, optionally mapkit align)."),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder."),
    crs: str = typer.Option(
        "utm",
        "--crs",
        help="utm (the workspace's zone), ecef (EPSG:4978), wgs84 (EPSG:4979, trajectories only) or EPSG:<code>.",
    ),
    session: list[str] | None = typer.Option(
        None, "--session", "-s", help="A session to export (repeatable); default: every georeferenced one."
    ),
    what: str = typer.Option("trajectory,map", "--what", help="Comma-separated: trajectory, map."),
    merged: bool = typer.Option(
        False, "--merged", help="Also write the merged map of `mapkit align` (merged_map.ply)."
    ),
    source: str = typer.Option(
        "auto", "--source", help="auto (aligned where `mapkit align` holds the session), aligned or built."
    ),
) -> None:
    """Write trajectories (TUM, or CSV lat/lon) and maps (PLY) of a workspace in a chosen CRS, for GIS tools, CloudCompare, evo."""  # noqa: E501 (Typer's rich help keeps a docstring's line breaks: one line per help line)
    from mapkit.deploy.crs_export import export_crs as run_export

    parts = {w.strip() for w in what.split(",") if w.strip()}
    if not parts <= {"trajectory", "map"} or not _is_source(source):
        raise MapkitError(
            f"--what {what!r} (expected trajectory and/or map) / --source {source!r} (expected auto, aligned or built)"
        )
    m = run_export(
        workspace,
        out,
        crs,
        sessions=session or None,
        trajectory="trajectory" in parts,
        map="map" in parts,
        merged=merged,
        source=source,
    )
    typer.echo(
        f"EPSG:{m['crs_epsg']} ({m['crs_name']}): {len(m['sessions'])} session(s)"
        f"{', merged map' if 'merged_map' in m else ''} written to {out} (see export.json)"
    )


def _is_source(value: str) -> TypeGuard[Source]:
    return value in ("auto", "aligned", "built")


@app.command()
@_writes("workspace")
def triplets(
    workspace: Path = typer.Argument(..., help="A workspace aligned by `mapkit align`."),
    out: Path | None = typer.Option(
        None, "--out", "-o", help="Dataset folder (default WORKSPACE/triplets, WORKSPACE/triplets-lidar with lidar)."
    ),
    config: Path | None = typer.Option(
        None, "--config", "-c", help="YAML overriding `mapkit config defaults triplets`."
    ),
    truth: Path | None = typer.Option(
        None, "--truth", help="Synthetic town: also measure the positives' true offsets."
    ),
    pointnetvlad: bool = typer.Option(
        False, "--pointnetvlad", help="Also write the PointNetVLAD tuple layout (DATASET/pointnetvlad)."
    ),
    map_source: str | None = typer.Option(
        None,
        "--map-source",
        help="Cut patches from the aligned semidense maps or the aligned lidar maps; default: the config's "
        "map_source (semidense).",
    ),
) -> None:
    """Export a triplet dataset of voxelised 3D patches (train/test split by UTM tiles)."""
    import json

    from mapkit.evaluation.triplets import evaluate_triplets
    from mapkit.places.pointnetvlad import export_triplets_pointnetvlad

    overrides: dict = {"pointnetvlad": {"enabled": True}} if pointnetvlad else {}
    if map_source is not None:
        overrides["map_source"] = map_source
    folder = export_triplets_pointnetvlad(workspace, out, config, overrides=overrides, progress=sys.stderr.isatty())
    typer.echo((folder / "metrics.json").read_text(), nl=False)
    if truth is not None:
        typer.echo(json.dumps(evaluate_triplets(folder, workspace, truth), indent=2))
    typer.echo(
        f"written to {folder}: patches-*.h5 (or .npz), patches.csv, triplets_train.npy, triplets_test.npy, "
        "manifest.json, examples.png" + (", pointnetvlad/" if (folder / "pointnetvlad").is_dir() else "")
    )


@app.command()
@_writes("workspace")
def model(
    workspace: Path = typer.Argument(..., help="A workspace with image databases (aligned by `mapkit align` or not)."),
    out: Path | None = typer.Option(None, "--out", "-o", help="Model folder (default WORKSPACE/reference_model)."),
    config: Path | None = typer.Option(
        None, "--config", "-c", help="YAML overriding `mapkit config defaults reference_model`."
    ),
    session: list[str] | None = typer.Option(None, "--session", help="A session to use (repeatable; default all)."),
    truth: Path | None = typer.Option(
        None,
        "--truth",
        help="A synthetic town: the images take their true poses, a model that measures a localizer alone.",
    ),
) -> None:
    """Build the triangulated reference model (COLMAP, SIFT) of the database images on their known poses."""
    from mapkit.localization.reference_model import build_reference_model

    folder = build_reference_model(workspace, session or None, out, config, truth)
    typer.echo((folder / "metrics.json").read_text(), nl=False)
    typer.echo(f"written to {folder}: sfm/ (COLMAP binary), sfm_text/, database.db, pairs.txt, statistics.png")


@app.command()
def localize(
    bundle: Path = typer.Argument(..., help="A VLAD bundle (`mapkit index vlad`)."),
    log: Path = typer.Argument(..., help="A drive log with camera images."),
    out: Path = typer.Option(Path("localize"), "--out", "-o", help="Output folder (TUM trajectories, metrics)."),
    config: Path | None = typer.Option(
        None, "--config", "-c", help="YAML overriding `mapkit config defaults localize`."
    ),
    camera: str | None = typer.Option(None, "--camera", help="Camera to use when the log has several."),
    refine: str | None = typer.Option(
        None,
        "--refine",
        help="none or 6dof: register each query against the reference model after the filter (default: the "
        "config's refine, none).",
    ),
    model: Path | None = typer.Option(
        None,
        "--model",
        help="The reference model of --refine 6dof (default: reference_model/ in the bundle's workspace).",
    ),
) -> None:
    """Run the Monte Carlo visual localizer on a drive log against a VLAD bundle."""
    from mapkit.localization.localize import localize_log

    overrides = _refine_overrides(refine, model)
    folder = localize_log(bundle, log, out, config, camera, progress=sys.stderr.isatty(), overrides=overrides)
    typer.echo(f"camera poses written to {folder}/poses_tum.txt (filter) and retrieval_tum.txt")
    if (folder / "sixdof.json").is_file():
        typer.echo(f"6-DoF poses written to {folder}/sixdof_tum.txt and sixdof_poses.txt (outcomes in sixdof.json)")


def _refine_overrides(refine: str | None, model: Path | None) -> dict | None:
    """The config overrides of ``--refine`` and ``--model``."""
    overrides: dict = {}
    if refine is not None:
        overrides["refine"] = refine
    if model is not None:
        overrides["reference_model"] = str(model)
    return overrides or None


@app.command("localize-benchmark")
def localize_benchmark(
    benchmark: Path = typer.Argument(..., help="A benchmark folder (`mapkit export benchmark`)."),
    out: Path = typer.Option(..., "--out", "-o", help="The poses file to write (name qw qx qy qz tx ty tz a line)."),
    config: Path | None = typer.Option(None, "--config", "-c", help="YAML overriding `mapkit config defaults sixdof`."),
    fallback: bool = typer.Option(
        False, "--fallback", help="Give a query that does not register its best retrieved database image's pose."
    ),
    localizer: str = typer.Option(
        "mapkit",
        "--localizer",
        help="mapkit (its 6-DoF localizer; `-c` overrides `mapkit config defaults sixdof`) or colmap (COLMAP's "
        "image registrator through pycolmap; `-c` overrides `mapkit config defaults colmap_registrator`).",
    ),
) -> None:
    """Register the benchmark's queries against its reference model (SIFT, 2D-3D matches, P3P RANSAC) from their retrieval pairs."""  # noqa: E501 (Typer's rich help keeps a docstring's line breaks: one line per help line)
    if localizer == "colmap":
        if fallback:
            raise ConfigError("--fallback is mapkit's localizer's: COLMAP's registrator leaves a query out")
        from mapkit.localization.colmap_registrator import register_benchmark

        poses = register_benchmark(benchmark, out, config, progress=sys.stderr.isatty())
    elif localizer == "mapkit":
        from mapkit.localization.sixdof import localize_benchmark as run

        poses = run(benchmark, out, config, retrieval_fallback=fallback, progress=sys.stderr.isatty())
    else:
        raise ConfigError(f"--localizer {localizer!r}: mapkit or colmap")
    typer.echo(f"poses written to {poses} (each query's outcome in {poses.stem}.queries.json)")


@export_app.command("benchmark")
def export_benchmark(
    workspace: Path = typer.Argument(..., help="A workspace with a reference model (`mapkit model`) and a VLAD index."),
    out: Path = typer.Option(..., "--out", "-o", help="The benchmark folder to write."),
    queries: list[str] = typer.Option(
        ..., "--queries", "--query", "-q", help="A query session (repeatable, or comma-separated)."
    ),
    truth: Path | None = typer.Option(
        None, "--truth", help="The synthetic town: true camera poses and conditions (else the sessions' own poses)."
    ),
    log: list[str] | None = typer.Option(
        None, "--log", help="SESSION=LOG: a query session without an image database, read from its log (repeatable)."
    ),
    config: Path | None = typer.Option(
        None, "--config", "-c", help="YAML overriding `mapkit config defaults benchmark_export`."
    ),
) -> None:
    """Export a 6-DoF visual localization benchmark: reference model, query images and intrinsics, ground truth, retrieval pairs."""  # noqa: E501 (Typer's rich help keeps a docstring's line breaks: one line per help line)
    from mapkit.deploy.benchmark import export_benchmark as run

    logs: dict[str, str] = {}
    for item in log or []:
        session, sep, path = item.partition("=")
        if not sep or not session or not path:
            raise ConfigError(f"--log {item!r}: expected SESSION=LOG")
        logs[session] = path
    names = [n for q in queries for n in q.split(",") if n]
    folder = run(workspace, out, names, truth, logs, config, progress=sys.stderr.isatty())
    typer.echo((folder / "metrics.json").read_text(), nl=False)
    typer.echo(f"benchmark written to {folder} (see README.md)")


@app.command()
def view(
    workspace: Path = typer.Argument(
        ..., help="A workspace made by `mapkit build` (aligned maps are added when `mapkit align` ran)."
    ),
    out: Path | None = typer.Option(None, "--out", "-o", help="The .rrd to write (default WORKSPACE/view.rrd)."),
    budget_points: int = typer.Option(
        2_000_000,
        "--budget-points",
        min=0,
        help="At most this many map points over all maps together; each map keeps the same share, sampled uniformly.",
    ),
    image_spacing: float = typer.Option(
        10.0, "--image-spacing", min=0.0, help="One camera thumbnail per this many metres of camera travel."
    ),
    thumbnail_width: int = typer.Option(320, "--thumbnail-width", min=16, help="Thumbnail width in pixels."),
    localize: Path | None = typer.Option(
        None,
        "--localize",
        help="A localization folder: `mapkit localize` runs (itself or its "
        "sub-folders) and cached retrieval hits (cache/); default WORKSPACE/localize.",
    ),
    gps: bool = typer.Option(
        True,
        "--gps/--no-gps",
        help="Draw the GPS fixes the georef stage used (its georef/gps_fixes.npz; where a session has none, read again "
        "from its log).",
    ),
    spawn: bool = typer.Option(False, "--spawn", help="Also open the Rerun viewer on it (needs a display)."),
    png: Path | None = typer.Option(
        None, "--png", help="Also render a top view of the recording to this PNG (matplotlib, no viewer needed)."
    ),
) -> None:
    """Write a Rerun recording (.rrd) of a workspace: trajectories, maps, GPS fixes, thumbnails at their poses, localizer runs.

    Kept to a budget whatever the workspace's size: at most --budget-points map points (default 2 M), one thumbnail per 10 m.

    Open it with `rerun FILE.rrd`. Needs the viewer extra (the rerun-sdk package).
    """  # noqa: E501 (Typer's rich help keeps a docstring's line breaks: one line per help line)
    from contextlib import nullcontext

    from mapkit.core.workspace import Workspace
    from mapkit.core.writers import lock_wait
    from mapkit.report.view import render_top_view, write_recording

    ws = Workspace(workspace)
    target = (out or ws.recording).resolve()
    # it only reads the workspace; its lock is held only when the recording lands inside it
    inside = ws.root.is_dir() and target.is_relative_to(ws.root.resolve())
    with ws.lock("mapkit view", lock_wait()) if inside else nullcontext():
        s = write_recording(
            ws,
            out,
            budget_points=budget_points,
            image_spacing_m=image_spacing,
            thumbnail_width_px=thumbnail_width,
            localize=localize,
            gps=gps,
            spawn=spawn,
            progress=sys.stderr.isatty(),
        )
    typer.echo(
        f"{s.path}: {s.bytes / 1e6:.1f} MB in {s.seconds:.1f} s; {s.points:,} of {sum(s.map_points_total.values()):,} "
        f"map points in {len(s.map_points)} map(s), {sum(s.images.values())} thumbnails, {sum(s.gps_fixes.values())} "
        f"GPS fixes, {sum(e.endswith('/trajectory') for e in s.poses)} trajectories"
    )
    for note in s.notes:
        typer.echo(f"note: {note}")
    if png is not None:
        typer.echo(f"top view written to {render_top_view(s.path, png)}")


@app.command()
def train(
    dataset: Path = typer.Argument(..., help="A triplet dataset (`mapkit triplets`)."),
    out: Path = typer.Option(
        ..., "--out", "-o", help="Model folder: checkpoints, model.pt, model.onnx, manifest, curve."
    ),
    config: Path | None = typer.Option(None, "--config", "-c", help="YAML overriding `mapkit config defaults train`."),
) -> None:
    """Train the 3D CNN patch descriptor with the triplet loss and hard-negative cycling (learning extra)."""
    from mapkit.learning.train import train_cnn

    folder = train_cnn(dataset, out, config, progress=sys.stderr.isatty())
    typer.echo((folder / "metrics.json").read_text()[:2000], nl=False)
    typer.echo(f"\nmodel written to {folder} (model.onnx loads without torch: `mapkit index structure --kind cnn`)")


@app.command()
def demo(
    out: Path = typer.Option(
        Path("mapkit-demo"), "--out", "-o", help="Output folder (town, workspace, bundles, report.html)."
    ),
    preset: str = typer.Option(
        "demo",
        help="Synthetic town preset: demo (default, every stage within ten minutes on 2 cores), "
        "tiny (every stage in a few minutes), places (the papers' claims) or benchmark.",
    ),
    seed: int | None = typer.Option(None, help="Seed of the town (the preset's if omitted)."),
    workers: int = typer.Option(2, help="Processes for image encoding."),
    train_cnn: bool = typer.Option(
        False, "--train-cnn", help="Also train the 3D CNN descriptor (learning extra; adds up to 30 min)."
    ),
    record_rate_hz: float | None = typer.Option(
        None,
        help="Cameras record video at this rate (RobotCar's 16) and the maps "
        "use every image, as the semi-dense paper's DSO maps do; image databases "
        "and queries keep the preset's rates.",
    ),
    lidar_maps: bool = typer.Option(
        True,
        "--lidar-maps/--no-lidar-maps",
        help="Build each session's LiDAR map beside its semi-dense map (align registers on them; place recognition "
        "scores both).",
    ),
    sixdof: bool = typer.Option(
        False,
        "--sixdof",
        help="Also build the reference model, localize the test drives in 6-DoF on it and export the localization "
        "benchmark (about 2 more minutes on the demo town).",
    ),
    synth_config: Path | None = typer.Option(
        None,
        "--synth-config",
        help="YAML over the town's preset, as `mapkit synth --config` takes it (configs/synth/demo-snowy.yaml adds "
        "a snowy test drive to the demo town).",
    ),
) -> None:
    """Synthetic town to deployable bundles and an HTML report, in one command."""
    from mapkit.pipelines.demo import run_demo

    m = run_demo(
        out,
        preset=preset,
        seed=seed,
        workers=workers,
        train_cnn=train_cnn,
        progress=sys.stderr.isatty(),
        record_rate_hz=record_rate_hz,
        lidar_maps=lidar_maps,
        sixdof=sixdof,
        synth_config=synth_config,
    )
    typer.echo((out / "timings.md").read_text(), nl=False)
    typer.echo(f"report: {m['report']}")
    if "bundles" in m:
        typer.echo(f"deployable bundle: {m['bundles']['path']} (indexes: {', '.join(m['bundles']['indexes'])})")
    failed = [n for n, s in m["stages"].items() if s["status"] in ("failed", "crashed")]
    if failed:
        raise MapkitError(f"demo stage(s) failed: {', '.join(failed)} (see {m['report']})")


@index_app.command("export")
@_writes("workspace")
def index_export(
    workspace: Path = typer.Argument(..., help="A workspace with finished indexes under WORKSPACE/indexes."),
    out: Path = typer.Option(..., "--out", "-o", help="Bundle folder to write (replaced atomically)."),
    name: list[str] | None = typer.Option(
        None, "--index", "-i", help="Index folder name (vlad, structure-nbld, ...); repeat; default all."
    ),
) -> None:
    """One deployable folder: every index with its manifest (format version, parameters, CRS, sessions, checksums)."""
    from mapkit.deploy.export import export_bundles, load_bundle

    path = export_bundles(workspace, out, name or None)  # verifies every index's checksums, then copies its files
    b = load_bundle(path, verify=False)
    for n, e in b.manifest["indexes"].items():
        typer.echo(f"{n}: {e['descriptor']}, {e['entries']} entries, sessions {', '.join(e['source_sessions'])}")
    typer.echo(f"bundle written to {path} and verified")


@index_app.command("vlad")
@_writes("workspace")
def index_vlad(
    workspace: Path = typer.Argument(
        ..., help="A workspace made by `mapkit build` (aligned poses are used when `mapkit align` ran)."
    ),
    out: Path | None = typer.Option(None, "--out", "-o", help="Bundle folder (default WORKSPACE/indexes/vlad)."),
    config: Path | None = typer.Option(
        None, "--config", "-c", help="YAML overriding `mapkit config defaults index_vlad`."
    ),
    reuse: Path | None = typer.Option(
        None,
        "--reuse",
        help="A bundle of the same images and settings but another whitening: "
        "its vectors are re-scaled, no image is encoded again.",
    ),
) -> None:
    """Dense SIFT, RootSIFT, VLAD and PCA-whitening image retrieval index, as a deployable bundle."""
    from mapkit.retrieval.index_vlad import build_vlad_index

    bundle = build_vlad_index(workspace, out, config, progress=sys.stderr.isatty(), reuse=reuse)
    typer.echo((bundle / "metrics.json").read_text(), nl=False)
    typer.echo(f"bundle written to {bundle}")


@index_app.command("structure")
@_writes("workspace")
def index_structure(
    workspace: Path = typer.Argument(..., help="A workspace (its aligned maps are used when `mapkit align` ran)."),
    kind: str = typer.Option("nbld", "--kind", "-k", help="Descriptor: nbld, m2dp, or cnn (with --model)."),
    model: Path | None = typer.Option(
        None, "--model", help="A trained CNN folder (`mapkit train`), for --kind cnn; runs its ONNX export."
    ),
    out: Path | None = typer.Option(
        None,
        "--out",
        "-o",
        help="Bundle folder (default WORKSPACE/indexes/structure-KIND, structure-KIND-lidar with --map-source lidar).",
    ),
    session: list[str] | None = typer.Option(
        None, "--session", "-s", help="Database session; repeat for several (default: all)."
    ),
    config: Path | None = typer.Option(
        None, "--config", "-c", help="YAML overriding `mapkit config defaults structure_index`."
    ),
    map_source: str | None = typer.Option(
        None,
        "--map-source",
        help="Index the semidense maps or the lidar maps (voxel centroids); default: the config's map_source "
        "(semidense).",
    ),
) -> None:
    """Structure index of a workspace's maps (NBLD, M2DP or a trained CNN's patch descriptors) with keypoint-to-frame voting, as a deployable bundle."""  # noqa: E501 (Typer's rich help keeps a docstring's line breaks: one line per help line)
    from mapkit.places.index_structure import build_structure_index

    overrides: dict = {"cnn_model": str(model)} if model is not None else {}
    if map_source is not None:
        overrides["map_source"] = map_source
    bundle = build_structure_index(
        workspace, kind, out, session or None, config, overrides=overrides or None, progress=sys.stderr.isatty()
    )
    typer.echo(f"bundle written to {bundle}")


@eval_app.command("build")
@_writes("workspace")
def eval_build(
    workspace: Path = typer.Argument(..., help="A workspace made by `mapkit build`."),
    truth: Path = typer.Option(
        ...,
        "--truth",
        help="The synthetic town folder the logs came from (all its sessions), or one "
        "session's true trajectory: a TUM file (stamp tx ty tz qx qy qz qw), a KITTI poses file (12 numbers "
        "a line; stamps from times.txt beside it or --truth-times), or a log's pose topic (LOG::/topic).",
    ),
    session: str | None = typer.Option(
        None, "--session", "-s", help="The session a true trajectory belongs to (default: the only one)."
    ),
    truth_topic: str | None = typer.Option(
        None, "--truth-topic", help="The pose topic of a --truth log (default: its only pose topic)."
    ),
    truth_times: Path | None = typer.Option(
        None, "--truth-times", help="Stamps of a KITTI poses file, one time in seconds a line."
    ),
    truth_time_offset: float = typer.Option(
        0.0,
        "--truth-time-offset",
        help="Seconds added to every true stamp (another clock, or times relative to the drive's start).",
    ),
    max_dt: float = typer.Option(
        0.02, "--max-dt", help="Largest stamp difference (s) at which a true pose is paired with an estimated one."
    ),
    align: str = typer.Option(
        "auto",
        "--align",
        help="How a true trajectory's own frame is fitted: se3 (rigid), sim3 (with scale), "
        "none (the truth is in the workspace's ENU frame), auto (sim3 for a camera-only trajectory that GPS did "
        "not scale, else se3).",
    ),
    segment: float = typer.Option(
        100.0, "--segment", help="Length of true path (m) over which the relative error (RPE) is measured."
    ),
) -> None:
    """Trajectory error (and map accuracy against the synthetic town) of a built workspace against ground truth.

    A true trajectory is in a frame of its own: the estimate is aligned to it first (SE(3) or Sim(3), as evo's -a / -as).
    """  # noqa: E501 (Typer's rich help keeps a docstring's line breaks: one line per help line)
    from mapkit.core.workspace import Workspace
    from mapkit.evaluation.evaluate import as_alignment, evaluate_build, format_eval

    r = evaluate_build(
        workspace,
        truth,
        session=session,
        truth_topic=truth_topic,
        truth_times=truth_times,
        time_offset_s=truth_time_offset,
        max_dt_s=max_dt,
        align=as_alignment(align),
        segment_m=segment,
    )
    typer.echo(format_eval(r), nl=False)
    typer.echo(f"written to {Workspace(workspace).eval_build_json} and eval_build.md")


@eval_app.command("align")
@_writes("workspace")
def eval_align(
    workspace: Path = typer.Argument(..., help="A workspace aligned by `mapkit align`."),
    truth: Path = typer.Option(..., "--truth", help="The synthetic town folder the logs came from."),
) -> None:
    """Inter-session misalignment of the same true surface, after GPS alone and after alignment."""
    from mapkit.core.workspace import Workspace
    from mapkit.evaluation.evaluate import evaluate_align, format_align_truth

    typer.echo(format_align_truth(evaluate_align(workspace, truth)))
    typer.echo(f"written to {Workspace(workspace).align_dir / 'eval_align.json'} and eval_align.md")


@eval_app.command("retrieval")
@_writes("workspace")
def eval_retrieval(
    workspace: Path = typer.Argument(..., help="The workspace the bundle was built from."),
    bundle: Path = typer.Argument(..., help="A VLAD bundle (`mapkit index vlad`)."),
    query: list[str] = typer.Option(
        ..., "--query", "-q", help="Query session (not in the bundle); repeat for several."
    ),
    truth: Path | None = typer.Option(
        None, "--truth", help="Synthetic town: true positions and appearance conditions."
    ),
) -> None:
    """Recall@1/5/20 within 25 m per query session and the error of the mean-shift measurement."""
    from mapkit.evaluation.retrieval import evaluate_retrieval, format_retrieval

    typer.echo(format_retrieval(evaluate_retrieval(workspace, bundle, query, truth, progress=sys.stderr.isatty())))
    typer.echo(f"written to {bundle}/eval_retrieval.json, .md and .png")


@eval_app.command("places")
@_writes("workspace")
def eval_places(
    workspace: Path = typer.Argument(..., help="An aligned workspace."),
    pair: list[str] = typer.Option(..., "--pair", "-p", help="DATABASE:QUERY session pair; repeat for several."),
    method: list[str] = typer.Option(
        ["nbld", "m2dp", "vlad"], "--method", "-m", help="nbld, m2dp, cnn (with --cnn-model), vlad; repeat for several."
    ),
    cnn_model: Path | None = typer.Option(
        None, "--cnn-model", help="A trained CNN folder (`mapkit train`) for the cnn method."
    ),
    truth: Path | None = typer.Option(None, "--truth", help="Synthetic town: true positions (else the aligned poses)."),
    vlad_bundle: Path | None = typer.Option(None, "--vlad-bundle", help="VLAD bundle for the image baseline."),
    out: Path | None = typer.Option(
        None, "--out", "-o", help="Output folder (default WORKSPACE/eval/places; eval/places-lidar with lidar)."
    ),
    config: Path | None = typer.Option(None, "--config", "-c", help="YAML overriding `mapkit config defaults places`."),
    map_source: str | None = typer.Option(
        None,
        "--map-source",
        help="The structure methods' maps: semidense or lidar (voxel centroids); default: the config's "
        "structure.map_source (semidense).",
    ),
) -> None:
    """Place recognition precision/recall and AUC per session pair (the semi-dense paper's Table 2)."""
    from mapkit.core.errors import ConfigError
    from mapkit.evaluation.places import evaluate_places, format_places

    pairs: list[tuple[str, str]] = []
    for p in pair:
        if p.count(":") != 1:
            raise ConfigError(f"--pair {p!r}: expected DATABASE:QUERY")
        database, query = p.split(":")
        pairs.append((database, query))
    structure: dict = {}
    if cnn_model is not None:
        structure["cnn_model"] = str(cnn_model)
    if map_source is not None:
        structure["map_source"] = map_source
    overrides = {"structure": structure} if structure else None
    r = evaluate_places(
        workspace, pairs, method, out, truth, vlad_bundle, config, overrides=overrides, progress=sys.stderr.isatty()
    )
    typer.echo(format_places(r))


@eval_app.command("localize")
@_writes("workspace")
def eval_localize(
    workspace: Path = typer.Argument(..., help="A built (and ideally aligned) workspace of a synthetic town."),
    truth: Path = typer.Option(..., "--truth", help="The synthetic town: session roles and true poses."),
    bundle: Path | None = typer.Option(
        None, "--bundle", help="A VLAD bundle; built from the training sessions if omitted."
    ),
    config: Path | None = typer.Option(
        None,
        "--config",
        "-c",
        help="YAML overriding `mapkit config defaults localize` (presets: configs/localize/, installed as "
        "mapkit/configs/localize/).",
    ),
    out: Path | None = typer.Option(None, "--out", "-o", help="Output folder (default WORKSPACE/localize)."),
    cache_dir: Path | None = typer.Option(
        None, "--cache-dir", help="Keep each test session's retrieval hits here; reused while the bundle is the same."
    ),
    refine: str | None = typer.Option(
        None,
        "--refine",
        help="none or 6dof: also register each query against the reference model and score the 6-DoF poses, the "
        "filter and retrieval at (0.25 m, 2 deg), (0.5 m, 5 deg), (5 m, 10 deg) (default: the config's refine, none).",
    ),
    model: Path | None = typer.Option(
        None,
        "--model",
        help="The reference model of --refine 6dof, built from the training sessions only (default: "
        "WORKSPACE/reference_model).",
    ),
) -> None:
    """MCVL's protocol: training sessions build the index, test sessions are localized (Table II, Fig. 5)."""
    from mapkit.core.workspace import Workspace
    from mapkit.evaluation.localization import evaluate_localization, format_localization

    r = evaluate_localization(
        workspace,
        truth,
        bundle,
        config=config,
        overrides=_refine_overrides(refine, model),
        out=out,
        cache_dir=cache_dir,
        progress=sys.stderr.isatty(),
    )
    typer.echo(format_localization(r), nl=False)
    typer.echo(
        f"written to {out or Workspace(workspace).localize_dir}: eval_localize.json, .md and one PNG per sequence"
    )


@eval_app.command("benchmark")
def eval_benchmark(
    benchmark: Path = typer.Argument(..., help="A benchmark folder (`mapkit export benchmark`)."),
    poses: Path = typer.Option(..., "--poses", help="Poses to score: name qw qx qy qz tx ty tz (cam_from_world)."),
) -> None:
    """Share of queries within (0.25 m, 2 deg), (0.5 m, 5 deg), (5 m, 10 deg), per condition and overall."""
    from mapkit.evaluation.benchmark import format_benchmark, score_benchmark

    typer.echo(format_benchmark(score_benchmark(benchmark, poses)), nl=False)
    typer.echo(f"written to {poses.parent}: eval_benchmark.json and eval_benchmark.md")


def configure_logging() -> None:
    """Show mapkit's INFO messages (a stage's progress lines, ``mapkit demo``'s stage lines) as
    plain lines on stderr, as its ``print`` calls did; other libraries' only from WARNING up. The
    handler is not added when the root logger has one already (an embedding application's, pytest's)."""
    logging.basicConfig(level=logging.WARNING, format="%(message)s", stream=sys.stderr)
    logging.getLogger("mapkit").setLevel(logging.INFO)


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``mapkit`` script."""
    configure_logging()
    original = warnings.formatwarning

    def fmt(message, category, filename, lineno, line=None):
        if issubclass(category, InputWarning):
            return f"warning: {message}\n"
        return original(message, category, filename, lineno, line)

    from mapkit.core.writers import lock_wait, set_lock_wait

    warnings.formatwarning = fmt
    wait = lock_wait()  # --wait holds for this command only, not for library calls after it in one process
    try:
        app(args=argv, prog_name="mapkit")
    except SystemExit as exc:  # click's standalone mode ends every run with SystemExit
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    except MapkitError as exc:
        typer.echo(f"error: {exc}", err=True)
        return 2
    finally:
        warnings.formatwarning = original
        set_lock_wait(wait)
    return 0


if __name__ == "__main__":
    sys.exit(main())
