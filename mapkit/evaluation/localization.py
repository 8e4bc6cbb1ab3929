"""``mapkit eval localize``: the MCVL paper's protocol (section IV) on a synthetic town.

Training sessions build the index, test sessions are queries; per sequence the translation error
||c_est - c_gt|| and the orientation error, mean and median, for retrieval alone and for the filter
(Table II), and a plot of the estimated against the true trajectory (Fig. 5).

Errors are those of camera poses, as Table II's are: the filter runs on the vehicle's base pose
(:mod:`mapkit.localization.mcl`) and :func:`~mapkit.localization.localize.run_localizer` returns
its estimates converted back to the camera through ``LocalizeConfig.base_from_camera``.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from mapkit.core.config import dump_config, load_config
from mapkit.core.errors import InputError
from mapkit.core.geometry import invert_pose
from mapkit.core.runio import atomic_write_text, write_json, write_timings
from mapkit.core.workspace import Workspace
from mapkit.core.writers import writes_workspace
from mapkit.io.plots import localization_track
from mapkit.localization.localize import LocalizeConfig, cached_query_all, run_localizer, write_run_trajectories
from mapkit.localization.mcl import pose_errors
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
    within ``RECALL_RADIUS_M`` of the truth (what any measurement model can work with)."""
    from mapkit.evaluation.truth import town_sessions

    ws, truth = Workspace(workspace), Path(truth)
    cfg = load_config(LocalizeConfig, config, overrides)
    out = Path(out) if out is not None else ws.localize_dir
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "config.yaml", dump_config(cfg))
    town = town_sessions(truth)
    if not town:
        raise InputError(
            truth / "world" / "manifest.json", "no sessions listed: not a synthetic town folder?", field="sessions"
        )
    built = ws.session_names("imagedb")
    train = [n for n in built if town.get(n, {}).get("role") == "train"]
    tests = test_sessions or [n for n in built if town.get(n, {}).get("role") == "test"]
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
    timings: dict = {}
    for name in tests:
        results["sessions"][name], timings[name] = _localize_session(
            ws, truth, name, index, cfg, ws_frame, town.get(name, {}), out, cache_dir, progress
        )
    write_json(out / "eval_localize.json", results)
    write_timings(out, sessions=timings)
    atomic_write_text(out / "eval_localize.md", format_localization(results))
    return results


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
) -> tuple[dict, dict]:
    """One test session through retrieval and the filter: its row of Table II and its recall, and
    its timings (a run record); draws its track against the truth into ``out/<name>.png``."""
    from mapkit.evaluation.truth import truth_camera_poses_at

    imgs = read_session_images(ws.root, name)
    gt, ok = truth_camera_poses_at(truth, name, ws_frame, imgs.table["stamp_ns"])
    paths = [p for p, good in zip(imgs.image_paths, ok, strict=True) if good]
    odo = None
    if cfg.odometry:
        # the query session's own relative camera motion between queries: its image table's
        # poses come from its odometry, placed rigidly (georef) or smoothly (align) in the
        # map, and relative motion does not see that placement; run_localizer turns it into the
        # base's motion through the mount
        cams = imgs.world_from_cam[ok]
        odo = [None] + [invert_pose(cams[k - 1]) @ cams[k] for k in range(1, len(cams))]
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
    timings = {
        "seconds": wall,
        "hits_from_cache": cached,
        "seconds_per_query": wall / max(1, len(paths)),
        "retrieval_s_per_query": t_retrieve / max(1, len(paths)),
        "filter_ms_per_step": 1000 * r.filter_s / max(1, len(paths)),
    }
    write_run_trajectories(out / name, imgs.table["stamp_ns"][ok], r)  # the estimates, for evo and mapkit view
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
    return "\n".join(lines) + "\n"
