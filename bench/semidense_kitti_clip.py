"""Semi-dense map of the real KITTI clip with its given poses: cross-frame consistency, with and without outlier
rejection.

Runs ``mapkit.mapping.semidense.build_semidense_map`` over the 51-frame KITTI odometry clip beside the
project (left grey camera, exact poses) twice in one process: once with every
outlier filter off (``FILTERS_OFF``: no multi-view, photometric or free-space test, no ratio test, no
convergence threshold, no statistical pass) and once with the filters of the config (``--config`` over
the defaults, or a build config's ``semidense`` section). Then:

- writes the filtered map (``points.ply``, ``observations.npz``, ``config.yaml``) into ``--out``;
- computes the cross-frame consistency figure for both maps: every map point reprojected into the
  keyframes that did not create it, its depth compared with that keyframe's own depth at the
  nearest pixel (median, 90th percentile, share of pairs where the map is > 5 % farther), broken
  down by the distance between the keyframes and by the keyframe's own depth. Two references:
  ``raw``, every keyframe's depths as the epipolar search accepted them (outliers included), and
  ``filtered``, the depths that passed the fusion's tests and entered the map (each keyframe's
  filtered depth map, as COLMAP's fusion reads them);
- tells apart the pairs where the map lies > 5 % farther than the keyframe's own depth: that depth
  failed the keyframe's own multi-view test (the reference is suspect, not the map), or it passed
  and the map point is confirmed by >= 2 other keyframes (occluded: that keyframe cannot see the
  point), or neither; and scores every run against one fixed reference, the unfiltered run's
  keyframe depths that pass the multi-view test (``verified_depths``), with and without the
  occluded pairs (``mapkit.mapping.semidense.consistency`` with ``verified``);
- breaks the figures down along the drive (``by_source_keyframe``, ``by_reference_keyframe``: ranges of
  ``KEYFRAME_RANGE`` frames, each with its farther pairs told apart) and by the distance between the
  keyframes up to the longest the clip holds (pairs more than ``HALF_CLIP_M`` apart exist only on the
  whole clip, not on either half);
- checks the given poses against the images (``pose_check``): SIFT matches (Lowe's ratio test) between
  frames 1 and ``POSE_CHECK_GAP`` apart, and their distance to the epipolar lines the given poses
  predict, per frame (KITTI's poses come from its GPS/INS; a rotation off by a few tenths of a degree
  moves an epipolar line by pixels, and the depths of a keyframe searched along such lines disagree
  with everyone's); ``--refine-rotations`` maps on the given positions with every frame's rotation
  re-estimated from those matches (:func:`refine_rotations`), a diagnostic of what the map measures on
  poses that agree with the images, not on the clip's given poses; ``--refine-in-mapper`` maps on the
  given poses with the mapper's own streaming refinement on (``refine_rotations``,
  :mod:`mapkit.mapping.pose_refine`), the way a build runs it;
- ``--ablation``: each filter alone, then combinations, one row each (same figures);
- writes ``metrics.json``, ``semidense_kitti.png`` (top view of the filtered map, one keyframe's
  depths over its image) and ``semidense_rejected.png`` (top view: kept points, and the points of
  the unfiltered map with no filtered point within ``REJECTED_RADIUS_M``: what the filters removed).

Run from the repository root (``--first-frame 25`` maps the second half only: parameters chosen on
the first half are scored there)::

    python bench/semidense_kitti_clip.py --out /tmp/kitti-sd
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from mapkit.core.config import load_config  # noqa: E402 (after sys.path points at this checkout)
from mapkit.core.runio import write_json  # noqa: E402 (after sys.path points at this checkout)
from mapkit.mapping.pose_refine import epipolar_distances_px, refine_rotations  # noqa: E402 (after sys.path points at this checkout)
from mapkit.mapping.semidense import (  # noqa: E402 (after sys.path points at this checkout)
    KeyframePoints,
    SemiDenseConfig,
    SemiDenseMap,
    build_semidense_map,
    consistency,
    multi_view_filter,
)

DEFAULT_CLIP = ROOT.parent / "shared" / "data" / "kitti-odometry-clip"
DEFAULT_OUT = Path("/tmp/mapkit-semidense-kitti")
FRAME_PERIOD_NS = 100_000_000  # KITTI odometry: 10 Hz
REJECTED_RADIUS_M = 0.1  # an unfiltered point with no filtered one this close was removed (2x the fusion radius)
KEYFRAME_RANGE = 5  # frames per row of the breakdown along the drive
#: distance bins (m) between the keyframes of a pair; 30 m is about the longest a half clip (26 frames at 1.2 m) holds
DISTANCE_BINS_M = (0.0, 2.0, 5.0, 10.0, 20.0, 30.0, np.inf)
HALF_CLIP_M = 30.0
POSE_CHECK_GAP = 3  # the neighbour window's farthest frame (neighbour_window_frames)
LOWE_RATIO = 0.7  # SIFT ratio test (Lowe, IJCV 2004: 0.8; 0.7 stricter, fewer wrong matches on repeated facades)
POSE_HUBER_PX = 1.0  # robust scale (px) of the epipolar distances in refine_rotations
#: every outlier filter off: a depth accepted where 3 frames agree
FILTERS_OFF = {
    "min_consistent_views": 0,
    "ambiguity_ratio": None,
    "max_sigma_inv_depth": None,
    "outlier_neighbours": 0,
    "photometric_min_views": 0,
    "free_space_window_keyframes": 0,
    "min_agreeing_frames": 3,
}
#: the filtered run without --config: the multi-view test at its defaults (chosen on frames 0-25 of the clip) and the
#: free-space test against 25 keyframes either side (the recommended filters, configs/build/clean-maps.yaml)
FILTERS_ON = {"min_consistent_views": 1, "free_space_window_keyframes": 25}
#: each filter alone for --ablation (then combinations), over FILTERS_OFF and the config's other fields
FILTERS_ALONE = {
    "ratio test": {"ambiguity_ratio": 0.8},
    "convergence": {"max_sigma_inv_depth": 0.001},
    "multi-view": {"min_consistent_views": 1},
    "photometric": {"photometric_min_views": 1},
    "free space": {"free_space_window_keyframes": 25},
    "statistical": {"outlier_neighbours": 20},
    "4 agreeing frames": {"min_agreeing_frames": 4},
}
FILTERS_ALONE["multi-view + free space"] = {**FILTERS_ALONE["multi-view"], **FILTERS_ALONE["free space"]}
FILTERS_ALONE["multi-view + photometric"] = {**FILTERS_ALONE["multi-view"], **FILTERS_ALONE["photometric"]}
FILTERS_ALONE["the three fusion tests"] = {**FILTERS_ALONE["multi-view + photometric"], **FILTERS_ALONE["free space"]}
FILTERS_ALONE["multi-view + free space, 4 agreeing frames"] = {
    **FILTERS_ALONE["multi-view + free space"],
    **FILTERS_ALONE["4 agreeing frames"],
}
FILTERS_ALONE["all six"] = {k: v for name, d in list(FILTERS_ALONE.items())[:6] for k, v in d.items()}


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


def stream_frames(
    poses: np.ndarray, images: list[Path], frames: range
) -> Iterator[tuple[int, int, np.ndarray, np.ndarray]]:
    for i in frames:
        yield i, i * FRAME_PERIOD_NS, cv2.imread(str(images[i]), cv2.IMREAD_GRAYSCALE), poses[i]


def feature_matches(
    images: Sequence[Path | np.ndarray], frames: range, max_gap: int
) -> list[tuple[int, int, np.ndarray, np.ndarray]]:
    """(i, j, pixels in i (n, 2), pixels in j (n, 2)) of SIFT matches passing Lowe's ratio test, for every
    pair of ``frames`` at most ``max_gap`` apart; ``images`` are paths or grey images already read."""
    sift = cv2.SIFT_create(nfeatures=3000)

    def grey(im):
        return im if isinstance(im, np.ndarray) else cv2.imread(str(im), cv2.IMREAD_GRAYSCALE)

    feats = {i: sift.detectAndCompute(grey(images[i]), None) for i in frames}
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    out = []
    for i in frames:
        for j in range(i + 1, min(i + max_gap, frames.stop - 1) + 1):
            (ki, di), (kj, dj) = feats[i], feats[j]
            if di is None or dj is None or len(di) < 2 or len(dj) < 2:
                continue
            good = [a for a, b in matcher.knnMatch(di, dj, k=2) if a.distance < LOWE_RATIO * b.distance]
            out.append(
                (
                    i,
                    j,
                    np.array([ki[a.queryIdx].pt for a in good]).reshape(-1, 2),
                    np.array([kj[a.trainIdx].pt for a in good]).reshape(-1, 2),
                )
            )
    return out


def pose_check(K: np.ndarray, given: np.ndarray, refined: np.ndarray | None, matches) -> list[dict]:
    """Per frame: median epipolar distance (px) of its matches with the next frame and with the frame
    ``POSE_CHECK_GAP`` on, under the given poses (and the refined ones), and the rotation between the two."""
    from mapkit.core.geometry import rotation_angle_rad

    out = []
    for i, j, a, b in matches:
        if j - i not in (1, POSE_CHECK_GAP):
            continue
        row = next((r for r in out if r["frame"] == i), None)
        if row is None:
            row = {"frame": i}
            if refined is not None:
                row["rotation_change_deg"] = float(
                    np.degrees(rotation_angle_rad(given[i, :3, :3].T @ refined[i, :3, :3]))
                )
            out.append(row)
        row[f"given_px_gap{j - i}"] = float(np.median(epipolar_distances_px(K, given, i, j, a, b))) if len(a) else None
        if refined is not None:
            row[f"refined_px_gap{j - i}"] = (
                float(np.median(epipolar_distances_px(K, refined, i, j, a, b))) if len(a) else None
            )
        row[f"matches_gap{j - i}"] = int(len(a))
    return out


class Run:
    """One mapping of the clip: the map, each keyframe's raw and filtered depths, the time it took."""

    def __init__(
        self, cfg: SemiDenseConfig, poses: np.ndarray, images: list[Path], frames: range, K: np.ndarray, progress: bool
    ):
        self.cfg = cfg
        self.raw: dict[int, tuple[np.ndarray, KeyframePoints]] = {}
        self.filtered: dict[int, tuple[np.ndarray, KeyframePoints]] = {}
        t0 = time.perf_counter()
        self.map = build_semidense_map(
            stream_frames(poses, images, frames),
            K,
            cfg,
            progress=progress,
            on_keyframe=lambda fid, T, pts: self.raw.__setitem__(fid, (T, pts)),
            on_fused=lambda fid, T, pts: self.filtered.__setitem__(fid, (T, pts)),
        )
        self.seconds = time.perf_counter() - t0
        self.consistency: dict = {}

    def score(self, verified: dict[int, tuple[np.ndarray, KeyframePoints]], keyframe_bins: list[float]) -> None:
        """The consistency figures against this run's own keyframe depths (``raw``: the headline figure, with
        the farther pairs told apart against ``verified``, and broken down along the drive by ``keyframe_bins``)
        and against those that entered fusion (``filtered``)."""

        def as_list(d):
            return [(fid, T, pts) for fid, (T, pts) in d.items()]

        self.consistency = {
            "raw": consistency(
                self.map,
                as_list(self.raw),
                verified=as_list(verified),
                baseline_bins_m=DISTANCE_BINS_M,
                keyframe_bins=keyframe_bins,
            ),
            "filtered": consistency(self.map, as_list(self.filtered), baseline_bins_m=DISTANCE_BINS_M),
        }

    def metrics(self) -> dict:
        return {
            "seconds": self.seconds,
            "keyframes_per_s": len(self.raw) / self.seconds,
            "keyframe_points_before_fusion": sum(len(p) for _, p in self.raw.values()),
            "keyframe_points_after_fusion_filters": sum(len(p) for _, p in self.filtered.values()),
            **self.map.stats(),
            "consistency": self.consistency,
        }


