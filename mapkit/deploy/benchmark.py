"""``mapkit export benchmark``: a workspace as a 6-DoF visual localization benchmark, the folder that
hloc's ``localize_sfm``, COLMAP's image registrator and the visual localization benchmark's
entries read, with the ground truth that scores them (:mod:`mapkit.evaluation.benchmark`).

Output (``OUT``)::

    sfm/                          the reference model (``mapkit model``), a byte copy: COLMAP binary
    database.db                   its COLMAP database (keypoints, descriptors, matches of the database images)
    reference_model.yaml          the model's feature settings (its config.yaml)
    images/<model image name>     the database images, under the names the model gives them
    images/query/<session>/...    the query images
    queries_with_intrinsics.txt   name MODEL width height params... per query (COLMAP camera models)
    queries_gt.txt                name qw qx qy qz tx ty tz per query: cam_from_world in the model's frame
    pairs-query-retrieval.txt     query_name db_name: each query's top-k of the workspace's VLAD index
    conditions.json               per query: its session and condition (weather, time of day) where known
    README.md, config.yaml, metrics.json

``images/`` is one image root for both: the model's names resolve under it as they are, so
``pycolmap.Reconstruction(OUT/sfm)``, hloc (``images=OUT/images``) and COLMAP (``--image_path
OUT/images``) read the folder without renaming anything. Files are copied, never hard-linked.

Ground truth: the synthetic town's true camera poses (``--truth TOWN``), carried into the
workspace's ENU frame exactly (via ECEF), else the query sessions' own recorded poses. The model's
frame may differ from the truth's by a rigid transform (the alignment's small corrections): it is
fitted on the database images alone (each camera centre and a point 1 m along each of its axes,
Umeyama without scale) and applied to the queries' truth; its residual goes into metrics.json and
the README.
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydantic import Field

from mapkit.core.bundle import building, copy_file
from mapkit.core.config import MapkitConfig, dump_config, load_config
from mapkit.core.errors import InputError, MapkitError
from mapkit.core.geometry import interpolate_poses, invert_pose, rotation_angle_rad, umeyama
from mapkit.core.runio import atomic_write_text, progress_bar, write_json, write_timings
from mapkit.core.types import StreamKind
from mapkit.core.workspace import Workspace
from mapkit.core.writers import writes_workspace
from mapkit.io import open_log
from mapkit.io.benchmark import (
    CONDITIONS,
    DATABASE,
    GROUND_TRUTH,
    IMAGES,
    MODEL_CONFIG,
    PAIRS,
    QUERIES,
    QUERY_PREFIX,
    SFM,
    colmap_camera_params,
    model_image_root,
    write_pairs,
    write_queries_with_intrinsics,
)
from mapkit.io.trajectory import write_benchmark_poses
from mapkit.retrieval.vlad_bundle import read_session_images

log = logging.getLogger(__name__)

#: the reference model's folder under the workspace (``mapkit model``'s default)
MODEL_FOLDER = "reference_model"
#: length (m) of the camera axes whose tips join the centres in the fit: it weighs orientation against position
_AXIS_M = 1.0


class BenchmarkExportConfig(MapkitConfig):
    retrieval_k: int = Field(
        20,
        ge=1,
        description="Database images per query in pairs-query-retrieval.txt: the smallest of 10, 20 and 50 at "
        "which COLMAP's registrator (with mapkit's acceptance) placed as many clear-drive queries of the demo's "
        "seed-10 town within (0.5 m, 5 deg) as with 50 (the outside-localizer comparison scores seeds 7, 8 and 9); "
        "hloc's RobotCar Seasons pipeline retrieves 20 too.",
    )
    camera: str | None = Field(None, description="The camera of a query log with several (default: its only one).")
    min_fit_images: int = Field(
        3, ge=3, description="Database images with truth needed to fit the model's frame to the truth's."
    )
    recall_radius_m: float = Field(
        10.0,
        gt=0,
        description="Retrieval recall (metrics.json): a retrieved database image shows the query's place when its "
        "camera lies within this distance of the query's true camera ...",
    )
    recall_max_angle_deg: float = Field(
        30.0,
        gt=0,
        le=180,
        description="... and its optical axis within this angle of the query's (a forward camera's view overlaps).",
    )


@dataclass
class _Query:
    name: str
    session: str
    stamp_ns: int
    model: str
    width: int
    height: int
    params: list[float]
    source: Path | None  # an image file, or None for a log frame (written from ``frame``)
    frame: object = None
    recorded_world_from_cam: np.ndarray | None = None  # the session's own pose, workspace frame


@dataclass
class BenchmarkTruth:
    """The truth's fit to the model: ``model_from_truth`` (4, 4) and its residual over the database images."""

    source: str
    model_from_truth: np.ndarray
    fit_images: int
    residual_rmse_m: float
    residual_max_m: float
    residual_rotation_median_deg: float
    residual_rotation_max_deg: float


