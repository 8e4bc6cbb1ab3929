"""The default georeferenced trajectory (one rigid GPS fit) against the factor-graph fusion, on the synthetic town.

    mapkit synth --preset tiny --out T
    mapkit build T/sessions/*/ --out W --config NOMAP.yaml      # NOMAP.yaml: "map: false" and "imagedb: false"
    python bench/factor_graph_budget.py W T

Per session, against the town's truth in the workspace frame: ATE (horizontal, vertical; absolute
and with the mean offset removed, which is what the GPS bias leaves), the height drift over the
drive (vertical error of the last tenth minus the first tenth; "offset removed" = after a yaw-only rigid fit
to truth, as ``mapkit eval build``), the pitch error, the fraction of
true positions inside their 95% ellipses (3-D chi-square, 7.815), and the seconds the graph takes
(preintegration or gravity, the solve, marginals) against the build's trajectory stage of the same run. Also
kiss-icp's error against truth as the odometry model states it (per-pose jitter plus a random walk, per axis;
:func:`odometry_noise_fit`): FactorGraphConfig's odometry defaults are tiny-sunny's fit.
The non-holonomic constraint's spread against truth (:func:`nhc_fit`): ``nhc_sigma_m_s``'s default is tiny-sunny's;
``--set nhc_sigma_m_s=0`` gives the graph without it.

The IMU is preintegrated by default with the town's own IMU noise (``world/config.yaml``, ``imu:``:
per-sample sigmas at ``rate_hz``, turned into densities; its constant biases' sigmas as the bias
priors); ``--no-imu`` fuses with the gravity direction instead (no IMU factors),
``--set`` overrides any FactorGraphConfig field after that.

Slips: the spans where kiss-icp's motion over 1 s differs from the truth's by more than
``--slip-m`` (evaluation side: found from the truth, never given to the graph); per span, the
error of the displacement across it (padded by 0.5 s) for kiss-icp, the rigid fit and the graph,
and the graph's largest offset-removed horizontal error inside it.
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
from mapkit.evaluation.evaluate import CHI2_95_3DOF
from mapkit.evaluation.truth import session_truth, ws_from_town
from mapkit.io import open_log
from mapkit.mapping.factor_graph import (
    FactorGraphConfig,
    GpsObservations,
    ImuObservations,
    fuse_session,
    gravity_from_imu,
)
from mapkit.mapping.gps_align import fit_transform
from mapkit.mapping.trajectory import Trajectory


def read_sensors(log_path: str, frame, body: str) -> tuple[GpsObservations, ImuObservations]:
    """GPS fixes in the workspace ENU frame and IMU samples with the base-from-IMU mount."""
    with open_log(log_path) as log:
        fixes = [f for f in log.records(StreamKind.GPS) if f.has_fix]
        imu = list(log.records(StreamKind.IMU))
        tree = FrameTree(log.transforms())
        base_from_gps = tree.lookup(body, fixes[0].frame_id)
        base_from_imu = tree.lookup(body, imu[0].frame_id)
    enu = frame.geodetic_to_enu([f.lat_deg for f in fixes], [f.lon_deg for f in fixes], [f.alt_m for f in fixes])
    gps = GpsObservations(
        np.array([f.stamp_ns for f in fixes], np.int64),
        enu,
        np.array([f.horizontal_sigma_m for f in fixes]),
        base_from_gps,
    )
    return gps, ImuObservations.from_samples(imu, base_from_imu)


def gps_mean_error(gps: GpsObservations, gt_stamps: np.ndarray, gt_ws: np.ndarray, cfg: FactorGraphConfig) -> dict:
    """The fixes' mean error against the true antenna positions (ENU m): over a drive of a minute it is
    nearly all the session's GPS bias, one draw, which no single-session graph can see. Its chi-square
    under the graph's own bias model (``gps_bias_sigma_m`` horizontally, times ``gps_vertical_sigma_factor``
    up) says whether that draw lies inside the model's 95% ellipsoid (7.81 for 3 dof)."""
    T, ok = interpolate_poses(gt_stamps, gt_ws, gps.stamps_ns)
    antenna = T[ok, :3, :3] @ gps.base_from_antenna[:3, 3] + T[ok, :3, 3]
    mean = np.mean(gps.enu[ok] - antenna, axis=0)
    sigma = cfg.gps_bias_sigma_m * np.array([1.0, 1.0, cfg.gps_vertical_sigma_factor])
    return {"mean_enu_m": mean.tolist(), "chi2_under_bias_model": float(np.sum((mean / sigma) ** 2))}


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