def verified_depths(
    raw: dict[int, tuple[np.ndarray, KeyframePoints]], K: np.ndarray, cfg: SemiDenseConfig, shape: tuple[int, int]
) -> dict[int, tuple[np.ndarray, KeyframePoints]]:
    """Each keyframe's depths that pass the mapper's multi-view test (at ``cfg``'s consistency settings,
    ``min_consistent_views`` at least 1) against the keyframes within ``consistency_window_keyframes``:
    one fixed reference for every run (the unfiltered run's depths), so that no run is scored
    against its own filters. ``shape``: (H, W) of the images."""
    ids = sorted(raw)
    n = cfg.consistency_window_keyframes
    depth = {f: raw[f][1].depth_image(shape, np.float32) for f in ids}
    out = {}
    for i, f in enumerate(ids):
        T, pts = raw[f]
        others = [(raw[g][0], depth[g]) for g in ids[max(0, i - n) : i + n + 1] if g != f]
        keep = multi_view_filter(
            pts.points_world(K, T),
            others,
            K,
            min_views=max(cfg.min_consistent_views, 1),
            min_agree_over_conflict=cfg.min_agree_over_conflict,
            rel_tol=cfg.consistency_rel_tol,
            pixel_radius=cfg.consistency_pixel_radius,
        )
        out[f] = (T, pts.select(keep))
    return out


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
    sc = ax1.scatter(
        X[order, 2], -X[order, 0], c=height[order], s=0.2, cmap="viridis", vmin=-1.8, vmax=4.0, rasterized=True
    )
    ax1.plot(poses[:, 2, 3], -poses[:, 0, 3], "r-", lw=1.5, label="camera path (given poses)")
    kf = np.isin(np.arange(len(poses)), sd_map.keyframe_ids)
    ax1.plot(poses[kf, 2, 3], -poses[kf, 0, 3], "r.", ms=4, label="keyframes")
    ax1.set_xlim(-5, 100)
    ax1.set_ylim(-30, 30)
    ax1.set_aspect("equal")
    ax1.set_xlabel("forward z (m)")
    ax1.set_ylabel("left -x (m)")
    ax1.set_title(
        f"top view: {len(sd_map)} fused map points (colour: height above the camera, m; the road is at -1.65)"
    )
    ax1.legend(loc="upper left", markerscale=3)
    fig.colorbar(sc, ax=ax1, fraction=0.015, pad=0.01)
    ax2.imshow(image, cmap="gray", vmin=0, vmax=255)
    d = pts.depth
    sc2 = ax2.scatter(
        pts.pixels_uv[:, 0],
        pts.pixels_uv[:, 1],
        c=d,
        s=0.8,
        cmap="turbo",
        vmin=0,
        vmax=float(np.percentile(d, 98)),
        rasterized=True,
    )
    ax2.set_title(f"keyframe {fid}: its {len(pts)} accepted depths (colour: depth, m)")
    ax2.set_axis_off()
    fig.colorbar(sc2, ax=ax2, fraction=0.015, pad=0.01)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def rejected_mask(unfiltered: SemiDenseMap, filtered: SemiDenseMap) -> np.ndarray:
    """(N,) bool over the unfiltered map: no filtered point within REJECTED_RADIUS_M."""
    from scipy.spatial import cKDTree

    if len(filtered) == 0:
        return np.ones(len(unfiltered), bool)
    d, _ = cKDTree(filtered.points_world).query(unfiltered.points_world, distance_upper_bound=REJECTED_RADIUS_M)
    return ~np.isfinite(d)


