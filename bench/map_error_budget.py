"""Where a session map's error comes from: the semi-dense mapper on true and estimated poses.

Rebuilds one demo session's semi-dense map (stage 3 of ``mapkit build``, the same code and config)
in a scratch workspace, once per pose variant, and measures every map against the town's true
mesh (with that session's parked cars), as ``mapkit eval build`` does:

* ``estimated``: the session's georeferenced trajectory (the rigid GPS fit, ``georef/trajectory_enu``,
  also in a workspace built with ``georef.fuse``) after a yaw-only rigid fit to truth (the GPS bias
  removed; what ``eval build`` calls "offset removed");
* ``truth``: the true poses: the mapper's own accuracy;
* ``true_rotation``: estimated positions, true orientations;
* ``true_position``: true positions, estimated orientations;
* ``true_roll_pitch``: estimated positions and heading, true roll and pitch (what leveling by
  gravity, from an IMU, could at best give);
* ``fused``: the trajectory the factor graph gives (``georef: {fuse: true}``: odometry, GPS and the
  preintegrated IMU), after the same yaw-only fit to truth;
* ``aligned``: not rebuilt: the session's map as ``mapkit align`` left it, after the same yaw-only
  fit of its refined trajectory (only when the workspace was aligned).

Each rebuilt variant's poses are written into the trajectory the mapper reads
(``georef/trajectory_fused`` in a workspace built with ``georef.fuse``, else ``georef/trajectory_enu``),
and the bench checks that the mapper read them. The baseline of the comparison is the ``estimated``
row; the ratio printed is each variant's median distance over it. Run on a built demo workspace (a
few minutes per variant on one core)::

    python3 bench/map_error_budget.py --workspace runs/main/workspace --town runs/main/town --session test-clear

``--semidense FILE.yaml`` sets semi-dense mapper fields over the workspace's build config, e.g. the
outlier filters (``min_consistent_views: 1``) for a run on true poses only::

    python3 bench/map_error_budget.py ... --variants truth --semidense filters.yaml
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

VARIANTS = ("estimated", "truth", "true_rotation", "true_position", "true_roll_pitch", "fused", "aligned")


def _variant_poses(variant: str, est: np.ndarray, gt: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    q = est.copy()
    if variant == "truth":
        q = gt.copy()
    elif variant == "true_rotation":
        q[:, :3, :3] = gt[:, :3, :3]
    elif variant == "true_position":
        q[:, :3, 3] = gt[:, :3, 3]
    elif variant == "true_roll_pitch":
        e = Rotation.from_matrix(q[:, :3, :3]).as_euler("ZYX")
        e[:, 1:] = Rotation.from_matrix(gt[:, :3, :3]).as_euler("ZYX")[:, 1:]
        q[:, :3, :3] = Rotation.from_euler("ZYX", e).as_matrix()
    elif variant != "estimated":
        raise ValueError(f"unknown variant {variant!r}; one of {VARIANTS}")
    return q


# the stages whose digests each reused stage's inputs record (as SessionBuilder.trajectory / .georef compute them)
_REUSED_STAGES: dict[str, tuple[str, ...]] = {"trajectory": (), "georef": ("trajectory",)}


def _copy_stages(builder, sdir: Path, stages: tuple[str, ...]) -> None:
    """Copy the workspace session's finished ``stages`` into the builder's (scratch) session."""
    for stage in stages:
        shutil.copytree(sdir / stage, getattr(builder.dirs, stage))
    shutil.copy(sdir.parents[1] / "origin.json", builder.workspace / "origin.json")


def _mark_finished(builder, stages: tuple[str, ...]) -> None:
    """Mark the scratch session's ``stages`` finished as the builder checks them: the config hash and
    inputs this checkout's code computes, and the outputs as they are (the variant's poses included).

    The workspace's own markers are not enough: a workspace built by another version of mapkit may
    hash a config section differently (a field added to it changes its hash; with ``georef.fuse`` the
    georef stage hashes the factor graph's section), and the builder would run the stage again,
    writing the estimated trajectory over the variant's."""
    from mapkit.core.runio import mark_done, read_marker
    from mapkit.mapping.build import _stage_hash, _stage_version

    for stage in stages:  # upstream first: a stage's inputs hold the digest of its upstream's marker
        upstream = _REUSED_STAGES[stage]
        out = getattr(builder.dirs, stage)
        kept = ("config_hash", "stage_version", "legacy_config_hash", "inputs", "outputs")
        info = {k: v for k, v in (read_marker(out) or {}).items() if k not in kept}
        mark_done(
            out,
            _stage_hash(builder.cfg, stage),
            version=_stage_version(stage),
            inputs=builder._inputs(*(getattr(builder.dirs, u) for u in upstream)),
            outputs=True,
            **info,
        )


def _fused(log, sdir: Path, name: str, cfg, scratch: Path):
    """The session's trajectory fused by the factor graph: its georef stage run again with
    ``georef.fuse`` (this checkout's factor graph) in a scratch copy (the trajectory stage reused)."""
    from mapkit.mapping.build import SessionBuilder
    from mapkit.mapping.trajectory import Trajectory

    fcfg = cfg.model_copy(update={"georef": cfg.georef.model_copy(update={"fuse": True})})
    builder = SessionBuilder(log, scratch, fcfg, progress=False, name=name)
    try:
        _copy_stages(builder, sdir, ("trajectory",))
        _mark_finished(builder, ("trajectory",))
        builder.georef()
        return Trajectory.load(builder.dirs.fused_trajectory)
    finally:
        builder.close()


def _print_row(r: dict) -> None:
    print(
        f"{r['variant']:16s} pose RMSE {r['position_rmse_m']:.3f} m  points {r['points']:7d}  median "
        f"{r['median_distance_m']:.3f} m  within 0.5 m {r['fraction_within_0.5m']:.3f}  "
        f"within 0.15 m {r['fraction_within_0.15m']:.3f}",
        flush=True,
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--workspace", type=Path, required=True, help="a workspace built by `mapkit build` from the town's logs"
    )
    ap.add_argument("--town", type=Path, required=True, help="the synthetic town (logs and truth)")
    ap.add_argument("--session", default="test-clear")
    ap.add_argument(
        "--variants",
        nargs="+",
        default=None,
        choices=VARIANTS,
        help="default: all, 'aligned' only when WORKSPACE/align holds the session",
    )
    ap.add_argument("--json", type=Path, default=None, help="also write the rows here")
    ap.add_argument(
        "--semidense",
        type=Path,
        default=None,
        help="YAML of SemiDenseConfig fields set over the workspace's build config (e.g. the outlier filters)",
    )
    a = ap.parse_args(argv)

    import open3d as o3d

    from mapkit.core.config import load_config
    from mapkit.core.geodesy import LocalFrame
    from mapkit.core.geometry import interpolate_poses, transform_points
    from mapkit.evaluation.metrics import map_accuracy
    from mapkit.evaluation.truth import session_truth_mesh, ws_from_town
    from mapkit.mapping.build import BuildConfig, SessionBuilder
    from mapkit.mapping.gps_align import fit_transform
    from mapkit.mapping.semidense import SemiDenseMap
    from mapkit.mapping.trajectory import Trajectory
    from mapkit.synth import gt_poses, session_log

    ws, town, name = a.workspace, a.town, a.session
    sdir = ws / "sessions" / name
    frame = LocalFrame.from_dict(json.loads((ws / "origin.json").read_text()))
    town_to_ws = ws_from_town(town, frame)
    mesh = o3d.io.read_triangle_mesh(str(town / "world" / "mesh.ply"))
    mesh.transform(town_to_ws)
    mesh = session_truth_mesh(mesh, town, name, town_to_ws)
    gt_stamps, gt = gt_poses(town, name)
    gt = town_to_ws @ gt
    est = Trajectory.load(sdir / "georef" / "trajectory_enu")
    gt_i, ok = interpolate_poses(gt_stamps, gt, est.stamps_ns)
    est_fit = fit_transform(est.world_from_base[ok, :3, 3], gt_i[:, :3, 3], mode="yaw") @ est.world_from_base[ok]
    aligned_dir = ws / "align" / "sessions" / name
    # by default every variant but the fused one (it runs the georef stage again), and aligned only where align ran
    variants = a.variants or [
        v for v in VARIANTS if v != "fused" and (v != "aligned" or (aligned_dir / "map").is_dir())
    ]
    cfg_path = ws / "build_config.yaml"
    cfg = load_config(BuildConfig, cfg_path) if cfg_path.is_file() else BuildConfig()
    if a.semidense is not None:
        import yaml

        cfg = cfg.model_copy(
            update={"semidense": cfg.semidense.model_copy(update=yaml.safe_load(a.semidense.read_text()) or {})}
        )
    log = session_log(town, name)  # the workspace's metrics hold the path as the build was given it

    rows = []
    with tempfile.TemporaryDirectory(prefix="map-error-budget-") as tmp:
        for v in variants:
            t0 = time.perf_counter()
            if v == "aligned":
                al = Trajectory.load(aligned_dir / "trajectory")
                al_gt, al_ok = interpolate_poses(gt_stamps, gt, al.stamps_ns)
                fix = fit_transform(al.world_from_base[al_ok, :3, 3], al_gt[:, :3, 3], mode="yaw")
                r = map_accuracy(transform_points(fix, SemiDenseMap.load(aligned_dir / "map").points_world), mesh)
                err = np.linalg.norm(transform_points(fix, al.world_from_base[al_ok, :3, 3]) - al_gt[:, :3, 3], axis=1)
                rows.append(
                    {
                        "variant": v,
                        "position_rmse_m": float(np.sqrt(np.mean(err**2))),
                        **r,
                        "seconds": time.perf_counter() - t0,
                    }
                )
                _print_row(rows[-1])
                continue
            stamps, truth_v = est.stamps_ns[ok], gt_i
            if v == "fused":
                fused = _fused(log, sdir, name, cfg, Path(tmp) / "fuse")
                truth_v, ok_f = interpolate_poses(gt_stamps, gt, fused.stamps_ns)
                stamps = fused.stamps_ns[ok_f]
                poses = (
                    fit_transform(fused.world_from_base[ok_f, :3, 3], truth_v[:, :3, 3], mode="yaw")
                    @ fused.world_from_base[ok_f]
                )
            else:
                poses = _variant_poses(v, est_fit, gt_i)
            builder = SessionBuilder(log, Path(tmp) / v, cfg, progress=False, name=name)
            try:
                # the workspace's trajectory and georef stages, the variant's poses in the trajectory the
                # mapper reads (the factor graph's with georef.fuse, else the rigid fit's), both stages
                # marked finished: the builder goes straight to the map
                _copy_stages(builder, sdir, ("trajectory", "georef"))
                mapped = builder.dirs.enu_trajectory
                shutil.rmtree(mapped)
                Trajectory(stamps, poses, est.source, frame=est.frame, body_frame=est.body_frame).save(mapped)
                _mark_finished(builder, ("trajectory", "georef"))
                out = builder.semidense()
                used = builder.enu_trajectory()
            finally:
                builder.close()
            if not (
                np.array_equal(used.stamps_ns, stamps) and np.allclose(used.world_from_base, poses, rtol=0, atol=1e-9)
            ):
                raise RuntimeError(f"{v}: the mapper read other poses than the variant's ({mapped} was rewritten)")
            pts = SemiDenseMap.load(out).points_world
            path_m = float(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1).sum())
            r = map_accuracy(pts, mesh, road_length_m=path_m)
            err = np.linalg.norm(poses[:, :3, 3] - truth_v[:, :3, 3], axis=1)
            rows.append(
                {
                    "variant": v,
                    "position_rmse_m": float(np.sqrt(np.mean(err**2))),
                    **r,
                    "seconds": time.perf_counter() - t0,
                }
            )
            _print_row(rows[-1])
    base = next((r for r in rows if r["variant"] == "estimated"), None)
    print(
        f"\n| {name}: poses | position RMSE m | map points | points per 100 m | median to mesh m | within 0.5 m "
        "| ratio of median to estimated |"
    )
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        ratio = f"{r['median_distance_m'] / base['median_distance_m']:.2f}" if base else ""
        per100 = f"{r['points_per_100m']:.0f}" if r.get("points_per_100m") is not None else ""
        print(
            f"| {r['variant']} | {r['position_rmse_m']:.3f} | {r['points']} | {per100} | "
            f"{r['median_distance_m']:.3f} | {r['fraction_within_0.5m']:.3f} | {ratio} |"
        )
    if a.json:
        a.json.write_text(json.dumps({"session": name, "rows": rows}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
