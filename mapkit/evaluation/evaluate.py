"""``mapkit eval build``: a built workspace against ground truth.

Against the synthetic town (georeferenced truth), per session: the absolute trajectory error of
the GPS-aligned trajectory (no further alignment: what a map user gets), the GPS fixes' own error
for comparison, and the semi-dense map's distance to the true surfaces (the town's mesh plus that
session's parked cars), with points per 100 m. The truth lives in the town's ENU frame; it is
moved exactly (through ECEF) into the workspace's.

Against a true trajectory of a real drive (a TUM or KITTI file, a pose topic of a log: see
:func:`mapkit.evaluation.truth.read_truth`), for one session: the truth is in a frame of its own,
so the estimate is first fitted to it, as evo's ``-a`` / ``-as`` do (:func:`compare_trajectories`):
a rigid SE(3) Umeyama fit for a metric trajectory, a Sim(3) one for a camera-only trajectory
that GPS did not scale; then the ATE and the relative error per ``segment_m`` of path (RPE, as
KITTI's odometry benchmark measures it). The report says which truth, how stamps were paired and
how the estimate was aligned.

``mapkit eval align``: the inter-session misalignment of the same true surface before and after
``mapkit align`` (:func:`evaluate_align`, its table :func:`format_align_truth`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, TypeGuard

import numpy as np

from mapkit.core.errors import ConfigError, InputError, MapkitError
from mapkit.core.geodesy import LocalFrame
from mapkit.core.geometry import (
    interpolate_poses,
    invert_pose,
    rotation_angle_rad,
    sim3_scale,
    transform_points,
    transform_poses,
    umeyama,
)
from mapkit.core.runio import atomic_write_text, write_json
from mapkit.core.types import StreamKind
from mapkit.core.workspace import SessionDirs, Workspace
from mapkit.core.writers import writes_workspace
from mapkit.evaluation.metrics import map_accuracy, trajectory_errors
from mapkit.evaluation.truth import (
    TruthTrajectory,
    associate_truth,
    error_transforms,
    is_town,
    read_truth,
    session_truth,
    session_truth_mesh,
    split_log_topic,
    ws_from_town,
)
from mapkit.io import open_log
from mapkit.mapping.gps_align import fit_transform
from mapkit.mapping.semidense import SemiDenseMap
from mapkit.mapping.trajectory import Trajectory
from mapkit.multisession.posegraph import support_points
from mapkit.multisession.registration import PairResult

Alignment = Literal["auto", "se3", "sim3", "none"]


def _is_alignment(value: str) -> TypeGuard[Alignment]:
    return value in ("auto", "se3", "sim3", "none")


def as_alignment(value: str) -> Alignment:
    """``value`` (e.g. the command line's ``--align``) as an :data:`Alignment`; a ConfigError otherwise."""
    if not _is_alignment(value):
        raise ConfigError(f"--align {value!r}: expected auto, se3, sim3 or none")
    return value


@writes_workspace("workspace")
def evaluate_build(
    workspace: str | Path | Workspace,
    truth: str | Path,
    *,
    session: str | None = None,
    truth_topic: str | None = None,
    truth_times: Path | None = None,
    time_offset_s: float = 0.0,
    max_dt_s: float = 0.02,
    align: Alignment = "auto",
    segment_m: float = 100.0,
) -> dict:
    """A built workspace against ``truth``; writes ``eval_build.json`` and ``eval_build.md`` into it.

    ``truth`` is a synthetic town folder (every session the town knows, or ``session``), or a true
    trajectory of one session (``session``, or the workspace's only one): a TUM or KITTI file, or
    a log's pose topic (``LOG::/topic`` or ``truth_topic``). See :func:`compare_trajectories` for
    ``max_dt_s``, ``align`` and ``segment_m``.
    """
    as_alignment(align)
    ws = Workspace(workspace)
    path, topic = split_log_topic(truth, truth_topic)
    if is_town(path):
        if topic is not None or truth_times is not None:
            raise InputError(
                path,
                "is a synthetic town, which holds every session's truth; a truth topic or --truth-times "
                "is for a log or a KITTI poses file",
            )
        return _evaluate_town(ws, path, session)
    name = _truth_session(ws, session)
    est, est_info = _session_estimate(ws.session(name))
    t = read_truth(path, topic=topic, times=truth_times, time_offset_s=time_offset_s, body_frame=est.body_frame)
    if align == "auto":
        align = "se3" if est_info["metric"] else "sim3"
    r = {
        "estimate": est_info,
        **compare_trajectories(est.stamps_ns, est.world_from_base, t, max_dt_s, align, segment_m),
    }
    results: dict = {"workspace": str(ws.root), "truth": t.source, "truth_kind": t.kind, "sessions": {name: r}}
    write_json(ws.eval_build_json, results)
    atomic_write_text(ws.eval_build_md, format_eval(results))
    return results


def _evaluate_town(ws: Workspace, truth: Path, session: str | None) -> dict:
    """Every session of the workspace that the town knows (or ``session`` only), against its truth."""
    import open3d as o3d

    ws_frame = ws.require_frame("nothing to compare with truth")
    town_to_ws = ws_from_town(truth, ws_frame)
    # open3d's stub says os.PathLike; its binding takes a str path as well
    mesh = o3d.io.read_triangle_mesh(str(truth / "world" / "mesh.ply"))  # type: ignore[arg-type]
    if not mesh.has_triangles():
        raise InputError(truth / "world" / "mesh.ply", "holds no triangles")
    mesh.transform(town_to_ws)
    results: dict = {"workspace": str(ws.root), "truth": str(truth), "truth_kind": "town", "sessions": {}}
    for name in ws.session_names() if session is None else [_truth_session(ws, session)]:
        try:
            gt_stamps, gt_world_from_base = session_truth(truth, name)
        except (FileNotFoundError, MapkitError):
            continue
        results["sessions"][name] = _evaluate_session(
            ws, ws.session(name), truth, mesh, town_to_ws, ws_frame, gt_stamps, town_to_ws @ gt_world_from_base
        )
    write_json(ws.eval_build_json, results)
    atomic_write_text(ws.eval_build_md, format_eval(results))
    return results


def _truth_session(ws: Workspace, session: str | None) -> str:
    """The session one true trajectory belongs to: ``session``, or the workspace's only one."""
    names = ws.session_names()
    if session is not None:
        if session not in names:
            raise InputError(
                ws.root, f"has no session {session!r}; its sessions: {', '.join(names) or 'none'}", field="--session"
            )
        return session
    if len(names) == 1:
        return names[0]
    if not names:
        raise InputError(ws.root, "holds no sessions (run mapkit build first)")
    raise InputError(
        ws.root,
        f"has {len(names)} sessions ({', '.join(names)}); name the one the truth belongs to with --session",
        field="--session",
    )


def _session_estimate(s: SessionDirs) -> tuple[Trajectory, dict]:
    """The trajectory to evaluate: the georef stage's (in the workspace's ENU frame when
    georeferenced), else the odometry's; and what it is, for the report."""
    georeferenced = s.gps_alignment.is_file() and bool(
        json.loads(s.gps_alignment.read_text()).get("georeferenced", False)
    )
    if s.enu_trajectory.is_dir():
        folder, which = (
            s.enu_trajectory,
            "the georef stage's trajectory"
            + (" (the factor graph's)" if s.enu_trajectory == s.fused_trajectory else "")
            + (" (GPS-aligned, workspace ENU)" if georeferenced else " (not georeferenced: the odometry's frame)"),
        )
    elif s.trajectory.is_dir():
        folder, which = s.trajectory, "the odometry trajectory (before GPS alignment)"
    else:
        raise InputError(s.root, "has no trajectory to evaluate (run mapkit build first)")
    est = Trajectory.load(folder)
    # structure from motion has no scale until GPS gives it one
    metric = georeferenced or not est.source.startswith("camera")
    return est, {
        "trajectory": which,
        "folder": str(folder),
        "source": est.source,
        "frame": est.frame,
        "body_frame": est.body_frame,
        "poses": len(est),
        "span_s": _span_s(est.stamps_ns),
        "georeferenced": georeferenced,
        "metric": metric,
    }


def _span_s(stamps_ns: np.ndarray) -> list[float]:
    return [int(stamps_ns[0]) * 1e-9, int(stamps_ns[-1]) * 1e-9]


def compare_trajectories(
    est_stamps_ns: np.ndarray,
    est_poses: np.ndarray,
    truth: TruthTrajectory,
    max_dt_s: float = 0.02,
    align: Literal["se3", "sim3", "none"] = "se3",
    segment_m: float = 100.0,
) -> dict:
    """An estimated trajectory against a true one in a frame of its own.

    Stamps are paired by :func:`~mapkit.evaluation.truth.associate_truth` within ``max_dt_s``.
    ``align``: ``se3`` fits a rigid transform truth_from_estimate to the paired positions (Umeyama;
    evo's ``-a``), ``sim3`` a similarity (``-as``: a camera-only trajectory has no scale of its
    own), ``none`` takes the truth to be in the estimate's frame (the workspace ENU) and adds
    horizontal and vertical figures. Then the ATE of the aligned positions and rotations, and the
    relative error over every stretch of ``segment_m`` metres of true path (RPE, translation in %
    of the length, rotation in degrees per 100 m). Rotation figures assume both trajectories are of
    one body frame (the report names both).
    """
    est_stamps_ns = np.asarray(est_stamps_ns, np.int64)
    max_dt_ns = int(round(max_dt_s * 1e9))
    ts, te = truth.stamps_ns, est_stamps_ns
    if ts[0] > te[-1] + max_dt_ns or ts[-1] < te[0] - max_dt_ns:
        raise InputError(
            truth.source,
            f"its stamps ({ts[0] * 1e-9:.3f} to {ts[-1] * 1e-9:.3f} s) do not overlap the session's "
            f"({te[0] * 1e-9:.3f} to {te[-1] * 1e-9:.3f} s){_clock_hint(ts, te)}",
            field="time",
        )
    a = associate_truth(te, ts, truth.world_from_body, max_dt_ns)
    if len(a.est_index) < 3:
        raise InputError(
            truth.source,
            f"only {len(a.est_index)} of the session's {len(te)} poses have a true pose within {max_dt_s} s "
            f"(truth {ts[0] * 1e-9:.3f} to {ts[-1] * 1e-9:.3f} s, {len(ts)} poses); at least 3 are needed "
            f"(a larger --max-dt?){_clock_hint(ts, te)}",
            field="time",
        )
    est = np.asarray(est_poses, np.float64)[a.est_index]
    gt = a.truth_poses
    out: dict = {
        "truth": {
            "kind": truth.kind,
            "source": truth.source,
            "frame": truth.frame,
            "body_frame": truth.body_frame,
            "stamps": truth.stamps,
            "poses": len(truth),
            "span_s": _span_s(ts),
        },
        "association": {
            "max_dt_s": max_dt_s,
            "estimated_poses": len(te),
            "associated": len(a.est_index),
            "interpolated": a.interpolated,
            "nearest": a.nearest,
            "nearest_dt_median_s": float(np.median(a.nearest_dt_s)) if len(a.nearest_dt_s) else None,
            "nearest_dt_max_s": float(a.nearest_dt_s.max()) if len(a.nearest_dt_s) else None,
        },
    }
    S = np.eye(4) if align == "none" else umeyama(est[:, :3, 3], gt[:, :3, 3], with_scale=align == "sim3")
    aligned = transform_poses(S, est)
    scale = sim3_scale(S)
    out["alignment"] = {
        "mode": align,
        "truth_from_estimate": S,
        "scale": scale,
        "rotation_deg": float(np.degrees(rotation_angle_rad(S[:3, :3] / scale))),
        "translation": [float(x) for x in S[:3, 3]],
        "straight_path": _straight(est[:, :3, 3]),
    }
    out["ate"] = _pose_errors(aligned, gt, enu=align == "none")
    out["rpe"] = relative_errors(aligned, gt, segment_m)
    return out


def _clock_hint(truth_ns: np.ndarray, est_ns: np.ndarray) -> str:
    """A hint when one side counts from the drive's start (KITTI ``times.txt``) and the other from the epoch."""
    truth_relative, est_relative = truth_ns[0] < _RELATIVE_NS, est_ns[0] < _RELATIVE_NS
    if truth_relative == est_relative:
        return ""
    side = "the truth's" if truth_relative else "the session's"
    return (
        f"; {side} stamps look relative to the drive's start: --truth-time-offset "
        f"{(est_ns[0] - truth_ns[0]) * 1e-9:.6f} would start both together"
    )


#: stamps below this (about 11.6 days) count from a drive's start, not from the epoch
_RELATIVE_NS = 10**6 * 10**9


def _straight(positions: np.ndarray) -> bool:
    """The path is (nearly) a line: a rotation about it is then not observable, and the fitted
    transform's roll about the path is arbitrary (the position errors are not affected)."""
    sv = np.linalg.svd(positions - positions.mean(axis=0), compute_uv=False)
    return bool(sv[1] < 1e-2 * sv[0])


def _pose_errors(est: np.ndarray, gt: np.ndarray, enu: bool) -> dict:
    """ATE statistics of paired poses (positions in metres, rotations in degrees)."""
    err = est[:, :3, 3] - gt[:, :3, 3]
    d = np.linalg.norm(err, axis=1)
    rot = np.degrees(rotation_angle_rad(np.swapaxes(gt[:, :3, :3], 1, 2) @ est[:, :3, :3]))
    r = {
        "poses": len(d),
        "rmse_m": float(np.sqrt(np.mean(d**2))),
        "mean_m": float(d.mean()),
        "median_m": float(np.median(d)),
        "max_m": float(d.max()),
        "rotation_rmse_deg": float(np.sqrt(np.mean(rot**2))),
        "rotation_median_deg": float(np.median(rot)),
    }
    if enu:
        r["horizontal_rmse_m"] = float(np.sqrt(np.mean(np.sum(err[:, :2] ** 2, axis=1))))
        r["vertical_rmse_m"] = float(np.sqrt(np.mean(err[:, 2] ** 2)))
    return r


def relative_errors(est: np.ndarray, gt: np.ndarray, segment_m: float) -> dict:
    """Relative pose error over stretches of ``segment_m`` metres of true path, from every pose.

    For each pose i, j is the first pose at least ``segment_m`` further along the true path; the
    error is (gt_i^-1 gt_j)^-1 (est_i^-1 est_j): its translation in % of the true stretch, its
    rotation in degrees per 100 m (KITTI odometry's measure, with one segment length).
    """
    along = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1))])
    j = np.searchsorted(along, along + segment_m, side="left")
    i = np.nonzero(j < len(gt))[0]
    j = j[i]
    r: dict = {"segment_m": segment_m, "segments": len(i), "path_m": float(along[-1])}
    if not len(i):
        return r
    E = invert_pose(invert_pose(gt[i]) @ gt[j]) @ (invert_pose(est[i]) @ est[j])
    length = along[j] - along[i]
    t_pct = np.linalg.norm(E[:, :3, 3], axis=1) / length * 100.0
    r_deg = np.degrees(rotation_angle_rad(E[:, :3, :3])) / length * 100.0
    r.update(
        translation_percent_mean=float(t_pct.mean()),
        translation_percent_median=float(np.median(t_pct)),
        rotation_deg_per_100m_mean=float(r_deg.mean()),
    )
    return r


