"""``mapkit eval localize``: the MCVL paper's protocol (section IV) on a synthetic town.

Training sessions build the index, test sessions are queries; per sequence the translation error
||c_est - c_gt|| and the orientation error, mean and median, for retrieval alone and for the filter
(Table II), and a plot of the estimated against the true trajectory (Fig. 5).

With ``refine: 6dof`` every query is also registered against the reference model
(:func:`~mapkit.localization.localize.refine_sixdof`), and each test session reports, for the
6-DoF poses, the filter and retrieval alone on the same queries, the share within the visual
localization benchmark's bands (0.25 m, 2 deg), (0.5 m, 5 deg), (5 m, 10 deg) and the median
errors (:mod:`mapkit.evaluation.benchmark`; a query without an estimate fails every band), each against the
truth in the reference model's frame (fitted on the model's database images, as ``mapkit export benchmark`` fits it).

Errors are those of camera poses, as Table II's are: the filter runs on the vehicle's base pose
(:mod:`mapkit.localization.mcl`) and :func:`~mapkit.localization.localize.run_localizer` returns
its estimates converted back to the camera through ``LocalizeConfig.base_from_camera``.
"""

from __future__ import annotations

import time
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from mapkit.core.config import dump_config, load_config
from mapkit.core.errors import InputError, MapkitError
from mapkit.core.geometry import invert_pose
from mapkit.core.runio import atomic_write_text, write_json, write_timings
from mapkit.core.workspace import Workspace
from mapkit.core.writers import writes_workspace
from mapkit.evaluation.benchmark import THRESHOLDS, BenchmarkScores, band_key, band_scores, errors_or_missing
from mapkit.io.plots import localization_track
from mapkit.localization.localize import (
    LocalizeConfig,
    cached_query_all,
    odometry_steps,
    open_reference_model,
    refine_sixdof,
    remove_sixdof_outputs,
    run_localizer,
    sixdof_timings,
    write_run_trajectories,
    write_sixdof,
)
from mapkit.localization.mcl import pose_errors
from mapkit.localization.reference_model import workspace_images
from mapkit.localization.sixdof import SixDofLocalizer
from mapkit.retrieval.index_vlad import VladIndex, build_vlad_index, read_session_images

if TYPE_CHECKING:
    from mapkit.core.geodesy import LocalFrame


#: radius (m) within which a retrieved image counts as the right place in the recall diagnostics
RECALL_RADIUS_M = 25.0


def hit_recall(index, ids: np.ndarray, gt_positions: np.ndarray, radius_m: float = RECALL_RADIUS_M) -> dict:
    """Share of queries one of whose first n retrieved images lies within ``radius_m`` of the
    query's true position (recall@n), for n = 1, 5 and the retrieved k (MCVL reports 1/5/20)."""
    valid = ids >= 0
    pos = index.world_from_cam[np.where(valid, ids, 0), :3, 3]
    d = np.where(valid, np.linalg.norm(pos - gt_positions[:, None, :], axis=-1), np.inf)
    out = {
        f"recall_at_{n}": float(np.mean(d[:, :n].min(axis=1) <= radius_m))
        for n in sorted({1, min(5, ids.shape[1]), ids.shape[1]})
    }
    return {**out, "recall_radius_m": radius_m}


def pose_band_scores(gt_world_from_cam: np.ndarray, est_world_from_cam: np.ndarray) -> BenchmarkScores:
    """The visual localization benchmark's scores of camera poses (n, 4, 4) against the truth (both
    ``world_from_camera``): the share within each band and the median errors; a query without an
    estimate (NaN) fails every band and counts as missing."""
    gt = np.asarray(gt_world_from_cam, np.float64).reshape(-1, 4, 4)
    est = np.asarray(est_world_from_cam, np.float64).reshape(-1, 4, 4)
    return band_scores(*errors_or_missing(invert_pose(gt), invert_pose(est)), THRESHOLDS)


def _model_clash(loc: SixDofLocalizer, ws: Workspace, tests: list[str]) -> list[str]:
    """The test sessions with an image in the reference model (queries must not be part of the map)."""
    in_model = set(loc.names_by_path())
    return [
        name
        for name in tests
        if any(Path(p).resolve() in in_model for p in read_session_images(ws.root, name).image_paths)
    ]