def max_h_error(fused, gt_stamps, gt_ws, mask) -> float:
    """Largest horizontal error of the fused poses in ``mask`` after the yaw-only rigid fit of the whole drive to
    truth."""
    gt, ok = interpolate_poses(gt_stamps, gt_ws, fused.stamps_ns)
    p = fused.enu_from_base[ok, :3, 3]
    fix = fit_transform(p, gt[:, :3, 3], mode="yaw")
    e = transform_points(fix, p) - gt[:, :3, 3]
    m = mask[ok]
    return float(np.max(np.linalg.norm(e[m, :2], axis=1))) if m.any() else float("nan")


def odometry_noise_fit(
    odom: Trajectory, gt_stamps, gt_ws, steps_m=(0.5, 1, 2, 4, 8, 16, 32), skip_s: float = 3.0
) -> dict:
    """kiss-icp's error against truth as FactorGraphConfig models it: per-pose white jitter plus a random walk in
    the distance driven. For each step length d, the robust (MAD) spread of the relative-motion error per axis (base
    frame: rotation roll/pitch/yaw, translation x/y/z) is fitted by var(d) = 2 jitter^2 + walk^2 d (non-negative
    least squares). The first and last ``skip_s`` are left out: starting from rest and the final braking are where
    kiss-icp slips, which the robust loss handles, not the Gaussian."""
    from scipy.optimize import nnls
    from scipy.spatial.transform import Rotation

    gt, ok = interpolate_poses(gt_stamps, gt_ws, odom.stamps_ns)
    est = odom.world_from_base[ok]
    t = (odom.stamps_ns[ok] - odom.stamps_ns[ok][0]) * 1e-9
    use = (t > skip_s) & (t < t[-1] - skip_s)
    s = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1))])
    rows, var = [], []
    for step in steps_m:
        e = []
        for i in np.nonzero(use)[0]:
            j = int(np.searchsorted(s, s[i] + step))
            if j >= len(s) or not use[j]:
                continue
            E = invert_pose(invert_pose(gt[i]) @ gt[j]) @ (invert_pose(est[i]) @ est[j])
            e.append(np.concatenate([Rotation.from_matrix(E[:3, :3]).as_rotvec(), E[:3, 3]]))
        if len(e) < 20:
            continue
        e = np.asarray(e)
        mad = 1.4826 * np.median(np.abs(e - np.median(e, axis=0)), axis=0)
        rows.append([2.0, step])
        var.append(mad**2)
    A, var = np.asarray(rows), np.asarray(var)
    fit = np.array([nnls(A, var[:, k])[0] for k in range(6)])  # (6, 2): jitter^2, walk^2
    return {"jitter": np.sqrt(fit[:, 0]).tolist(), "walk_per_sqrt_m": np.sqrt(fit[:, 1]).tolist()}


def nhc_fit(odom: Trajectory, gt_stamps, gt_ws, cfg: FactorGraphConfig) -> dict:
    """The non-holonomic constraint as FactorGraphConfig models it, against the truth: at the graph's keyframes, the
    true base's displacement across the chord of the odometry's heading change (half of it from the earlier
    keyframe's x axis), per second of the step (rms and robust spread, m/s); ``nhc_sigma_m_s``'s default is
    tiny-sunny's rms. Also the same with the truth's own heading change (what the car does: lane wander) and with
    the odometry's displacement (what kiss-icp's steps say, its sideways errors included)."""
    from mapkit.mapping.factor_graph import select_keyframes

    kf = select_keyframes(odom.stamps_ns, odom.world_from_base, cfg.keyframe_distance_m, cfg.keyframe_interval_s)
    gt, ok = interpolate_poses(gt_stamps, gt_ws, odom.stamps_ns[kf])
    est, st = odom.world_from_base[kf][ok], odom.stamps_ns[kf][ok]
    out = {}
    for label, heading, disp in (("model", est, gt), ("truth", gt, gt), ("odometry", est, est)):
        r = []
        for k in range(len(st) - 1):
            h = invert_pose(heading[k]) @ heading[k + 1]
            half = 0.5 * np.arctan2(h[1, 0], h[0, 0])
            t = (invert_pose(disp[k]) @ disp[k + 1])[:3, 3]
            r.append((np.cos(half) * t[1] - np.sin(half) * t[0]) / ((st[k + 1] - st[k]) * 1e-9))
        r = np.asarray(r)
        out[label] = {
            "rms_m_s": float(np.sqrt(np.mean(r**2))),
            "robust_m_s": float(1.4826 * np.median(np.abs(r - np.median(r)))),
        }
    return out


