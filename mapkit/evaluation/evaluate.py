"""``mapkit eval build``: a built workspace against the synthetic town's ground truth.

Per session: the absolute trajectory error of the GPS-aligned trajectory (no further alignment:
what a map user gets), the GPS fixes' own error for comparison, and the semi-dense map's distance
to the true surfaces (the town's mesh plus that session's parked cars), with points per 100 m.
The truth lives in the town's ENU frame; it is moved exactly (through ECEF) into the workspace's.

``mapkit eval align``: the inter-session misalignment of the same true surface before and after
``mapkit align`` (:func:`evaluate_align`, its table :func:`format_align_truth`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mapkit.core.errors import InputError
from mapkit.core.geodesy import LocalFrame
from mapkit.core.geometry import interpolate_poses, sim3_scale, transform_points
from mapkit.core.runio import atomic_write_text, write_json
from mapkit.core.types import StreamKind
from mapkit.core.workspace import SessionDirs, Workspace
from mapkit.evaluation.metrics import map_accuracy, trajectory_errors
from mapkit.evaluation.truth import error_transforms, session_truth, session_truth_mesh, ws_from_town
from mapkit.io import open_log
from mapkit.mapping.gps_align import fit_transform
from mapkit.mapping.semidense import SemiDenseMap
from mapkit.mapping.trajectory import Trajectory
from mapkit.multisession.align import PairResult, _support_points


def evaluate_build(workspace: str | Path | Workspace, truth: str | Path) -> dict:
    """Every session of the workspace that the town knows, against its truth; writes
    ``eval_build.json`` and ``eval_build.md`` into the workspace."""
    import open3d as o3d

    ws, truth = Workspace(workspace), Path(truth)
    ws_frame = ws.require_frame("nothing to compare with truth")
    town_to_ws = ws_from_town(truth, ws_frame)
    mesh = o3d.io.read_triangle_mesh(str(truth / "world" / "mesh.ply"))
    if not mesh.has_triangles():
        raise InputError(truth / "world" / "mesh.ply", "holds no triangles")
    mesh.transform(town_to_ws)
    results: dict = {"workspace": str(ws.root), "truth": str(truth), "sessions": {}}
    for name in ws.session_names():
        try:
            gt_stamps, gt_world_from_base = session_truth(truth, name)
        except (FileNotFoundError, InputError):
            continue
        results["sessions"][name] = _evaluate_session(ws, ws.session(name), truth, mesh, town_to_ws, ws_frame,
                                                      gt_stamps, town_to_ws @ gt_world_from_base)
    write_json(ws.eval_build_json, results)
    atomic_write_text(ws.eval_build_md, format_eval(results))
    return results


def _evaluate_session(ws: Workspace, s: SessionDirs, truth: Path, mesh, town_to_ws: np.ndarray, ws_frame: LocalFrame,
                      gt_stamps: np.ndarray, gt_ws: np.ndarray) -> dict:
    """One session's entry of ``eval_build.json``: trajectory and map against the truth, absolute
    figures only when the session is georeferenced (they mean nothing otherwise)."""
    georeferenced = s.gps_alignment.is_file() and json.loads(s.gps_alignment.read_text()).get("georeferenced", False)
    r: dict = {"georeferenced": bool(georeferenced)}
    est = Trajectory.load(s.georef_trajectory) if s.georef_trajectory.is_dir() else None
    fix = None
    if est is not None:
        r["trajectory_local"], fix = _offset_removed_errors(est, gt_stamps, gt_ws)
        if georeferenced:
            r["trajectory"] = _absolute_errors(est, gt_stamps, gt_ws)
        r["gps_alone"] = _gps_error(ws, s.name, gt_stamps, gt_ws, ws_frame)
    if s.has("map"):
        from mapkit.mapping.semidense import SemiDenseMap

        smap = SemiDenseMap.load(s.map)
        session_mesh = session_truth_mesh(mesh, truth, s.name, town_to_ws)
        length = float(np.linalg.norm(np.diff(gt_ws[:, :3, 3], axis=0), axis=1).sum())
        if georeferenced:
            r["map"] = map_accuracy(smap.points_world, session_mesh, road_length_m=length)
        if fix is not None:
            r["map_local"] = map_accuracy(transform_points(fix, smap.points_world), session_mesh, road_length_m=length)
            r["map_local"]["driven_m"] = length
    return r


def _errors(stamps, poses, gt_stamps, gt_poses) -> dict:
    return {k: v for k, v in trajectory_errors(stamps, poses, gt_stamps, gt_poses).items() if k != "per_pose_translation_m"}


def _gps_error(ws: Workspace, name: str, gt_stamps, gt_ws, frame: LocalFrame) -> dict:
    """Horizontal error of the session's raw GPS fixes against the true base position.

    The antenna's lever arm is not applied: on the synthetic car it is 0.3 m along the heading.
    """

    meta = json.loads(ws.metrics.read_text()) if ws.metrics.is_file() else {}
    log_path = meta.get("sessions", {}).get(name, {}).get("log")
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


# --------------------------------------------------------------------------- mapkit eval align


@dataclass
class _SessionError:
    """One aligned session's error field: E = T_est T_gt^-1 at each of its poses, before (the
    ``georef`` trajectory, GPS alone) and after ``mapkit align``, looked up by the nearest pose."""

    tree: Any  # cKDTree of the "before" positions (east, north)
    before: np.ndarray  # (n, 4, 4)
    after: np.ndarray  # (n, 4, 4)
    points: np.ndarray  # (m, 3) the aligned map's points

    def nearest(self, xy: np.ndarray) -> np.ndarray:
        return self.tree.query(xy)[1]


def evaluate_align(workspace: str | Path | Workspace, truth: str | Path, max_points_per_pair: int = 5000,
                   overlap_m: float = 25.0) -> dict:
    """Inter-session misalignment of the same true surface, after GPS alone and after ``mapkit align``.

    A session's map puts a true point x at E(x) x, with E = T_est T_gt^-1 of the session's pose
    nearest to x. For two sessions that both drove within ``overlap_m`` of a map point, their
    misalignment there is |E_A x - E_B x|: medians per session pair, before (GPS alone: the
    ``georef`` trajectories) and after (the ``align`` trajectories). Also the true error of every
    accepted ICP registration, at its support points, and each session's absolute trajectory
    error before and after: alignment leaves all sessions with one common offset, the mean of
    their GPS biases. Writes ``eval_align.json`` and ``.md`` into the align folder.
    """
    ws, truth = Workspace(workspace), Path(truth)
    town_to_ws = ws_from_town(truth, ws.require_frame())
    if not ws.align_done.is_file():
        raise InputError(ws.align_dir, "multi-session alignment has not finished (run mapkit align first)")
    names = ws.aligned_sessions()
    sess, traj = _session_errors(ws, truth, names, town_to_ws)
    out: dict = {"pairs": {}, "trajectories": traj}
    out.update(_pair_misalignment(sess, names, max_points_per_pair, overlap_m, out["pairs"]))
    out.update(_registration_errors(ws, sess))
    write_json(ws.eval_align_json, out)
    atomic_write_text(ws.eval_align_md,
                      "# Multi-session alignment against the synthetic truth\n\n" + format_align_truth(out) + "\n")
    return out


def _session_errors(ws: Workspace, truth: Path, names: list[str], town_to_ws: np.ndarray) -> tuple[dict[str, _SessionError], dict]:
    """Each aligned session's error field, and its absolute trajectory errors (as it stands and
    with the offset removed) before (``gps``) and after (``aligned``) alignment."""
    from scipy.spatial import cKDTree

    sess: dict[str, _SessionError] = {}
    traj: dict = {}
    for name in names:
        gt_stamps, gt = session_truth(truth, name)
        gt_ws = town_to_ws @ gt
        before = Trajectory.load(ws.session(name).georef_trajectory)
        after = Trajectory.load(ws.aligned(name).trajectory)
        pb, Eb = error_transforms(before.stamps_ns, before.world_from_base, gt_stamps, gt_ws)
        _, Ea = error_transforms(after.stamps_ns, after.world_from_base, gt_stamps, gt_ws)
        sess[name] = _SessionError(cKDTree(pb[:, :2]), Eb, Ea, SemiDenseMap.load(ws.aligned(name).map).points_world)
        traj[name] = {when: _absolute_errors(t, gt_stamps, gt_ws) for when, t in (("gps", before), ("aligned", after))}
        for when, t in (("gps", before), ("aligned", after)):
            traj[name][when]["offset_removed"] = _offset_removed_errors(t, gt_stamps, gt_ws)[0]
    return sess, traj


def _pair_misalignment(sess: dict[str, _SessionError], names: list[str], max_points_per_pair: int, overlap_m: float,
                       pairs: dict) -> dict:
    """Fills ``pairs`` with the misalignment of every session pair that overlaps (50 points at
    least), sampled on the first session's map points; returns the pooled figures."""
    rng = np.random.default_rng(0)
    all_b, all_a = [], []
    for i, na in enumerate(names):
        for nb in names[i + 1 :]:
            A, B = sess[na], sess[nb]
            pts = A.points
            if len(pts) > max_points_per_pair * 4:
                pts = pts[rng.choice(len(pts), max_points_per_pair * 4, replace=False)]
            dB, kB = B.tree.query(pts[:, :2])
            near = dB < overlap_m
            if near.sum() < 50:
                continue
            pts, kB = pts[near], kB[near]
            if len(pts) > max_points_per_pair:
                sel = rng.choice(len(pts), max_points_per_pair, replace=False)
                pts, kB = pts[sel], kB[sel]
            kA = A.nearest(pts[:, :2])
            res = {}
            for when in ("before", "after"):
                Ta, Tb = getattr(A, when)[kA], getattr(B, when)[kB]
                xa = np.einsum("nij,nj->ni", Ta[:, :3, :3], pts) + Ta[:, :3, 3]
                xb = np.einsum("nij,nj->ni", Tb[:, :3, :3], pts) + Tb[:, :3, 3]
                res[when] = np.linalg.norm(xa - xb, axis=1)
            all_b.append(res["before"])
            all_a.append(res["after"])
            pairs[f"{na} / {nb}"] = {"points": int(len(pts)), "before_median_m": float(np.median(res["before"])),
                                     "after_median_m": float(np.median(res["after"])),
                                     "after_p90_m": float(np.percentile(res["after"], 90))}
    per_pair_after = [v["after_median_m"] for v in pairs.values()]
    return {
        "before_median_m": float(np.median(np.concatenate(all_b))) if all_b else None,
        "after_median_m": float(np.median(np.concatenate(all_a))) if all_a else None,
        "pairs_after_median_below_0.2m": int(sum(v < 0.2 for v in per_pair_after)),
        "pairs_evaluated": len(per_pair_after),
    }