# --- inputs ------------------------------------------------------------------------------------------


def _require_inputs(ws: Workspace) -> tuple[Path, Path]:
    """The reference model folder and the VLAD index, or one InputError naming what to run."""
    model = ws.root / MODEL_FOLDER
    needed = (f"{SFM}/cameras.bin", f"{SFM}/images.bin", f"{SFM}/points3D.bin", DATABASE)
    if not all((model / f).is_file() for f in needed):
        raise InputError(model, f"no reference model here: run mapkit model {ws.root} first", field="reference_model")
    index = ws.vlad_index
    if not (index / "manifest.json").is_file():
        raise InputError(index, f"no VLAD index here: run mapkit index vlad {ws.root} first", field="vlad")
    return model, index


def _session_of_images(ws: Workspace) -> dict[Path, tuple[str, int, np.ndarray]]:
    """Every database image of the workspace by resolved path: (session, stamp, recorded world_from_cam)."""
    out: dict[Path, tuple[str, int, np.ndarray]] = {}
    for name in ws.sessions_with_images():
        s = read_session_images(ws, name)
        for p, stamp, T in zip(s.image_paths, s.table["stamp_ns"], s.world_from_cam, strict=True):
            out[Path(p).resolve()] = (name, int(stamp), T)
    return out


def _imagedb_queries(ws: Workspace, session: str) -> list[_Query]:
    """A query session's images from its image database, with the COLMAP cameras the database wrote."""
    import pycolmap

    s = read_session_images(ws, session)
    imagedb = ws.session(session).imagedb
    rec = pycolmap.Reconstruction(str(imagedb / "colmap"))
    out = []
    for p, stamp, T in zip(s.image_paths, s.table["stamp_ns"], s.world_from_cam, strict=True):
        rel = Path(os.path.relpath(p, imagedb))
        im = rec.find_image_with_name(rel.as_posix())
        if im is None:
            raise InputError(imagedb / "colmap", f"session {session!r}: image {rel} has no intrinsics", field="images")
        cam = rec.cameras[im.camera_id]
        sub = Path(*rel.parts[1:]) if rel.parts[0] == "images" and len(rel.parts) > 1 else rel
        out.append(
            _Query(
                f"{QUERY_PREFIX}/{session}/{sub.as_posix()}",
                session,
                int(stamp),
                cam.model_name,
                int(cam.width),
                int(cam.height),
                [float(v) for v in cam.params],
                Path(p),
                recorded_world_from_cam=T,
            )
        )
    return out


def _log_queries(lg, session: str, path: Path, camera: str | None) -> list[_Query]:
    """A query session's camera frames from its log (pixels decoded when written)."""
    frames = [f for f in lg.records(StreamKind.IMAGE) if camera is None or f.camera == camera]
    if not frames:
        raise InputError(path, "no camera images" + (f" from camera {camera!r}" if camera else ""), field="camera")
    cams = sorted({f.camera for f in frames})
    if len(cams) > 1:
        raise InputError(path, f"images of {len(cams)} cameras ({cams}): choose one with camera", field="camera")
    info = lg.camera_infos().get(cams[0])
    if info is None:
        raise InputError(path, f"camera {cams[0]!r} has no intrinsics (camera_info) in the log", field="camera")
    model, params = colmap_camera_params(info)
    return [
        _Query(
            f"{QUERY_PREFIX}/{session}/{f.camera}/{f.stamp_ns}.png",
            session,
            f.stamp_ns,
            model,
            info.width,
            info.height,
            params,
            None,
            f,
        )
        for f in frames
    ]


