"""An outside localizer on mapkit's benchmark export: COLMAP's own image registrator beside mapkit's 6-DoF localizer.

On a workspace with a VLAD index (the README's main job makes one: `runs/main/workspace`), this builds the
reference model of the training sessions if it is missing (`mapkit model`), exports the benchmark of the query
sessions with the town's truth (`mapkit export benchmark`), registers the queries with mapkit's localizer and
with COLMAP's image registrator (`mapkit localize-benchmark --localizer mapkit|colmap`; mapkit's also without its
guided matching, and COLMAP's with its own acceptance and with mapkit's), scores each with mapkit's
evaluator (`mapkit eval benchmark`) and writes the record that docs/guide/benchmark.md's table is made from:

    python3 bench/outside_localizer.py runs/main/workspace --truth runs/main/town --queries test-clear \\
        --queries test-night --out runs/outside-localizer.json
    python3 docs/figures.py collect outside-localizer runs/outside-localizer.json && python3 docs/figures.py render
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

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


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workspace", type=Path)
    ap.add_argument("--truth", type=Path, required=True, help="the synthetic town the workspace was built from")
    ap.add_argument("--queries", action="append", required=True, help="a query session (repeatable)")
    ap.add_argument("--out", type=Path, required=True, help="the record to write (JSON)")
    args = ap.parse_args(argv)
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
        + " --out FILE",
        "queries": args.queries,
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
    record["same_acceptance"] = same_acceptance.model_dump(
        include={"abs_pose_max_error_px", "abs_pose_min_num_inliers", "abs_pose_min_inlier_ratio"}
    )
    args.out.write_text(json.dumps(record, indent=1) + "\n")
    print(f"record written to {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
