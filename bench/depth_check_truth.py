"""The reference model's depth check against the truth: how far the triangulated points and the maps' depths lie
from the true surfaces, at the same keypoints, on a synthetic town's workspace.

Per observation of the model (a keypoint with a triangulated point; every ``--every``-th image), the true depth is
where the keypoint's ray meets the town's mesh, moved into the model's frame by the fit ``mapkit eval localize
--refine 6dof`` wrote (``WS/localize/6dof/eval_localize.json``: ``model_from_truth``, on the database images). The
table gives each depth's relative difference from it, ``|z - z_true| / z_true`` (median, 90th percentile):

* the triangulated points, all, by their triangulation angle (the widest angle between two rays of the track) and
  where their rays fix their depth to ``depth_check_max_depth_uncertainty``;
* each map's depth as the check takes it (all of its conditions: one surface, facing the camera where the map has
  normals, a point its rays fix) and as the median of all its points there, whatever their spread;
* the triangulated points at the observations each map's check compares.

A second table runs the check's conditions with the surface's angle from head-on at each of ``--incidence`` (deg)
and the point's condition as configured: per map that has normals, the fraction of observations compared, the
check's median, and how far the triangulated points it compares lie from the truth.

So it says which side of a disagreement the check reports is the model's and which the map's. Run on the main job's
workspace with ``--sixdof`` (or the tiny town's, where the check's spread was chosen); ``--model M --true-poses``
measures a model built on the true poses (``mapkit model --truth``) instead, whose maps' rows mean nothing (the maps
lie on the build's poses)::

    python3 bench/depth_check_truth.py runs/main/workspace --truth runs/main/town
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.common import report  # noqa: E402 (after sys.path points at this checkout)

ANGLE_BINS = ((0.0, 3.0), (3.0, 6.0), (6.0, 12.0), (12.0, 180.0))


def _relative(est: np.ndarray, truth: np.ndarray) -> np.ndarray:
    m = np.isfinite(est) & np.isfinite(truth)
    return np.abs(est[m] - truth[m]) / truth[m]


def _row(what: str, est: np.ndarray, truth: np.ndarray) -> dict:
    rel = _relative(est, truth)
    return {
        "depth": what,
        "observations": len(rel),
        "median": round(float(np.median(rel)), 4) if len(rel) else None,
        "p90": round(float(np.percentile(rel, 90)), 3) if len(rel) else None,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workspace", type=Path)
    ap.add_argument("--truth", type=Path, required=True, help="the synthetic town the workspace was built from")
    ap.add_argument("--every", type=int, default=3, help="every n-th image of the model (default 3)")
    ap.add_argument("--model", type=Path, help="a reference model folder (default WORKSPACE/reference_model)")
    ap.add_argument(
        "--true-poses",
        action="store_true",
        help="the model was built on the town's true poses (mapkit model --truth): its frame is the truth's",
    )
    ap.add_argument(
        "--incidence",
        type=float,
        nargs="+",
        default=[50.0, 60.0, 70.0, 80.0, 90.0],
        help="the surface angles from head-on (deg) the second table tries",
    )
    args = ap.parse_args(argv)
    import open3d as o3d
    import pycolmap

    from mapkit.core.config import load_config
    from mapkit.core.workspace import Workspace
    from mapkit.evaluation.truth import ws_from_town
    from mapkit.localization import reference_model as rm

    ws = Workspace(args.workspace)
    model = args.model or ws.root / rm.DEFAULT_FOLDER
    fit_file = ws.localize_dir / "6dof" / "eval_localize.json"
    if args.true_poses:
        model_from_truth = np.eye(4)
    elif not fit_file.is_file():
        print(f"no {fit_file}: run the main job with --sixdof (mapkit eval localize --refine 6dof)", file=sys.stderr)
        return 2
    else:
        model_from_truth = np.array(json.loads(fit_file.read_text())["model_from_truth"]["matrix"])
    rec = pycolmap.Reconstruction(str(model / "sfm"))
    cfg = rm.ReferenceModelConfig()
    sessions = load_config(rm.ReferenceModelConfig, model / "config.yaml").sessions
    maps = rm.session_maps(ws, sessions)
    grids = {
        k: rm._GroundGrid(v[:, :3], rm.DEPTH_CHECK_CELL_M, v[:, 3:] if v.shape[1] == 6 else None)
        for k, v in maps.items()
        if v is not None
    }
    mesh = o3d.io.read_triangle_mesh(str(args.truth / "world" / "mesh.ply"))
    mesh.transform(model_from_truth @ ws_from_town(args.truth, ws.require_frame("the truth is georeferenced")))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    centres = {i: np.asarray(im.projection_center()) for i, im in rec.images.items()}
    xyz = {pid: p.xyz for pid, p in rec.points3D.items()}
    cov = rm.point_covariances(rec)
    cols: dict[str, list[np.ndarray]] = {"tri": [], "true": [], "angle": [], "fixed": []}
    for kind in grids:
        cols[f"{kind}:one"], cols[f"{kind}:all"], cols[f"{kind}:incidence"] = [], [], []
    for image_id in sorted(rec.images)[:: args.every]:
        im = rec.images[image_id]
        kp, X_obs, pids = rm._observations(im, xyz)
        if not len(pids):
            continue
        T = np.asarray(im.cam_from_world().matrix(), np.float64)
        z_tri = X_obs @ T[2, :3] + T[2, 3]
        rays = np.c_[np.asarray(im.camera.cam_from_img(kp), np.float64), np.ones(len(kp))] @ T[:, :3]  # z = 1
        origin = np.tile(centres[image_id], (len(kp), 1))
        hits = scene.cast_rays(o3d.core.Tensor(np.c_[origin, rays].astype(np.float32)))["t_hit"].numpy()
        angles = []
        for pid in pids.tolist():
            track = np.array([centres[e.image_id] for e in rec.points3D[pid].track.elements]) - xyz[pid]
            track /= np.linalg.norm(track, axis=1)[:, None]
            angles.append(np.degrees(np.arccos(np.clip((track @ track.T).min(), -1.0, 1.0))))
        cols["tri"].append(z_tri)
        cols["true"].append(np.where(np.isfinite(hits), hits, np.nan))
        cols["angle"].append(np.array(angles))
        sigma = rm.point_depth_uncertainty(rec, image_id, pids, cov)
        cols["fixed"].append(sigma <= cfg.depth_check_max_depth_uncertainty)
        reach = rm.DEPTH_CHECK_REACH * float(z_tri.max())
        for kind, grid in grids.items():
            z_map, spread, incidence = rm.map_depths(im, grid, kp, reach, cfg.depth_check_radius_px, 3, 16)
            cols[f"{kind}:all"].append(z_map)
            cols[f"{kind}:one"].append(np.where(spread <= cfg.depth_check_max_spread * z_map, z_map, np.nan))
            cols[f"{kind}:incidence"].append(incidence)
    a = {k: np.concatenate(v) if v else np.zeros(0) for k, v in cols.items()}
    fixed = a["fixed"].astype(bool)

    def checked(kind: str, max_incidence: float) -> np.ndarray:
        """The map's depth where the check compares, NaN elsewhere."""
        facing = rm.facing_surface(a[f"{kind}:incidence"], max_incidence, grids[kind].normals is not None)
        return np.where(fixed & facing & np.isfinite(a[f"{kind}:one"]), a[f"{kind}:one"], np.nan)

    rows = [_row("triangulated, all", a["tri"], a["true"])]
    for lo, hi in ANGLE_BINS:
        sel = (a["angle"] >= lo) & (a["angle"] < hi)
        rows.append(_row(f"triangulated, rays {lo:g}-{hi:g} deg apart", a["tri"][sel], a["true"][sel]))
    rows.append(
        _row(
            f"triangulated, depth fixed to {cfg.depth_check_max_depth_uncertainty:g} by its rays",
            a["tri"][fixed],
            a["true"][fixed],
        )
    )
    for kind in grids:
        rows.append(
            _row(f"{kind} map, as the check takes it", checked(kind, cfg.depth_check_max_incidence_deg), a["true"])
        )
        rows.append(_row(f"{kind} map, median of all its points there", a[f"{kind}:all"], a["true"]))
    for kind in grids:  # the observations the check compares: how far each side lies from the truth there
        sel = np.isfinite(checked(kind, cfg.depth_check_max_incidence_deg))
        rows.append(_row(f"triangulated, where the {kind} check compares", a["tri"][sel], a["true"][sel]))
    report(
        "Depths at the reference model's keypoints against the true surfaces (relative difference)",
        rows,
        f"{len(a['tri'])} observations of every {args.every}. image of the model; the truth moved by the fit on the "
        "database images",
    )
    sweep = []
    for kind in (k for k, g in grids.items() if g.normals is not None):
        for limit in args.incidence:
            z_map = checked(kind, limit)
            sel = np.isfinite(z_map)
            check, tri = _relative(a["tri"][sel], z_map[sel]), _relative(a["tri"][sel], a["true"][sel])
            sweep.append(
                {
                    "map": kind,
                    "surface at most (deg from head-on)": limit,
                    "compared": f"{np.mean(sel):.3f}",
                    "check's median": round(float(np.median(check)), 4) if len(check) else None,
                    "triangulated from truth (median)": round(float(np.median(tri)), 4) if len(tri) else None,
                }
            )
    if sweep:
        report(
            "The depth check at each surface angle: what it compares and how far those points lie from the truth",
            sweep,
            f"points whose rays fix their depth to {cfg.depth_check_max_depth_uncertainty:g} (configured); "
            f"configured angle {cfg.depth_check_max_incidence_deg:g} deg",
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
