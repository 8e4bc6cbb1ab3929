"""``mapkit localize`` and ``mapkit eval localize``: the MCVL localizer on a VLAD bundle.

Each query image is encoded once; its top-20 database images give the measurement z_t (mean
shift, largest cluster); the particle filter of :mod:`mapkit.mcl` runs over the sequence. The
evaluation follows the MCVL paper's protocol (section IV): training sessions build the index,
test sessions are queries; per sequence the translation error ||c_est - c_gt|| and the orientation
error, mean and median, for retrieval alone and for the filter (Table II), and a plot of the
estimated against the true trajectory (Fig. 5).

Camera poses: the filter's state is the camera pose ``world_from_camera`` in the workspace's ENU
frame, as the database's poses are.

Beyond the paper (presets in ``configs/localize/``): the query session's relative motion as
odometry, and the multi-hypothesis measurement model of :mod:`mapkit.mcl`, which weighs the
particles by all top-k retrieved poses. Retrieval (encoding each image with dense SIFT, the
expensive part) can be cached per test session (:func:`cached_query_all`), so that runs with
other filter settings reuse the hits of the same bundle.
"""

from __future__ import annotations

import hashlib
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
from .measurement import PoseHypotheses
from .runio import atomic_path, atomic_write_text, write_json


class LocalizeConfig(MapkitConfig):
    mcl: MclConfig = MclConfig()
    top_k: int = Field(20, ge=1, description="Retrieved database images per query (MCVL IV-A: R = 20).")
    bandwidth_m: float = Field(5.0, gt=0, description="Mean-shift bandwidth over the retrieved translations (m; the authors' code).")
    odometry: bool = Field(False, description="Beyond the paper: drive the motion model by the query session's own trajectory "
                           "(its relative camera motion between queries) instead of eqs. 1-2. Sets mcl.odometry.enabled.")
    seed: int = Field(0, description="Seed of the particle filter.")


def run_localizer(index, images, cfg: LocalizeConfig, odometry: Optional[list] = None, progress: bool = False,
                  hits: Optional[tuple[np.ndarray, np.ndarray]] = None) -> dict:
    """Retrieval alone and the filter over a sequence of images (arrays or files).

    ``hits`` = ``(ids, distances)`` (n, top_k) already retrieved for the images (e.g. from
    :func:`cached_query_all`) skips encoding them. Returns per query: the measurement's pose
    (retrieval alone), the filter's pose, the measurement's cluster size, and the retrieved ids.
    """
    mcl_cfg = cfg.mcl.model_copy(update={"odometry": cfg.mcl.odometry.model_copy(update={"enabled": cfg.odometry})})
    mh = mcl_cfg.multi_hypothesis
    loc = MonteCarloLocalizer(mcl_cfg, seed=cfg.seed)
    n = len(images)
    if hits is not None and (hits[0].shape[0] != n or hits[0].shape[1] < 1):
        raise ValueError(f"hits for {hits[0].shape[0]} queries given with {n} images")
    z_pos, z_rot = np.full((n, 3), np.nan), np.full((n, 3, 3), np.nan)
    f_pos, f_rot = np.full((n, 3), np.nan), np.full((n, 3, 3), np.nan)
    sizes = np.zeros(n, np.int64)
    all_ids = np.full((n, cfg.top_k), -1, np.int64)
    seconds = {"retrieval": 0.0, "filter": 0.0}
    for t, im in enumerate(images):
        t0 = time.perf_counter()
        h = index.query(im, cfg.top_k) if hits is None else index.hits(hits[0][t, :cfg.top_k], hits[1][t, :cfg.top_k])
        z = index.measurement_from_hits(h) if cfg.bandwidth_m == index.cfg.mean_shift_bandwidth_m else _measure(h, cfg.bandwidth_m)
        t1 = time.perf_counter()
        hyp = (PoseHypotheses.from_retrieval(h.translations, h.world_from_cam[:, :3, :3], h.distances, mh.hit_weighting, mh.hit_weight_scale)
               if mh.enabled else None)
        est = loc.step(z, None if odometry is None or not loc.initialized else odometry[t], hyp)
        seconds["retrieval"] += t1 - t0
        seconds["filter"] += time.perf_counter() - t1
        z_pos[t], z_rot[t], sizes[t] = z.translation, z.rotation, z.cluster_size
        all_ids[t, :len(h)] = h.ids
        if est is not None:
            f_pos[t], f_rot[t] = est.position, est.rotation
        if progress:
            print(f"\r[localize] {t + 1}/{n} queries", end="", file=sys.stderr, flush=True)
    if progress:
        print(file=sys.stderr)
    return {"retrieval_position": z_pos, "retrieval_rotation": z_rot, "filter_position": f_pos, "filter_rotation": f_rot,
            "cluster_size": sizes, "ids": all_ids, "seconds": seconds}


