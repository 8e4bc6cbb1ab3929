"""Outside localizers on mapkit's benchmark export: COLMAP's image registrator and hloc beside mapkit's localizer.

On a workspace with a VLAD index (the README's main job makes one: `runs/main/workspace`), this builds the
reference model of the training sessions if it is missing (`mapkit model`), exports the benchmark of the query
sessions with the town's truth (`mapkit export benchmark`), registers the queries with mapkit's localizer and
with COLMAP's image registrator (`mapkit localize-benchmark --localizer mapkit|colmap`; mapkit's also without its
guided matching, and COLMAP's with its own acceptance and with mapkit's), scores each with mapkit's
evaluator (`mapkit eval benchmark`) and writes the record that docs/guide/benchmark.md's table is made from:

    python3 bench/outside_localizer.py runs/main/workspace --truth runs/main/town --queries test-clear \\
        --queries test-night --out runs/outside-localizer.json [--hloc SRC --hloc-python PY]
    python3 docs/figures.py collect outside-localizer runs/outside-localizer.json && python3 docs/figures.py render

With `--hloc SRC` (a checkout of https://github.com/cvg/Hierarchical-Localization: the folder that holds the
`hloc` package) it also runs hloc's pipeline on the export, as its `pipelines/` and docs/guide/benchmark.md do,
with the interpreter `--hloc-python` (one with hloc's requirements: torch, kornia, h5py, pycolmap): SIFT with the
model's settings (reference_model.yaml) for every image, the model re-triangulated with them (10 pairs per
database image by pose, nearest-neighbour ratio matching), the retrieval pairs matched the same way, and
`localize_sfm` with hloc's RANSAC threshold and with mapkit's. Its poses are scored as the others' ("hloc",
"hloc-4px"); its working files are in the run folder's `hloc/`.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's mapkit, whatever is installed

from mapkit.core.workspace import Workspace  # noqa: E402 (after sys.path points at this checkout)
from mapkit.deploy.benchmark import export_benchmark  # noqa: E402 (after sys.path points at this checkout)
from mapkit.evaluation.benchmark import score_benchmark  # noqa: E402 (after sys.path points at this checkout)
from mapkit.localization.colmap_registrator import (  # noqa: E402 (after sys.path points at this checkout)
    ColmapRegistratorConfig,
    register_benchmark,
)
from mapkit.localization.reference_model import build_reference_model  # noqa: E402 (after sys.path points at this checkout)
from mapkit.localization.sixdof import (  # noqa: E402 (after sys.path points at this checkout)
    SixDofConfig,
    localize_benchmark,
)


def _scores(ev) -> dict:
    def one(s) -> dict:
        return {
            "queries": s.queries,
            "missing": s.missing,
            "recall": s.recall,
            "median_translation_m": s.median_translation_m,
            "median_rotation_deg": s.median_rotation_deg,
        }

    return {"overall": one(ev.overall), "conditions": {c: one(s) for c, s in ev.conditions.items()}}


#: hloc's pipeline, run by the interpreter that has hloc's requirements (mapkit's need not); its one argument is a
#: JSON object of paths and settings, and it writes ``hloc.json`` (seconds per stage, points, PnP failures) in
#: the working folder
HLOC_RUNNER = """\
import inspect
import json
import pickle
import sys
import time
from pathlib import Path

import pycolmap
import torch

args = json.loads(sys.argv[1])
torch.set_num_threads(args["threads"])
# pycolmap 4.2 leaves out of the triangulation the two-view geometries whose configuration is UNDEFINED, as
# hloc's triangulation writes them (pycolmap.TwoViewGeometry(inlier_matches=...)): such a model has no points.
# The pairs' geometry is that of the model's calibrated cameras, so a geometry made without a configuration is
# given CALIBRATED; a call that passes one, as a fixed hloc would, keeps it.
if hasattr(pycolmap, "TwoViewGeometryConfiguration"):

    class CalibratedTwoViewGeometry(pycolmap.TwoViewGeometry):
        def __init__(self, *a, **kw):
            if not a:
                kw.setdefault("config", pycolmap.TwoViewGeometryConfiguration.CALIBRATED)
            super().__init__(*a, **kw)

    pycolmap.TwoViewGeometry = CalibratedTwoViewGeometry

