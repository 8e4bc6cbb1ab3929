"""Speed of semi-dense mapping at 640x480 against two baselines measured in the same run.

Also the cost of the outlier filters: the end-to-end run is timed with every filter off
(``FILTERS_OFF``), with the recommended ones on (``FILTERS_ON``) and with every fusion filter on
(multi-view, photometric, free space: ``FILTERS_FUSION_ALL``), and with the recommended ones and the
camera-rotation refinement (``refine_rotations``; with its default tracked corners, and with SIFT
matching: 3,000 features, Lowe's ratio test), in turn, best of ``--repeat`` each in wall and CPU
time; goal: ``FILTERS_ON``, and ``FILTERS_ON`` with the refinement, within 1.3x of off.

Goal: at least 2 keyframes per second at 640x480 on the 2-core machine. The frames are
real: the KITTI clip beside the project, resized to 640x480 (the camera matrix is scaled with
them, fx != fy, which is still an exact pinhole camera), with its given poses. Three figures:

1. ``mapkit``: ``build_semidense_map`` end to end over ``--frames`` frames (pyramids, candidates,
   epipolar searches over 6 neighbours, fusion), in keyframes per second; and ``map_keyframe``
   alone on one keyframe (best of ``--repeat``).
2. ``naive loop``: the same full-range epipolar search (32 samples, 8-pixel pattern, ZNCC,
   bilinear sampling) written as per-pixel Python loops, timed on ``--naive`` candidates and
   scaled by the number of samples that ``map_keyframe`` searched on that keyframe. It
   does not refine or use a pyramid, so it does less work than mapkit per search: the ratio is
   a lower bound of the speed-up from vectorising.
3. ``StereoSGBM``: OpenCV's semi-global matcher on one 640x480 pair (128 disparities, 5x5
   blocks, the usual dense-stereo reference). The clip has no right images and forward motion
   cannot be rectified, so it runs on two consecutive frames: its time hardly depends on the
   content, and it answers "what does a dense matcher cost per frame on this machine".

Run from the repository root (keep other load low; the machine has 2 cores)::

    python bench/bench_semidense.py
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.common import best_of, report  # noqa: E402 (after sys.path points at this checkout)
from bench.semidense_kitti_clip import DEFAULT_CLIP, FILTERS_ALONE, FILTERS_OFF, FILTERS_ON, read_clip_geometry  # noqa: E402 (after sys.path points at this checkout)
from mapkit.core.geometry import invert_pose  # noqa: E402 (after sys.path points at this checkout)
from mapkit.mapping.semidense import PATTERN_DSO8, SemiDenseConfig, build_semidense_map, map_keyframe, select_candidates  # noqa: E402 (after sys.path points at this checkout)

GOAL_KEYFRAMES_PER_S = 2.0
GOAL_FILTER_SLOWDOWN = 1.3  # mapkit goal: mapping with the outlier filters within 1.3x of the time without
SIZE_WH = (640, 480)
#: every test at fusion: multi-view, photometric, free space
FILTERS_FUSION_ALL = {**FILTERS_ALONE["multi-view"], **FILTERS_ALONE["photometric"], **FILTERS_ALONE["free space"]}


def load_frames(clip: Path, n: int) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    K, poses, paths = read_clip_geometry(clip)
    h0, w0 = cv2.imread(str(paths[0]), cv2.IMREAD_GRAYSCALE).shape
    sx, sy = SIZE_WH[0] / w0, SIZE_WH[1] / h0
    # pixel centres map as x' + 0.5 = s (x + 0.5) under cv2.resize
    S = np.array([[sx, 0, 0.5 * sx - 0.5], [0, sy, 0.5 * sy - 0.5], [0, 0, 1]])
    images = [
        cv2.resize(cv2.imread(str(p), cv2.IMREAD_GRAYSCALE), SIZE_WH, interpolation=cv2.INTER_AREA) for p in paths[:n]
    ]
    return S @ K, poses[:n], images


def naive_full_search(
    ref: np.ndarray,
    tgt: np.ndarray,
    K: np.ndarray,
    ref_world_from_cam: np.ndarray,
    world_from_cam: np.ndarray,
    us: np.ndarray,
    vs: np.ndarray,
    cfg: SemiDenseConfig,
) -> list[float]:
    """Per-pixel loops: for each candidate, 32 inverse depths on the full range, ZNCC of the pattern."""
    cam_from_ref = invert_pose(world_from_cam) @ ref_world_from_cam
    KRKi = K @ cam_from_ref[:3, :3] @ np.linalg.inv(K)
    Kt = K @ cam_from_ref[:3, 3]
    h, w = tgt.shape
    ref_f = ref.astype(np.float64)
    tgt_f = tgt.astype(np.float64)

    def bilinear(img, x, y):
        if not (0 <= x < w - 1 and 0 <= y < h - 1):
            return None
        x0, y0 = int(x), int(y)
        ax, ay = x - x0, y - y0
        return (
            (1 - ax) * (1 - ay) * img[y0, x0]
            + ax * (1 - ay) * img[y0, x0 + 1]
            + (1 - ax) * ay * img[y0 + 1, x0]
            + ax * ay * img[y0 + 1, x0 + 1]
        )

    def zncc(a, b):
        ma, mb = sum(a) / len(a), sum(b) / len(b)
        num = sum((x - ma) * (y - mb) for x, y in zip(a, b, strict=True))
        da = sum((x - ma) ** 2 for x in a) ** 0.5
        db = sum((y - mb) ** 2 for y in b) ** 0.5
        return num / (da * db) if da > 0 and db > 0 else 0.0

    rho_min, rho_max = 1.0 / cfg.max_depth_m, 1.0 / cfg.min_depth_m
    best = []
    for u, v in zip(us.tolist(), vs.tolist(), strict=True):
        ref_vals = [ref_f[int(v + dv), int(u + du)] for du, dv in PATTERN_DSO8]
        best_cost, best_rho = 9.0, float("nan")
        for k in range(cfg.search_samples):
            rho = rho_min + (rho_max - rho_min) * k / (cfg.search_samples - 1)
            vals = []
            for du, dv in PATTERN_DSO8:
                x, y, z = KRKi @ np.array([u + du, v + dv, 1.0]) + rho * Kt
                val = bilinear(tgt_f, x / z, y / z) if z > 0 else None
                if val is None:
                    break
                vals.append(val)
            if len(vals) == len(PATTERN_DSO8):
                cost = 1.0 - zncc(ref_vals, vals)
                if cost < best_cost:
                    best_cost, best_rho = cost, rho
        best.append(best_rho)
    return best


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clip", type=Path, default=DEFAULT_CLIP)
    ap.add_argument("--frames", type=int, default=24, help="frames for the end-to-end run")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--naive", type=int, default=150, help="candidates for the naive loop")
    args = ap.parse_args(argv)
    if not (args.clip / "poses.txt").is_file():
        print(f"error: the benchmark runs on the real KITTI clip, not found at {args.clip}", file=sys.stderr)
        return 2
    cfg = SemiDenseConfig()
    K, poses, images = load_frames(args.clip, args.frames)
    print(f"{len(images)} KITTI frames resized to {SIZE_WH[0]}x{SIZE_WH[1]}; cv2 threads: {cv2.getNumThreads()}")

    # 1. end to end, and one keyframe alone
    def end_to_end():
        return build_semidense_map(
            ((i, i, img, T) for i, (img, T) in enumerate(zip(images, poses, strict=True))), K, cfg, progress=False
        )

    t_e2e = best_of(end_to_end, repeat=max(1, args.repeat - 1))
    sd = end_to_end()
    kfs_e2e = len(sd.keyframe_ids) / t_e2e

    # 1b. the outlier filters: all off, the recommended ones, all at fusion; in turn, wall and CPU
    filter_cfgs = {
        "off": cfg.model_copy(update=FILTERS_OFF),
        "on": cfg.model_copy(update={**FILTERS_OFF, **FILTERS_ON}),
        "all fusion tests": cfg.model_copy(update={**FILTERS_OFF, **FILTERS_FUSION_ALL}),
        "on + rotation refinement": cfg.model_copy(update={**FILTERS_OFF, **FILTERS_ON, "refine_rotations": True}),
        # the refinement with SIFT matching (3,000 features, Lowe's ratio test): the tracked corners' baseline
        "on + rotation refinement, SIFT": cfg.model_copy(
            update={
                **FILTERS_OFF,
                **FILTERS_ON,
                "refine_rotations": True,
                "refine_matcher": "sift",
                "refine_features": 3000,
            }
        ),
    }
    filter_t = {k: [float("inf"), float("inf")] for k in filter_cfgs}
    filter_pts = {}
    for _ in range(args.repeat):
        for k, c in filter_cfgs.items():
            t0, c0 = time.perf_counter(), time.process_time()
            frames = ((i, i, img, T) for i, (img, T) in enumerate(zip(images, poses, strict=True)))
            filter_pts[k] = len(build_semidense_map(frames, K, c, progress=False))
            filter_t[k] = [min(filter_t[k][0], time.perf_counter() - t0), min(filter_t[k][1], time.process_time() - c0)]
    slow_wall, slow_cpu = filter_t["on"][0] / filter_t["off"][0], filter_t["on"][1] / filter_t["off"][1]
    refine_wall, refine_cpu = (filter_t["on + rotation refinement"][k] / filter_t["off"][k] for k in (0, 1))
    c = len(images) // 2
    nb = [
        i
        for i in range(c - cfg.neighbour_window_frames, c + cfg.neighbour_window_frames + 1)
        if i != c and 0 <= i < len(images)
    ]

    def one():
        return map_keyframe(images[c], poses[c], [(images[i], poses[i]) for i in nb], K, cfg)

    cpu0 = time.process_time()
    t_kf = best_of(one, repeat=args.repeat)
    cpu_kf = (time.process_time() - cpu0) / args.repeat
    pts = one()
    n_full, n_prior = pts.stats["full_range_searches"], pts.stats["prior_searches"]

    # 2. naive loop on a subset, scaled by the number of searches
    u, v = select_candidates(images[c], cfg)
    sub = np.random.default_rng(0).choice(len(u), size=min(args.naive, len(u)), replace=False)
    t0 = time.perf_counter()
    naive_full_search(images[c], images[nb[len(nb) // 2]], K, poses[c], poses[nb[len(nb) // 2]], u[sub], v[sub], cfg)
    t_naive_each = (time.perf_counter() - t0) / len(sub)
    # a prior search samples prior_search_samples instead of search_samples positions
    t_naive_kf = t_naive_each * (n_full + n_prior * cfg.prior_search_samples / cfg.search_samples)

    # 3. StereoSGBM on one 640x480 pair
    sgbm = cv2.StereoSGBM_create(
        minDisparity=0, numDisparities=128, blockSize=5, P1=8 * 25, P2=32 * 25, mode=cv2.STEREO_SGBM_MODE_SGBM
    )
    t_sgbm = best_of(lambda: sgbm.compute(images[c], images[c + 1]), repeat=args.repeat)

    t_e2e_kf = t_e2e / len(sd.keyframe_ids)
    rows = [
        {
            "method": "mapkit build_semidense_map (end to end, per keyframe)",
            "s_per_keyframe": t_e2e_kf,
            "keyframes_per_s": kfs_e2e,
            "time_vs_map_keyframe": t_e2e_kf / t_kf,
        },
        *(
            {
                "method": f"  end to end, outlier filters {k} ({filter_pts[k]} points)",
                "s_per_keyframe": filter_t[k][0] / len(sd.keyframe_ids),
                "keyframes_per_s": len(sd.keyframe_ids) / filter_t[k][0],
                "time_vs_map_keyframe": filter_t[k][0] / len(sd.keyframe_ids) / t_kf,
            }
            for k in filter_cfgs
        ),
        {
            "method": "mapkit map_keyframe (one keyframe, 6 neighbours)",
            "s_per_keyframe": t_kf,
            "keyframes_per_s": 1.0 / t_kf,
            "time_vs_map_keyframe": 1.0,
        },
        {
            "method": (
                f"naive per-pixel loop ({len(sub)} candidates, scaled to {n_full} full + {n_prior} prior searches)"
            ),
            "s_per_keyframe": t_naive_kf,
            "keyframes_per_s": 1.0 / t_naive_kf,
            "time_vs_map_keyframe": t_naive_kf / t_kf,
        },
        {
            "method": "OpenCV StereoSGBM, one 640x480 pair, 128 disparities",
            "s_per_keyframe": t_sgbm,
            "keyframes_per_s": 1.0 / t_sgbm,
            "time_vs_map_keyframe": t_sgbm / t_kf,
        },
    ]
    report(
        "semi-dense mapping at 640x480",
        rows,
        ratio_note=(
            f"keyframe {c}: {pts.stats['candidates']} candidates, {n_full} full-range and {n_prior} prior epipolar "
            f"searches, {len(pts)} accepted depths; "
            f"map_keyframe CPU time {cpu_kf:.3f} s (both cores) per {t_kf:.3f} s wall.\n"
            f"end to end: {len(sd.keyframe_ids)} keyframes, {len(sd)} fused points in {t_e2e:.2f} s.\n"
            f"speed-up over the naive loop: {t_naive_kf / t_kf:.0f}x; mapkit keyframe vs one SGBM pair: "
            f"{t_kf / t_sgbm:.2f}x the time.\n"
            f"goal >= {GOAL_KEYFRAMES_PER_S} keyframes/s end to end: "
            f"{'met' if kfs_e2e >= GOAL_KEYFRAMES_PER_S else 'NOT met'} ({kfs_e2e:.2f})\n"
            f"outlier filters on ({FILTERS_ON}) / off, end to end: {slow_wall:.2f}x the wall time, "
            f"{slow_cpu:.2f}x the CPU time (goal <= {GOAL_FILTER_SLOWDOWN}x: "
            f"{'met' if max(slow_wall, slow_cpu) <= GOAL_FILTER_SLOWDOWN else 'NOT met'}); "
            f"all fusion tests / off: {filter_t['all fusion tests'][0] / filter_t['off'][0]:.2f}x wall, "
            f"{filter_t['all fusion tests'][1] / filter_t['off'][1]:.2f}x CPU; "
            f"recommended filters with the rotation refinement (refine_rotations, tracked corners) / off: "
            f"{refine_wall:.2f}x wall, {refine_cpu:.2f}x CPU "
            f"(goal <= {GOAL_FILTER_SLOWDOWN}x: "
            f"{'met' if max(refine_wall, refine_cpu) <= GOAL_FILTER_SLOWDOWN else 'NOT met'}); "
            f"with SIFT matching instead: {filter_t['on + rotation refinement, SIFT'][0] / filter_t['off'][0]:.2f}x "
            "wall, "
            f"{filter_t['on + rotation refinement, SIFT'][1] / filter_t['off'][1]:.2f}x CPU"
        ),
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