def _measure(hits, bandwidth_m: float):
    from .measurement import mean_shift_measurement

    return mean_shift_measurement(hits.translations, hits.world_from_cam[:, :3, :3], bandwidth=bandwidth_m)


# --- per-session query hits, cached ----------------------------------------------------------------

#: version of the hits cache files; bump when their content changes meaning
HITS_CACHE_VERSION = 1


def bundle_fingerprint(index) -> str:
    """What identifies a bundle's answers to queries: its build hash and the sha256 of its manifest.

    The build hash alone is not enough: :meth:`VladIndex.add_session` grows a bundle in place and
    keeps its build hash, and query-time settings (e.g. ``nprobe``) change the hits without a
    rebuild; the manifest lists every file's sha256 and the resolved config, so its digest
    changes with either.
    """
    digest = hashlib.sha256((Path(index.path) / "manifest.json").read_bytes()).hexdigest()[:16]
    return f"{index.manifest.get('build_hash', 'nohash')}-{digest}"


def _images_digest(images: list) -> str:
    """Digest of the query images' paths, sizes and modification times (files only)."""
    h = hashlib.sha256()
    for p in images:
        st = Path(p).stat()
        h.update(f"{Path(p).resolve()}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
    return h.hexdigest()[:16]


def query_all(index, images, top_k: int, progress: bool = False, label: str = "query",
              vector_cache: str | Path | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Retrieved ids (n, top_k; -1 pads when the index is smaller) and squared L2 distances of every image."""
    n = len(images)
    ids, dist = np.full((n, top_k), -1, np.int64), np.full((n, top_k), np.inf, np.float32)
    if n and all(isinstance(im, (str, Path)) for im in images):
        # image files: encoded on the run's executor (a process pool or Ray), then one batched search
        d, i = index.search(index.encode_files(images, progress=progress, desc=label, cache_dir=vector_cache), top_k)
        ids[:, : i.shape[1]], dist[:, : d.shape[1]] = i, d
        return ids, dist
    for t, im in enumerate(images):
        d, i = index.search(index._as_vector(im)[None], top_k)
        ids[t], dist[t] = i[0], d[0]
        if progress:
            print(f"\r[{label}] {t + 1}/{n} queries", end="", file=sys.stderr, flush=True)
    if progress:
        print(file=sys.stderr)
    return ids, dist


def cached_query_all(index, images: list, top_k: int, cache_dir: str | Path | None, session: str,
                     progress: bool = False) -> tuple[np.ndarray, np.ndarray, bool]:
    """:func:`query_all` through a cache file ``hits-<session>-k<top_k>-<bundle fingerprint>.npz``.

    A cached file is used only if it names the same bundle fingerprint, session, top_k and query
    images (paths, sizes, mtimes); otherwise the images are encoded again and the file replaced.
    Returns ``(ids, distances, from_cache)``.
    """
    if cache_dir is None:
        return (*query_all(index, images, top_k, progress, session), False)
    fp = bundle_fingerprint(index)
    path = Path(cache_dir) / f"hits-{session}-k{top_k}-{fp}.npz"
    img_digest = _images_digest(images)
    if path.is_file():
        try:
            with np.load(path, allow_pickle=False) as f:
                ok = (int(f["version"]) == HITS_CACHE_VERSION and str(f["bundle"]) == fp and str(f["session"]) == session
                      and int(f["top_k"]) == top_k and str(f["images"]) == img_digest and f["ids"].shape == (len(images), top_k))
                if ok:
                    return f["ids"].astype(np.int64), f["distances"].astype(np.float32), True
        except (OSError, KeyError, ValueError):
            pass  # unreadable or from another version: recompute below
    ids, dist = query_all(index, images, top_k, progress, session, vector_cache=cache_dir)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez(f, version=HITS_CACHE_VERSION, bundle=fp, bundle_path=str(Path(index.path).resolve()), session=session,
                 top_k=top_k, images=img_digest, ids=ids, distances=dist)
    return ids, dist, False


#: radius (m) within which a retrieved image counts as the right place in the recall diagnostics
RECALL_RADIUS_M = 25.0


def hit_recall(index, ids: np.ndarray, gt_positions: np.ndarray, radius_m: float = RECALL_RADIUS_M) -> dict:
    """Share of queries whose top-1, and whose best of the top-k, retrieved image lies within
    ``radius_m`` of the query's true position."""
    valid = ids >= 0
    pos = index.world_from_cam[np.where(valid, ids, 0), :3, 3]
    d = np.where(valid, np.linalg.norm(pos - gt_positions[:, None, :], axis=-1), np.inf)
    return {"recall_at_1": float(np.mean(d[:, 0] <= radius_m)), f"recall_at_{ids.shape[1]}": float(np.mean(d.min(axis=1) <= radius_m)),
            "recall_radius_m": radius_m}


def evaluate_localization(workspace: str | Path, truth: str | Path, bundle: str | Path | None = None,
                          test_sessions: Optional[list[str]] = None, config: str | Path | None = None,
                          overrides: Optional[dict] = None, out: str | Path | None = None, progress: bool = True,
                          cache_dir: str | Path | None = None) -> dict:
    """MCVL's protocol on a synthetic town: training sessions build the index (``bundle``, built
    into ``WORKSPACE/indexes/vlad`` from the town's training sessions if not given), test sessions
    are queries. Writes ``eval_localize.json``, ``.md`` and one PNG per sequence into ``out``
    (default ``WORKSPACE/localize``).

    ``cache_dir``: keep each test session's retrieved ids and distances there
    (:func:`cached_query_all`), so that runs with other filter settings do not encode the images
    again; hits are reused only for the same bundle (fingerprint), session, top_k and images.
    Besides Table II, each session reports how often the top-1 and any of the top-k hits lie
    within ``RECALL_RADIUS_M`` of the truth (what any measurement model can work with)."""
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
        ids, dist, cached = cached_query_all(index, paths, cfg.top_k, cache_dir, name, progress=progress)
        t_retrieve = time.perf_counter() - t0
        r = run_localizer(index, paths, cfg, odo, progress=False, hits=(ids, dist))
        wall = time.perf_counter() - t0
        e_ret = pose_errors(r["retrieval_position"], r["retrieval_rotation"], gt[:, :3, 3], gt[:, :3, :3])
        e_fil = pose_errors(r["filter_position"], r["filter_rotation"], gt[:, :3, 3], gt[:, :3, :3])
        results["sessions"][name] = {
            "condition": town.get(name, {}).get("condition") or town.get(name, {}).get("weather"),
            "queries": len(paths), "retrieval": e_ret.summary(), "filter": e_fil.summary(),
            **hit_recall(index, ids, gt[:, :3, 3]), "seconds": wall, "hits_from_cache": cached,
            "seconds_per_query": wall / max(1, len(paths)), "retrieval_s_per_query": t_retrieve / max(1, len(paths)),
            "filter_ms_per_step": 1000 * r["seconds"]["filter"] / max(1, len(paths)),
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
    and of the filter; then how often the top-1 and the top-k hold the right place."""
    lines = ["| sequence | condition | queries | retrieval mean m / deg | retrieval median m / deg | MCVL mean m / deg | MCVL median m / deg | recall@1 / @k |",
             "|---|---|---|---|---|---|---|---|"]
    f = lambda s, k: "" if s.get(k) is None else f"{s[k]:.2f}"  # noqa: E731
    for name, r in results["sessions"].items():
        a, b = r["retrieval"], r["filter"]
        at_k = next((v for k, v in r.items() if k.startswith("recall_at_") and k != "recall_at_1"), None)
        recall = "" if at_k is None else f"{r['recall_at_1']:.2f} / {at_k:.2f}"
        lines.append(f"| {name} | {r.get('condition') or ''} | {r['queries']} | {f(a, 'mean_translation_m')} / {f(a, 'mean_rotation_deg')} | "
                     f"{f(a, 'median_translation_m')} / {f(a, 'median_rotation_deg')} | {f(b, 'mean_translation_m')} / {f(b, 'mean_rotation_deg')} | "
                     f"{f(b, 'median_translation_m')} / {f(b, 'median_rotation_deg')} | {recall} |")
    return "\n".join(lines) + "\n"