def _evaluate_session(
    ws: Workspace,
    s: SessionDirs,
    truth: Path,
    mesh,
    town_to_ws: np.ndarray,
    ws_frame: LocalFrame,
    gt_stamps: np.ndarray,
    gt_ws: np.ndarray,
) -> dict:
    """One session's entry of ``eval_build.json``: trajectory and map against the truth, absolute
    figures only when the session is georeferenced (they mean nothing otherwise)."""
    georeferenced = s.gps_alignment.is_file() and json.loads(s.gps_alignment.read_text()).get("georeferenced", False)
    r: dict = {
        "georeferenced": bool(georeferenced),
        "trajectory_used": "factor graph" if s.enu_trajectory == s.fused_trajectory else "rigid GPS fit",
    }
    est = Trajectory.load(s.enu_trajectory) if s.enu_trajectory.is_dir() else None  # what the map was made with
    fix = None
    if est is not None:
        r["trajectory_local"], fix = _offset_removed_errors(est, gt_stamps, gt_ws)
        if georeferenced:
            r["trajectory"] = _absolute_errors(est, gt_stamps, gt_ws)
        r["gps_alone"] = _gps_error(ws, s.name, gt_stamps, gt_ws, ws_frame)
    maps: dict[str, np.ndarray] = {}  # the map points of each source the session has, workspace frame
    if s.has("map"):
        from mapkit.mapping.semidense import SemiDenseMap

        maps["map"] = SemiDenseMap.load(s.map).points_world
    if s.has("lidar_map"):
        from mapkit.mapping.lidar_map import load_voxel_stats

        maps["lidar_map"] = load_voxel_stats(s.lidar_map).centroid  # one point per voxel
    if maps:
        session_mesh = session_truth_mesh(mesh, truth, s.name, town_to_ws)
        length = float(np.linalg.norm(np.diff(gt_ws[:, :3, 3], axis=0), axis=1).sum())
    for key, points in maps.items():
        if georeferenced:
            r[key] = map_accuracy(points, session_mesh, road_length_m=length)
        if fix is not None:
            r[f"{key}_local"] = map_accuracy(transform_points(fix, points), session_mesh, road_length_m=length)
    if "map_local" in r:
        r["map_local"]["driven_m"] = length
    return r


