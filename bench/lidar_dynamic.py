"""Moving cars in the LiDAR map: how many of their points the map keeps, how many static points go, and what
the removal costs.

A synthetic session with oncoming cars (the tiny town of seed 11, 150 m, eight cars: the session
tests/test_lidar_dynamic.py checks; the filter's defaults were chosen on another, seed 7 with six cars over
90 m) is scored point by point against the renderer's labels (:func:`mapkit.evaluation.dynamic.score_dynamic_removal`)
on its true poses and on the build's own trajectory (kiss-icp, GPS-aligned). The same session is then built twice,
with the removal on and off, and the LiDAR map stage's time is compared with the trajectory stage's.

    python3 bench/lidar_dynamic.py --out runs/lidar-dynamic.json
    python3 docs/figures.py collect lidar-dynamic runs/lidar-dynamic.json && python3 docs/figures.py render

Under a minute on 2 cores.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's mapkit, whatever is installed

from mapkit.core.errors import InputWarning  # noqa: E402 (after sys.path points at this checkout)
from mapkit.core.geometry import interpolate_poses  # noqa: E402 (as above)
from mapkit.core.types import StreamKind  # noqa: E402 (as above)
from mapkit.core.workspace import Workspace  # noqa: E402 (as above)
from mapkit.evaluation.dynamic import score_dynamic_removal  # noqa: E402 (as above)
from mapkit.io import open_log  # noqa: E402 (as above)
from mapkit.mapping.build import BuildConfig, build  # noqa: E402 (as above)
from mapkit.mapping.lidar_map import LidarMapConfig, build_lidar_map  # noqa: E402 (as above)
from mapkit.mapping.trajectory import Trajectory  # noqa: E402 (as above)
from mapkit.synth import gt_poses, load_config, session_log, synthesize  # noqa: E402 (as above)

DEFAULT_CLIP = Path(__file__).resolve().parents[2] / "shared" / "data" / "kitti-raw-velodyne-clip"
SESSION = "traffic"
EARLY_S = 3.0  # the drive's first seconds, reported apart (a trajectory's start is where it is least sure)
TRAFFIC = {
    "seed": 11,
    "sessions": [
        {
            **load_config("tiny").model_dump(mode="json")["sessions"][0],
            "name": SESSION,
            "length_m": 150.0,
            "camera_rate_hz": None,
            "moving_cars": 8,
        }
    ],
    "motion": {"start_from_rest": False},
}


def built(town: Path, ws: Path, dynamic: bool) -> tuple[Workspace, dict]:
    """The session built with its own trajectory (no semi-dense map: not what is measured), and its stage times."""
    cfg = BuildConfig.model_validate({"map": False, "lidar_map": {"dynamic": {"enabled": dynamic}}})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputWarning)
        w = Workspace(build([session_log(town, SESSION)], ws, config=cfg, progress=False))
    times = json.loads((w.session(SESSION).root / "timings.json").read_text())["wall_s_this_run"]
    return w, times


def relative_error_1s(own: Trajectory, town: Path) -> list[float]:
    """Every 0.5 s, how far the build's own motion over the next second is from the true one (m): frame-free."""
    true_stamps, true_poses = gt_poses(town, SESSION)
    t = np.arange(own.stamps_ns[0], own.stamps_ns[-1] - 1_000_000_000, 500_000_000)
    a, _ = interpolate_poses(own.stamps_ns, own.world_from_base, t)
    b, _ = interpolate_poses(own.stamps_ns, own.world_from_base, t + 1_000_000_000)
    c, _ = interpolate_poses(true_stamps, true_poses, t)
    d, _ = interpolate_poses(true_stamps, true_poses, t + 1_000_000_000)
    err = np.linalg.inv(np.linalg.inv(c) @ d) @ (np.linalg.inv(a) @ b)
    return [round(float(x), 3) for x in np.linalg.norm(err[:, :3, 3], axis=1)]


