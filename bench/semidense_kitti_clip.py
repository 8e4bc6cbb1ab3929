"""Semi-dense map of the real KITTI clip with its given poses, and its cross-frame consistency.

Runs ``mapkit.mapping.semidense.build_semidense_map`` over the 51-frame KITTI odometry clip beside the
project (left grey camera, exact poses), then:

- writes the map (``points.ply``, ``observations.npz``, ``config.yaml``) into ``--out``;
- computes the consistency figure of the issue: every map point reprojected into the keyframes
  that did not create it, its depth compared with that keyframe's own estimate at the nearest
  pixel; the median relative disagreement is the headline (goal: below 5%);
- writes ``metrics.json`` and ``semidense_kitti.png`` (top view of the map over the trajectory,
  and one keyframe's accepted points coloured by depth over its image).

Run from the repository root::

    python bench/semidense_kitti_clip.py --out /tmp/kitti-sd
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from mapkit.core.config import load_config  # noqa: E402
from mapkit.core.runio import write_json  # noqa: E402
from mapkit.mapping.semidense import KeyframePoints, SemiDenseConfig, build_semidense_map, consistency  # noqa: E402

DEFAULT_CLIP = ROOT.parent / "shared" / "data" / "kitti-odometry-clip"
FRAME_PERIOD_NS = 100_000_000  # KITTI odometry: 10 Hz


def read_clip_geometry(clip: Path) -> tuple[np.ndarray, np.ndarray, list[Path]]:
    """(K 3x3 from P0, world_from_cam (N, 4, 4) from poses.txt, image paths) of a KITTI clip."""
    first = (clip / "calib.txt").read_text().splitlines()[0].split()
    P0 = np.array([float(x) for x in first if not x.endswith(":")]).reshape(3, 4)
    rows = np.loadtxt(clip / "poses.txt").reshape(-1, 3, 4)
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :] = rows
    images = sorted((clip / "image_l").glob("*.png"))
    if len(images) != len(poses):
        raise SystemExit(f"{clip}: {len(images)} images but {len(poses)} poses")
    return P0[:, :3], poses, images


def stream_frames(poses: np.ndarray, images: list[Path], n: int) -> Iterator[tuple[int, int, np.ndarray, np.ndarray]]:
    for i in range(min(n, len(images))):
        yield i, i * FRAME_PERIOD_NS, cv2.imread(str(images[i]), cv2.IMREAD_GRAYSCALE), poses[i]


def picture(path: Path, sd_map, poses: np.ndarray, keyframe: tuple[int, KeyframePoints], image: np.ndarray) -> None:
    """Top view of the fused map (forward to the right) over one keyframe's depths on its image."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fid, pts = keyframe
    X = sd_map.points_world
    height = -X[:, 1]  # KITTI cameras: y points down; height above the camera in metres
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(14, 10), gridspec_kw={"height_ratios": [1.25, 1.0]})
    order = np.argsort(height)  # high points on top
    sc = ax1.scatter(X[order, 2], -X[order, 0], c=height[order], s=0.2, cmap="viridis", vmin=-1.8, vmax=4.0, rasterized=True)
    ax1.plot(poses[:, 2, 3], -poses[:, 0, 3], "r-", lw=1.5, label="camera path (given poses)")
    kf = np.isin(np.arange(len(poses)), sd_map.keyframe_ids)
    ax1.plot(poses[kf, 2, 3], -poses[kf, 0, 3], "r.", ms=4, label="keyframes")
    ax1.set_xlim(-5, 100)
    ax1.set_ylim(-30, 30)
    ax1.set_aspect("equal")
    ax1.set_xlabel("forward z (m)")
    ax1.set_ylabel("left -x (m)")
    ax1.set_title(f"top view: {len(sd_map)} fused map points (colour: height above the camera, m; the road is at -1.65)")
    ax1.legend(loc="upper left", markerscale=3)
    fig.colorbar(sc, ax=ax1, fraction=0.015, pad=0.01)
    ax2.imshow(image, cmap="gray", vmin=0, vmax=255)
    d = pts.depth
    sc2 = ax2.scatter(pts.pixels_uv[:, 0], pts.pixels_uv[:, 1], c=d, s=0.8, cmap="turbo", vmin=0, vmax=float(np.percentile(d, 98)), rasterized=True)
    ax2.set_title(f"keyframe {fid}: its {len(pts)} accepted depths (colour: depth, m)")
    ax2.set_axis_off()
    fig.colorbar(sc2, ax=ax2, fraction=0.015, pad=0.01)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clip", type=Path, default=DEFAULT_CLIP, help="KITTI clip folder (image_l/, poses.txt, calib.txt)")
    ap.add_argument("--out", type=Path, required=True, help="output folder")
    ap.add_argument("--frames", type=int, default=10**9, help="use only the first N frames")
    ap.add_argument("--config", type=Path, default=None, help="YAML over SemiDenseConfig defaults")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    if not (args.clip / "poses.txt").is_file():
        print(f"error: no KITTI clip at {args.clip}", file=sys.stderr)
        return 2
    cfg = load_config(SemiDenseConfig, args.config)
    K, poses, images = read_clip_geometry(args.clip)
    own: dict[int, tuple[np.ndarray, KeyframePoints]] = {}

    t0 = time.perf_counter()
    sd_map = build_semidense_map(
        stream_frames(poses, images, args.frames), K, cfg, progress=not args.no_progress,
        on_keyframe=lambda fid, T, pts: own.__setitem__(fid, (T, pts)),
    )
    t_map = time.perf_counter() - t0
    sd_map.save(args.out)
    cons = consistency(sd_map, [(fid, T, pts) for fid, (T, pts) in own.items()])

    raw = sum(len(p) for _, p in own.values())
    metrics = {
        "clip": str(args.clip),
        "frames": int(min(args.frames, len(images))),
        "image_size_wh": list(sd_map.image_size_wh),
        "seconds": t_map,
        "keyframes_per_s": len(own) / t_map,
        "keyframe_points_before_fusion": raw,
        **sd_map.stats(),
        "consistency": cons,
    }
    write_json(args.out / "metrics.json", metrics)
    mid = sorted(own)[len(own) // 2]
    picture(args.out / "semidense_kitti.png", sd_map, poses[: metrics["frames"]], (mid, own[mid][1]), cv2.imread(str(images[mid]), cv2.IMREAD_GRAYSCALE))

    print(f"\n## Semi-dense map of {args.clip.name} ({metrics['frames']} frames, {sd_map.image_size_wh[0]}x{sd_map.image_size_wh[1]})\n")
    print("| figure | value |\n|---|---|")
    rows = [
        ("keyframes", len(own)),
        ("time (s) / keyframes per s", f"{t_map:.1f} / {len(own) / t_map:.2f}"),
        ("points before fusion / after", f"{raw} / {len(sd_map)}"),
        ("points per 100 m of path", f"{metrics['points_per_100m']:.0f}"),
        ("observations per point (median)", metrics["obs_per_point_median"]),
        ("depth sigma (median, m)", f"{metrics['sigma_depth_median_m']:.3f}"),
        ("consistency pairs (point, other keyframe)", cons["pairs"]),
        ("median relative depth disagreement", f"{100 * cons['median_rel']:.2f} % (goal < 5 %)"),
        ("p90 relative disagreement", f"{100 * cons['p90_rel']:.2f} %"),
        ("share of pairs within 5 %", f"{100 * cons['frac_below_5pct']:.1f} %"),
        ("pairs with map nearer / farther than own by > 5 %", f"{100 * cons['frac_map_nearer_5pct']:.1f} % / {100 * cons['frac_map_farther_5pct']:.1f} %"),
        ("projections that hit an own depth (1 px)", f"{100 * cons['hit_rate']:.1f} %"),
    ]
    for b in cons["by_keyframe_distance_m"]:
        if b["pairs"]:
            span = f"{b['from_m']:.0f}-{b['to_m']:.0f} m" if b["to_m"] is not None else f">= {b['from_m']:.0f} m"
            rows.append((f"  keyframes {span} apart: median / within 5 %",
                         f"{100 * b['median_rel']:.2f} % / {100 * b['frac_below_5pct']:.1f} % ({b['pairs']} pairs)"))
    for k, v in rows:
        print(f"| {k} | {v} |")
    print(f"\nwrote {args.out}/points.ply, observations.npz, config.yaml, metrics.json, semidense_kitti.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