def _registration_errors(ws: Workspace, sess: dict[str, _SessionError]) -> dict:
    """The true error of every accepted ICP registration (measured on the maps as built: the
    "before" frames), the largest displacement of its support points."""

    pairs_json = ws.align_pairs
    errs = []
    for r in (PairResult.from_dict(v) for v in json.loads(pairs_json.read_text())["pairs"]):
        if not r.accepted or r.source[0] not in sess or r.target[0] not in sess:
            continue
        A, B = sess[r.source[0]], sess[r.target[0]]
        T_true = B.before[B.nearest(r.centre[:2])] @ np.linalg.inv(A.before[A.nearest(r.centre[:2])])
        P = _support_points(r.centre, np.array([1.0, 0.0, 0.0]), 10.0)
        d = (P @ r.target_from_source[:3, :3].T + r.target_from_source[:3, 3]) - (P @ T_true[:3, :3].T + T_true[:3, 3])
        errs.append(float(np.linalg.norm(d, axis=1).max()))
    errs_a = np.asarray(errs)
    return {
        "accepted_pairs": int(len(errs_a)),
        "accepted_pair_true_error_median_m": float(np.median(errs_a)) if len(errs_a) else None,
        "accepted_pair_true_error_max_m": float(errs_a.max()) if len(errs_a) else 0.0,
        "accepted_pairs_true_error_above_1m": int((errs_a > 1.0).sum()),
    }