import hloc  # noqa: E402 (after the wrap above)
from hloc import (  # noqa: E402 (after the wrap above)
    extract_features,
    localize_sfm,
    match_features,
    pairs_from_poses,
    triangulation,
)

bench, work = Path(args["benchmark"]), Path(args["work"])
seconds = {}


def timed(stage, fn, *a, **kw):
    t = time.perf_counter()
    out = fn(*a, **kw)
    seconds[stage] = round(time.perf_counter() - t, 3)
    return out


sift = {**extract_features.confs["sift"], "output": "feats-sift-model"}
sift["model"] = {**sift["model"], "options": args["sift_options"]}
matcher = match_features.confs["NN-ratio"]
queries = [line.split()[0] for line in (bench / "queries_with_intrinsics.txt").read_text().splitlines() if line.strip()]
database = sorted(image.name for image in pycolmap.Reconstruction(bench / "sfm").images.values())
# queries and database images in two calls into one file, so that the queries' share is timed on its own
feats = timed("extract_database", extract_features.main, sift, bench / "images", work, image_list=database,
              overwrite=True)
timed("extract_queries", extract_features.main, sift, bench / "images", work, image_list=queries, overwrite=True)
timed("pairs_from_poses", pairs_from_poses.main, bench / "sfm", work / "pairs-db.txt", args["pairs_per_image"])
db_matches = timed("match_database", match_features.main, matcher, work / "pairs-db.txt", feats.stem, work,
                   overwrite=True)
model = timed("triangulation", triangulation.main, work / "sfm", bench / "sfm", bench / "images",
              work / "pairs-db.txt", feats, db_matches)
if model.num_points3D() == 0:
    sys.exit("hloc's triangulation gave a model with no points: its two-view geometries were not used")
retrieval = bench / "pairs-query-retrieval.txt"
q_matches = timed("match_queries", match_features.main, matcher, retrieval, feats.stem, work, overwrite=True)
default_px = inspect.signature(localize_sfm.main).parameters["ransac_thresh"].default
localized = {}
for key, px in args["ransac_px"].items():
    px = default_px if px is None else px
    poses = work / f"poses-{px:g}px.txt"
    timed(f"localize_{key}", localize_sfm.main, work / "sfm", bench / "queries_with_intrinsics.txt", retrieval,
          feats, q_matches, poses, ransac_thresh=px)
    # where PnP fails, localize_sfm writes the pose of the top retrieved image; its log tells which
    with open(f"{poses}_logs.pkl", "rb") as f:
        loc = pickle.load(f)["loc"]
    failed = sorted(q for q, log in loc.items() if log["PnP_ret"] is None)
    localized[key] = {"poses": str(poses), "ransac_px": px, "pnp_failed": failed}
