"""Seconds per query of the reference 6-DoF localizer against VLAD retrieval alone, on the real KITTI clip.

The database is every other frame of ``../shared/data/kitti-odometry-clip`` (2.4 m apart) on its
ground-truth poses; the queries are the frames between (held out of both the VLAD index and the
reference model). Per query, measured in this run:

* VLAD retrieval alone: dense RootSIFT, VLAD, PCA-whitening (:class:`mapkit.retrieval.vlad.VladEncoder`, MCVL's
  settings, vocabulary and PCA learned on the database images), exact inner-product search for the top-k;
  its top-1 database pose is the position estimate retrieval gives;
* the 6-DoF localizer (:class:`mapkit.localization.sixdof.SixDofLocalizer`) on VLAD's top-k: SIFT, matching,
  2D-3D lifting, RANSAC and refinement;
* their ratio, and the position and rotation errors of both against poses.txt (medians), with the share of
  queries the localizer accepted.

Building the reference model and fitting VLAD are timed apart, not per query.

Run from the repository root (about 4 minutes with ``--fast``, which builds the model from full-resolution SIFT;
fitting VLAD on the 26 database images takes most of it)::

    python3 bench/bench_sixdof.py [--top-k 10] [--fast]
"""

from __future__ import annotations

import argparse
import logging
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.common import report  # noqa: E402 (after sys.path points at this checkout)
from mapkit.core.geometry import rotation_angle_rad  # noqa: E402 (after sys.path points at this checkout)
from mapkit.core.types import CameraInfo  # noqa: E402 (after sys.path points at this checkout)
from mapkit.localization.reference_model import (  # noqa: E402 (after sys.path points at this checkout)
    PosedImage,
    ReferenceModelConfig,
    triangulate_reference_model,
)
from mapkit.localization.sixdof import SixDofConfig, SixDofLocalizer  # noqa: E402 (after sys.path points at this checkout)
from mapkit.retrieval.vlad import VladConfig, VladEncoder  # noqa: E402 (after sys.path points at this checkout)

CLIP = ROOT.parent / "shared" / "data" / "kitti-odometry-clip"


def kitti(clip: Path) -> tuple[CameraInfo, np.ndarray]:
    """The left grey camera (calib.txt's first projection) and the clip's world_from_cam poses (N, 4, 4)."""
    P0 = np.loadtxt(clip / "calib.txt")[0].reshape(3, 4)
    rows = np.loadtxt(clip / "poses.txt").reshape(-1, 3, 4)
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3] = rows
    return CameraInfo("cam0", 1226, 370, P0[:, :3].copy()), poses


def errors(world_from_cam: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """(position error m, rotation error deg)."""
    dR = world_from_cam[:3, :3].T @ truth[:3, :3]
    return float(np.linalg.norm(world_from_cam[:3, 3] - truth[:3, 3])), float(np.degrees(rotation_angle_rad(dR)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--top-k", type=int, default=10, help="VLAD candidates per query (SixDofConfig.max_candidates)")
    ap.add_argument("--fast", action="store_true", help="model and queries from full-resolution SIFT (first_octave 0)")
    ap.add_argument("--clip", type=Path, default=CLIP)
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    if not (args.clip / "poses.txt").is_file():
        raise SystemExit(f"error: no KITTI clip at {args.clip} (expected ../shared/data/kitti-odometry-clip)")
    cam, poses = kitti(args.clip)
    frames = sorted(int(p.stem) for p in (args.clip / "image_l").glob("*.png"))
    database = [f for f in frames if f % 2 == 0]
    queries = [f for f in frames if f % 2 == 1]
    paths = {f: args.clip / "image_l" / f"{f:06d}.png" for f in frames}
    db_names = [paths[f].name for f in database]

    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        model_cfg = ReferenceModelConfig(**({"first_octave": 0, "max_features": 4096} if args.fast else {}))
        folder = triangulate_reference_model(
            [PosedImage(paths[f], cam, poses[f]) for f in database], Path(tmp) / "model", model_cfg
        )
        build_s = time.perf_counter() - t0

        t0 = time.perf_counter()
        db_images = [cv2.imread(str(paths[f]), cv2.IMREAD_GRAYSCALE) for f in database]
        encoder = VladEncoder(VladConfig()).fit(db_images)
        db_vectors = np.stack([encoder.encode(im) for im in db_images])
        vlad_fit_s = time.perf_counter() - t0
        print(
            f"{len(database)} database images, {len(queries)} queries; reference model {build_s:.1f} s, "
            f"VLAD fit and database encoding {vlad_fit_s:.1f} s",
            flush=True,
        )

        vlad_s, sixdof_s, vlad_err, sixdof_err, accepted = [], [], [], [], 0
        with SixDofLocalizer(folder, SixDofConfig(max_candidates=args.top_k)) as loc:
            loc.localize(paths[queries[0]], cam, db_names[:1])  # warm-up: first-use costs out of the figures
            for f in queries:
                t0 = time.perf_counter()
                image = cv2.imread(str(paths[f]), cv2.IMREAD_GRAYSCALE)
                score = db_vectors @ encoder.encode(image)
                top = np.argsort(-score, kind="stable")[: args.top_k]
                vlad_s.append(time.perf_counter() - t0)
                retrieved = poses[database[top[0]]]
                vlad_err.append(errors(retrieved, poses[f]))

                r = loc.localize(paths[f], cam, [db_names[i] for i in top], retrieved, name=paths[f].name)
                sixdof_s.append(r.seconds)
                accepted += r.accepted
                assert r.world_from_cam is not None
                sixdof_err.append(errors(r.world_from_cam, poses[f]))

    v_ms, s_ms = 1e3 * np.median(vlad_s), 1e3 * np.median(sixdof_s)
    ve, se = np.median(np.array(vlad_err), axis=0), np.median(np.array(sixdof_err), axis=0)
    rows = [
        {
            "method": "VLAD retrieval alone (top-1 pose)",
            "ms_per_query_median": round(v_ms, 1),
            "position_error_m_median": round(float(ve[0]), 3),
            "rotation_error_deg_median": round(float(ve[1]), 2),
            "accepted": "-",
        },
        {
            "method": f"6-DoF on VLAD top-{args.top_k}",
            "ms_per_query_median": round(s_ms, 1),
            "position_error_m_median": round(float(se[0]), 3),
            "rotation_error_deg_median": round(float(se[1]), 2),
            "accepted": f"{accepted}/{len(queries)}",
        },
    ]
    report(
        "6-DoF localizer against VLAD retrieval, per query (KITTI clip, held-out odd frames)",
        rows,
        f"6-DoF / VLAD time: {s_ms / v_ms:.2f}x; retrieval plus 6-DoF: {(v_ms + s_ms) / v_ms:.2f}x of retrieval alone",
        headline={
            "mapkit": f"{s_ms:.0f} ms/query, {se[0]:.3f} m",
            "baseline": f"VLAD {v_ms:.0f} ms/query, {ve[0]:.2f} m",
            "ratio": f"{s_ms / v_ms:.2f}x",
        },
    )


if __name__ == "__main__":
    main()
