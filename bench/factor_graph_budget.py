"""Today's georeferenced trajectory (one rigid GPS fit) against the factor-graph fusion, on the synthetic town.

    mapkit synth --preset tiny --out T
    mapkit build T/sessions/*/ --out W --config NOMAP.yaml      # NOMAP.yaml: "map: false" and "imagedb: false"
    python bench/factor_graph_budget.py W T

Per session, against the town's truth in the workspace frame: ATE (horizontal, vertical; absolute
and with the mean offset removed, which is what the GPS bias leaves), the height drift over the
drive (vertical error of the last tenth minus the first tenth; "offset removed" = after a yaw-only rigid fit
to truth, as ``mapkit eval build``), the pitch error, the fraction of
true positions inside their 95% ellipses (3-D chi-square, 7.815), and the seconds the graph takes
(reading the IMU, gravity, the solve) against the build's trajectory stage of the same run. Also
kiss-icp's drift against truth over 1 m steps: the rates the odometry noise model states.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import yaml

from mapkit.core.frames import FrameTree
from mapkit.core.geometry import interpolate_poses, invert_pose, transform_points
from mapkit.core.types import StreamKind
from mapkit.core.workspace import Workspace
from mapkit.evaluation.truth import session_truth, ws_from_town
from mapkit.io import open_log
from mapkit.mapping.factor_graph import FactorGraphConfig, GpsObservations, fuse_session, gravity_from_imu
from mapkit.mapping.gps_align import fit_transform
from mapkit.mapping.trajectory import Trajectory

CHI2_95_3DOF = 7.815


def read_sensors(log_path: str, frame, body: str) -> tuple[GpsObservations, tuple]:
    """GPS fixes in the workspace ENU frame and IMU samples with the base-from-IMU mount."""
    with open_log(log_path) as log:
        fixes = [f for f in log.records(StreamKind.GPS) if f.has_fix]
        imu = list(log.records(StreamKind.IMU))
        tree = FrameTree(log.transforms())
        base_from_gps = tree.lookup(body, fixes[0].frame_id)
        base_from_imu = tree.lookup(body, imu[0].frame_id)
    enu = frame.geodetic_to_enu([f.lat_deg for f in fixes], [f.lon_deg for f in fixes], [f.alt_m for f in fixes])
    gps = GpsObservations(np.array([f.stamp_ns for f in fixes], np.int64), enu, np.array([f.horizontal_sigma_m for f in fixes]),
                          base_from_gps)
    imu_t = np.array([s.stamp_ns for s in imu], np.int64)
    gyro = np.stack([s.angular_velocity_rad_s for s in imu])
    accel = np.stack([s.linear_acceleration_m_s2 for s in imu])
    return gps, (imu_t, gyro, accel, base_from_imu)


def pitch_deg(poses: np.ndarray) -> np.ndarray:
    """Elevation of the base's x axis (forward) in degrees."""
    return np.degrees(np.arcsin(np.clip(poses[:, 2, 0], -1, 1)))