def _town_sessions(truth: Path | None) -> dict[str, dict]:
    """The town manifest's entry of every session (role, condition, weather, time), by name."""
    p = None if truth is None else Path(truth) / "world" / "manifest.json"
    if p is None or not p.is_file():
        return {}
    return {s["name"]: s for s in json.loads(p.read_text()).get("sessions", [])}


def _town_truth(truth: Path, ws: Workspace):
    """``poses(session, stamps) -> (world_from_cam (M, 4, 4), mask)``: the town's true cameras in the workspace's
    frame."""
    from mapkit.synth import camera_poses, town_frame

    try:
        ws_from_town = town_frame(truth).to_frame(ws.require_frame("the truth is georeferenced: the workspace must be"))
    except MapkitError as exc:
        raise InputError(truth, str(exc), field="truth") from None
    cache: dict[str, tuple[np.ndarray, np.ndarray] | None] = {}

    def poses(session: str, stamps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if session not in cache:
            try:
                s, T = camera_poses(truth, session)
                cache[session] = (s, ws_from_town @ T)
            except MapkitError:
                cache[session] = None  # a session the town did not drive: no truth
        got = cache[session]
        if got is None:
            return np.zeros((0, 4, 4)), np.zeros(len(stamps), bool)
        return interpolate_poses(got[0], got[1], np.asarray(stamps, np.int64))

    return poses


def fit_model_from_truth(model_world_from_cam: np.ndarray, truth_world_from_cam: np.ndarray) -> np.ndarray:
    """The rigid ``model_from_truth`` that best maps the true cameras onto the model's (least squares over each
    camera centre and the tips of its three axes, 1 m long: a straight drive alone leaves the roll about its
    line free)."""

    def points(T: np.ndarray) -> np.ndarray:
        T = np.asarray(T, np.float64).reshape(-1, 4, 4)
        tips = T[:, None, :3, 3] + _AXIS_M * np.swapaxes(T[:, :3, :3], 1, 2)  # (n, 3, 3): centre + each axis
        return np.concatenate([T[:, :3, 3], tips.reshape(-1, 3)])

    return umeyama(points(truth_world_from_cam), points(model_world_from_cam), with_scale=False)


def fit_truth(model_T: np.ndarray, truth_T: np.ndarray, source: str, min_images: int, where: Path) -> BenchmarkTruth:
    """:func:`fit_model_from_truth` of the database images' model poses ``model_T`` and true poses ``truth_T`` (both
    world_from_cam), with its residual; fewer than ``min_images`` is one error at ``where`` (field ``truth``)."""
    if len(model_T) < min_images:
        raise InputError(
            where,
            f"{len(model_T)} database images of the model have truth ({source}); {min_images} needed",
            field="truth",
        )
    S = fit_model_from_truth(model_T, truth_T)
    moved = S @ truth_T
    d = np.linalg.norm(moved[:, :3, 3] - model_T[:, :3, 3], axis=1)
    ang = np.degrees(rotation_angle_rad(np.swapaxes(model_T[:, :3, :3], 1, 2) @ moved[:, :3, :3]))
    return BenchmarkTruth(
        source,
        S,
        len(model_T),
        float(np.sqrt(np.mean(d**2))),
        float(d.max()),
        float(np.median(ang)),
        float(ang.max()),
    )


# --- the export -----------------------------------------------------------------------------------------


@writes_workspace("out", within=True)
def export_benchmark(
    workspace: str | Path | Workspace,
    out: str | Path,
    queries: list[str],
    truth: str | Path | None = None,
    logs: Mapping[str, str | Path] | None = None,
    config: str | Path | BenchmarkExportConfig | None = None,
    progress: bool | None = None,
    cache_dir: str | Path | None = None,
) -> Path:
    """Export the workspace's reference model, the query sessions' images and their ground truth into ``out``
    (see the module's docstring); returns ``out``. A query session's images come from its image database, else
    from its log in ``logs`` (session -> log path). The folder is written aside and renamed into place when
    complete. ``cache_dir``: where the VLAD encodings of image-database queries are kept and found (a
    localization's ``--cache-dir`` that encoded the same files already)."""
    import pycolmap

    t0 = time.perf_counter()
    ws = Workspace(workspace)
    cfg = load_config(BenchmarkExportConfig, config)
    log_paths = {k: Path(v) for k, v in (logs or {}).items()}
    model_dir, index_dir = _require_inputs(ws)
    if not queries:
        raise InputError(ws.root, "no query session given", field="queries")
    truth = None if truth is None else Path(truth)
    unknown = sorted(set(log_paths) - set(queries))
    if unknown:
        raise InputError(log_paths[unknown[0]], f"a log for {unknown}, which are not query sessions", field="logs")
    rec = pycolmap.Reconstruction(str(model_dir / SFM))
    root = model_image_root(model_dir)
    by_path = _session_of_images(ws)
    db_names = {i: im.name for i, im in rec.images.items()}
    db_sessions = {by_path.get((root / n).resolve(), ("?", 0, None))[0] for n in db_names.values()}
    clash = sorted(set(queries) & db_sessions)
    if clash:
        raise InputError(model_dir, f"query sessions {clash} are database images of the model", field="queries")
    for q in queries:
        if not ws.session(q).images_csv.is_file() and q not in log_paths:
            raise InputError(
                ws.session(q).imagedb, f"query session {q!r} has no image database: give its log", field="logs"
            )
        if q in log_paths and truth is None:
            raise InputError(log_paths[q], f"query session {q!r} is a log: its truth needs the town", field="truth")

    # truth of the database images, and the model's frame fitted to it
    poses = _town_truth(truth, ws) if truth is not None else None
    source = "synthetic town (true camera poses)" if truth is not None else "the sessions' recorded poses (imagedb)"
    # each database image's world_from_cam in the model: the truth's fit and the retrieval recall
    db_T = {
        n: invert_pose(np.vstack([rec.images[i].cam_from_world().matrix(), [0, 0, 0, 1]])) for i, n in db_names.items()
    }
    model_T, truth_T = [], []
    for i in sorted(db_names):
        hit = by_path.get((root / db_names[i]).resolve())
        if hit is None:
            continue
        if poses is None:
            T_true = hit[2]
        else:
            T, ok = poses(hit[0], np.array([hit[1]]))
            if not ok[0]:
                continue
            T_true = T[0]
        model_T.append(db_T[db_names[i]])
        truth_T.append(T_true)
    fit = fit_truth(
        np.array(model_T).reshape(-1, 4, 4),
        np.array(truth_T).reshape(-1, 4, 4),
        source,
        cfg.min_fit_images,
        truth if truth is not None else model_dir,
    )
    log.info(
        "benchmark: model from truth fitted on %d database images, residual RMSE %.3f m (max %.3f m)",
        fit.fit_images,
        fit.residual_rmse_m,
        fit.residual_max_m,
    )
    town = _town_sessions(truth)
    out = Path(out)
    with building(out) as folder:
        for f in sorted((model_dir / SFM).iterdir()):
            copy_file(f, folder / SFM / f.name)
        copy_file(model_dir / DATABASE, folder / DATABASE)
        if (model_dir / "config.yaml").is_file():
            copy_file(model_dir / "config.yaml", folder / MODEL_CONFIG)
        bar = progress_bar(len(db_names), progress, "database images", "image")
        for name in db_names.values():
            copy_file(root / name, folder / IMAGES / name)
            bar.update()
        bar.close()
        kept: list[_Query] = []
        gt: list[np.ndarray] = []
        dropped: dict[str, int] = {}
        for session in queries:
            if session in log_paths:
                with open_log(log_paths[session]) as lg:
                    qs = _log_queries(lg, session, log_paths[session], cfg.camera)
                    kept_s, gt_s = _with_truth(qs, session, poses, fit)
                    _write_log_images(kept_s, folder / IMAGES, progress)
            else:
                qs = _imagedb_queries(ws, session)
                kept_s, gt_s = _with_truth(qs, session, poses, fit)
                for query in kept_s:
                    assert query.source is not None
                    copy_file(query.source, folder / IMAGES / query.name)
            dropped[session] = len(qs) - len(kept_s)
            kept += kept_s
            gt += gt_s
        if not kept:
            raise InputError(truth or ws.root, f"no query of {queries} has truth", field="truth")
        names = [q.name for q in kept]
        write_queries_with_intrinsics(folder / QUERIES, [(q.name, q.model, q.width, q.height, q.params) for q in kept])
        write_benchmark_poses(folder / GROUND_TRUTH, names, np.array([invert_pose(T) for T in gt]))
        sources = [q.source if q.source is not None else folder / IMAGES / q.name for q in kept]
        pairs, pair_stats = _retrieval_pairs(index_dir, sources, names, db_names, root, ws, cfg, progress, cache_dir)
        pair_stats["recall"] = retrieval_recall(
            pairs,
            {q.name: T for q, T in zip(kept, gt, strict=True)},
            db_T,
            {q.name: q.session for q in kept},
            cfg.retrieval_k,
            cfg.recall_radius_m,
            cfg.recall_max_angle_deg,
        )
        write_pairs(folder / PAIRS, pairs)
        conditions = {q.name: _condition(q.session, town.get(q.session, {})) for q in kept}
        write_json(folder / CONDITIONS, conditions)
        frame = ws.frame()
        metrics = {
            "queries": len(kept),
            "queries_per_session": {s: sum(q.session == s for q in kept) for s in queries},
            "queries_without_truth": dropped,
            "database_images": len(db_names),
            "points3D": rec.num_points3D(),
            "truth": {
                "source": fit.source,
                "fit_images": fit.fit_images,
                "residual_rmse_m": round(fit.residual_rmse_m, 6),
                "residual_max_m": round(fit.residual_max_m, 6),
                "residual_rotation_median_deg": round(fit.residual_rotation_median_deg, 6),
                "residual_rotation_max_deg": round(fit.residual_rotation_max_deg, 6),
                "model_from_truth": np.round(fit.model_from_truth, 9).tolist(),
            },
            "retrieval": pair_stats,
            "frame": frame.to_dict() if frame is not None else "the trajectory's own frame",
            "query_sources": {s: (str(log_paths[s]) if s in log_paths else "image database") for s in queries},
        }
        write_json(folder / "metrics.json", metrics)
        atomic_write_text(folder / "config.yaml", dump_config(cfg))
        atomic_write_text(folder / "README.md", _readme(metrics, ws, queries, log_paths, cfg))
        write_timings(folder, seconds=time.perf_counter() - t0)
    log.info("benchmark: %d queries of %s written to %s", len(kept), ", ".join(queries), out)
    return out


def _with_truth(qs: list[_Query], session: str, poses, fit: BenchmarkTruth) -> tuple[list[_Query], list[np.ndarray]]:
    """The queries that have truth, and their true world_from_cam in the model's frame."""
    if poses is None:
        T = np.array([q.recorded_world_from_cam for q in qs]).reshape(-1, 4, 4)
        ok = np.ones(len(qs), bool)
    else:
        T, ok = poses(session, np.array([q.stamp_ns for q in qs], np.int64))
    kept = [q for q, good in zip(qs, ok, strict=True) if good]
    return kept, list(fit.model_from_truth @ T)


def _write_log_images(qs: list[_Query], images: Path, progress: bool | None) -> None:
    import cv2

    from mapkit.core.runio import atomic_write_bytes

    bar = progress_bar(len(qs), progress, "query images", "image")
    for q in qs:
        frame = q.frame
        img = frame.image  # type: ignore[attr-defined]
        if getattr(frame, "encoding", "") == "rgb8":
            img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
        ok, png = cv2.imencode(".png", img)
        if not ok:
            raise InputError(None, f"{q.name}: the frame could not be encoded as PNG")
        (images / q.name).parent.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(images / q.name, png.tobytes())
        bar.update()
    bar.close()


def _retrieval_pairs(
    index_dir: Path,
    images: list[Path],
    names: list[str],
    db_names: dict[int, str],
    root: Path,
    ws: Workspace,
    cfg: BenchmarkExportConfig,
    progress: bool | None,
    cache_dir: str | Path | None = None,
) -> tuple[list[tuple[str, str]], dict]:
    """Each query's top-k database images of the VLAD index, as the model names them (hits outside the model
    are left out and counted); ``images``: each query's image file, the exported copy's content."""
    from mapkit.retrieval.index_vlad import VladIndex

    index = VladIndex.load(index_dir)
    model_name = {(root / n).resolve(): n for n in db_names.values()}
    vectors = index.encode_files(images, progress=bool(progress), desc="retrieval", cache_dir=cache_dir)
    _, ids = index.search(vectors, cfg.retrieval_k)
    pairs, outside = [], 0
    for q, row in zip(names, ids, strict=True):
        for i in row[row >= 0]:
            db = model_name.get((ws.root / str(index.database["image"][i])).resolve())
            if db is None:
                outside += 1
                continue
            pairs.append((q, db))
    stats = {
        "index": str(index_dir),
        "k": cfg.retrieval_k,
        "pairs": len(pairs),
        "hits_outside_the_model": outside,
        "index_sessions": index.database_sessions,
    }
    return pairs, stats


#: the depths at which retrieval recall is reported (those up to the export's k, and k itself)
RECALL_AT = (1, 5, 10, 20, 50)


def retrieval_recall(
    pairs: list[tuple[str, str]],
    query_T: Mapping[str, np.ndarray],
    db_T: Mapping[str, np.ndarray],
    session_of: Mapping[str, str],
    k: int,
    radius_m: float,
    max_angle_deg: float,
) -> dict:
    """Per query session, the share of its queries with at least one database image among their first n pairs
    (in the pairs' order, the retrieval's rank) that shows the query's place: camera within ``radius_m`` of the
    query's true camera and optical axis within ``max_angle_deg`` of its (poses world_from_cam, one frame);
    n in :data:`RECALL_AT` up to ``k``, and ``k``."""
    ranked: dict[str, list[str]] = {}
    for q, d in pairs:
        ranked.setdefault(q, []).append(d)
    depths = sorted({n for n in RECALL_AT if n <= k} | {k})
    cos_max = np.cos(np.radians(max_angle_deg))
    first: dict[str, int | None] = {}  # rank (1-based) of each query's first database image at its place
    for q, T in query_T.items():
        ds = ranked.get(q, [])
        if not ds:
            first[q] = None
            continue
        D = np.array([db_T[d] for d in ds])
        near = np.linalg.norm(D[:, :3, 3] - T[:3, 3], axis=1) <= radius_m
        facing = D[:, :3, 2] @ T[:3, 2] >= cos_max  # optical axes (z) within the angle
        hit = np.flatnonzero(near & facing)
        first[q] = int(hit[0]) + 1 if len(hit) else None
    out: dict = {"radius_m": radius_m, "max_angle_deg": max_angle_deg, "sessions": {}}
    for session in sorted(set(session_of.values())):
        ranks = [first[q] for q in query_T if session_of[q] == session]
        out["sessions"][session] = {
            "queries": len(ranks),
            "recall_at": {str(n): round(sum(r is not None and r <= n for r in ranks) / len(ranks), 6) for n in depths},
        }
    return out


def _condition(session: str, entry: dict) -> dict:
    """A query's condition: the town manifest's label, weather and time of day where it has them."""
    out: dict = {"session": session, "condition": entry.get("condition") or entry.get("weather")}
    for key in ("weather", "time_of_day", "date", "season"):
        if key in entry:
            out[key] = entry[key]
    return out


def _recall_table(recall: dict) -> str:
    """The README's table of retrieval recall per query session."""
    sessions = recall["sessions"]
    depths = list(next(iter(sessions.values()))["recall_at"]) if sessions else []
    rows = [
        f"| {s} | {v['queries']} | " + " | ".join(f"{100 * v['recall_at'][n]:.1f} %" for n in depths) + " |"
        for s, v in sessions.items()
    ]
    return (
        "Per query session, the share of queries with at least one database image of their place (camera within "
        f"{recall['radius_m']:g} m of the query's true camera, optical axis within {recall['max_angle_deg']:g} deg) "
        "among their first n retrieval pairs:\n\n"
        + "| session | queries | "
        + " | ".join(f"n = {n}" for n in depths)
        + " |\n|---|---|"
        + "---|" * len(depths)
        + "\n"
        + "\n".join(rows)
    )


def _readme(metrics: dict, ws: Workspace, queries: list[str], logs: dict[str, Path], cfg) -> str:
    t = metrics["truth"]
    frame = metrics["frame"]
    if isinstance(frame, dict):
        o = frame["origin_wgs84"]
        where = (
            "the workspace's local ENU frame (x east, y north, z up, metres) at the WGS84 origin "
            f"lat {o['lat_deg']:.9f}, "
            f"lon {o['lon_deg']:.9f}, alt {o['alt_m']:.3f} m (from {ws.origin}; UTM EPSG:{frame['utm_crs_epsg']})"
        )
    else:
        where = "the trajectory's own frame (the workspace has no origin.json: not georeferenced)"
    sources = "\n".join(
        f"- `{s}`: {f'its log {logs[s]} (camera frames written as PNG)' if s in logs else 'its image database'}"
        f", {metrics['queries_per_session'][s]} queries"
        for s in queries
    )
    return f"""# Visual localization benchmark

Exported by `mapkit export benchmark` from the workspace `{ws.root}`: {metrics["queries"]} query images
against a reference model of {metrics["database_images"]} database images and {metrics["points3D"]} 3D points.

## Files

| file | what it is |
|---|---|
| `sfm/` | the reference model (`mapkit model`), COLMAP binary: cameras, images with keypoints, points3D |
| `database.db` | the model's COLMAP database: keypoints, descriptors and matches of the database images |
| `reference_model.yaml` | the model's SIFT settings: extract query features with the same |
| `images/` | the image root of database and query images: `images/<name>` for every image name |
| `queries_with_intrinsics.txt` | `name MODEL width height params...` per query (COLMAP camera models) |
| `queries_gt.txt` | ground truth, `name qw qx qy qz tx ty tz` per query: `cam_from_world` (world to camera) |
| `pairs-query-retrieval.txt` | `query_name db_name`: each query's top {cfg.retrieval_k} of the workspace's VLAD index |
| `conditions.json` | per query: its session and condition (weather, time of day) where known |
| `config.yaml`, `metrics.json` | the export's settings and figures |

The database images keep the names the model gives them (paths under the workspace), so
`images/` serves hloc (`images=OUT/images`, `reference_sfm=OUT/sfm`) and COLMAP
(`--image_path OUT/images`) as it is. Query images are named `query/<session>/...`.

## Frame

Poses are in the reference model's frame: {where}. Cameras are optical frames (x right, y down,
z forward).

## Queries

{sources}

## Ground truth

Source: {t["source"]}. The rigid transform from the truth's frame to the model's was fitted on the
{t["fit_images"]} database images alone (camera centres and axes) and applied to the queries' truth;
its residual over the database images: RMSE {t["residual_rmse_m"]:.4f} m, max {t["residual_max_m"]:.4f} m,
rotation median {t["residual_rotation_median_deg"]:.4f} deg, max {t["residual_rotation_max_deg"]:.4f} deg.

## Retrieval

{_recall_table(metrics["retrieval"]["recall"])}

## Scoring

`mapkit eval benchmark OUT --poses POSES.txt` gives the share of queries within (0.25 m, 2 deg),
(0.5 m, 5 deg) and (5 m, 10 deg), per condition and overall; a query missing from the poses file
counts as a failure.
"""