@writes_workspace("workspace")
def evaluate_localization(
    workspace: str | Path | Workspace,
    truth: str | Path,
    bundle: str | Path | None = None,
    test_sessions: list[str] | None = None,
    config: str | Path | None = None,
    overrides: dict | None = None,
    out: str | Path | None = None,
    progress: bool = True,
    cache_dir: str | Path | None = None,
) -> dict:
    """MCVL's protocol on a synthetic town: training sessions build the index (``bundle``, built
    into ``WORKSPACE/indexes/vlad`` from the town's training sessions if not given), test sessions
    are queries. Writes ``eval_localize.json``, ``.md`` and one PNG per sequence into ``out``
    (default ``WORKSPACE/localize``).

    ``cache_dir``: keep each test session's retrieved ids and distances there
    (:func:`cached_query_all`), so that runs with other filter settings do not encode the images
    again; hits are reused only for the same bundle (fingerprint), session, top_k and images.
    Besides Table II, each session reports how often the top-1 and any of the top-k hits lie
    within ``RECALL_RADIUS_M`` of the truth (what any measurement model can work with).

    With ``refine: 6dof`` (the config or ``overrides``) the queries are registered against the
    reference model (``reference_model``, default ``WORKSPACE/reference_model``), which must hold
    no image of a test session; each session then gains the ``sixdof`` scores and its folder the
    6-DoF poses, and ``eval_localize.md`` a second table."""
    from mapkit.evaluation.truth import town_sessions

    ws, truth = Workspace(workspace), Path(truth)
    cfg = load_config(LocalizeConfig, config, overrides)
    town = town_sessions(truth)
    if not town:
        raise InputError(
            truth / "world" / "manifest.json", "no sessions listed: not a synthetic town folder?", field="sessions"
        )
    built = ws.session_names("imagedb")
    train = [n for n in built if town.get(n, {}).get("role") == "train"]
    tests = test_sessions or [n for n in built if town.get(n, {}).get("role") == "test"]
    loc = open_reference_model(cfg, ws.root) if cfg.refine == "6dof" else None
    try:
        if loc is not None and (clash := _model_clash(loc, ws, tests)):
            raise InputError(
                loc.folder,
                f"test session(s) {clash} are in the reference model: they cannot be queries (build it from the "
                "training sessions: mapkit model --session ...)",
                field="sessions",
            )
        return _evaluate(ws, truth, bundle, cfg, town, train, tests, out, progress, cache_dir, loc)
    finally:
        if loc is not None:
            loc.close()


def _evaluate(
    ws: Workspace,
    truth: Path,
    bundle: str | Path | None,
    cfg: LocalizeConfig,
    town: dict,
    train: list[str],
    tests: list[str],
    out: str | Path | None,
    progress: bool,
    cache_dir: str | Path | None,
    loc: SixDofLocalizer | None,
) -> dict:
    out = Path(out) if out is not None else ws.localize_dir
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "config.yaml", dump_config(cfg))
    if bundle is None:  # `mapkit eval localize WS --truth TOWN` without --bundle: the town's training sessions
        bundle = build_vlad_index(
            ws.root, overrides={"train_sessions": train, "database_sessions": train}, progress=progress
        )
    index = VladIndex.load(bundle)
    clash = sorted(set(tests) & (set(index.database_sessions) | set(index.train_sessions)))
    if clash:
        raise InputError(
            Path(bundle) / "manifest.json",
            f"test session(s) {clash} are in the index: they cannot be queries",
            field="sessions",
        )
    ws_frame = ws.require_frame()
    results: dict = {"bundle": str(bundle), "train_sessions": index.train_sessions, "sessions": {}}
    model_fit = None
    if loc is not None:
        model_fit = _model_frame_truth(ws, truth, ws_frame, loc)
        results["model_from_truth"] = {k: v for k, v in model_fit.items() if k != "transform"}
        results["model_from_truth"]["matrix"] = model_fit["transform"].tolist()
    timings: dict = {}
    for name in tests:
        results["sessions"][name], timings[name] = _localize_session(
            ws, truth, name, index, cfg, ws_frame, town.get(name, {}), out, cache_dir, progress, loc, model_fit
        )
    write_json(out / "eval_localize.json", results)
    write_timings(out, sessions=timings)
    atomic_write_text(out / "eval_localize.md", format_localization(results))
    return results


def stacked_poses(poses: list[np.ndarray | None]) -> np.ndarray:
    """(n, 4, 4) the given poses, NaN where one is None (a query without an estimate fails every band)."""
    nan = np.full((4, 4), np.nan)
    return np.array([nan if T is None else T for T in poses])


