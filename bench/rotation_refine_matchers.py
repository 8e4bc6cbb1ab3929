"""How the rotation refinement matches frames: SIFT against tracked corners, on the real KITTI clip.

``mapkit.mapping.pose_refine.RotationRefiner`` needs correspondences between each frame and the next few. It
can match 3,000 SIFT features per frame by Lowe's ratio test (``matcher: sift``), or, by default, track corners from
frame to frame (Shi-Tomasi, pyramidal Lucas-Kanade, forward-backward check). This bench runs the streaming
refiner alone over ``--frames`` frames of the clip at 640x480 with its given poses, once per matcher setting, and
prints for each:

- the refiner's best wall and CPU time of ``--repeat`` runs, and its ratio to SIFT's (the baseline, same run);
- the rotations' quality as something the refiner did not use: SIFT matches between frames 1 to 3 apart (ratio
  test 0.7, all pairs of the range), their median distance to the epipolar lines of the refined poses (median over
  the pairs, matches within 10 px), beside the given poses' figure;
- the largest difference of the refined rotations from SIFT's (deg).

Frames 0-23 (the default) are where the tracker's settings were chosen; ``--first-frame 25`` scores them on the
clip's other half. Run from the repository root::

    python3 bench/rotation_refine_matchers.py [--first-frame 25]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.bench_semidense import load_frames  # noqa: E402 (after sys.path points at this checkout)
from bench.common import best_wall_and_cpu, report  # noqa: E402 (after sys.path points at this checkout)
from bench.semidense_kitti_clip import DEFAULT_CLIP, feature_matches  # noqa: E402 (after sys.path points at this checkout)
from mapkit.core.geometry import rotation_angle_rad  # noqa: E402 (after sys.path points at this checkout)
from mapkit.mapping.pose_refine import RotationRefiner, epipolar_distances_px  # noqa: E402 (after sys.path points at this checkout)

#: (label, RotationRefiner keywords); the first is the baseline of the ratios
SETTINGS = [
    ("SIFT, 3,000 features", {"matcher": "sift", "features": 3000}),
    ("tracks, 600 corners, 11 px window (default)", {}),
    ("tracks, 600 corners, 15 px window", {"track_window_px": 15}),
    ("tracks, 1,000 corners", {"features": 1000}),
    ("tracks, 400 corners, 15 px apart", {"features": 400, "track_min_distance_px": 15}),
]


def check_px(K: np.ndarray, poses: np.ndarray, matches) -> float:
    """Median over the pairs of the median distance (px) of their matches (within 10 px) to the epipolar lines of
    ``poses``."""
    per_pair = []
    for i, j, a, b in matches:
        d = epipolar_distances_px(K, poses, i, j, a, b)
        if np.any(d < 10):
            per_pair.append(np.median(d[d < 10]))
    return float(np.median(per_pair))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--clip", type=Path, default=DEFAULT_CLIP)
    ap.add_argument("--first-frame", type=int, default=0)
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--repeat", type=int, default=2)
    args = ap.parse_args()
    if not args.clip.exists():
        raise SystemExit(f"{args.clip}: the KITTI clip is not there (../shared/data, see its README)")

    K, poses, images = load_frames(args.clip, args.first_frame + args.frames)
    poses, images = poses[args.first_frame :], images[args.first_frame :]
    matches = feature_matches(
        images, range(len(images)), 3
    )  # the independent check: SIFT, ratio test, 1-3 frames apart
    given_px = check_px(K, poses, matches)

    refined, rows = {}, []
    for label, kw in SETTINGS:

        def run(kw=kw, label=label):
            r = RotationRefiner(K, **kw)
            refined[label] = np.array(
                [
                    T
                    for _, _, _, T in r.stream(
                        (i, i, im, T) for i, (im, T) in enumerate(zip(images, poses, strict=True))
                    )
                ]
            )

        wall, cpu = best_wall_and_cpu(run, repeat=args.repeat)
        rows.append({"matcher": label, "wall_s": wall, "cpu_s": cpu, "check_px": check_px(K, refined[label], matches)})
    base = rows[0]
    R0 = refined[base["matcher"]][:, :3, :3]
    for row in rows:
        row["cpu_vs_sift"] = row["cpu_s"] / base["cpu_s"]
        R = refined[row["matcher"]][:, :3, :3]
        row["max_deg_from_sift"] = max(
            float(np.degrees(rotation_angle_rad(a.T @ b))) for a, b in zip(R, R0, strict=True)
        )
    report(
        "rotation refinement matchers, "
        f"KITTI frames {args.first_frame}-{args.first_frame + len(images) - 1} at 640x480",
        rows,
        ratio_note=(
            f"check: median distance (px) of independent SIFT matches (1-3 frames apart) to the epipolar lines; "
            f"given poses {given_px:.4f} px. cpu_vs_sift: the refiner's CPU time over SIFT's, same run."
        ),
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
