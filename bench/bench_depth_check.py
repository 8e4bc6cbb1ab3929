"""Time of the reference model's depth check against projecting every map point into every image.

On a workspace with a reference model (``mapkit model``; the main job with ``--sixdof`` makes one), per map
source of the model's sessions (semi-dense points, LiDAR voxel centroids):

* mapkit: :func:`mapkit.localization.reference_model.depth_agreement` as the model stage runs it (its
  ``num_threads`` images at a time): the map's points gathered per image from the ground cells its view pyramid
  reaches, moved to the camera by OpenCV in one pass, and only those whose pixel lies next to a keypoint's kept
  for the radius search;
* baseline: the textbook check, one image at a time: every map point moved into every camera in numpy (float64),
  those inside the image projected by the camera model, the radius search over all of them. It gives the same
  figures up to the few observations a float32 rounding of the points moves across a bound: the table shows both
  medians and counts of observations compared.

Run from the repository root::

    python3 bench/bench_depth_check.py runs/main/workspace
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.common import report  # noqa: E402 (after sys.path points at this checkout)

WORKSPACE_NEEDS = "reference_model/sfm/images.bin"  # bench/run_all.py skips a workspace without it


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workspace", type=Path)
    ap.add_argument("--model", type=Path, default=None, help="the model's sfm folder (default WS/reference_model/sfm)")
    args = ap.parse_args(argv)
    import pycolmap

    from mapkit.core.config import load_config
    from mapkit.core.workspace import Workspace
    from mapkit.localization import reference_model as rm

    sfm = args.model or args.workspace / rm.DEFAULT_FOLDER / "sfm"
    if not (sfm / "images.bin").is_file():
        print(f"no reference model at {sfm}: run `mapkit model {args.workspace}` first", file=sys.stderr)
        return 2
    rec = pycolmap.Reconstruction(str(sfm))
    ws = Workspace(args.workspace)
    cfg = load_config(rm.ReferenceModelConfig, sfm.parent / "config.yaml")
    maps = {k: v for k, v in rm.session_maps(ws, cfg.sessions).items() if v is not None}
    every_point, projection = rm._GroundGrid.seen_by, rm._project_into

    def uncull(grid, im, reach):  # every map point, whatever the camera sees
        return grid.points, None

    def textbook(im, X, max_depth=np.inf, origin=None, keypoints=None, radius_px=0.0):  # every pixel in the image
        T = np.asarray(im.cam_from_world().matrix(), np.float64)
        Xc = (np.asarray(X, np.float64) + (0.0 if origin is None else origin)) @ T[:, :3].T + T[:, 3]
        ahead = np.flatnonzero((Xc[:, 2] > 1e-6) & (Xc[:, 2] <= max_depth))
        inside, uv = rm.image_pixels(im.camera, Xc[ahead, 0], Xc[ahead, 1], Xc[ahead, 2])
        return uv, Xc[ahead[inside], 2], ahead[inside]

    rows = []
    for kind, points in maps.items():
        t = time.perf_counter()
        culled = rm.depth_agreement(rec, points, num_threads=cfg.num_threads)
        culled_s = time.perf_counter() - t
        rm._GroundGrid.seen_by = uncull  # type: ignore[method-assign]
        rm._project_into = textbook
        try:
            t = time.perf_counter()
            full = rm.depth_agreement(rec, points)
            full_s = time.perf_counter() - t
        finally:
            rm._GroundGrid.seen_by = every_point  # type: ignore[method-assign]
            rm._project_into = projection
        rows.append(
            {
                "map": kind,
                "map points": len(points),
                "images": rec.num_images(),
                "mapkit s": round(culled_s, 2),
                "every point s": round(full_s, 2),
                "speed-up": round(full_s / culled_s, 2),
                "compared (mapkit / every point)": f"{culled['compared']} / {full['compared']}",
                "median (mapkit / every point)": f"{culled['median_relative_difference']} / "
                f"{full['median_relative_difference']}",
            }
        )
    total_mapkit = sum(r["mapkit s"] for r in rows)
    total_full = sum(r["every point s"] for r in rows)
    report(
        "Reference model depth check: cells in the view, near the keypoints, against every map point",
        rows,
        f"both sources: {total_mapkit:.1f} s against {total_full:.1f} s, {total_full / total_mapkit:.2f}x",
        headline={
            "mapkit": f"{total_mapkit:.1f} s",
            "baseline": f"{total_full:.1f} s (every map point into every image, one image at a time)",
            "ratio": f"{total_full / total_mapkit:.2f}x",
        },
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