def _model_frame_truth(ws: Workspace, truth: Path, ws_frame: LocalFrame, loc: SixDofLocalizer) -> dict:
    """The rigid transform that takes the town's true camera poses into the reference model's frame, fitted on the
    model's database images alone (their known poses against their truth, as ``mapkit export benchmark`` fits it):
    the aligned frame the model is built in sits off the truth by the drives' common GPS bias, which no localizer
    on that map can see. ``transform`` (4, 4), the images it was fitted on and its residual."""
    from mapkit.deploy.benchmark import fit_truth
    from mapkit.evaluation.truth import truth_camera_poses_at

    by_path = loc.names_by_path()
    model_T, truth_T = [], []
    for session in ws.sessions_with_images():
        imgs = read_session_images(ws.root, session)
        found = [(i, by_path.get(Path(p).resolve())) for i, p in enumerate(imgs.image_paths)]
        names = {i: n for i, n in found if n is not None}
        at = sorted(names)
        if not at:
            continue
        try:
            T, ok = truth_camera_poses_at(truth, session, ws_frame, imgs.table["stamp_ns"][at])
        except MapkitError:
            continue  # a session the town did not drive: no truth
        model_T += [loc.world_from_cam(names[i]) for i, good in zip(at, ok, strict=True) if good]
        truth_T += list(T[ok])
    fit = fit_truth(np.array(model_T).reshape(-1, 4, 4), np.array(truth_T).reshape(-1, 4, 4), "the town", 3, loc.folder)
    return {
        "transform": fit.model_from_truth,
        "fit_images": fit.fit_images,
        "offset_m": float(np.linalg.norm(fit.model_from_truth[:3, 3])),
        "residual_rmse_m": fit.residual_rmse_m,
        "residual_max_m": fit.residual_max_m,
    }


def _localize_session(
    ws: Workspace,
    truth: Path,
    name: str,
    index: VladIndex,
    cfg: LocalizeConfig,
    ws_frame: LocalFrame,
    town_entry: dict,
    out: Path,
    cache_dir: str | Path | None,
    progress: bool,
    loc: SixDofLocalizer | None = None,
    model_fit: dict | None = None,
) -> tuple[dict, dict]:
    """One test session through retrieval and the filter (and the 6-DoF registration with ``loc``):
    its row of Table II and its recall, and its timings (a run record); draws its track against the
    truth into ``out/<name>.png``. The 6-DoF scores of all three estimates are against the truth in the
    model's frame (``model_fit``), as a localization benchmark states it."""
    from mapkit.evaluation.truth import truth_camera_poses_at

    imgs = read_session_images(ws.root, name)
    gt, ok = truth_camera_poses_at(truth, name, ws_frame, imgs.table["stamp_ns"])
    paths = [p for p, good in zip(imgs.image_paths, ok, strict=True) if good]
    # the query session's own relative camera motion between queries: its image table's poses come from its
    # odometry, placed rigidly (georef) or smoothly (align) in the map, and relative motion does not see that
    # placement; run_localizer turns it into the base's motion through the mount (with odometry on), and the 6-DoF
    # refinement checks consecutive poses with it
    cams = imgs.world_from_cam[ok]
    steps = odometry_steps(list(cams))
    odo = steps if cfg.odometry else None
    t0 = time.perf_counter()
    ids, dist, cached = cached_query_all(index, paths, cfg.top_k, cache_dir, name, progress=progress)
    t_retrieve = time.perf_counter() - t0
    r = run_localizer(index, paths, cfg, odo, progress=False, hits=(ids, dist))
    wall = time.perf_counter() - t0
    e_ret = pose_errors(r.retrieval_position, r.retrieval_rotation, gt[:, :3, 3], gt[:, :3, :3])
    e_fil = pose_errors(r.filter_position, r.filter_rotation, gt[:, :3, 3], gt[:, :3, :3])
    entry = {
        "condition": town_entry.get("condition") or town_entry.get("weather"),
        "queries": len(paths),
        "retrieval": e_ret.summary(),
        "filter": e_fil.summary(),
        **hit_recall(index, ids, gt[:, :3, 3]),
    }
    timings: dict[str, float | bool | None] = {
        "seconds": wall,
        "hits_from_cache": cached,
        "seconds_per_query": wall / max(1, len(paths)),
        "retrieval_s_per_query": t_retrieve / max(1, len(paths)),
        "filter_ms_per_step": 1000 * r.filter_s / max(1, len(paths)),
    }
    write_run_trajectories(out / name, imgs.table["stamp_ns"][ok], r)  # the estimates, for evo and mapkit view
    if loc is None:
        remove_sixdof_outputs(out / name)
    else:
        t1 = time.perf_counter()
        cameras = [im.camera for im, good in zip(workspace_images(ws, [name]), ok, strict=True) if good]
        names = [p for p, good in zip(imgs.workspace_paths, ok, strict=True) if good]
        found = refine_sixdof(loc, index, r, paths, cameras, names, progress, odometry=steps)
        summary = write_sixdof(out / name, imgs.table["stamp_ns"][ok], found, loc)
        est = stacked_poses([x.world_from_cam for x in found])
        sequence = [x.sequence_world_from_cam for x in found]
        gt_model = gt if model_fit is None else model_fit["transform"] @ gt
        entry["sixdof"] = {
            "accepted_share": summary["accepted_share"],
            "6dof": asdict(pose_band_scores(gt_model, est)),
            # the pose graph's, where the run made one
            **(
                {"sequence": asdict(pose_band_scores(gt_model, stacked_poses(sequence)))}
                if any(T is not None for T in sequence)
                else {}
            ),
            "filter": asdict(pose_band_scores(gt_model, r.poses("filter"))),
            "retrieval": asdict(pose_band_scores(gt_model, r.poses("retrieval"))),
        }
        timings["sixdof_s_per_query"] = (time.perf_counter() - t1) / max(1, len(paths))
        timings.update(sixdof_timings(found))
    localization_track(
        out / f"{name}.png",
        gt[:, :3, 3],
        r.retrieval_position,
        r.filter_position,
        f"{name}: MCVL on {len(paths)} queries (median error: retrieval "
        f"{entry['retrieval']['median_translation_m']:.1f} m, filter "
        f"{entry['filter']['median_translation_m']:.1f} m)",
    )
    return entry, timings


