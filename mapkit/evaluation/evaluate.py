"""``mapkit eval build``: a built workspace against the synthetic town's ground truth.

Per session: the absolute trajectory error of the GPS-aligned trajectory (no further alignment:
what a map user gets), the GPS fixes' own error for comparison, and the semi-dense map's distance
to the true surfaces (the town's mesh plus that session's parked cars), with points per 100 m.
The truth lives in the town's ENU frame; it is moved exactly (through ECEF) into the workspace's.
"""

from __future__ import annotations

import json
from pathlib import Path


import numpy as np

from mapkit.core.errors import InputError
from mapkit.core.geodesy import WORKSPACE_ORIGIN, LocalFrame, read_workspace_frame
from mapkit.core.geometry import interpolate_poses, sim3_scale, transform_points
from mapkit.mapping.gps_align import fit_transform
from mapkit.evaluation.metrics import map_accuracy, trajectory_errors
from mapkit.evaluation.truth import error_transforms, session_truth, session_truth_mesh, ws_from_town
from mapkit.core.runio import atomic_write_text, write_json
from mapkit.mapping.trajectory import Trajectory










def evaluate_build(workspace: str | Path, truth: str | Path) -> dict:
    import open3d as o3d

    workspace, truth = Path(workspace), Path(truth)
    ws_frame = read_workspace_frame(workspace)
    if ws_frame is None:
        raise InputError(workspace / WORKSPACE_ORIGIN, "the workspace is not georeferenced (no origin.json): nothing to compare with truth")
    town_to_ws = ws_from_town(truth, ws_frame)
    mesh = o3d.io.read_triangle_mesh(str(truth / "world" / "mesh.ply"))
    if not mesh.has_triangles():
        raise InputError(truth / "world" / "mesh.ply", "holds no triangles")
    mesh.transform(town_to_ws)
    results: dict = {"workspace": str(workspace), "truth": str(truth), "sessions": {}}
    for sdir in sorted((workspace / "sessions").iterdir()):
        name = sdir.name
        try:
            gt_stamps, gt_world_from_base = session_truth(truth, name)
        except (FileNotFoundError, InputError):
            continue
        gt_ws = town_to_ws @ gt_world_from_base
        ga_path = sdir / "georef" / "gps_alignment.json"
        georeferenced = ga_path.is_file() and json.loads(ga_path.read_text()).get("georeferenced", False)
        r: dict = {"georeferenced": bool(georeferenced)}
        traj_dir = sdir / "georef" / "trajectory_enu"
        est = Trajectory.load(traj_dir) if traj_dir.is_dir() else None
        fix = None
        if est is not None:
            r["trajectory_local"], fix = _offset_removed_errors(est, gt_stamps, gt_ws)
            if georeferenced:  # absolute figures only mean something in the georeferenced frame
                r["trajectory"] = _absolute_errors(est, gt_stamps, gt_ws)
            r["gps_alone"] = _gps_error(workspace, sdir, gt_stamps, gt_ws, ws_frame)
        map_dir = sdir / "map"
        if (map_dir / ".done").is_file():
            from mapkit.mapping.semidense import SemiDenseMap

            smap = SemiDenseMap.load(map_dir)
            session_mesh = session_truth_mesh(mesh, truth, name, town_to_ws)
            length = float(np.linalg.norm(np.diff(gt_ws[:, :3, 3], axis=0), axis=1).sum())
            if georeferenced:
                r["map"] = map_accuracy(smap.points_world, session_mesh, road_length_m=length)
            if fix is not None:
                r["map_local"] = map_accuracy(transform_points(fix, smap.points_world), session_mesh, road_length_m=length)
                r["map_local"]["driven_m"] = length
        results["sessions"][name] = r
    write_json(workspace / "eval_build.json", results)
    atomic_write_text(workspace / "eval_build.md", format_eval(results))
    return results




def _errors(stamps, poses, gt_stamps, gt_poses) -> dict:
    return {k: v for k, v in trajectory_errors(stamps, poses, gt_stamps, gt_poses).items() if k != "per_pose_translation_m"}


def _gps_error(workspace: Path, sdir: Path, gt_stamps, gt_ws, frame: LocalFrame) -> dict:
    """Horizontal error of the session's raw GPS fixes against the true base position.

    The antenna's lever arm is not applied: on the synthetic car it is 0.3 m along the heading.
    """
    from mapkit.io import open_log
    from mapkit.core.types import StreamKind

    meta_path = workspace / "metrics.json"
    meta = json.loads(meta_path.read_text()) if meta_path.is_file() else {}
    log_path = meta.get("sessions", {}).get(sdir.name, {}).get("log")
    if not log_path or not Path(log_path).exists():  # a .mcap file or a rosbag2 folder
        return {}
    with open_log(log_path) as log:
        fixes = [f for f in log.records(StreamKind.GPS) if f.has_fix]
    if not fixes:
        return {}
    stamps = np.array([f.stamp_ns for f in fixes], np.int64)
    enu = frame.geodetic_to_enu([f.lat_deg for f in fixes], [f.lon_deg for f in fixes], [f.alt_m for f in fixes])
    gt, ok = interpolate_poses(gt_stamps, gt_ws, stamps)
    d = np.linalg.norm(enu[ok, :2] - gt[:, :2, 3], axis=1)
    return {"fixes": int(ok.sum()), "horizontal_rmse_m": float(np.sqrt(np.mean(d**2))), "horizontal_median_m": float(np.median(d))}


