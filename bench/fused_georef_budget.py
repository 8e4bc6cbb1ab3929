"""The rigid GPS fit against the factor graph (``georef: {fuse: true}``) on one straight synthetic drive, as the map
sees them.

    python bench/fused_georef_budget.py [--out DIR] [--set KEY=VALUE ...]

The drive is ``tests/test_build_synth.py``'s: 80 m of the tiny town, GPS with white noise and
multipath but no bias. It is built twice into one workspace's copies, once with the default rigid
fit and once fused, and each trajectory is scored against the town's truth: frame-to-frame motion
error (median, mm: what the semi-dense mapper's epipolar geometry needs), mean roll and pitch error
(deg: what places map points far from the road), position error after removing the mean offset, and
the map's median distance to the true surfaces with the offset removed (``mapkit eval build``).
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np
import yaml
from scipy.spatial.transform import Rotation

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from test_build_synth import OVERRIDES  # noqa: E402 (after sys.path points at this checkout's tests)

from mapkit.core.geometry import interpolate_poses, invert_pose  # noqa: E402 (after sys.path points at this checkout)
from mapkit.core.workspace import Workspace  # noqa: E402 (after sys.path points at this checkout)
from mapkit.evaluation.evaluate import evaluate_build  # noqa: E402 (after sys.path points at this checkout)
from mapkit.evaluation.truth import session_truth, ws_from_town  # noqa: E402 (after sys.path points at this checkout)
from mapkit.mapping.build import build  # noqa: E402 (after sys.path points at this checkout)
from mapkit.mapping.trajectory import Trajectory  # noqa: E402 (after sys.path points at this checkout)
from mapkit.synth import session_log, synthesize  # noqa: E402 (after sys.path points at this checkout)


def score(traj: Trajectory, stamps: np.ndarray, truth: np.ndarray) -> dict:
    gt, ok = interpolate_poses(stamps, truth, traj.stamps_ns)
    est = traj.world_from_base[ok]

    def rel(T):
        return invert_pose(T[:-1]) @ T[1:]

    step = invert_pose(rel(gt)) @ rel(est)
    d = est[:, :3, 3] - gt[:, :3, 3]
    d -= d.mean(axis=0)
    rpy = Rotation.from_matrix(np.swapaxes(gt[:, :3, :3], 1, 2) @ est[:, :3, :3]).as_euler("xyz", degrees=True)
    return {
        "step_mm": float(np.median(np.linalg.norm(step[:, :3, 3], axis=1)) * 1000),
        "roll_deg": float(rpy[:, 0].mean()),
        "pitch_deg": float(rpy[:, 1].mean()),
        "ate_offset_removed_m": float(np.sqrt((d**2).sum(axis=1).mean())),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=None, help="working folder (default: a temporary one)")
    ap.add_argument(
        "--set",
        nargs="*",
        default=[],
        metavar="KEY=VALUE",
        help="FactorGraphConfig overrides for the fused build (YAML values), e.g. nhc_sigma_m_s=0 for the graph "
        "without the non-holonomic constraint",
    )
    args = ap.parse_args()
    root = args.out or Path(tempfile.mkdtemp(prefix="mapkit-fused-"))
    town = root / "town"
    if not (town / "world").is_dir():
        synthesize(preset="tiny", out=town, overrides=OVERRIDES, progress=False)
    log = session_log(town, "drive")
    rigid_ws = Path(build([log], root / "rigid", progress=False))
    fused_ws = root / "fused"
    if not fused_ws.exists():
        shutil.copytree(rigid_ws, fused_ws)  # the trajectory stage is kept, georef and map redone
    fg = {k: yaml.safe_load(v) for k, v in (kv.split("=", 1) for kv in args.set)}
    (root / "fuse.yaml").write_text(yaml.safe_dump({"georef": {"fuse": True, **({"factor_graph": fg} if fg else {})}}))
    build([log], fused_ws, config=root / "fuse.yaml", progress=False)
    stamps, truth = session_truth(town, "drive")
    truth = ws_from_town(town, Workspace(rigid_ws).frame()) @ truth
    rows = []
    for label, ws, traj_dir in (
        ("rigid fit", rigid_ws, Workspace(rigid_ws).session("drive").georef_trajectory),
        ("factor graph", fused_ws, Workspace(fused_ws).session("drive").fused_trajectory),
    ):
        s = score(Trajectory.load(traj_dir), stamps, truth)
        m = evaluate_build(ws, town)["sessions"]["drive"]["map_local"]
        rows.append(
            f"| {label} | {s['step_mm']:.1f} | {s['roll_deg']:+.3f} / {s['pitch_deg']:+.3f} | "
            f"{s['ate_offset_removed_m']:.3f} | "
            f"{m['median_distance_m']:.3f} / {m['fraction_within_0.5m']:.3f} |"
        )
    print(
        "| trajectory | frame-to-frame motion error, median mm | roll / pitch error, mean deg | ATE, offset removed m "
        "| map to true surfaces, offset removed: median m / within 0.5 m |"
    )
    print("|---|---|---|---|---|")
    print("\n".join(rows))
    print(f"\nworking folder: {root}")


if __name__ == "__main__":
    main()