def rejected_picture(
    path: Path, unfiltered: SemiDenseMap, filtered: SemiDenseMap, rejected: np.ndarray, poses: np.ndarray
) -> None:
    """Top view: the filtered map (grey) and what the filters removed (red), side by side and overlaid."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    kept, gone = filtered.points_world, unfiltered.points_world[rejected]
    fig, axes = plt.subplots(3, 1, figsize=(13, 15), sharex=True)
    panels = (
        (f"kept: {len(kept)} points of the filtered map", [(kept, "0.25")]),
        (
            f"rejected: {len(gone)} points of the unfiltered map ({len(unfiltered)}) with no kept point within "
            f"{REJECTED_RADIUS_M} m",
            [(gone, "tab:red")],
        ),
        ("both (kept drawn over rejected)", [(gone, "tab:red"), (kept, "0.25")]),
    )
    for ax, (title, layers) in zip(axes, panels, strict=True):
        for X, colour in layers:
            ax.scatter(X[:, 2], -X[:, 0], s=0.15, c=colour, rasterized=True)
        ax.plot(poses[:, 2, 3], -poses[:, 0, 3], "-", color="tab:blue", lw=1.5, label="camera path (given poses)")
        ax.set_xlim(-5, 100)
        ax.set_ylim(-30, 30)
        ax.set_aspect("equal")
        ax.set_ylabel("left -x (m)")
        ax.set_title(title)
    axes[0].legend(loc="upper left")
    axes[-1].set_xlabel("forward z (m)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _summary_rows(c: dict) -> list[str]:
    return [
        f"{100 * c['median_rel']:.2f} %",
        f"{100 * c['p90_rel']:.1f} %",
        f"{100 * c['frac_map_farther_5pct']:.1f} %",
        f"{100 * c['frac_map_nearer_5pct']:.1f} %",
        f"{100 * c['frac_below_5pct']:.1f} %",
        str(c["pairs"]),
    ]


def _four(c: dict) -> str:
    if not c.get("pairs"):
        return "-"
    return (
        f"{100 * c['median_rel']:.2f} / {100 * c['p90_rel']:.1f} / {100 * c['frac_map_farther_5pct']:.1f} / "
        f"{100 * c['frac_map_nearer_5pct']:.1f} %"
    )


def _fusion_filters_on(cfg: SemiDenseConfig) -> bool:
    return cfg.min_consistent_views > 0 or cfg.photometric_min_views > 0 or cfg.free_space_window_keyframes > 0


def _bins(c: dict, key: str) -> list[tuple[str, str]]:
    out = []
    for b in c[key]:
        if b["pairs"]:
            span = f"{b['from_m']:.0f}-{b['to_m']:.0f} m" if b["to_m"] is not None else f">= {b['from_m']:.0f} m"
            figures = (
                f"{100 * b['median_rel']:.2f} / {100 * b['p90_rel']:.1f} / {100 * b['frac_map_farther_5pct']:.1f} %"
            )
            out.append((span, f"{figures} ({b['pairs']})"))
    return out


def _load_semidense(path: Path) -> SemiDenseConfig:
    """SemiDenseConfig from a YAML of its fields, or the ``semidense`` section of a build config (configs/build/)."""
    import yaml

    doc = yaml.safe_load(path.read_text()) or {}
    if isinstance(doc, dict) and "semidense" in doc:
        from mapkit.mapping.build import BuildConfig

        return load_config(BuildConfig, path).semidense
    return load_config(SemiDenseConfig, path)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--clip", type=Path, default=DEFAULT_CLIP, help="KITTI clip folder (image_l/, poses.txt, calib.txt)"
    )
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT, help=f"output folder (default {DEFAULT_OUT})")
    ap.add_argument("--first-frame", type=int, default=0, help="start at this frame (25: the second half of the clip)")
    ap.add_argument("--frames", type=int, default=10**9, help="use at most N frames")
    ap.add_argument(
        "--config",
        type=Path,
        default=None,
        help="YAML over SemiDenseConfig defaults for the filtered run, or a build config (its semidense section; "
        "e.g. configs/build/clean-maps.yaml) (default: FILTERS_ON); "
        "the unfiltered run sets FILTERS_OFF over it",
    )
    ap.add_argument(
        "--ablation", action="store_true", help="also map with each outlier filter alone, and with combinations of them"
    )
    ap.add_argument(
        "--refine-rotations",
        action="store_true",
        help="map on the given positions with each frame's rotation re-estimated from SIFT matches (a diagnostic: "
        "what the map measures on poses that agree with the images)",
    )
    ap.add_argument(
        "--refine-in-mapper",
        action="store_true",
        help="map on the given poses with the mapper's own rotation refinement on (refine_rotations: true, "
        "mapkit.mapping.pose_refine; the same as a --config that sets it): both runs",
    )
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    if not (args.clip / "poses.txt").is_file():
        print(f"error: no KITTI clip at {args.clip}", file=sys.stderr)
        return 2
    cfg = _load_semidense(args.config) if args.config else SemiDenseConfig(**FILTERS_ON)
    if args.refine_in_mapper:
        cfg = cfg.model_copy(update={"refine_rotations": True})
    off = cfg.model_copy(update=FILTERS_OFF)
    K, poses, images = read_clip_geometry(args.clip)
    frames = range(args.first_frame, min(args.first_frame + args.frames, len(images)))
    if len(frames) < 2:
        print(f"error: frames {args.first_frame}.. of a {len(images)}-frame clip: nothing to map", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    matches = feature_matches(images, frames, POSE_CHECK_GAP)
    refined = refine_rotations(K, poses, matches, huber_px=POSE_HUBER_PX) if args.refine_rotations else None
    checked = pose_check(K, poses, refined, matches)
    pose_seconds = time.perf_counter() - t0
    if refined is not None:
        poses = refined
    runs: dict[str, Run] = {}
    for name, c in [("unfiltered", off), ("filtered", cfg)] + (
        [(k, off.model_copy(update=v)) for k, v in FILTERS_ALONE.items()] if args.ablation else []
    ):
        runs[name] = Run(c, poses, images, frames, K, progress=not args.no_progress)
    base, new = runs["unfiltered"], runs["filtered"]
    w, h = new.map.image_size_wh
    verified = verified_depths(base.raw, K, cfg, (h, w))
    keyframe_bins = list(range(frames.start, frames.stop, KEYFRAME_RANGE)) + [float("inf")]
    for r in runs.values():
        r.score(verified, keyframe_bins)
    new.map.save(args.out)
    gone = rejected_mask(base.map, new.map)

    metrics = {
        "clip": str(args.clip),
        "frames": [frames.start, frames.stop],
        "image_size_wh": list(new.map.image_size_wh),
        "filters_off": FILTERS_OFF,
        "config": cfg.model_dump(mode="json"),
        "runs": {name: r.metrics() for name, r in runs.items()},
        "rejected_points": int(gone.sum()),
        "speed_ratio_filtered_over_unfiltered": new.seconds / base.seconds,
        "poses": {
            "refined_rotations": bool(args.refine_rotations),
            "refined_in_mapper": new.map.pose_refinement or None,
            "seconds": pose_seconds,
            "lowe_ratio": LOWE_RATIO,
            "huber_px": POSE_HUBER_PX,
            "epipolar_check": checked,
        },
    }
    write_json(args.out / "metrics.json", metrics)
    kf = sorted(new.raw)
    mid = kf[len(kf) // 2]
    mid_image = cv2.imread(str(images[mid]), cv2.IMREAD_GRAYSCALE)
    picture(args.out / "semidense_kitti.png", new.map, poses, (mid, new.filtered[mid][1]), mid_image)
    rejected_picture(args.out / "semidense_rejected.png", base.map, new.map, gone, poses)

    print(f"\n## Semi-dense map of {args.clip.name}, frames {frames.start}-{frames.stop - 1} ({w}x{h})\n")
    print(
        "Consistency: map points against other keyframes' own depths; reference raw = every keyframe's accepted depths,"
    )
    print("filtered = those that passed the fusion's outlier tests (the same as raw when they are off).\n")
    heads = ["median", "p90", "map farther > 5 %", "map nearer > 5 %", "within 5 %", "pairs"]
    print("| run | points | per 100 m | s | reference | " + " | ".join(heads) + " |")
    print("|---|---|---|---|---|" + "---|" * len(heads))
    for name, r in runs.items():
        st = r.map.stats()
        for ref in ("raw", "filtered"):
            if ref == "filtered" and not _fusion_filters_on(r.cfg):
                continue
            head = f"| {name} | {len(r.map)} | {st['points_per_100m']:.0f} | {r.seconds:.1f} | {ref} | "
            print(head + " | ".join(_summary_rows(r.consistency[ref])) + " |")
    print(
        f"\npoints before / after the filters: {len(base.map)} / {len(new.map)} "
        f"({100 * len(new.map) / max(len(base.map), 1):.0f} %); "
        f"removed (no kept point within {REJECTED_RADIUS_M} m): {int(gone.sum())}; "
        f"filtered run took {metrics['speed_ratio_filtered_over_unfiltered']:.2f}x the unfiltered one's time"
    )
    print(f"rejected by the fusion filters (filtered run): {new.map.rejected}")
    print(
        "\nWhere the pairs with the map > 5 % farther come from (shares of all pairs, raw reference): "
        "the keyframe's own depth"
    )
    print(
        "there failed its multi-view test (reference unverified); "
        "it passed and the map point agrees with >= 2 other keyframes'"
    )
    print(
        "verified depths (occluded: the keyframe cannot see the point); the rest (unexplained). "
        "Then the figures against one fixed"
    )
    print(
        "reference for all runs, the unfiltered run's keyframe depths that pass the multi-view test (verified), "
        "with and without"
    )
    print("the occluded pairs.\n")
    print(
        "| run | points | farther | ref. unverified | occluded | unexplained "
        "| verified ref.: median / p90 / farther / nearer "
        "| verified, occluded excluded: median / p90 / farther / nearer |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for name, r in runs.items():
        c = r.consistency["raw"]
        fc = c["farther_causes"]
        print(
            f"| {name} | {len(r.map)} | {100 * c['frac_map_farther_5pct']:.1f} % | "
            f"{100 * fc['reference_unverified']:.1f} % | {100 * fc['occluded']:.1f} % | "
            f"{100 * fc['unexplained']:.1f} % | {_four(c['verified_reference'])} | {_four(c['verified_visible'])} |"
        )
    for key, label in (
        ("by_depth_m", "keyframe's own depth"),
        ("by_keyframe_distance_m", "distance between the keyframes"),
    ):
        print(f"\nby {label}: median / p90 / map farther > 5 % (pairs)\n")
        cols = [("unfiltered", "raw"), ("filtered", "raw"), ("filtered", "filtered")]
        table = {(n, ref): dict(_bins(runs[n].consistency[ref], key)) for n, ref in cols}
        names = [f"{n} ({ref} ref.)" for n, ref in cols]
        if key == "by_keyframe_distance_m":
            for n in ("unfiltered", "filtered"):
                table[(n, "visible")] = dict(_bins(runs[n].consistency["raw"]["verified_visible"], key))
                names.append(f"{n} (verified ref., occluded excluded)")
        spans = list(dict.fromkeys(s for t in table.values() for s in t))
        print("| range | " + " | ".join(names) + " |")
        print("|---|" + "---|" * len(table))
        for span in spans:
            print(f"| {span} | " + " | ".join(t.get(span, "") for t in table.values()) + " |")
    print(
        "\nAlong the drive, map points by their keyframe (source) and pairs by the keyframe whose own depth is compared"
    )
    print("(reference): median / p90 / map farther > 5 % (pairs); then the farther pairs' shares of the range's pairs:")
    print("reference unverified / occluded / unexplained\n")
    print(
        "| frames | "
        + " | ".join(f"{n} by {side}" for n in ("unfiltered", "filtered") for side in ("source", "reference"))
        + " |"
    )
    print("|---|" + "---|" * 4)
    cells = {
        (n, side): runs[n].consistency["raw"][f"by_{side}_keyframe"]
        for n in ("unfiltered", "filtered")
        for side in ("source", "reference")
    }
    for k, lo in enumerate(keyframe_bins[:-1]):
        row = []
        for b in cells.values():
            b = b[k]
            if not b["pairs"]:
                row.append("-")
                continue
            fc = b["farther_causes"]
            row.append(
                f"{100 * b['median_rel']:.2f} / {100 * b['p90_rel']:.1f} / {100 * b['frac_map_farther_5pct']:.1f} % "
                f"({b['pairs']}); {100 * fc['reference_unverified']:.1f} / {100 * fc['occluded']:.1f} / "
                f"{100 * fc['unexplained']:.1f}"
            )
        hi = min(int(lo) + KEYFRAME_RANGE, frames.stop) - 1
        print(f"| {int(lo)}-{hi} | " + " | ".join(row) + " |")
    far_new = new.consistency["raw"]["by_keyframe_distance_m"]
    beyond = [b for b in far_new if b["from_m"] >= HALF_CLIP_M]
    if beyond and beyond[0]["pairs"]:
        share = beyond[0]["pairs"] / new.consistency["raw"]["pairs"]
        print(
            f"\nfiltered run: {100 * share:.1f} % of the pairs are keyframes >= {HALF_CLIP_M:.0f} m apart "
            f"(none on a half clip), {100 * beyond[0]['frac_map_farther_5pct']:.0f} % of them farther"
        )
    mapped_on = (
        "rotations re-estimated: mapped on the refined poses" if refined is not None else "mapped on the given poses"
    )
    print(
        f"\nGiven poses against the images ({mapped_on}; "
        f"{pose_seconds:.0f} s): median distance (px) of SIFT matches from the epipolar lines, frames 1 and "
        f"{POSE_CHECK_GAP} apart\n"
    )
    cols = ["given_px_gap1", f"given_px_gap{POSE_CHECK_GAP}"] + (
        ["refined_px_gap1", f"refined_px_gap{POSE_CHECK_GAP}", "rotation_change_deg"] if refined is not None else []
    )
    print("| frames | " + " | ".join(cols) + " |")
    print("|---|" + "---|" * len(cols))
    for lo in keyframe_bins[:-1]:
        rows = [r for r in checked if lo <= r["frame"] < lo + KEYFRAME_RANGE]
        vals = []
        for c in cols:
            v = [r[c] for r in rows if r.get(c) is not None]
            vals.append(f"{np.median(v):.2f}" if v else "-")
        print(f"| {int(lo)}-{min(int(lo) + KEYFRAME_RANGE, frames.stop) - 1} | " + " | ".join(vals) + " |")
    pr = new.map.pose_refinement
    if pr:
        print(
            "\nThe mapper's own rotation refinement "
            f"(refine_rotations, window of {cfg.refine_lag_frames} frames either side): {pr['frames']} frames, "
            f"correction median {pr['correction_deg_median']:.3f} deg, max {pr['correction_deg_max']:.3f} deg; "
            f"matched pairs' median epipolar distance {pr['epipolar_px_median_given']:.2f} px given, "
            f"{pr['epipolar_px_median_refined']:.2f} px refined"
        )
    print(
        f"\nwrote {args.out}/points.ply, observations.npz, config.yaml, metrics.json, "
        "semidense_kitti.png, semidense_rejected.png"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