def format_align_truth(t: dict) -> str:
    """The Markdown of :func:`evaluate_align`'s result: misalignment per session pair before and
    after alignment, the accepted registrations' true errors, each session's trajectory error."""
    lines = ["| session pair | overlap points | misalignment median m, GPS alone | after refinement |", "|---|---|---|---|"]
    for k, v in t["pairs"].items():
        lines.append(f"| {k} | {v['points']} | {v['before_median_m']:.3f} | {v['after_median_m']:.3f} |")
    lines.append("")
    lines.append(f"Overall median: {t['before_median_m']:.3f} m -> {t['after_median_m']:.3f} m. "
                 f"Accepted ICP pairs with a true error above 1 m: {t['accepted_pairs_true_error_above_1m']} of {t['accepted_pairs']} "
                 f"(max {t['accepted_pair_true_error_max_m']:.2f} m).")
    if t.get("trajectories"):
        lines += ["", "Absolute trajectory error in the workspace frame (3D / horizontal RMSE, mean offset east, north, up), "
                  "and with that offset removed by a rigid yaw-only fit to truth (3D / horizontal / vertical RMSE):", "",
                  "| session | GPS alignment alone | after mapkit align | offset removed, GPS alone | offset removed, after align |",
                  "|---|---|---|---|---|"]
        for name, e in t["trajectories"].items():
            cells = [f"{e[w]['ate_rmse_m']:.2f} / {e[w]['horizontal_rmse_m']:.2f} m, ({', '.join(f'{x:.1f}' for x in e[w]['mean_offset_enu_m'])})"
                     for w in ("gps", "aligned")]
            cells += [f"{o['ate_rmse_m']:.2f} / {o['horizontal_rmse_m']:.2f} / {o['vertical_rmse_m']:.2f} m"
                      for o in (e[w].get("offset_removed") for w in ("gps", "aligned")) if o]
            lines.append("| " + " | ".join([name, *cells]) + " |")
    return "\n".join(lines)


__all__ = ["evaluate_align", "evaluate_build", "format_align_truth", "format_eval"]