def format_eval(results: dict) -> str:
    lines = [
        "| session | georef. | ATE RMSE m | horizontal RMSE m | mean offset ENU m | ATE RMSE m, offset removed | GPS alone horiz. RMSE m "
        "| rot median deg | map points | to mesh, as georeferenced: median m / within 0.5 m | to mesh, offset removed: median m / within 0.5 m "
        "| points / 100 m |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    f = lambda v, p=2: "" if v is None else f"{v:.{p}f}"  # noqa: E731
    for name, r in results["sessions"].items():
        t, g, m, ml = r.get("trajectory", {}), r.get("gps_alone", {}), r.get("map", {}), r.get("map_local", {})
        off = t.get("mean_offset_enu_m")
        lines.append(
            f"| {name} | {'yes' if r.get('georeferenced') else 'NO'} | {f(t.get('ate_rmse_m'))} | {f(t.get('horizontal_rmse_m'))} | "
            f"{'' if off is None else ', '.join(f'{x:.1f}' for x in off)} | {f(r.get('trajectory_local', {}).get('ate_rmse_m'))} | "
            f"{f(g.get('horizontal_rmse_m'))} | "
            f"{f((t or r.get('trajectory_local', {})).get('rotation_median_deg'))} | {ml.get('points', '')} | "
            f"{f(m.get('median_distance_m'), 3)} / {f(m.get('fraction_within_0.5m'), 3)} | "
            f"{f(ml.get('median_distance_m'), 3)} / {f(ml.get('fraction_within_0.5m'), 3)} | {f(ml.get('points_per_100m'), 0)} |"
        )
    return "\n".join(lines) + "\n"




def _absolute_errors(est: Trajectory, gt_stamps: np.ndarray, gt_ws: np.ndarray) -> dict:
    """``_errors`` of a trajectory as it stands in the workspace frame, with its mean offset (east,
    north, up): a georeferencing bias shows as the offset."""
    r = _errors(est.stamps_ns, est.world_from_base, gt_stamps, gt_ws)
    g, ok = interpolate_poses(gt_stamps, gt_ws, est.stamps_ns)
    r["mean_offset_enu_m"] = [float(x) for x in (est.world_from_base[ok, :3, 3] - g[:, :3, 3]).mean(axis=0)]
    return r


def _offset_removed_errors(est: Trajectory, gt_stamps: np.ndarray, gt_ws: np.ndarray) -> tuple[dict, np.ndarray]:
    """``_errors`` after the offset is removed by a rigid fit of the trajectory to truth, as SLAM
    evaluations align before measuring (what is left is the trajectory's shape: odometry drift),
    and that fit. Yaw-only, since gravity is known and a nearly straight drive leaves roll about
    it unobservable."""
    gt_i, ok = interpolate_poses(gt_stamps, gt_ws, est.stamps_ns)
    fix = fit_transform(est.world_from_base[ok, :3, 3], gt_i[:, :3, 3], mode="yaw")
    r = _errors(est.stamps_ns, fix @ est.world_from_base, gt_stamps, gt_ws)
    # the trajectory's scale error: what a fit that may also scale finds (not applied)
    r["scale_vs_truth"] = sim3_scale(fit_transform(est.world_from_base[ok, :3, 3], gt_i[:, :3, 3], mode="yaw_scale"))
    return r, fix


def evaluate_align(workspace: str | Path, truth: str | Path, max_points_per_pair: int = 5000, overlap_m: float = 25.0) -> dict:
    """Inter-session misalignment of the same true surface, after GPS alone and after ``mapkit align``.

    A session's map puts a true point x at E(x) x, with E = T_est T_gt^-1 of the session's pose
    nearest to x. For two sessions that both drove within ``overlap_m`` of a map point, their
    misalignment there is |E_A x - E_B x|: medians per session pair, before (GPS alone: the
    ``georef`` trajectories) and after (the ``align`` trajectories). Also the true error of every
    accepted ICP registration, at its support points, and each session's absolute trajectory
    error before and after: alignment leaves all sessions with one common offset, the mean of
    their GPS biases.
    """
    from scipy.spatial import cKDTree

    from mapkit.multisession.align import PairResult, _support_points
    from mapkit.mapping.semidense import SemiDenseMap

    workspace, truth = Path(workspace), Path(truth)
    ws_frame = LocalFrame.from_dict(json.loads((workspace / "origin.json").read_text()))
    town_to_ws = ws_from_town(truth, ws_frame)
    al = workspace / "align"
    if not (al / ".done").is_file():
        raise InputError(al, "multi-session alignment has not finished (run mapkit align first)")
    names = json.loads((al / ".done").read_text())["sessions"]
    rng = np.random.default_rng(0)
    sess: dict = {}
    traj: dict = {}
    for name in names:
        gt_stamps, gt = session_truth(truth, name)
        gt_ws = town_to_ws @ gt
        before = Trajectory.load(workspace / "sessions" / name / "georef" / "trajectory_enu")
        after = Trajectory.load(al / "sessions" / name / "trajectory")
        pb, Eb = error_transforms(before.stamps_ns, before.world_from_base, gt_stamps, gt_ws)
        pa, Ea = error_transforms(after.stamps_ns, after.world_from_base, gt_stamps, gt_ws)
        pts = SemiDenseMap.load(al / "sessions" / name / "map").points_world
        sess[name] = {"tree": cKDTree(pb[:, :2]), "Eb": Eb, "Ea": Ea, "points": pts}
        traj[name] = {when: _absolute_errors(t, gt_stamps, gt_ws) for when, t in (("gps", before), ("aligned", after))}
        for when, t in (("gps", before), ("aligned", after)):
            traj[name][when]["offset_removed"] = _offset_removed_errors(t, gt_stamps, gt_ws)[0]
    out: dict = {"pairs": {}, "trajectories": traj}
    all_b, all_a = [], []
    for i, na in enumerate(names):
        for nb in names[i + 1 :]:
            A, B = sess[na], sess[nb]
            pts = A["points"]
            if len(pts) > max_points_per_pair * 4:
                pts = pts[rng.choice(len(pts), max_points_per_pair * 4, replace=False)]
            dB, kB = B["tree"].query(pts[:, :2])
            near = dB < overlap_m
            if near.sum() < 50:
                continue
            pts, kB = pts[near], kB[near]
            if len(pts) > max_points_per_pair:
                sel = rng.choice(len(pts), max_points_per_pair, replace=False)
                pts, kB = pts[sel], kB[sel]
            _, kA = A["tree"].query(pts[:, :2])
            res = {}
            for when in ("Eb", "Ea"):
                xa = np.einsum("nij,nj->ni", A[when][kA][:, :3, :3], pts) + A[when][kA][:, :3, 3]
                xb = np.einsum("nij,nj->ni", B[when][kB][:, :3, :3], pts) + B[when][kB][:, :3, 3]
                res[when] = np.linalg.norm(xa - xb, axis=1)
            all_b.append(res["Eb"])
            all_a.append(res["Ea"])
            out["pairs"][f"{na} / {nb}"] = {"points": int(len(pts)), "before_median_m": float(np.median(res["Eb"])),
                                            "after_median_m": float(np.median(res["Ea"])),
                                            "after_p90_m": float(np.percentile(res["Ea"], 90))}
    per_pair_after = [v["after_median_m"] for v in out["pairs"].values()]
    out["before_median_m"] = float(np.median(np.concatenate(all_b))) if all_b else None
    out["after_median_m"] = float(np.median(np.concatenate(all_a))) if all_a else None
    out["pairs_after_median_below_0.2m"] = int(sum(v < 0.2 for v in per_pair_after))
    out["pairs_evaluated"] = len(per_pair_after)
    # true error of the accepted registrations (measured on the maps as built: the "before" frames)
    reg = json.loads((al / "pairs.json").read_text())["pairs"]
    errs = []
    for r in (PairResult.from_dict(v) for v in reg):
        if not r.accepted or r.source[0] not in sess or r.target[0] not in sess:
            continue
        A, B = sess[r.source[0]], sess[r.target[0]]
        _, kA = A["tree"].query(r.centre[:2])
        _, kB = B["tree"].query(r.centre[:2])
        T_true = B["Eb"][kB] @ np.linalg.inv(A["Eb"][kA])
        P = _support_points(r.centre, np.array([1.0, 0.0, 0.0]), 10.0)
        d = (P @ r.target_from_source[:3, :3].T + r.target_from_source[:3, 3]) - (P @ T_true[:3, :3].T + T_true[:3, 3])
        errs.append(float(np.linalg.norm(d, axis=1).max()))
    errs_a = np.asarray(errs)
    out["accepted_pairs"] = int(len(errs_a))
    out["accepted_pair_true_error_median_m"] = float(np.median(errs_a)) if len(errs_a) else None
    out["accepted_pair_true_error_max_m"] = float(errs_a.max()) if len(errs_a) else 0.0
    out["accepted_pairs_true_error_above_1m"] = int((errs_a > 1.0).sum())
    write_json(al / "eval_align.json", out)
    from mapkit.multisession.align import format_align_truth

    atomic_write_text(al / "eval_align.md", "# Multi-session alignment against the synthetic truth\n\n" + format_align_truth(out) + "\n")
    return out
