"""How far kiss-icp (as ``mapkit build`` runs it) drifts on the tiny town: a coarse synthetic LiDAR
sweep (64 x 256 columns) against the presets' (64 x 512), in the same run.

For each sweep layout the tiny town is synthesized (or read with ``--town LABEL=DIR``), and
``mapkit.mapping.trajectory.trajectory_from_lidar`` runs on every session's log with the build's
default config. Against the truth (``mapkit.evaluation.truth.session_truth``) each session prints:

* KITTI's odometry metric: relative pose errors over every sub-path of 50, 100, 150 and 200 m
  (the tiny drives are 250 m; KITTI uses 100-800 m), starting every 10th scan, as translation in
  % of the distance and rotation in deg/100 m;
* ATE with the offset removed: RMSE of positions after a yaw-only rigid fit (4 DoF), as
  ``mapkit eval build`` removes the georeferencing offset;
* height drift: the estimate anchored at the first true pose (the town is flat, truth z = 0),
  largest |z error| over the drive and at its end;
* distance driven, estimated over true, and how many scans "slip" (estimated speed more than 30%
  below the true speed, counted above 1 m/s): kiss-icp's failure mode on the coarse sweep.

The ratio printed is each layout's translational drift over the coarse sweep's, per session.

    python bench/lidar_odometry_budget.py [--town coarse=/tmp/town256 --town default=/tmp/town] [--session NAME]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import report
from mapkit.core.geometry import interpolate_poses, invert_pose, rotation_angle_rad
from mapkit.evaluation.truth import session_truth
from mapkit.io import open_log
from mapkit.mapping.gps_align import fit_transform
from mapkit.mapping.trajectory import TrajectoryConfig, trajectory_from_lidar
from mapkit.synth import load_world, session_log, synthesize

#: the sweep layouts compared: 1.4 deg columns, on which kiss-icp slips on the flat road, and the presets' 0.7 deg
LAYOUTS = {"coarse": {"lidar": {"azimuth_steps": 256}}, "default": {"lidar": {"azimuth_steps": 512}}}
SEGMENTS_M = (50.0, 100.0, 150.0, 200.0)
STEP = 10  # KITTI's devkit starts a sub-path every 10th frame


def kitti_drift(gt: np.ndarray, est: np.ndarray, lengths=SEGMENTS_M, step: int = STEP) -> tuple[float, float, int]:
    """KITTI's odometry metric over poses of one drive: (translation %, rotation deg/100 m, sub-paths)."""
    dist = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1))]
    t_err, r_err = [], []
    for i in range(0, len(gt), step):
        for L in lengths:
            j = int(np.searchsorted(dist, dist[i] + L))
            if j >= len(gt):
                continue
            E = invert_pose(invert_pose(gt[i]) @ gt[j]) @ (invert_pose(est[i]) @ est[j])
            t_err.append(np.linalg.norm(E[:3, 3]) / L)
            r_err.append(float(rotation_angle_rad(E[None, :3, :3])[0]) / L)
    if not t_err:
        return float("nan"), float("nan"), 0
    return 100.0 * float(np.mean(t_err)), float(np.degrees(np.mean(r_err))) * 100.0, len(t_err)


def session_row(town: Path, name: str, cfg: TrajectoryConfig) -> dict:
    """kiss-icp on one session's log, measured against the town's truth."""
    log = open_log(session_log(town, name))
    t0 = time.perf_counter()
    try:
        traj = trajectory_from_lidar(log, "/lidar/points", cfg)
    finally:
        log.close()
    wall = time.perf_counter() - t0
    gs, gp = session_truth(town, name)
    gt, ok = interpolate_poses(gs, gp, traj.stamps_ns)
    est = gt[0] @ invert_pose(traj.world_from_base[ok][0]) @ traj.world_from_base[ok]  # anchored at the first true pose
    t_pct, r_deg, n = kitti_drift(gt, est)
    fit = fit_transform(est[:, :3, 3], gt[:, :3, 3], mode="yaw")
    ate = np.linalg.norm(est[:, :3, 3] @ fit[:3, :3].T + fit[:3, 3] - gt[:, :3, 3], axis=1)
    dz = est[:, 2, 3] - gt[:, 2, 3]
    dt = np.diff(traj.stamps_ns[ok]) * 1e-9
    v_gt = np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1) / dt
    v_est = np.linalg.norm(np.diff(est[:, :3, 3], axis=0), axis=1) / dt
    slips = int(np.sum((v_gt > 1.0) & (v_est < 0.7 * v_gt)))
    return {
        "session": name,
        "scans": int(ok.sum()),
        "distance_m": round(float(np.sum(v_gt * dt)), 1),
        "estimated_distance_m": round(float(np.sum(v_est * dt)), 1),
        "slipping_scans": slips,
        "drift_pct": round(t_pct, 3),
        "drift_deg_per_100m": round(r_deg, 3),
        "subpaths": n,
        "ate_offset_removed_m": round(float(np.sqrt(np.mean(ate**2))), 3),
        "height_drift_max_m": round(float(np.abs(dz).max()), 3),
        "height_drift_end_m": round(float(dz[-1]), 3),
        "kiss_icp_wall_s": round(wall, 1),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "--town",
        action="append",
        default=[],
        metavar="LABEL=DIR",
        help=f"an already synthesized town for a layout ({', '.join(LAYOUTS)}); others are synthesized",
    )
    ap.add_argument("--session", action="append", help="session name (repeatable; default: all)")
    args = ap.parse_args(argv)
    given = dict(t.split("=", 1) for t in args.town)
    unknown = set(given) - set(LAYOUTS)
    if unknown:
        raise SystemExit(f"--town labels are {', '.join(LAYOUTS)}, not {', '.join(sorted(unknown))}")
    cfg = TrajectoryConfig()
    rows = []
    with tempfile.TemporaryDirectory(prefix="lidar-odometry-budget-") as tmp:
        for label, overrides in LAYOUTS.items():
            town = (
                Path(given[label])
                if label in given
                else synthesize("tiny", Path(tmp) / label, overrides=overrides, progress=False)
            )
            world = load_world(town)
            steps = world.config.lidar.azimuth_steps
            if steps != overrides["lidar"]["azimuth_steps"]:
                raise SystemExit(
                    f"{town}: its sweep has {steps} columns; the {label} layout has "
                    f"{overrides['lidar']['azimuth_steps']}"
                )
            for name in args.session or [s["name"] for s in world.sessions]:
                row = {"layout": f"{label} ({world.config.lidar.beams} x {steps})", **session_row(town, name, cfg)}
                rows.append(row)
                print(row, flush=True)
    coarse = {r["session"]: r["drift_pct"] for r in rows if r["layout"].startswith("coarse")}
    for r in rows:
        r["ratio_to_coarse"] = round(r["drift_pct"] / coarse[r["session"]], 3) if coarse.get(r["session"]) else None
    report(
        "kiss-icp on the tiny town: KITTI drift, ATE and height drift per session, 256 vs 512 columns a sweep",
        rows,
        "ratio = translational drift (%) over the coarse sweep's on the same session",
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