def _errors(stamps, poses, gt_stamps, gt_poses) -> dict:
    return {
        k: v for k, v in trajectory_errors(stamps, poses, gt_stamps, gt_poses).items() if k != "per_pose_translation_m"
    }


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
    return {
        "fixes": int(ok.sum()),
        "horizontal_rmse_m": float(np.sqrt(np.mean(d**2))),
        "horizontal_median_m": float(np.median(d)),
    }


def format_eval(results: dict) -> str:
    """The Markdown of :func:`evaluate_build`'s result: the town's table, or the trajectory report."""
    if results.get("truth_kind", "town") != "town":
        return format_trajectory_eval(results)
    lines = [
        "| session | georef. | ATE RMSE m | horizontal RMSE m | mean offset ENU m | ATE RMSE m, offset removed "
        "| GPS alone horiz. RMSE m | rot median deg | map points "
        "| to mesh, as georeferenced: median m / within 0.5 m | to mesh, offset removed: median m / within 0.5 m "
        "| points / 100 m |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    f = lambda v, p=2: "" if v is None else f"{v:.{p}f}"  # noqa: E731 (a one-line helper local to this function)
    for name, r in results["sessions"].items():
        t, g, m, ml = r.get("trajectory", {}), r.get("gps_alone", {}), r.get("map", {}), r.get("map_local", {})
        off = t.get("mean_offset_enu_m")
        lines.append(
            f"| {name} | {'yes' if r.get('georeferenced') else 'NO'} | {f(t.get('ate_rmse_m'))} | "
            f"{f(t.get('horizontal_rmse_m'))} | {'' if off is None else ', '.join(f'{x:.1f}' for x in off)} | "
            f"{f(r.get('trajectory_local', {}).get('ate_rmse_m'))} | {f(g.get('horizontal_rmse_m'))} | "
            f"{f((t or r.get('trajectory_local', {})).get('rotation_median_deg'))} | {ml.get('points', '')} | "
            f"{f(m.get('median_distance_m'), 3)} / {f(m.get('fraction_within_0.5m'), 3)} | "
            f"{f(ml.get('median_distance_m'), 3)} / {f(ml.get('fraction_within_0.5m'), 3)} | "
            f"{f(ml.get('points_per_100m'), 0)} |"
        )
    lidar = {name: r for name, r in results["sessions"].items() if "lidar_map_local" in r}
    if lidar:
        lines += [
            "",
            "Both maps of each session against the true surfaces, offset removed (the trajectory's rigid fit to truth; "
            "the LiDAR map's points are its voxels' centroids):",
            "",
            "| session | map | points | median m | within 0.25 m | within 0.5 m | points / 100 m |",
            "|---|---|---|---|---|---|---|",
        ]
        for name, r in lidar.items():
            for label, key in (("semi-dense", "map_local"), ("LiDAR", "lidar_map_local")):
                m = r.get(key, {})
                lines.append(
                    f"| {name} | {label} | {m.get('points', '')} | {f(m.get('median_distance_m'), 3)} | "
                    f"{f(m.get('fraction_within_0.25m'), 3)} | {f(m.get('fraction_within_0.5m'), 3)} | "
                    f"{f(m.get('points_per_100m'), 0)} |"
                )
    return "\n".join(lines) + "\n"


def format_trajectory_eval(results: dict) -> str:
    """Per session: what was compared with what (frames, stamps, alignment), then the errors."""
    kinds = {"tum": "a TUM trajectory file", "kitti": "a KITTI poses file", "topic": "a pose topic of a log"}
    modes = {
        "se3": "a rigid SE(3) Umeyama fit of the estimated positions to the true ones (the truth is in a frame of its "
        "own; evo -a)",
        "sim3": "a Sim(3) Umeyama fit, scale included (a camera-only trajectory has no metric scale; evo -as)",
        "none": "none: the truth is taken to be in the workspace's ENU frame (absolute figures)",
    }
    lines: list[str] = []
    f = lambda v, p=3: "" if v is None else f"{v:.{p}f}"  # noqa: E731 (a one-line helper local to this function)
    for name, r in results["sessions"].items():
        e, t, a, al, ate, rpe = r["estimate"], r["truth"], r["association"], r["alignment"], r["ate"], r["rpe"]
        dt = (
            f" (|dt| median {f(a['nearest_dt_median_s'], 4)} s, max {f(a['nearest_dt_max_s'], 4)} s)"
            if a["nearest"]
            else ""
        )
        S = np.asarray(al["truth_from_estimate"], np.float64)
        lines += [
            f"## Session {name} against {kinds.get(t['kind'], t['kind'])}",
            "",
            f"- Estimate: {e['trajectory']}, {e['poses']} poses of {e['body_frame']} from {e['source']}, "
            f"{e['span_s'][0]:.3f} to {e['span_s'][1]:.3f} s.",
            f"- Truth: `{t['source']}`, {t['poses']} poses (body frame: {t['body_frame']}; frame: {t['frame']}), "
            f"{t['span_s'][0]:.3f} to {t['span_s'][1]:.3f} s; stamps from {t['stamps']}.",
            f"- Association: {a['associated']} of {a['estimated_poses']} estimated poses; {a['interpolated']} "
            f"interpolated between true poses within {a['max_dt_s']} s on both sides, {a['nearest']} paired with the "
            f"nearest true pose within {a['max_dt_s']} s{dt}; the others have no true pose that close and are not "
            "compared.",
            f"- Alignment: {modes[al['mode']]}"
            + (
                ""
                if al["mode"] == "none"
                else f": rotation {al['rotation_deg']:.3f} deg, translation "
                f"({', '.join(f'{x:.3f}' for x in S[:3, 3])}), scale {al['scale']:.6f}"
            )
            + "."
            + (
                " The path is nearly straight: the fit's roll about it is arbitrary (position errors are not affected)."
                if al["straight_path"] and al["mode"] != "none"
                else ""
            ),
            f"- Rotation errors: both are poses of {e['body_frame']}."
            if t["body_frame"] == e["body_frame"]
            else f"- Rotation errors compare {e['body_frame']} with the truth's body frame as they are: a fixed "
            "rotation between the two counts as error.",
            "",
            "| ATE RMSE m | mean m | median m | max m | rotation RMSE deg "
            + ("| horizontal RMSE m | vertical RMSE m " if "horizontal_rmse_m" in ate else "")
            + f"| RPE over {rpe['segment_m']:g} m: translation % | rotation deg / 100 m | segments |",
            "|---|---|---|---|---|" + ("---|---|" if "horizontal_rmse_m" in ate else "") + "---|---|---|",
            f"| {f(ate['rmse_m'])} | {f(ate['mean_m'])} | {f(ate['median_m'])} | {f(ate['max_m'])} | "
            f"{f(ate['rotation_rmse_deg'])} | "
            + (f"{f(ate['horizontal_rmse_m'])} | {f(ate['vertical_rmse_m'])} | " if "horizontal_rmse_m" in ate else "")
            + f"{f(rpe.get('translation_percent_mean'), 2)} | {f(rpe.get('rotation_deg_per_100m_mean'), 3)} | "
            f"{rpe['segments']} |",
            "",
        ]
        if not rpe["segments"]:
            lines += [f"The true path is {rpe['path_m']:.1f} m long, shorter than one RPE segment.", ""]
    return "\n".join(lines)


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


@writes_workspace("workspace")
def evaluate_align(
    workspace: str | Path | Workspace, truth: str | Path, max_points_per_pair: int = 5000, overlap_m: float = 25.0
) -> dict:
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
    out["consistency"] = _consistency(ws, sess)
    out["gps_bias_bound"] = _bias_bound(traj)
    write_json(ws.eval_align_json, out)
    atomic_write_text(
        ws.eval_align_md, "# Multi-session alignment against the synthetic truth\n\n" + format_align_truth(out) + "\n"
    )
    return out


def _session_errors(
    ws: Workspace, truth: Path, names: list[str], town_to_ws: np.ndarray
) -> tuple[dict[str, _SessionError], dict]:
    """Each aligned session's error field, and its absolute trajectory errors (as it stands and
    with the offset removed) before (``gps``) and after (``aligned``) alignment."""
    from scipy.spatial import cKDTree

    sess: dict[str, _SessionError] = {}
    traj: dict = {}
    for name in names:
        gt_stamps, gt = session_truth(truth, name)
        gt_ws = town_to_ws @ gt
        before = Trajectory.load(ws.session(name).enu_trajectory)
        after = Trajectory.load(ws.aligned(name).trajectory)
        pb, Eb = error_transforms(before.stamps_ns, before.world_from_base, gt_stamps, gt_ws)
        _, Ea = error_transforms(after.stamps_ns, after.world_from_base, gt_stamps, gt_ws)
        sess[name] = _SessionError(cKDTree(pb[:, :2]), Eb, Ea, SemiDenseMap.load(ws.aligned(name).map).points_world)
        traj[name] = {when: _absolute_errors(t, gt_stamps, gt_ws) for when, t in (("gps", before), ("aligned", after))}
        for when, t in (("gps", before), ("aligned", after)):
            traj[name][when]["offset_removed"] = _offset_removed_errors(t, gt_stamps, gt_ws)[0]
    return sess, traj


def _pair_misalignment(
    sess: dict[str, _SessionError], names: list[str], max_points_per_pair: int, overlap_m: float, pairs: dict
) -> dict:
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
            pairs[f"{na} / {nb}"] = {
                "points": int(len(pts)),
                "before_median_m": float(np.median(res["before"])),
                "after_median_m": float(np.median(res["after"])),
                "after_p90_m": float(np.percentile(res["after"], 90)),
            }
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
        P = support_points(r.centre, np.array([1.0, 0.0, 0.0]), 10.0)
        d = (P @ r.target_from_source[:3, :3].T + r.target_from_source[:3, 3]) - (P @ T_true[:3, :3].T + T_true[:3, 3])
        errs.append(float(np.linalg.norm(d, axis=1).max()))
    errs_a = np.asarray(errs)
    return {
        "accepted_pairs": int(len(errs_a)),
        "accepted_pair_true_error_median_m": float(np.median(errs_a)) if len(errs_a) else None,
        "accepted_pair_true_error_max_m": float(errs_a.max()) if len(errs_a) else 0.0,
        "accepted_pairs_true_error_above_1m": int((errs_a > 1.0).sum()),
    }


CHI2_95_3DOF = 7.815  # 95% quantile of chi-square with 3 degrees of freedom


OVERCONFIDENT_OUTSIDE = 0.10  # a session whose truth leaves its 95% ellipsoids more often than this is flagged


def _consistency(ws: Workspace, sess: dict[str, _SessionError]) -> dict:
    """Are the graph's covariances honest? At every submap's centre c, the true position error of
    the aligned session there (E_after c - c) against the submap's marginal position covariance:
    the fraction inside its 95% ellipsoid (NEES <= 7.815) should be near 0.95 (evo and SLAM
    benchmarks check the same). A session whose truth lies outside for more than 10% of its submap
    centres is *overconfident*: its map claims a certainty it does not have, and ``overconfident``
    names it. Submaps without a covariance (aligned by an older mapkit) are left out."""
    d2_all: list[float] = []
    per: dict = {}
    for name, se in sess.items():
        path = ws.aligned(name).submaps
        if not path.is_file():
            continue
        d2 = []
        for sm in json.loads(path.read_text())["submaps"]:
            cov = np.asarray(sm.get("covariance", np.zeros((6, 6))), np.float64)[3:, 3:]
            if not np.all(np.isfinite(cov)) or np.linalg.det(cov) <= 0:
                continue
            c = np.asarray(sm["centre_enu"], np.float64)
            E = se.after[se.nearest(c[None, :2])[0]]
            e = E[:3, :3] @ c + E[:3, 3] - c
            d2.append(float(e @ np.linalg.solve(cov, e)))
        if d2:
            inside = float(np.mean(np.asarray(d2) <= CHI2_95_3DOF))
            per[name] = {
                "submaps": len(d2),
                "inside_95": inside,
                "nees_mean": float(np.mean(d2)),
                "overconfident": bool(1.0 - inside > OVERCONFIDENT_OUTSIDE),
            }
            d2_all += d2
    a = np.asarray(d2_all)
    return {
        "submaps": int(len(a)),
        "inside_95": float(np.mean(a <= CHI2_95_3DOF)) if len(a) else None,
        "nees_mean": float(a.mean()) if len(a) else None,
        "sessions": per,
        "overconfident": [n for n, v in per.items() if v["overconfident"]],
    }


def _bias_bound(traj: dict) -> dict:
    """What GPS allows: relative alignment cannot tell a bias that all sessions share from the
    truth, so with equal bias priors the best frame sits at the mean of the N sessions' biases
    (expected horizontal error sigma_b sqrt(2 / N)). Each session's bias is measured as its GPS-alone
    mean offset from the truth; the bound is the horizontal norm of their mean, and the figure to
    hold against it each session's horizontal RMSE after alignment."""
    if not traj:
        return {}
    gps = np.array([e["gps"]["mean_offset_enu_m"] for e in traj.values()])
    allowed = float(np.linalg.norm(gps.mean(axis=0)[:2]))
    after = np.array([e["aligned"]["horizontal_rmse_m"] for e in traj.values()])
    return {
        "sessions": len(gps),
        "mean_gps_bias_enu_m": gps.mean(axis=0).tolist(),
        "allowed_horizontal_m": allowed,
        "aligned_horizontal_rmse_median_m": float(np.median(after)),
        "ratio_median": float(np.median(after) / allowed) if allowed > 0 else None,
    }


def format_align_truth(t: dict) -> str:
    """The Markdown of :func:`evaluate_align`'s result: misalignment per session pair before and
    after alignment, the accepted registrations' true errors, each session's trajectory error."""
    lines = [
        "| session pair | overlap points | misalignment median m, GPS alone | after refinement |",
        "|---|---|---|---|",
    ]
    for k, v in t["pairs"].items():
        lines.append(f"| {k} | {v['points']} | {v['before_median_m']:.3f} | {v['after_median_m']:.3f} |")
    lines.append("")
    lines.append(
        f"Overall median: {t['before_median_m']:.3f} m -> {t['after_median_m']:.3f} m. "
        f"Accepted ICP pairs with a true error above 1 m: {t['accepted_pairs_true_error_above_1m']} of "
        f"{t['accepted_pairs']} (max {t['accepted_pair_true_error_max_m']:.2f} m)."
    )
    if t.get("trajectories"):
        lines += [
            "",
            "Absolute trajectory error in the workspace frame (3D / horizontal RMSE, mean offset east, north, up), "
            "and with that offset removed by a rigid yaw-only fit to truth (3D / horizontal / vertical RMSE):",
            "",
            "| session | GPS alignment alone | after mapkit align | offset removed, GPS alone "
            "| offset removed, after align |",
            "|---|---|---|---|---|",
        ]
        for name, e in t["trajectories"].items():
            cells = [
                f"{e[w]['ate_rmse_m']:.2f} / {e[w]['horizontal_rmse_m']:.2f} m, "
                f"({', '.join(f'{x:.1f}' for x in e[w]['mean_offset_enu_m'])})"
                for w in ("gps", "aligned")
            ]
            cells += [
                f"{o['ate_rmse_m']:.2f} / {o['horizontal_rmse_m']:.2f} / {o['vertical_rmse_m']:.2f} m"
                for o in (e[w].get("offset_removed") for w in ("gps", "aligned"))
                if o
            ]
            lines.append("| " + " | ".join([name, *cells]) + " |")
    b = t.get("gps_bias_bound")
    if b:
        lines += [
            "",
            f"GPS bound: the frame cannot beat the mean of the {b['sessions']} sessions' GPS biases "
            f"({', '.join(f'{x:.2f}' for x in b['mean_gps_bias_enu_m'])} m east, north, up; "
            f"{b['allowed_horizontal_m']:.2f} m horizontally). Median horizontal RMSE after alignment "
            f"{b['aligned_horizontal_rmse_median_m']:.2f} m: "
            + (f"{b['ratio_median']:.2f}x the bound." if b["ratio_median"] is not None else "the bound is zero."),
        ]
    c = t.get("consistency")
    if c and c.get("submaps"):
        lines += [
            "",
            f"Covariance consistency: {100 * c['inside_95']:.0f}% of {c['submaps']} submap centres lie inside their "
            f"95% position ellipsoids (mean NEES {c['nees_mean']:.2f}; 3 expected): "
            + ", ".join(f"{n} {100 * v['inside_95']:.0f}%" for n, v in c["sessions"].items())
            + ".",
        ]
        bad = c.get("overconfident") or []
        lines += [
            "",
            (
                f"**Overconfident: {', '.join(bad)}**: the true position lies outside the 95% ellipsoid at more than "
                f"{100 * OVERCONFIDENT_OUTSIDE:.0f}% of the submap centres ("
                + ", ".join(f"{n} {100 * (1 - c['sessions'][n]['inside_95']):.0f}%" for n in bad)
                + "); their covariances claim a certainty these maps do not have."
            )
            if bad
            else f"No session is overconfident (truth outside the 95% ellipsoid at more than "
            f"{100 * OVERCONFIDENT_OUTSIDE:.0f}% of its submap centres).",
        ]
    return "\n".join(lines)


__all__ = [
    "as_alignment",
    "compare_trajectories",
    "evaluate_align",
    "evaluate_build",
    "format_align_truth",
    "format_eval",
    "format_trajectory_eval",
    "relative_errors",
]