summary = {
    "hloc": hloc.__version__,
    "pycolmap": pycolmap.__version__,
    "sift_options": sift["model"]["options"],
    "matcher": matcher["model"],
    "points3D": model.num_points3D(),
    "seconds": seconds,
    "localized": localized,
}
(work / "hloc.json").write_text(json.dumps(summary, indent=1) + "\\n")
"""


#: what the runner imports, the extractor and matcher it loads by name included: an interpreter that lacks one fails
#: at once, not after the other localizers' runs
HLOC_MODULES = (
    "hloc.extract_features",
    "hloc.localize_sfm",
    "hloc.match_features",
    "hloc.pairs_from_poses",
    "hloc.triangulation",
    "hloc.extractors.dog",
    "hloc.matchers.nearest_neighbor",
)


def _hloc_env(src: Path) -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(src.resolve()), env.get("PYTHONPATH")) if p)
    return env


def run_hloc(bench: Path, work: Path, src: Path, python: str, ransac_px: dict[str, float | None]) -> dict:
    """hloc's pipeline on the benchmark export ``bench`` in ``work`` (features, matches, its re-triangulated model
    ``sfm/`` and ``poses-*px.txt``), by ``python`` with the checkout ``src`` on its path; ``ransac_px``: record key ->
    localize_sfm's RANSAC threshold (None: hloc's default). Returns what the runner wrote (``hloc.json``)."""
    model = yaml.safe_load((bench / "reference_model.yaml").read_text())
    args = {
        "benchmark": str(bench.resolve()),
        "work": str(work.resolve()),
        # hloc's own sift configuration starts at the image's scale with a higher peak threshold: the model's
        # settings instead, so that hloc's features are the model's
        "sift_options": {
            "first_octave": model["first_octave"],
            "peak_threshold": model["peak_threshold"],
            "max_num_features": model["max_features"],
        },
        "pairs_per_image": model["pair_neighbours"],
        "ransac_px": ransac_px,
        "threads": 2,  # torch's, as on the 2-core machines the record is measured on
    }
    work.mkdir(parents=True, exist_ok=True)
    runner = work / "run_hloc.py"
    runner.write_text(HLOC_RUNNER)
    # the runner works in ``work``: paths relative to here would not resolve there
    python = os.path.abspath(python) if os.sep in python else python  # not resolve(): a venv's python is a link
    subprocess.run([python, str(runner.resolve()), json.dumps(args)], env=_hloc_env(src), cwd=work, check=True)
    return json.loads((work / "hloc.json").read_text())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workspace", type=Path)
    ap.add_argument("--truth", type=Path, required=True, help="the synthetic town the workspace was built from")
    ap.add_argument("--queries", action="append", required=True, help="a query session (repeatable)")
    ap.add_argument("--out", type=Path, required=True, help="the record to write (JSON)")
    ap.add_argument("--hloc", type=Path, metavar="SRC", help="also run hloc: a checkout (the folder of `hloc/`)")
    ap.add_argument(
        "--hloc-python", default=sys.executable, metavar="PY", help="an interpreter with hloc's requirements"
    )
    args = ap.parse_args(argv)
    if args.hloc is not None:  # before the long runs: this interpreter must import that hloc
        if not (args.hloc / "hloc" / "__init__.py").is_file():
            ap.error(f"--hloc {args.hloc}: no hloc package in it")
        probe = [args.hloc_python, "-c", f"import {', '.join(HLOC_MODULES)}"]
        found = subprocess.run(probe, env=_hloc_env(args.hloc), capture_output=True, text=True)
        if found.returncode != 0:
            why = (found.stderr.strip().splitlines() or ["?"])[-1]
            ap.error(f"{args.hloc_python} cannot run hloc from {args.hloc}: {why}")
    ws = Workspace(args.workspace)
    if not (ws.root / "reference_model" / "sfm").is_dir():
        train = [s for s in ws.sessions_with_images() if s not in args.queries]
        build_reference_model(ws, train)
    run = args.out.with_suffix("")
    bench = export_benchmark(ws, run / "benchmark", args.queries, truth=args.truth)
    model = json.loads((bench / "metrics.json").read_text())
    record: dict = {
        "command": "python3 bench/outside_localizer.py WS --truth TOWN "
        + " ".join(f"--queries {q}" for q in args.queries)
        + " --out FILE"
        + (" --hloc SRC --hloc-python PY" if args.hloc is not None else ""),
        "queries": args.queries,
        "town_seed": json.loads((args.truth / "world" / "manifest.json").read_text()).get("seed"),
        "database_images": model["database_images"],
        "points3D": model["points3D"],
        "localizers": {},
    }
    # COLMAP's registrator twice: with COLMAP's defaults, and with the acceptance mapkit's localizer uses (its RANSAC
    # threshold and inlier count, and no floor on the inliers' share, which mapkit's localizer does not have), so
    # that what differs is the pipeline, not where a pose is accepted
    six = SixDofConfig()
    same_acceptance = ColmapRegistratorConfig(
        abs_pose_max_error_px=six.ransac_max_error_px,
        abs_pose_min_num_inliers=six.min_inliers,
        abs_pose_min_inlier_ratio=0.0,
    )
    # and mapkit's localizer without its guided matching: what its second pass adds to matching the pairs whole
    unguided = SixDofConfig(guided_radii_px=[])
    runs = (
        ("mapkit", localize_benchmark),
        ("mapkit-unguided", lambda folder, out: localize_benchmark(folder, out, config=unguided)),
        ("colmap", register_benchmark),
        ("colmap-same-acceptance", lambda folder, out: register_benchmark(folder, out, config=same_acceptance)),
    )
    for name, localize in runs:
        t = time.perf_counter()
        poses = localize(bench, run / name / "poses.txt")
        seconds = time.perf_counter() - t
        ev = score_benchmark(bench, poses)
        record["localizers"][name] = {"seconds_per_query": round(seconds / max(ev.overall.queries, 1), 3)}
        record["localizers"][name].update(_scores(ev))
        print(f"{name}: {ev.overall.recall} median {ev.overall.median_translation_m} m", file=sys.stderr)
    if args.hloc is not None:
        # hloc's RANSAC threshold (localize_sfm's default, 12 px) and mapkit's localizer's
        ransac_px = {"hloc": None, "hloc-4px": six.ransac_max_error_px}
        t = time.perf_counter()
        out = run_hloc(bench, run / "hloc", args.hloc, args.hloc_python, ransac_px)
        wall = time.perf_counter() - t
        conditions = json.loads((bench / "conditions.json").read_text())
        for name, loc in out["localized"].items():
            ev = score_benchmark(bench, Path(loc["poses"]))
            tag = Path(loc["poses"]).stem.removeprefix("poses-")
            for ext in ("json", "md"):  # both poses files are in one folder: each its own evaluation
                (run / "hloc" / f"eval_benchmark.{ext}").replace(run / "hloc" / f"eval_benchmark-{tag}.{ext}")
            # the query side as mapkit's and COLMAP's are timed: the queries' features, the matching of their
            # retrieval pairs and localize_sfm (not the database's features nor the re-triangulation)
            stage_s = out["seconds"]
            query_s = stage_s["extract_queries"] + stage_s["match_queries"] + stage_s[f"localize_{name}"]
            record["localizers"][name] = {"seconds_per_query": round(query_s / max(ev.overall.queries, 1), 3)}
            record["localizers"][name].update(_scores(ev))
            # a query whose PnP failed has the top retrieved image's pose, scored as its estimate
            failed = Counter(
                c.get("condition") if isinstance(c := conditions.get(q), dict) else c for q in loc["pnp_failed"]
            )
            record["localizers"][name]["pnp_failed"] = {
                "overall": len(loc["pnp_failed"]),
                "conditions": {c: failed[c] for c in ev.conditions},
            }
            record["localizers"][name]["ransac_px"] = loc["ransac_px"]
            print(f"{name}: {ev.overall.recall} median {ev.overall.median_translation_m} m", file=sys.stderr)
        record["hloc"] = {k: out[k] for k in ("hloc", "pycolmap", "sift_options", "matcher", "points3D", "seconds")}
        record["hloc"]["wall_seconds"] = round(wall, 1)
    record["same_acceptance"] = same_acceptance.model_dump(
        include={"abs_pose_max_error_px", "abs_pose_min_num_inliers", "abs_pose_min_inlier_ratio"}
    )
    args.out.write_text(json.dumps(record, indent=1) + "\n")
    print(f"record written to {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
