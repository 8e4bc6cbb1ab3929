"""How the 6-DoF localizer's RANSAC threshold and inlier count are chosen: on held-out training drives.

Each training drive of a demo workspace is localized against a reference model of the other training drives,
built on their true poses (`mapkit model --truth`), so that a pose's error is the localizer's alone. The test
drives, on which docs/accuracy.md scores the localizer, are not used. Each query is matched against the model's
images nearest its true camera pose that look its way (the images the filter's prior picks in
`mapkit eval localize --refine 6dof`). For every RANSAC threshold the pose of each query is kept with its inlier
count; for every inlier count a query is then

* right: accepted and within (0.25 m, 2 deg) of its true pose;
* off: accepted and outside (0.25 m, 2 deg);
* not accepted (it keeps the filter's pose).

The choice: the pair with the most right queries among those whose off share is at most ``--max-off`` of the
queries (pooled over the drives), ties to the stricter threshold and the larger inlier count. The record it writes
is where `SixDofConfig`'s defaults and docs/guide/localize.md's table come from:

    python3 bench/sixdof_thresholds.py runs/main/workspace --truth runs/main/town --out runs/sixdof-thresholds.json
    python3 docs/figures.py collect sixdof-thresholds runs/sixdof-thresholds.json && python3 docs/figures.py render

About 5 minutes on the demo town (three models of two drives, four thresholds).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's mapkit, whatever is installed

from mapkit.core.geometry import rotation_angle_rad  # noqa: E402 (after sys.path points at this checkout)
from mapkit.core.workspace import Workspace  # noqa: E402 (after sys.path points at this checkout)
from mapkit.evaluation.truth import town_sessions, truth_camera_poses_at  # noqa: E402 (as above)
from mapkit.localization.reference_model import (  # noqa: E402 (after sys.path points at this checkout)
    build_reference_model,
    workspace_images,
)
from mapkit.localization.sixdof import SixDofConfig, SixDofLocalizer  # noqa: E402 (as above)
from mapkit.retrieval.vlad_bundle import read_session_images  # noqa: E402 (after sys.path points at this checkout)

RANSAC_PX = (2.0, 4.0, 8.0, 12.0)
MIN_INLIERS = (8, 10, 12, 15, 20, 30)
#: the band a right pose lies in: the benchmarks' finest
RIGHT_M, RIGHT_DEG = 0.25, 2.0


def held_out_drive(
    ws: Workspace, truth: Path, query: str, others: list[str], scratch: Path, model_config: Path | None = None
) -> dict:
    """Every image of ``query`` localized against the true-pose model of ``others`` (``model_config``: its settings,
    mapkit's defaults where None), once per RANSAC threshold: per threshold the inlier count, position and rotation
    error of each query's pose (inf without one)."""
    model = build_reference_model(ws, sessions=others, out=scratch / f"model-{query}", config=model_config, truth=truth)
    imgs = read_session_images(ws.root, query)
    gt, ok = truth_camera_poses_at(truth, query, ws.require_frame(), imgs.table["stamp_ns"])
    cams = [im.camera for im, good in zip(workspace_images(ws, [query]), ok, strict=True) if good]
    paths = [p for p, good in zip(imgs.image_paths, ok, strict=True) if good]
    gt = gt[ok]
    out = {"queries": len(paths), "model_points": json.loads((model / "metrics.json").read_text())["points"]}
    for px in RANSAC_PX:
        cfg = SixDofConfig(ransac_max_error_px=px, min_inliers=4)
        rows = []
        with SixDofLocalizer(model, cfg) as loc:
            for path, cam, T in zip(paths, cams, gt, strict=True):
                r = loc.localize(path, cam, loc.candidates_near(T), None, Path(path).name)
                if r.world_from_cam is None:
                    rows.append([r.inliers, np.inf, np.inf])
                    continue
                dR = r.world_from_cam[:3, :3].T @ T[:3, :3]
                rows.append(
                    [
                        r.inliers,
                        float(np.linalg.norm(r.world_from_cam[:3, 3] - T[:3, 3])),
                        float(np.degrees(rotation_angle_rad(dR))),
                    ]
                )
        out[f"{px:g}"] = rows
    return out


def table(drives: dict) -> list[dict]:
    """Per (RANSAC threshold, inlier count): queries, right, off and accepted shares, pooled over the drives."""
    rows = []
    for px in RANSAC_PX:
        a = np.array([r for d in drives.values() for r in d[f"{px:g}"]], np.float64).reshape(-1, 3)
        within = (a[:, 1] <= RIGHT_M) & (a[:, 2] <= RIGHT_DEG)
        for m in MIN_INLIERS:
            acc = a[:, 0] >= m
            rows.append(
                {
                    "ransac_px": px,
                    "min_inliers": m,
                    "queries": len(a),
                    "accepted": round(float(acc.mean()), 4),
                    "right": round(float((acc & within).mean()), 4),
                    "off": round(float((acc & ~within).mean()), 4),
                }
            )
    return rows


def choose(rows: list[dict], max_off: float) -> dict:
    ok = [r for r in rows if r["off"] <= max_off]
    if not ok:
        raise SystemExit(f"error: no setting keeps the off share at most {max_off}")
    return max(ok, key=lambda r: (r["right"], -r["ransac_px"], r["min_inliers"]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workspace", type=Path, help="a demo workspace after align (runs/main/workspace)")
    ap.add_argument("--truth", type=Path, required=True, help="its synthetic town (runs/main/town)")
    ap.add_argument("--out", type=Path, required=True, help="the record (JSON)")
    ap.add_argument("--max-off", type=float, default=0.05, help="largest share of queries accepted off (default 0.05)")
    ap.add_argument(
        "--model-config", type=Path, default=None, help="the reference models' settings (YAML; mapkit's defaults)"
    )
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    ws = Workspace(args.workspace)
    town = town_sessions(args.truth)
    train = [n for n in ws.sessions_with_images() if town.get(n, {}).get("role") == "train"]
    if len(train) < 2:
        raise SystemExit(f"error: {args.workspace}: {len(train)} training drives with images; two or more needed")
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="sixdof-thresholds-") as scratch:
        drives = {
            q: held_out_drive(ws, args.truth, q, [n for n in train if n != q], Path(scratch), args.model_config)
            for q in train
        }
    rows = table(drives)
    best = choose(rows, args.max_off)
    record = {
        "command": "python3 bench/sixdof_thresholds.py runs/main/workspace --truth runs/main/town --out F",
        "seconds": round(time.perf_counter() - t0, 1),
        "max_off": args.max_off,
        "model_config": None if args.model_config is None else args.model_config.read_text(),
        "drives": {q: {"queries": d["queries"], "model_points": d["model_points"]} for q, d in drives.items()},
        "rows": rows,
        "chosen": best,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(record, indent=2) + "\n")
    for r in rows:
        print(" ".join(f"{k}={v}" for k, v in r.items()))
    print(f"chosen: RANSAC {best['ransac_px']:g} px, {best['min_inliers']} inliers ({best})")


if __name__ == "__main__":
    main()