def errors(stamps, poses, gt_stamps, gt_ws, covs=None) -> dict:
    gt, ok = interpolate_poses(gt_stamps, gt_ws, stamps)
    e = poses[ok, :3, 3] - gt[:, :3, 3]
    fix = fit_transform(poses[ok, :3, 3], gt[:, :3, 3], mode="yaw")  # what eval build calls "offset removed"
    e0 = transform_points(fix, poses[ok, :3, 3]) - gt[:, :3, 3]
    n = len(e)
    tenth = max(1, n // 10)
    r = {
        "ate_h_m": float(np.sqrt(np.mean(np.sum(e[:, :2] ** 2, axis=1)))),
        "ate_v_m": float(np.sqrt(np.mean(e[:, 2] ** 2))),
        "ate_h_offset_removed_m": float(np.sqrt(np.mean(np.sum(e0[:, :2] ** 2, axis=1)))),
        "ate_v_offset_removed_m": float(np.sqrt(np.mean(e0[:, 2] ** 2))),
        "height_drift_m": float(e[-tenth:, 2].mean() - e[:tenth, 2].mean()),
        "height_p2p_m": float(np.ptp(e[:, 2])),
        "pitch_err_rms_deg": float(np.sqrt(np.mean((pitch_deg(poses[ok]) - pitch_deg(gt)) ** 2))),
        "pitch_err_mean_deg": float(np.mean(pitch_deg(poses[ok]) - pitch_deg(gt))),
    }
    if covs is not None:
        P = covs[ok][:, 3:, 3:]
        d2 = np.einsum("ni,ni->n", e, np.linalg.solve(P, e[:, :, None])[:, :, 0])
        r["inside_95_3d"] = float(np.mean(d2 <= CHI2_95_3DOF))
        r["nees_mean"] = float(d2.mean())
        r["sigma_enu_median_m"] = np.median(np.sqrt(np.diagonal(P, axis1=1, axis2=2)), axis=0).round(3).tolist()
    return r


def odometry_drift_rates(odom: Trajectory, gt_stamps, gt_ws, step_m: float = 1.0) -> tuple[float, float]:
    """kiss-icp's drift per sqrt(metre) against truth: the RMS per-axis rotation and translation error of
    relative motions over about ``step_m``, divided by sqrt(step)."""
    gt, ok = interpolate_poses(gt_stamps, gt_ws, odom.stamps_ns)
    est = odom.world_from_base[ok]
    s = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1))])
    from scipy.spatial.transform import Rotation

    rot, tr, d = [], [], []
    for i in range(len(s)):
        j = int(np.searchsorted(s, s[i] + step_m))
        if j >= len(s):
            break
        E = invert_pose(invert_pose(gt[i]) @ gt[j]) @ (invert_pose(est[i]) @ est[j])
        rot.append(Rotation.from_matrix(E[:3, :3]).as_rotvec())
        tr.append(E[:3, 3])
        d.append(s[j] - s[i])
    d = np.asarray(d)
    rot, tr = np.asarray(rot), np.asarray(tr)
    return float(np.sqrt(np.mean(rot**2 / d[:, None]))), float(np.sqrt(np.mean(tr**2 / d[:, None])))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("workspace", type=Path)
    ap.add_argument("town", type=Path)
    ap.add_argument("--no-gravity", action="store_true", help="Fuse GPS and odometry only.")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="FactorGraphConfig overrides (YAML values).")
    ap.add_argument("--json", type=Path, default=None, help="Write the figures here too.")
    args = ap.parse_args()
    ws = Workspace(args.workspace)
    frame = ws.require_frame()
    town_to_ws = ws_from_town(args.town, frame)
    build = json.loads(ws.metrics.read_text())["sessions"]
    cfg = FactorGraphConfig(**{k: yaml.safe_load(v) for k, v in (kv.split("=", 1) for kv in args.set)})
    rows, out = [], {}
    for name in ws.session_names():
        s = ws.session(name)
        odom = Trajectory.load(s.trajectory)
        georef = Trajectory.load(s.georef_trajectory)
        enu_from_odom = np.asarray(json.loads(s.gps_alignment.read_text())["enu_from_map"], np.float64)
        gt_stamps, gt = session_truth(args.town, name)
        gt_ws = town_to_ws @ gt
        t0 = time.perf_counter()
        gps, (imu_t, gyro, accel, base_from_imu) = read_sensors(build[name]["log"], frame, odom.body_frame)
        t_read = time.perf_counter() - t0
        t1 = time.perf_counter()
        gravity = None
        if not args.no_gravity:
            gravity = gravity_from_imu(imu_t, gyro, accel, base_from_imu, odom.stamps_ns, odom.world_from_base, odom.stamps_ns)
        fused = fuse_session(odom.stamps_ns, odom.world_from_base, gps, gravity, cfg, enu_from_odom=enu_from_odom, source=name)
        t_graph = time.perf_counter() - t1
        traj_s = build[name]["stages"]["trajectory"]["seconds"]
        rot_rate, tr_rate = odometry_drift_rates(odom, gt_stamps, gt_ws)
        before = errors(georef.stamps_ns, georef.world_from_base, gt_stamps, gt_ws)
        after = errors(fused.stamps_ns, fused.enu_from_base, gt_stamps, gt_ws, fused.covariances)
        geo_sig = np.sqrt(np.diag(fused.georef_covariance)[3:])
        out[name] = {"georef": before, "fused": after, "seconds_read_sensors": t_read, "seconds_graph": t_graph,
                     "seconds_trajectory_stage": traj_s, "odom_rot_rad_per_sqrt_m": rot_rate, "odom_trans_m_per_sqrt_m": tr_rate,
                     "georef_sigma_enu_m": geo_sig.tolist(), "stats": fused.stats}
        for label, r in (("georef (rigid fit)", before), ("fused (graph)", after)):
            rows.append(f"| {name} | {label} | {r['ate_h_m']:.2f} | {r['ate_v_m']:.2f} | {r['ate_h_offset_removed_m']:.2f} | "
                        f"{r['ate_v_offset_removed_m']:.2f} | {r['height_drift_m']:+.2f} | {r['height_p2p_m']:.2f} | "
                        f"{r['pitch_err_mean_deg']:+.2f} / {r['pitch_err_rms_deg']:.2f} | "
                        + (f"{100 * r['inside_95_3d']:.0f}% (NEES {r['nees_mean']:.1f}) |" if "inside_95_3d" in r else " |"))
    print("| session | trajectory | ATE h m | ATE v m | ATE h m, offset removed | ATE v m, offset removed | height drift m "
          "| height p2p m | pitch err mean / rms deg | inside 95% ellipse |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    print("\n".join(rows))
    print()
    print("| session | graph s (gravity + solve + marginals) | sensor read s | trajectory stage s | ratio | kiss-icp drift rot "
          "deg/sqrt(m) | trans m/sqrt(m) | keyframes | GPS outliers (> 3.37 sigma) | georef sigma ENU m |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name, r in out.items():
        st = r["stats"]
        print(f"| {name} | {r['seconds_graph']:.2f} | {r['seconds_read_sensors']:.2f} | {r['seconds_trajectory_stage']:.1f} | "
              f"{100 * r['seconds_graph'] / r['seconds_trajectory_stage']:.1f}% | {np.degrees(r['odom_rot_rad_per_sqrt_m']):.3f} | "
              f"{r['odom_trans_m_per_sqrt_m']:.4f} | {st['keyframes']} | {st.get('gps_fixes_outliers', '')} of {st.get('gps_fixes', '')} | "
              f"{', '.join(f'{x:.2f}' for x in r['georef_sigma_enu_m'])} |")
    total_graph = sum(r["seconds_graph"] for r in out.values())
    total_traj = sum(r["seconds_trajectory_stage"] for r in out.values())
    print(f"\ngraph / trajectory stage, all sessions: {total_graph:.2f} s / {total_traj:.1f} s = {100 * total_graph / total_traj:.1f}%")
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