def real_clip(clip: Path, scratch: Path) -> dict:
    """The real KITTI clip (no labels): the share of its points removed, and of its points near the ground (within
    0.15 m of the lowest point around them), with the defaults and without the height tolerance near the ground."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputWarning)
        w = Workspace(
            build([clip], scratch / "ws-clip", config=BuildConfig.model_validate({"map": False}), progress=False)
        )
    name = w.session_names()[0]
    traj = Trajectory.load(w.session(name).enu_trajectory)
    out: dict = {}
    for label, dynamic in (("defaults", {}), ("no height tolerance", {"margin_vertical_m": 0.0})):
        cfg = LidarMapConfig(dynamic=dynamic)
        with open_log(clip) as log:
            result = build_lidar_map(log.records(StreamKind.LIDAR), traj, np.eye(4), cfg)
        m = result.metrics(cfg)["dynamic"]
        out["scans"] = result.scans_used
        out[label] = {
            "removed_fraction": round(m["fraction_removed"], 4),
            "near_ground_removed_fraction": round(m["near_ground_fraction_removed"], 4),
        }
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True, help="the record (JSON)")
    ap.add_argument("--clip", type=Path, default=DEFAULT_CLIP, help="the real KITTI clip (skipped when absent)")
    ap.add_argument("--scratch", type=Path, default=None, help="where the town and workspaces go (a temp dir)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        root = args.scratch or Path(tmp)
        town = synthesize(preset="tiny", out=root / "town", overrides=TRAFFIC, progress=False)
        ws_on, t_on = built(town, root / "ws-on", True)
        _, t_off = built(town, root / "ws-off", False)
        own = Trajectory.load(ws_on.session(SESSION).enu_trajectory)
        if own.body_frame != "base_link":
            raise SystemExit(f"the build's trajectory is of {own.body_frame!r}, not base_link")
        rows = [
            score_dynamic_removal(town, SESSION),
            score_dynamic_removal(town, SESSION, trajectory=own),
            score_dynamic_removal(town, SESSION, LidarMapConfig(dynamic={"enabled": False})),
        ]
        rows[1]["poses"] = "own"
        rpe = relative_error_1s(own, town)
        rows[2]["poses"] = "truth, removal off"
        for r in rows:  # where in the drive the static points went: the first seconds against the rest
            per_scan = r.pop("per_scan")
            start = per_scan[0][0]
            early = [row for row in per_scan if row[0] - start < EARLY_S * 1e9]
            r["static_removed_first_s"] = EARLY_S
            r["static_points_removed_first"] = int(sum(row[4] for row in early))
        record = {
            "command": "python3 bench/lidar_dynamic.py --out runs/lidar-dynamic.json",
            "session": {"preset": "tiny", "seed": TRAFFIC["seed"], "length_m": 150.0, "moving_cars": 8},
            "rows": rows,
            "real_clip": real_clip(args.clip, root) if (args.clip / "velodyne").is_dir() else None,
            "own_motion_error_1s_m": {"first_second": rpe[0], "median_after_3s": float(np.median(rpe[6:]))},
            "stage_s": {
                "trajectory": round(t_on["trajectory"], 2),
                "lidar_map_with_removal": round(t_on["lidar_map"], 2),
                "lidar_map_without_removal": round(t_off["lidar_map"], 2),
            },
        }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(record, indent=1) + "\n")
    for r in rows:
        print(
            f"{r['poses']:>20}: car points kept {100 * r['car_kept_fraction']:.2f} % of {r['car_points']}, "
            f"static removed {100 * r['static_removed_fraction']:.3f} % of {r['static_points']} "
            f"({r['static_points_removed_first']} of those {r['static_points_removed']} in the first {EARLY_S:g} s)"
        )
    if record["real_clip"]:
        for label, v in record["real_clip"].items():
            if isinstance(v, dict):
                print(
                    f"real clip, {label}: {100 * v['removed_fraction']:.2f} % of points removed, "
                    f"{100 * v['near_ground_removed_fraction']:.2f} % of the points near the ground"
                )
    e = record["own_motion_error_1s_m"]
    print(
        f"own trajectory's motion over 1 s: {e['first_second']:.2f} m off in the first second, median "
        f"{e['median_after_3s']:.3f} m after 3 s"
    )
    s = record["stage_s"]
    print(
        f"LiDAR map stage {s['lidar_map_with_removal']:.1f} s with removal, {s['lidar_map_without_removal']:.1f} s "
        f"without (ratio {s['lidar_map_with_removal'] / s['lidar_map_without_removal']:.2f}); trajectory stage "
        f"{s['trajectory']:.1f} s: LiDAR map / trajectory = {s['lidar_map_with_removal'] / s['trajectory']:.2f}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
