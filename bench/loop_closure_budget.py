"""Loop closures in the fused trajectory: a synthetic drive that comes back to its start, built with and without them.

    python bench/loop_closure_budget.py [--out DIR] [--size W H R] [--speed M_S] [--extra M] [--lidar-hz HZ] [--seed N]
                                        [--robust-k K]

The drive is ``tests/test_loop_closure.py``'s: a town generated around a rounded rectangle (by
default 90 x 70 m, 12 m corners) driven from rest a lap and 40 m on. kiss-icp runs once; copies of
that workspace are georeferenced back to back with ``georef: {fuse: true, factor_graph:
{loop_closures: false}}`` and with loop closures, and each fused trajectory is scored against the
town's truth: absolute ATE, ATE with the mean offset removed, the error of the motion between the
two passes of the revisit (median over the second pass), the height error's spread (offset
removed: max minus min), the georef stage's time with and without the loop step, and their ratio.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from test_loop_closure import loop_route, revisit_error_m  # noqa: E402 (after sys.path points at this checkout's tests)

from mapkit.core.geometry import interpolate_poses  # noqa: E402 (after sys.path points at this checkout)
from mapkit.core.workspace import Workspace  # noqa: E402 (after sys.path points at this checkout)
from mapkit.evaluation.truth import session_truth, ws_from_town  # noqa: E402 (after sys.path points at this checkout)
from mapkit.mapping.build import build  # noqa: E402 (after sys.path points at this checkout)
from mapkit.mapping.trajectory import Trajectory  # noqa: E402 (after sys.path points at this checkout)
from mapkit.synth import session_log, synthesize  # noqa: E402 (after sys.path points at this checkout)


def score(ws: Path, town: Path) -> dict:
    w = Workspace(ws)
    s = w.session("loop")
    traj = Trajectory.load(s.fused_trajectory)
    stamps, truth = session_truth(town, "loop")
    gt, ok = interpolate_poses(stamps, ws_from_town(town, w.frame()) @ truth, traj.stamps_ns)
    e = traj.world_from_base[ok, :3, 3] - gt[:, :3, 3]
    local = e - e.mean(axis=0)
    georef = json.loads(s.gps_alignment.read_text())
    return {
        "ate_m": float(np.sqrt((e**2).sum(axis=1).mean())),
        "ate_local_m": float(np.sqrt((local**2).sum(axis=1).mean())),
        "revisit_m": revisit_error_m(ws, town),
        "height_spread_m": float(np.ptp(local[:, 2])),
        "georef_s": georef["seconds"],
        "loops": georef["fused"].get("loop_accepted"),
        "loop_s": georef["fused"].get("loop_seconds"),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--out", type=Path, default=None, help="working folder (default: a temporary one; reused when given)"
    )
    ap.add_argument(
        "--size",
        type=float,
        nargs=3,
        default=(90.0, 70.0, 12.0),
        metavar=("W", "H", "R"),
        help="the route's rounded rectangle: width, height, corner radius (m)",
    )
    ap.add_argument("--speed", type=float, default=9.0, help="cruising speed (m/s)")
    ap.add_argument("--extra", type=float, default=40.0, help="metres driven past the start after the lap")
    ap.add_argument("--lidar-hz", type=float, default=5.0, help="LiDAR sweep rate")
    ap.add_argument("--seed", type=int, default=3, help="the town's seed")
    ap.add_argument("--robust-k", type=float, default=None, help="factor_graph.loop_robust_k (default: the config's)")
    args = ap.parse_args()
    root = args.out or Path(tempfile.mkdtemp(prefix="mapkit-loops-"))
    root.mkdir(parents=True, exist_ok=True)
    town = root / "town"
    if not (town / "world").is_dir():
        loop_route(root / "loop.tum", tuple(args.size), args.extra, args.speed)
        (root / "synth.yaml").write_text(
            f"seed: {args.seed}\nsessions:\n"
            "  - {name: loop, role: train, time: '12:00', weather: sunny, length_m: 400.0, "
            f"camera_rate_hz: 0.2}}\ncamera: {{width: 64, height: 48}}\nlidar: {{rate_hz: {args.lidar_hz}}}\n"
        )
        synthesize(preset="tiny", out=town, config=root / "synth.yaml", trajectory=root / "loop.tum", progress=False)
    log = session_log(town, "loop")
    (root / "base.yaml").write_text("map: false\nimagedb: false\n")
    build([log], root / "ws-base", config=root / "base.yaml", progress=False)  # kiss-icp once
    on = "{}" if args.robust_k is None else f"{{loop_robust_k: {args.robust_k}}}"
    for label, fg in (("off", "{loop_closures: false}"), ("on", on)):  # the georef stage of each, back to back
        (root / f"{label}.yaml").write_text(f"georef: {{fuse: true, factor_graph: {fg}}}\nmap: false\nimagedb: false\n")
        shutil.rmtree(root / f"ws-{label}", ignore_errors=True)
        shutil.copytree(root / "ws-base", root / f"ws-{label}")
        build([log], root / f"ws-{label}", config=root / f"{label}.yaml", progress=False)
    kiss = json.loads((Workspace(root / "ws-base").session("loop").trajectory / "metrics.json").read_text())["seconds"]
    off, on = score(root / "ws-off", town), score(root / "ws-on", town)
    print(
        "| fused trajectory | ATE m | ATE, offset removed m | revisit motion error, median m | height error spread m "
        "| georef stage s | loops accepted | loop step s |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for label, r in (("without loop closures", off), ("with loop closures", on)):
        loops = "-" if r["loops"] is None else str(r["loops"])
        loop_s = "-" if r["loop_s"] is None else f"{r['loop_s']:.1f}"
        print(
            f"| {label} | {r['ate_m']:.3f} | {r['ate_local_m']:.3f} | {r['revisit_m']:.3f} | "
            f"{r['height_spread_m']:.3f} | "
            f"{r['georef_s']:.1f} | {loops} | {loop_s} |"
        )
    print(
        f"\ngeoref stage with / without loop closures: {on['georef_s'] / off['georef_s']:.2f}x; the loop step is "
        f"{on['loop_s'] / kiss:.0%} of kiss-icp's {kiss:.1f} s on this drive"
    )
    print(f"working folder: {root}")


if __name__ == "__main__":
    main()