def town_imu_config(town: Path) -> dict:
    """FactorGraphConfig fields for the town's simulated IMU: white noise as densities (sigma / sqrt(rate)), its
    constant per-session biases' sigmas as the bias priors. The biases are constant there, but the random walk stays
    the library's (a trace over a drive; much less makes the bias chain's information 1e15 and the marginals
    singular)."""
    c = yaml.safe_load((town / "world" / "config.yaml").read_text()).get("imu") or {}
    if not c.get("enabled", False):
        return {}
    root = np.sqrt(float(c["rate_hz"]))
    return {
        "imu_gyro_noise_density": float(c["gyro_noise_rad_s"]) / root,
        "imu_accel_noise_density": float(c["accel_noise_m_s2"]) / root,
        "imu_gyro_bias_sigma": max(float(c["gyro_bias_rad_s"]), 1e-6),
        "imu_accel_bias_sigma": max(float(c["accel_bias_m_s2"]), 1e-6),
    }


def slip_spans(odom: Trajectory, gt_stamps, gt_ws, slip_m: float, window_s: float = 1.0) -> list[tuple[int, int]]:
    """Stamp spans (ns) where the odometry's relative motion over ``window_s`` misses the truth's by more than
    ``slip_m``."""
    gt, ok = interpolate_poses(gt_stamps, gt_ws, odom.stamps_ns)
    st, est = odom.stamps_ns[ok], odom.world_from_base[ok]
    w = int(window_s * 1e9)
    j = np.searchsorted(st, st + w)
    bad = []
    for i in np.nonzero(j < len(st))[0]:
        e = (invert_pose(est[i]) @ est[j[i]])[:3, 3] - (invert_pose(gt[i]) @ gt[j[i]])[:3, 3]
        if np.linalg.norm(e) > slip_m:
            bad.append((int(st[i]), int(st[j[i]])))
    spans: list[list[int]] = []
    for a, b in bad:
        if spans and a <= spans[-1][1]:
            spans[-1][1] = max(spans[-1][1], b)
        else:
            spans.append([a, b])
    return [(a, b) for a, b in spans]


