"""``mapkit localize`` and ``mapkit eval localize``: the MCVL localizer on a VLAD bundle.

Each query image is encoded once; its top-20 database images give the measurement z_t (mean
shift, largest cluster); the particle filter of :mod:`mapkit.mcl` runs over the sequence. The
evaluation follows the MCVL paper's protocol (section IV): training sessions build the index,
test sessions are queries; per sequence the translation error ||c_est - c_gt|| and the orientation
error, mean and median, for retrieval alone and for the filter (Table II), and a plot of the
estimated against the true trajectory (Fig. 5).

Camera poses: the filter's state is the camera pose ``world_from_camera`` in the workspace's ENU
frame, as the database's poses are.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Optional

import numpy as np
from pydantic import Field

from .config import MapkitConfig, dump_config, load_config
from .errors import InputError
from .geometry import invert_pose
from .mcl import MclConfig, MonteCarloLocalizer, pose_errors
from .runio import atomic_write_text, write_json


class LocalizeConfig(MapkitConfig):
    mcl: MclConfig = MclConfig()
    top_k: int = Field(20, ge=1, description="Retrieved database images per query (MCVL IV-A: R = 20).")
    bandwidth_m: float = Field(5.0, gt=0, description="Mean-shift bandwidth over the retrieved translations (m; the authors' code).")
    odometry: bool = Field(False, description="Beyond the paper: drive the motion model by the query session's own trajectory "
                           "(its relative camera motion between queries) instead of eqs. 1-2. Sets mcl.odometry.enabled.")
    seed: int = Field(0, description="Seed of the particle filter.")


def run_localizer(index, images, cfg: LocalizeConfig, odometry: Optional[list] = None, progress: bool = False) -> dict:
    """Retrieval alone and the filter over a sequence of images (arrays or files).

    Returns per query: the measurement's pose (retrieval alone), the filter's pose, and the
    measurement's cluster size.
    """
    mcl_cfg = cfg.mcl.model_copy(update={"odometry": cfg.mcl.odometry.model_copy(update={"enabled": cfg.odometry})})
    loc = MonteCarloLocalizer(mcl_cfg, seed=cfg.seed)
    n = len(images)
    z_pos, z_rot = np.full((n, 3), np.nan), np.full((n, 3, 3), np.nan)
    f_pos, f_rot = np.full((n, 3), np.nan), np.full((n, 3, 3), np.nan)
    sizes = np.zeros(n, np.int64)
    seconds = {"retrieval": 0.0, "filter": 0.0}
    for t, im in enumerate(images):
        t0 = time.perf_counter()
        hits = index.query(im, cfg.top_k)
        z = index.measurement_from_hits(hits) if cfg.bandwidth_m == index.cfg.mean_shift_bandwidth_m else _measure(hits, cfg.bandwidth_m)
        t1 = time.perf_counter()
        est = loc.step(z, None if odometry is None or not loc.initialized else odometry[t])
        seconds["retrieval"] += t1 - t0
        seconds["filter"] += time.perf_counter() - t1
        z_pos[t], z_rot[t], sizes[t] = z.translation, z.rotation, z.cluster_size
        if est is not None:
            f_pos[t], f_rot[t] = est.position, est.rotation
        if progress:
            print(f"\r[localize] {t + 1}/{n} queries", end="", file=sys.stderr, flush=True)
    if progress:
        print(file=sys.stderr)
    return {"retrieval_position": z_pos, "retrieval_rotation": z_rot, "filter_position": f_pos, "filter_rotation": f_rot,
            "cluster_size": sizes, "seconds": seconds}


def _measure(hits, bandwidth_m: float):
    from .measurement import mean_shift_measurement

    return mean_shift_measurement(hits.translations, hits.world_from_cam[:, :3, :3], bandwidth=bandwidth_m)


def evaluate_localization(workspace: str | Path, truth: str | Path, bundle: str | Path | None = None,
                          test_sessions: Optional[list[str]] = None, config: str | Path | None = None,
                          overrides: Optional[dict] = None, out: str | Path | None = None, progress: bool = True) -> dict:
    """MCVL's protocol on a synthetic town: training sessions build the index (``bundle``, built
    into ``WORKSPACE/indexes/vlad`` from the town's training sessions if not given), test sessions
    are queries. Writes ``eval_localize.json``, ``.md`` and one PNG per sequence into ``out``
    (default ``WORKSPACE/localize``)."""
    from .eval_retrieval import _truth_camera_poses
    from .evaluate import town_sessions
    from .geodesy import LocalFrame
    from .index_vlad import VladIndex, build_vlad_index, read_session_images

    ws, truth = Path(workspace), Path(truth)
    cfg = load_config(LocalizeConfig, config, overrides)
    out = Path(out) if out is not None else ws / "localize"
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "config.yaml", dump_config(cfg))
    town = town_sessions(truth)
    if not town:
        raise InputError(truth / "world" / "manifest.json", "no sessions listed: not a synthetic town folder?", field="sessions")
    built = sorted(p.name for p in (ws / "sessions").iterdir() if (p / "imagedb" / ".done").is_file())
    train = [n for n in built if town.get(n, {}).get("role") == "train"]
    tests = test_sessions or [n for n in built if town.get(n, {}).get("role") == "test"]
    if bundle is None:
        bundle = build_vlad_index(ws, overrides={"train_sessions": train, "database_sessions": train}, progress=progress)
    index = VladIndex.load(bundle)
    clash = sorted(set(tests) & (set(index.database_sessions) | set(index.train_sessions)))
    if clash:
        raise InputError(Path(bundle) / "manifest.json", f"test session(s) {clash} are in the index: they cannot be queries", field="sessions")
    ws_frame = LocalFrame.from_dict(json.loads((ws / "origin.json").read_text()))
    results: dict = {"bundle": str(bundle), "train_sessions": index.train_sessions, "sessions": {}}
    for name in tests:
        imgs = read_session_images(ws, name)
        gt, ok = _truth_camera_poses(truth, name, ws_frame, imgs.table["stamp_ns"])
        paths = [p for p, good in zip(imgs.image_paths, ok) if good]
        odo = None
        if cfg.odometry:
            # the query session's own relative camera motion between queries: its image table's
            # poses come from its odometry, placed rigidly (georef) or smoothly (align) in the
            # map, and relative motion does not see that placement
            cams = imgs.world_from_cam[ok]
            odo = [None] + [invert_pose(cams[k - 1]) @ cams[k] for k in range(1, len(cams))]
        t0 = time.perf_counter()
        r = run_localizer(index, paths, cfg, odo, progress=progress)
        wall = time.perf_counter() - t0
        e_ret = pose_errors(r["retrieval_position"], r["retrieval_rotation"], gt[:, :3, 3], gt[:, :3, :3])
        e_fil = pose_errors(r["filter_position"], r["filter_rotation"], gt[:, :3, 3], gt[:, :3, :3])
        results["sessions"][name] = {
            "condition": town.get(name, {}).get("condition") or town.get(name, {}).get("weather"),
            "queries": len(paths), "retrieval": e_ret.summary(), "filter": e_fil.summary(), "seconds": wall,
            "seconds_per_query": wall / max(1, len(paths)), "filter_ms_per_step": 1000 * r["seconds"]["filter"] / max(1, len(paths)),
        }
        from .plots import localization_track

        localization_track(out / f"{name}.png", gt[:, :3, 3], r["retrieval_position"], r["filter_position"],
                           f"{name}: MCVL on {len(paths)} queries (median error: retrieval "
                           f"{results['sessions'][name]['retrieval']['median_translation_m']:.1f} m, filter "
                           f"{results['sessions'][name]['filter']['median_translation_m']:.1f} m)")
    write_json(out / "eval_localize.json", results)
    atomic_write_text(out / "eval_localize.md", format_localization(results))
    return results


def localize_log(bundle: str | Path, log: str | Path, out: str | Path, config: str | Path | None = None,
                 camera: Optional[str] = None, progress: bool = True) -> Path:
    """Run the localizer on the camera images of a drive log against a VLAD bundle; writes the
    filter's and retrieval's camera poses as TUM files, the resolved config and metrics."""
    from .index_vlad import VladIndex
    from .io import open_log
    from .io.trajectory import write_tum
    from .types import StreamKind

    cfg = load_config(LocalizeConfig, config)
    index = VladIndex.load(bundle)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "config.yaml", dump_config(cfg))
    with open_log(log) as lg:
        frames = [f for f in lg.records(StreamKind.IMAGE) if camera is None or f.camera == camera]
        if not frames:
            raise InputError(log, "no camera images" + (f" from camera {camera!r}" if camera else ""), field="topics.images")
        cams = {f.camera for f in frames}
        if len(cams) > 1:
            raise InputError(log, f"images of {len(cams)} cameras ({sorted(cams)}): choose one with --camera", field="camera")
        stamps = np.array([f.stamp_ns for f in frames], np.int64)
        t0 = time.perf_counter()
        r = run_localizer(index, [f.image for f in frames], cfg, progress=progress)
    ok = np.isfinite(r["filter_position"][:, 0])
    for key, name in (("filter", "poses_tum.txt"), ("retrieval", "retrieval_tum.txt")):
        T = np.tile(np.eye(4), (len(stamps), 1, 1))
        T[:, :3, :3], T[:, :3, 3] = r[f"{key}_rotation"], r[f"{key}_position"]
        write_tum(out / name, stamps[ok], T[ok])
    write_json(out / "metrics.json", {"bundle": str(bundle), "log": str(log), "queries": len(stamps), "seconds": time.perf_counter() - t0,
                                      "filter_ms_per_step": 1000 * r["seconds"]["filter"] / len(stamps),
                                      "frame": "workspace ENU of the bundle (world_from_camera)"})
    return out


def format_localization(results: dict) -> str:
    """Table II of the MCVL paper: per test sequence, mean and median errors of retrieval alone
    and of the filter."""
    lines = ["| sequence | condition | queries | retrieval mean m / deg | retrieval median m / deg | MCVL mean m / deg | MCVL median m / deg |",
             "|---|---|---|---|---|---|---|"]
    f = lambda s, k: "" if s.get(k) is None else f"{s[k]:.2f}"  # noqa: E731
    for name, r in results["sessions"].items():
        a, b = r["retrieval"], r["filter"]
        lines.append(f"| {name} | {r.get('condition') or ''} | {r['queries']} | {f(a, 'mean_translation_m')} / {f(a, 'mean_rotation_deg')} | "
                     f"{f(a, 'median_translation_m')} / {f(a, 'median_rotation_deg')} | {f(b, 'mean_translation_m')} / {f(b, 'mean_rotation_deg')} | "
                     f"{f(b, 'median_translation_m')} / {f(b, 'median_rotation_deg')} |")
    return "\n".join(lines) + "\n"