def format_localization(results: dict) -> str:
    """Table II of the MCVL paper: per test sequence, mean and median errors of retrieval alone
    and of the filter; then how often the top-1, top-5 and top-k hold the right place."""
    lines = [
        "| sequence | condition | queries | retrieval mean m / deg | retrieval median m / deg | MCVL mean m / deg | "
        "MCVL median m / deg | recall@1 / @5 / @k |",
        "|---|---|---|---|---|---|---|---|",
    ]
    f = lambda s, k: "" if s.get(k) is None else f"{s[k]:.2f}"  # noqa: E731 (a one-line helper local to this function)
    for name, r in results["sessions"].items():
        a, b = r["retrieval"], r["filter"]
        at = sorted((int(k[len("recall_at_") :]), v) for k, v in r.items() if k.startswith("recall_at_"))
        recall = " / ".join(f"{v:.2f}" for _, v in at)
        lines.append(
            f"| {name} | {r.get('condition') or ''} | {r['queries']} | {f(a, 'mean_translation_m')} / "
            f"{f(a, 'mean_rotation_deg')} | {f(a, 'median_translation_m')} / {f(a, 'median_rotation_deg')} | "
            f"{f(b, 'mean_translation_m')} / {f(b, 'mean_rotation_deg')} | {f(b, 'median_translation_m')} / "
            f"{f(b, 'median_rotation_deg')} | {recall} |"
        )
    table = "\n".join(lines) + "\n"
    return table + ("\n" + format_sixdof(results) if any("sixdof" in r for r in results["sessions"].values()) else "")


#: the estimates of the 6-DoF table, in its row order
SIXDOF_ROWS = (("6dof", "6-DoF"), ("sequence", "6-DoF + odometry"), ("filter", "MCVL"), ("retrieval", "retrieval"))


def format_sixdof(results: dict) -> str:
    """Per test sequence, on the same queries: the share of the 6-DoF poses (each image's own registration, and the
    pose graph's that joins them by the odometry where the run made one), the filter's and retrieval's
    within each band of the visual localization benchmark and their median errors; the share of queries the
    registration accepted (its times are in the run's ``timings.json``)."""
    head = " | ".join(f"{a:g} m, {b:g} deg" for a, b in THRESHOLDS)
    lines = [
        f"| sequence | queries | estimate | {head} | median m / deg | accepted |",
        "|---|---|---|" + "---|" * len(THRESHOLDS) + "---|---|",
    ]
    med = lambda v, d=2: "-" if v is None else f"{v:.{d}f}"  # noqa: E731 (a one-line helper local to this function)
    for name, r in results["sessions"].items():
        s = r.get("sixdof")
        if s is None:
            continue
        for key, label in SIXDOF_ROWS:
            e = s.get(key)
            if e is None:
                continue  # a run without the pose graph has no sequence row
            shares = " | ".join(f"{100 * e['recall'][band_key(a, b)]:.1f} %" for a, b in THRESHOLDS)
            extra = f"{100 * (s['accepted_share'] or 0):.1f} %" if key == "6dof" else ""
            lines.append(
                f"| {name} | {e['queries']} | {label} | {shares} | {med(e['median_translation_m'], 3)} / "
                f"{med(e['median_rotation_deg'])} | {extra} |"
            )
    return "\n".join(lines) + "\n"
