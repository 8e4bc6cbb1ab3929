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

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's mapkit, whatever is installed

from mapkit.core.errors import InputWarning  # noqa: E402 (after sys.path points at this checkout)
from mapkit.core.workspace import Workspace  # noqa: E402 (as above)
from mapkit.evaluation.dynamic import score_dynamic_removal  # noqa: E402 (as above)
from mapkit.mapping.build import BuildConfig, build  # noqa: E402 (as above)
from mapkit.mapping.lidar_map import LidarMapConfig  # noqa: E402 (as above)
from mapkit.mapping.trajectory import Trajectory  # noqa: E402 (as above)
from mapkit.synth import load_config, session_log, synthesize  # noqa: E402 (as above)

SESSION = "traffic"
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


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True, help="the record (JSON)")
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
        rows[2]["poses"] = "truth, removal off"
        record = {
            "command": "python3 bench/lidar_dynamic.py --out runs/lidar-dynamic.json",
            "session": {"preset": "tiny", "seed": TRAFFIC["seed"], "length_m": 150.0, "moving_cars": 8},
            "rows": rows,
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
            f"static removed {100 * r['static_removed_fraction']:.3f} % of {r['static_points']}"
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