def slip_errors(span, trajectories: dict, gt_stamps, gt_ws, pad_s: float = 0.5) -> dict:
    """Per trajectory: error (m) of its motion across the padded span against the truth's, in the span's first pose's
    frame (so that the odometry's own frame compares)."""
    a, b = span[0] - int(pad_s * 1e9), span[1] + int(pad_s * 1e9)
    out = {}
    for label, (stamps, poses) in trajectories.items():
        q = np.clip(np.array([a, b], np.int64), max(stamps[0], gt_stamps[0]), min(stamps[-1], gt_stamps[-1]))
        p, _ = interpolate_poses(stamps, poses, q)
        gq, _ = interpolate_poses(gt_stamps, gt_ws, q)
        out[label] = float(np.linalg.norm((invert_pose(p[0]) @ p[1])[:3, 3] - (invert_pose(gq[0]) @ gq[1])[:3, 3]))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("workspace", type=Path)
    ap.add_argument("town", type=Path)
    ap.add_argument("--no-gravity", action="store_true", help="Without the IMU: fuse GPS and odometry only.")
    ap.add_argument("--no-imu", action="store_true", help="Do not preintegrate the IMU (its gravity direction only).")
    ap.add_argument(
        "--slip-m", type=float, default=0.5, help="A 1 s odometry motion this far off the truth's is a slip."
    )
    ap.add_argument("--sessions", nargs="*", default=None, help="Only these sessions.")
    ap.add_argument(
        "--set", nargs="*", default=[], metavar="KEY=VALUE", help="FactorGraphConfig overrides (YAML values)."
    )
    ap.add_argument("--json", type=Path, default=None, help="Write the figures here too.")
    args = ap.parse_args()
    ws = Workspace(args.workspace)
    frame = ws.require_frame()
    town_to_ws = ws_from_town(args.town, frame)
    build = json.loads(ws.metrics.read_text())["sessions"]
    fields = {} if args.no_imu else town_imu_config(args.town)
    fields.update({k: yaml.safe_load(v) for k, v in (kv.split("=", 1) for kv in args.set)})
    cfg = FactorGraphConfig(**fields)
    rows, out, slip_rows = [], {}, []
    for name in ws.session_names():
        if args.sessions and name not in args.sessions:
            continue
        s = ws.session(name)
        odom = Trajectory.load(s.trajectory)
        georef = Trajectory.load(s.georef_trajectory)
        enu_from_odom = np.asarray(json.loads(s.gps_alignment.read_text())["enu_from_map"], np.float64)
        gt_stamps, gt = session_truth(args.town, name)
        gt_ws = town_to_ws @ gt
        t0 = time.perf_counter()
        gps, samples = read_sensors(build[name]["log"], frame, odom.body_frame)
        t_read = time.perf_counter() - t0
        t1 = time.perf_counter()
        gravity, imu = None, None
        if not args.no_imu:
            imu = samples
        elif not args.no_gravity:
            gravity = gravity_from_imu(
                samples.stamps_ns,
                samples.gyro_rad_s,
                samples.accel_m_s2,
                samples.base_from_imu,
                odom.stamps_ns,
                odom.world_from_base,
                odom.stamps_ns,
            )
        fused = fuse_session(
            odom.stamps_ns, odom.world_from_base, gps, gravity, cfg, enu_from_odom=enu_from_odom, source=name, imu=imu
        )
        t_graph = time.perf_counter() - t1
        traj_s = build[name]["stages"]["trajectory"]["seconds"]
        noise_fit = odometry_noise_fit(odom, gt_stamps, gt_ws)
        nhc = nhc_fit(odom, gt_stamps, gt_ws, cfg)
        before = errors(georef.stamps_ns, georef.world_from_base, gt_stamps, gt_ws)
        after = errors(fused.stamps_ns, fused.enu_from_base, gt_stamps, gt_ws, fused.covariances)
        geo_sig = np.sqrt(np.diag(fused.georef_covariance)[3:])
        spans = []
        for span in slip_spans(odom, gt_stamps, gt_ws, args.slip_m):
            errs = slip_errors(
                span,
                {
                    "kiss-icp": (odom.stamps_ns, odom.world_from_base),
                    "georef": (georef.stamps_ns, georef.world_from_base),
                    "fused": (fused.stamps_ns, fused.enu_from_base),
                },
                gt_stamps,
                gt_ws,
            )
            inside = (fused.stamps_ns >= span[0]) & (fused.stamps_ns <= span[1])
            t0 = odom.stamps_ns[0]
            spans.append(
                {
                    "from_s": (span[0] - t0) * 1e-9,
                    "to_s": (span[1] - t0) * 1e-9,
                    **errs,
                    "fused_max_h_err_offset_removed_m": max_h_error(fused, gt_stamps, gt_ws, inside),
                }
            )
            slip_rows.append(
                f"| {name} | {spans[-1]['from_s']:.1f}-{spans[-1]['to_s']:.1f} | {errs['kiss-icp']:.2f} | "
                f"{errs['georef']:.2f} | {errs['fused']:.2f} | {spans[-1]['fused_max_h_err_offset_removed_m']:.2f} |"
            )
        out[name] = {
            "georef": before,
            "fused": after,
            "seconds_read_sensors": t_read,
            "seconds_graph": t_graph,
            "seconds_trajectory_stage": traj_s,
            "odometry_noise_fit": noise_fit,
            "nhc_fit": nhc,
            "georef_sigma_enu_m": geo_sig.tolist(),
            "slips": spans,
            "stats": fused.stats,
            "gps_mean_error": gps_mean_error(gps, gt_stamps, gt_ws, cfg),
        }
        after["height_drift_sigma_m"] = fused.stats["end_minus_start_sigma_enu_m"][2]
        for label, r in (("georef (rigid fit)", before), ("fused (graph)", after)):
            sig = f" (1σ {r['height_drift_sigma_m']:.2f})" if "height_drift_sigma_m" in r else ""
            rows.append(
                f"| {name} | {label} | {r['ate_h_m']:.2f} | {r['ate_v_m']:.2f} | {r['ate_h_offset_removed_m']:.2f} | "
                f"{r['ate_v_offset_removed_m']:.2f} | {r['height_drift_m']:+.2f}{sig} | {r['height_p2p_m']:.2f} | "
                f"{r['pitch_err_mean_deg']:+.2f} / {r['pitch_err_rms_deg']:.2f} | "
                + (f"{100 * r['inside_95_3d']:.0f}% (NEES {r['nees_mean']:.1f}) |" if "inside_95_3d" in r else " |")
            )
    print(
        "| session | trajectory | ATE h m | ATE v m | ATE h m, offset removed | ATE v m, offset removed "
        "| height drift m (graph: its own 1σ, end minus start) | height p2p m | pitch err mean / rms deg "
        "| inside 95% ellipse |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    print("\n".join(rows))
    print()
    print(
        "| session | graph s (IMU or gravity + solve + marginals) | sensor read s | trajectory stage s | ratio "
        "| keyframes | GPS outliers (> 3.37 sigma) | georef sigma ENU m |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for name, r in out.items():
        st = r["stats"]
        print(
            f"| {name} | {r['seconds_graph']:.2f} | {r['seconds_read_sensors']:.2f} | "
            f"{r['seconds_trajectory_stage']:.1f} | {100 * r['seconds_graph'] / r['seconds_trajectory_stage']:.1f}% | "
            f"{st['keyframes']} | {st.get('gps_fixes_outliers', '')} of {st.get('gps_fixes', '')} | "
            f"{', '.join(f'{x:.2f}' for x in r['georef_sigma_enu_m'])} |"
        )
    print()
    print(
        "| session | kiss-icp jitter rot roll/pitch/yaw rad | trans x/y/z m | walk rot rad/sqrt(m) | trans m/sqrt(m) |"
    )
    print("|---|---|---|---|---|")

    def f(v):
        return ", ".join(f"{x:.1e}" for x in v)

    for name, r in out.items():
        j, w = r["odometry_noise_fit"]["jitter"], r["odometry_noise_fit"]["walk_per_sqrt_m"]
        print(f"| {name} | {f(j[:3])} | {f(j[3:])} | {f(w[:3])} | {f(w[3:])} |")
    print()
    print(
        "| session | across the chord, m/s: model (odometry's heading, true displacement) rms / robust "
        f"| the truth's own | the odometry's own | nhc_sigma_m_s = {cfg.nhc_sigma_m_s} |"
    )
    print("|---|---|---|---|---|")
    for name, r in out.items():
        n = r["nhc_fit"]
        print(
            f"| {name} | {n['model']['rms_m_s']:.4f} / {n['model']['robust_m_s']:.4f} | {n['truth']['rms_m_s']:.4f} / "
            f"{n['truth']['robust_m_s']:.4f} | {n['odometry']['rms_m_s']:.4f} / {n['odometry']['robust_m_s']:.4f} | |"
        )
    print()
    print(
        f"| session | slip span s (1 s motion > {args.slip_m} m off) | kiss-icp displacement err m | rigid fit m "
        "| graph m | graph max h err inside, offset removed m |"
    )
    print("|---|---|---|---|---|---|")
    print("\n".join(slip_rows))
    print()
    print(
        "| session | slips the graph found: span s (metres it moved the odometry) "
        "| drift / jitter factors down-weighted | IMU bias at the end: gyro rad/s; accel m/s^2 |"
    )
    print("|---|---|---|---|")
    for name, r in out.items():
        st = r["stats"]
        b = st.get("imu_bias_end")
        bias = (
            ""
            if b is None
            else (
                f"{', '.join(f'{x:+.4f}' for x in b['gyro_rad_s'])}; {', '.join(f'{x:+.3f}' for x in b['accel_m_s2'])}"
            )
        )
        found = ", ".join(
            f"{a:.1f}-{b_:.1f} ({m:.2f})" for (a, b_), m in zip(st["odom_slip_spans_s"], st["odom_slip_m"], strict=True)
        )
        print(
            f"| {name} | {found} | {st['odom_drift_downweighted']} / {st['odom_jitter_downweighted']} of "
            f"{st['keyframes']} | {bias} |"
        )
    total_graph = sum(r["seconds_graph"] for r in out.values())
    total_traj = sum(r["seconds_trajectory_stage"] for r in out.values())
    print()
    print(
        "| session | GPS fixes' mean error ENU m (the session's bias draw) "
        "| chi-square under the bias model (95%: 7.81) |"
    )
    print("|---|---|---|")
    for name, r in out.items():
        g = r["gps_mean_error"]
        print(f"| {name} | {', '.join(f'{v:+.2f}' for v in g['mean_enu_m'])} | {g['chi2_under_bias_model']:.1f} |")
    print(
        f"\ngraph / trajectory stage, all sessions: {total_graph:.2f} s / {total_traj:.1f} s = "
        f"{100 * total_graph / total_traj:.1f}%"
    )
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
