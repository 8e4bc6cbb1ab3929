"""``mapkit localize`` and ``mapkit eval localize``: the MCVL localizer on a VLAD bundle.

Each query image is encoded once; its top-20 database images give the measurement z_t (mean
shift, largest cluster); the particle filter of :mod:`mapkit.localization.mcl` runs over the sequence. The
evaluation follows the MCVL paper's protocol (section IV): training sessions build the index,
test sessions are queries; per sequence the translation error ||c_est - c_gt|| and the orientation
error, mean and median, for retrieval alone and for the filter (Table II), and a plot of the
estimated against the true trajectory (Fig. 5).

Frames: the database's poses, hence the measurements, are camera poses ``world_from_camera`` in the
workspace's ENU frame (optical axes: x right, y down, z forward). The filter's state is the
vehicle's base pose (x forward, y left, z up), whose third Euler angle is the heading, as MCVL's
covariances (section IV-A) assume; see :mod:`mapkit.localization.mcl` for why the camera pose is
the wrong state. Every measurement, retrieved hypothesis and odometry step is converted to the
base through the rig's mount ``LocalizeConfig.base_from_camera`` before the filter sees it, and
the filter's estimates are converted back, so that everything this module returns or writes is
a camera pose, as the paper's Table II reports.

Beyond the paper (presets in ``configs/localize/``): the query session's relative motion as
odometry, and the multi-hypothesis measurement model of :mod:`mapkit.localization.mcl`, which weighs the
particles by all top-k retrieved poses. Retrieval (encoding each image with dense SIFT, the
expensive part) can be cached per test session (:func:`cached_query_all`), so that runs with
other filter settings reuse the hits of the same bundle.

Beyond the paper, ``refine: 6dof`` registers every query against the triangulated reference model
(``mapkit model``) once the filter has run over the sequence (:func:`refine_sixdof`): the filter
gives a place to metres, the registration a camera pose to centimetres where it succeeds, and the
filter's pose where it does not.
"""

from __future__ import annotations

import hashlib
import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field, field_validator

from mapkit.core.config import MapkitConfig, dump_config, load_config
from mapkit.core.errors import ConfigError, InputError
from mapkit.core.geometry import invert_pose, pose_difference
from mapkit.core.runio import atomic_path, atomic_write_text, progress_bar, sha256_file, write_json, write_timings
from mapkit.core.types import CameraInfo, StreamKind
from mapkit.core.writers import writes_workspace
from mapkit.io import open_log
from mapkit.io.trajectory import write_benchmark_poses, write_tum
from mapkit.localization.mcl import FORWARD_CAMERA_ROTATION, CameraMount, MclConfig, MonteCarloLocalizer
from mapkit.localization.reference_model import DEFAULT_FOLDER as MODEL_FOLDER
from mapkit.localization.sequence import SequenceNoise, smooth_sequence
from mapkit.localization.sixdof import (
    SixDofConfig,
    SixDofLocalizer,
    SixDofResult,
    extract_with_shares,
    map_queries,
)
from mapkit.retrieval.index_vlad import VladIndex
from mapkit.retrieval.measurement import PoseHypotheses, mean_shift_measurement

logger = logging.getLogger(__name__)

Row4 = tuple[float, float, float, float]

#: the files a 6-DoF refinement writes beside the filter's (removed by a run without one)
SIXDOF_FILES = ("sixdof_tum.txt", "sixdof_poses.txt", "sixdof.json", "sequence_tum.txt", "sequence_poses.txt")


def _row4(row: np.ndarray, last: float) -> Row4:
    return (float(row[0]), float(row[1]), float(row[2]), last)


#: the default ``base_from_camera``: a camera looking straight ahead at the base's origin
DEFAULT_BASE_FROM_CAMERA: tuple[Row4, Row4, Row4, Row4] = (
    _row4(FORWARD_CAMERA_ROTATION[0], 0.0),
    _row4(FORWARD_CAMERA_ROTATION[1], 0.0),
    _row4(FORWARD_CAMERA_ROTATION[2], 0.0),
    (0.0, 0.0, 0.0, 1.0),
)


class LocalizeConfig(MapkitConfig):
    mcl: MclConfig = MclConfig()
    base_from_camera: tuple[Row4, Row4, Row4, Row4] | None = Field(
        None,
        description="The rig's camera mount, a rigid 4x4 base_from_camera (base: x forward, y left, z up; camera: "
        "optical x right, y down, z forward). The filter runs on the base pose, whose third Euler angle is the heading "
        "(MCVL Sec. IV-A's covariances assume it); the database's camera poses are converted through this and the "
        "estimates back. None (default): the mount the bundle recorded from its database sessions (mapkit build writes "
        "it), else a camera looking straight ahead at the base origin (mapkit choice). A mount pitched a few degrees "
        "or offset from the true one only tilts or shifts the base the filter tracks (the round trip back to the "
        "camera is exact); a camera turned about its optical axis or looking steeply down needs its true mount.",
    )
    top_k: int = Field(20, ge=1, description="Retrieved database images per query (MCVL IV-A: R = 20).")
    bandwidth_m: float = Field(
        5.0, gt=0, description="Mean-shift bandwidth over the retrieved translations (m; the authors' code)."
    )
    odometry: bool = Field(
        False,
        description="Beyond the paper: drive the motion model by the query drive's own odometry (its relative "
        "camera motion between queries, turned into the base's through base_from_camera) instead of eqs. 1-2: "
        "mapkit eval localize takes the query session's built trajectory, mapkit localize the log's (kiss-icp on "
        "its LiDAR, else its pose stream). Sets mcl.odometry.enabled.",
    )
    seed: int = Field(0, description="Seed of the particle filter.")
    refine: Literal["none", "6dof"] = Field(
        "none",
        description="Beyond the paper: '6dof' registers every query against the triangulated reference model "
        "(mapkit model) once the filter has run over the sequence: SIFT 2D-3D matches with its retrieved database "
        "images, else with the model's images near the filter's pose, then P3P in RANSAC (hloc's localize_sfm). A "
        "query that registers neither way keeps the filter's pose. 'none': the filter alone, as the paper.",
    )
    reference_model: str | None = Field(
        None,
        description="The reference model folder of refine '6dof' (default: reference_model/ in the workspace: the "
        "bundle's source workspace for mapkit localize, the evaluated one for mapkit eval localize).",
    )
    sixdof: SixDofConfig = Field(
        default_factory=SixDofConfig, description="The registration of refine '6dof' (mapkit config defaults sixdof)."
    )

    @field_validator("base_from_camera")
    @classmethod
    def _rigid_mount(cls, v):
        if v is not None:
            CameraMount(np.asarray(v, dtype=np.float64))  # raises ValueError unless a rigid pose
        return v

    def camera_mount(self, index=None) -> CameraMount:
        """The mount the filter uses: :attr:`base_from_camera` when set, else the one ``index`` (a
        VLAD bundle) recorded, else the forward camera of :data:`DEFAULT_BASE_FROM_CAMERA`."""
        if self.base_from_camera is not None:
            return CameraMount(np.asarray(self.base_from_camera, dtype=np.float64))
        recorded = getattr(index, "base_from_camera", None)
        if recorded is not None:
            return CameraMount(np.asarray(recorded, dtype=np.float64))
        return CameraMount(np.asarray(DEFAULT_BASE_FROM_CAMERA, dtype=np.float64))


@dataclass(frozen=True)
class LocalizationRun:
    """Per query of a sequence (n queries): retrieval alone (the measurement z_t) and the filter.

    Positions (n, 3) and rotations (n, 3, 3) are the camera's ``world_from_camera`` in the
    bundle's workspace ENU (the filter's base estimates converted back through the mount); NaN
    where the filter has no estimate yet."""

    retrieval_position: np.ndarray
    retrieval_rotation: np.ndarray
    filter_position: np.ndarray
    filter_rotation: np.ndarray
    cluster_size: np.ndarray  # (n,) hits in the measurement's mean-shift cluster
    ids: np.ndarray  # (n, top_k) retrieved database ids, -1 where fewer
    retrieval_s: float
    filter_s: float

    def poses(self, which: Literal["retrieval", "filter"]) -> np.ndarray:
        """(n, 4, 4) world_from_camera of ``which``."""
        T = np.tile(np.eye(4), (len(self.ids), 1, 1))
        T[:, :3, :3] = getattr(self, f"{which}_rotation")
        T[:, :3, 3] = getattr(self, f"{which}_position")
        return T


def write_run_trajectories(out: Path, stamps_ns: np.ndarray, r: LocalizationRun) -> Path:
    """The filter's and retrieval's camera poses of a run as TUM files in ``out`` (``poses_tum.txt``,
    ``retrieval_tum.txt``; queries where the filter has no estimate yet are left out of both), as
    evo and ``mapkit view`` read them."""
    ok = np.isfinite(r.filter_position[:, 0])
    files: tuple[tuple[Literal["retrieval", "filter"], str], ...] = (
        ("filter", "poses_tum.txt"),
        ("retrieval", "retrieval_tum.txt"),
    )
    for key, name in files:
        write_tum(out / name, np.asarray(stamps_ns, np.int64)[ok], r.poses(key)[ok])
    return out


def run_localizer(
    index,
    images,
    cfg: LocalizeConfig,
    odometry: list | None = None,
    progress: bool = False,
    hits: tuple[np.ndarray, np.ndarray] | None = None,
) -> LocalizationRun:
    """Retrieval alone and the filter over a sequence of images (arrays or files).

    ``hits`` = ``(ids, distances)`` (n, top_k) already retrieved for the images (e.g. from
    :func:`cached_query_all`) skips encoding them. ``odometry[t]`` is the query camera's motion
    ``cam_{t-1} <- cam_t`` (4, 4) into step t or None. Returns per query: the measurement's camera
    pose (retrieval alone), the filter's camera pose, the measurement's cluster size, and the
    retrieved ids. The filter itself runs on base poses (:meth:`LocalizeConfig.camera_mount`).
    """
    mcl_cfg = cfg.mcl.model_copy(update={"odometry": cfg.mcl.odometry.model_copy(update={"enabled": cfg.odometry})})
    mount = cfg.camera_mount(index)
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
    bar = progress_bar(n, progress, "localize", "query")
    for t, im in enumerate(images):
        t0 = time.perf_counter()
        h = index.query(im, cfg.top_k) if hits is None else index.hits(hits[0][t, : cfg.top_k], hits[1][t, : cfg.top_k])
        z = (
            index.measurement_from_hits(h)
            if cfg.bandwidth_m == index.cfg.mean_shift_bandwidth_m
            else _measure(h, cfg.bandwidth_m)
        )
        t1 = time.perf_counter()
        hyp = (
            mount.hypotheses_to_base(
                PoseHypotheses.from_retrieval(
                    h.translations, h.world_from_cam[:, :3, :3], h.distances, mh.hit_weighting, mh.hit_weight_scale
                )
            )
            if mh.enabled
            else None
        )
        odo = (
            None
            if odometry is None or not loc.initialized or odometry[t] is None
            else mount.odometry_to_base(odometry[t])
        )
        est = loc.step(mount.measurement_to_base(z), odo, hyp)
        seconds["retrieval"] += t1 - t0
        seconds["filter"] += time.perf_counter() - t1
        z_pos[t], z_rot[t], sizes[t] = z.translation, z.rotation, z.cluster_size
        all_ids[t, : len(h)] = h.ids
        if est is not None:
            f_pos[t], f_rot[t] = mount.to_camera(est.position, est.rotation)
        bar.update(1)
    bar.close()
    return LocalizationRun(z_pos, z_rot, f_pos, f_rot, sizes, all_ids, seconds["retrieval"], seconds["filter"])


def _measure(hits, bandwidth_m: float):
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
    """Digest of the query images' paths, sizes and contents (files only; not their modification
    times, so that the same images written again keep their cache)."""
    h = hashlib.sha256()
    for p in images:
        h.update(f"{Path(p).resolve()}\0{Path(p).stat().st_size}\0{sha256_file(p)}\n".encode())
    return h.hexdigest()[:16]


def query_all(
    index, images, top_k: int, progress: bool = False, label: str = "query", vector_cache: str | Path | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Retrieved ids (n, top_k; -1 pads when the index is smaller) and squared L2 distances of every image."""
    n = len(images)
    ids, dist = np.full((n, top_k), -1, np.int64), np.full((n, top_k), np.inf, np.float32)
    if n and all(isinstance(im, (str, Path)) for im in images):
        # image files: encoded on the run's executor (a process pool or Ray), then one batched search
        d, i = index.search(index.encode_files(images, progress=progress, desc=label, cache_dir=vector_cache), top_k)
        ids[:, : i.shape[1]], dist[:, : d.shape[1]] = i, d
        return ids, dist
    bar = progress_bar(n, progress, label, "query")
    for t, im in enumerate(images):
        d, i = index.search(index._as_vector(im)[None], top_k)
        ids[t], dist[t] = i[0], d[0]
        bar.update(1)
    bar.close()
    return ids, dist


def cached_query_all(
    index, images: list, top_k: int, cache_dir: str | Path | None, session: str, progress: bool = False
) -> tuple[np.ndarray, np.ndarray, bool]:
    """:func:`query_all` through a cache file ``hits-<session>-k<top_k>-<bundle fingerprint>.npz``.

    A cached file is used only if it names the same bundle fingerprint, session, top_k and query
    images (paths, sizes, contents); otherwise the images are encoded again and the file replaced.
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
                ok = (
                    int(f["version"]) == HITS_CACHE_VERSION
                    and str(f["bundle"]) == fp
                    and str(f["session"]) == session
                    and int(f["top_k"]) == top_k
                    and str(f["images"]) == img_digest
                    and f["ids"].shape == (len(images), top_k)
                )
                if ok:
                    return f["ids"].astype(np.int64), f["distances"].astype(np.float32), True
        except (OSError, KeyError, ValueError):
            pass  # unreadable or from another version: recompute below
    ids, dist = query_all(index, images, top_k, progress, session, vector_cache=cache_dir)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez(
            f,
            version=HITS_CACHE_VERSION,
            bundle=fp,
            bundle_path=str(Path(index.path).resolve()),
            session=session,
            top_k=top_k,
            images=img_digest,
            ids=ids,
            distances=dist,
        )
    return ids, dist, False


# --- the 6-DoF refinement -------------------------------------------------------------------------


def reference_model_folder(cfg: LocalizeConfig, workspace: str | Path | None) -> Path:
    """The reference model of ``refine: 6dof``: ``cfg.reference_model``, else ``WORKSPACE/reference_model``."""
    if cfg.reference_model is not None:
        return Path(cfg.reference_model)
    if workspace is None:
        raise ConfigError(
            "refine 6dof: no reference_model given, and no workspace to find WORKSPACE/reference_model in"
        )
    return Path(workspace) / MODEL_FOLDER


def open_reference_model(cfg: LocalizeConfig, workspace: str | Path | None) -> SixDofLocalizer:
    """The 6-DoF localizer on the reference model of ``refine: 6dof`` (read and checked now: a missing or damaged
    model is one InputError naming it before any query is encoded)."""
    folder = reference_model_folder(cfg, workspace)
    if not folder.is_dir():
        raise InputError(folder, "no reference model folder here: run mapkit model, or give its folder (--model)")
    return SixDofLocalizer(folder, cfg.sixdof)


def database_model_names(index, loc: SixDofLocalizer) -> list[str | None]:
    """Each database entry of a VLAD bundle as an image name of the reference model (None where the model does not
    hold it). database.csv names images relative to the bundle's source workspace, the model relative to its image
    root (the same folder when ``mapkit model`` ran on that workspace, but either may have been built elsewhere):
    they are compared as resolved paths, and by name where no path is shared."""
    images = [str(n) for n in index.database["image"]]
    source = index.manifest.get("source_workspace")
    if source is not None:
        by_path = loc.names_by_path()
        names = [by_path.get((Path(source) / n).resolve()) for n in images]
        if any(n is not None for n in names):
            return names
    known = set(loc.image_names)
    names = [n if n in known else None for n in images]
    if images and not any(n is not None for n in names):
        logger.warning(
            "6-DoF: none of the bundle's %d database images is in the reference model %s: candidates come from the "
            "filter's pose alone",
            len(images),
            loc.folder,
        )
    return names


def refine_sixdof(
    loc: SixDofLocalizer,
    index,
    run: LocalizationRun,
    images: Sequence[np.ndarray | str | Path],
    cameras: Sequence[CameraInfo | None],
    names: Sequence[str],
    progress: bool = False,
    odometry: Sequence[np.ndarray | None] | None = None,
) -> list[SixDofResult]:
    """Every query of a filter run registered against the reference model (``loc``): from its retrieved database
    images (``run.ids``, best first) that the model holds; where these do not register, from the model's images
    near the filter's pose that look its way. A query that registers neither way keeps the filter's pose (None
    before the filter's first estimate), not accepted, and its reason names both attempts. With ``odometry``
    (per query the camera's motion since the previous query, ``cam_prev_from_cam``; None for the first), poses
    that disagree with every registered neighbour are refused as well (:func:`check_sequence`)."""
    n = len(run.ids)
    if not len(images) == len(cameras) == len(names) == n:
        raise ValueError(f"{n} queries in the run, {len(images)} images, {len(cameras)} cameras, {len(names)} names")
    db_names = database_model_names(index, loc)
    priors = [T if np.all(np.isfinite(T)) else None for T in run.poses("filter")]
    shared = extract_with_shares(loc, images, progress)  # once for every attempt
    features = [f for f, _ in shared]

    def register(t: int) -> SixDofResult:
        prior = priors[t]
        retrieved = [name for i in run.ids[t] if i >= 0 and (name := db_names[i]) is not None]
        r = loc.localize(images[t], cameras[t], retrieved, prior, names[t], features[t])
        r.seconds += shared[t][1]
        if not r.accepted and prior is not None:
            near = loc.candidates_near(prior)
            if near and near[: loc.cfg.max_candidates] != r.candidates:
                again = loc.localize(images[t], cameras[t], near, prior, names[t], features[t])
                again.seconds += r.seconds
                again.reason = f"retrieved images: {r.reason}; images near the filter's pose: {again.reason}"
                r = again
        return r

    # each query on its own (its features, its prior): loc.cfg.num_threads at a time
    results = map_queries(register, n, loc.cfg.num_threads, progress_bar(n, progress, "6-DoF", "query"))
    if odometry is not None and loc.cfg.sequence_max_m is not None:
        results = check_sequence(results, odometry, priors, loc.cfg.sequence_max_m, loc.cfg.sequence_max_deg)
    if odometry is not None and loc.cfg.guided_radii_px:
        results = follow_neighbours(loc, results, images, cameras, names, priors, odometry, features)
        if loc.cfg.sequence_max_m is not None:
            results = check_sequence(results, odometry, priors, loc.cfg.sequence_max_m, loc.cfg.sequence_max_deg)
    if odometry is not None:
        results = with_sequence_poses(results, odometry, priors, loc.cfg)
    logger.info("6-DoF: %d of %d queries registered", sum(r.accepted for r in results), n)
    return results


def sequence_noise(cfg: SixDofConfig) -> SequenceNoise:
    """The pose graph's noise (:class:`mapkit.localization.sequence.SequenceNoise`) of a 6-DoF configuration: its
    agreement band is the neighbour check's (``sequence_max_m``, ``sequence_max_deg``; (0.5 m, 5 deg) when off)."""
    return SequenceNoise(
        prior_m=cfg.smoothing_sigma_m,
        prior_deg=cfg.smoothing_sigma_deg,
        odometry_m=cfg.odometry_sigma_m,
        odometry_fraction=cfg.odometry_sigma_fraction,
        odometry_deg=cfg.odometry_sigma_deg,
        agree_m=cfg.sequence_max_m if cfg.sequence_max_m is not None else 0.5,
        agree_deg=cfg.sequence_max_deg,
        window_m=cfg.smoothing_window_m,
    )


def with_sequence_poses(
    results: Sequence[SixDofResult],
    odometry: Sequence[np.ndarray | None],
    fallback: Sequence[np.ndarray | None],
    cfg: SixDofConfig,
) -> list[SixDofResult]:
    """``results`` with each query's ``sequence_world_from_cam``: the pose graph of the accepted registrations and the
    odometry (:func:`mapkit.localization.sequence.smooth_sequence`, ``cfg.smoothing``), started from ``fallback``."""
    if cfg.smoothing == "off":
        return list(results)
    registered = [r.world_from_cam if r.accepted else None for r in results]
    covariances = [r.covariance if r.accepted else None for r in results] if cfg.smoothing_covariance else None
    poses = smooth_sequence(registered, odometry, fallback, sequence_noise(cfg), cfg.smoothing, covariances)
    return [replace(r, sequence_world_from_cam=T) for r, T in zip(results, poses, strict=True)]


def odometry_steps(world_from_cam: Sequence[np.ndarray | None]) -> list[np.ndarray | None]:
    """The camera's motion between consecutive poses, as the filter and the 6-DoF sequence check take odometry:
    ``odometry[t]`` is camera t-1 from camera t (``cam_prev_from_cam``), None for the first and beside a missing
    pose."""
    steps: list[np.ndarray | None] = [None]
    for a, b in zip(world_from_cam[:-1], world_from_cam[1:], strict=True):
        steps.append(None if a is None or b is None else invert_pose(a) @ b)
    return steps


def moved_by_odometry(
    world_from_cam_k: np.ndarray, odometry: Sequence[np.ndarray | None], t: int, k: int
) -> np.ndarray | None:
    """Query t's camera pose from its neighbour k's (k = t - 1 or t + 1) moved by the odometry between them; None
    where that step is unknown."""
    if k == t - 1:
        step = odometry[t]
        return None if step is None else world_from_cam_k @ step
    step = odometry[k]
    return None if step is None else world_from_cam_k @ invert_pose(step)


def follow_neighbours(
    loc: SixDofLocalizer,
    results: Sequence[SixDofResult],
    images: Sequence[np.ndarray | str | Path],
    cameras: Sequence[CameraInfo | None],
    names: Sequence[str],
    priors: Sequence[np.ndarray | None],
    odometry: Sequence[np.ndarray | None],
    features: Sequence[tuple[np.ndarray, np.ndarray]] | None = None,
) -> list[SixDofResult]:
    """``results`` with each query not accepted tried once more, matched guided from an accepted neighbour's pose
    moved by the odometry between them: forward through the sequence from the previous query, then backward from
    the next, so that a run of queries the filter and retrieval both missed is registered from the first good pose
    beside it. A query that still does not register keeps its result. ``features``: each query's
    :meth:`~SixDofLocalizer.extract`, when the caller has them (extracted again otherwise)."""
    out = list(results)
    order = [(range(1, len(out)), -1), (range(len(out) - 2, -1, -1), 1)]
    for steps, side in order:
        for t in steps:
            k = t + side
            if out[t].accepted or not out[k].accepted or out[k].world_from_cam is None:
                continue
            guide = moved_by_odometry(np.asarray(out[k].world_from_cam), odometry, t, k)
            if guide is None:
                continue
            again = loc.localize(
                images[t], cameras[t], [], priors[t], names[t], None if features is None else features[t], [guide]
            )
            if again.accepted:
                again.seconds += out[t].seconds
                again.reason = f"{out[t].reason}; from the {'previous' if side == -1 else 'next'} query: {again.reason}"
                out[t] = again
    return out


def check_sequence(
    results: Sequence[SixDofResult],
    odometry: Sequence[np.ndarray | None],
    fallback: Sequence[np.ndarray | None],
    max_m: float,
    max_deg: float,
) -> list[SixDofResult]:
    """``results`` with each accepted pose that disagrees with every accepted neighbour (the previous and the next
    query) refused: the neighbour's pose moved by the odometry between them (``odometry[t]``: the camera's motion
    from query t-1 to t, ``cam_prev_from_cam``) must lie within ``max_m`` and ``max_deg`` of it. A pose whose
    neighbours are not accepted stays. The verdicts use the poses as registered, so one wrong pose does not refuse
    its right neighbours; a refused query keeps its ``fallback`` pose and says why."""
    if len(odometry) != len(results) or len(fallback) != len(results):
        raise ValueError(f"{len(results)} results, {len(odometry)} odometry steps, {len(fallback)} fallback poses")
    accepted = [r.accepted and r.world_from_cam is not None for r in results]
    out = []
    for t, r in enumerate(results):
        verdicts = []
        for k in (t - 1, t + 1):
            if not (0 <= k < len(results) and accepted[k] and accepted[t]):
                continue
            P = moved_by_odometry(np.asarray(results[k].world_from_cam), odometry, t, k)
            if P is None:
                continue
            dm, ddeg = pose_difference(P, np.asarray(r.world_from_cam))
            verdicts.append((dm <= max_m and ddeg <= max_deg, dm, ddeg))
        if not verdicts or any(ok for ok, _, _ in verdicts):
            out.append(r)
            continue
        dm, ddeg = min((v[1], v[2]) for v in verdicts)
        T = fallback[t]
        out.append(
            replace(
                r,
                accepted=False,
                world_from_cam=None if T is None else np.array(T, np.float64),
                cam_from_world=None if T is None else invert_pose(np.asarray(T, np.float64)),
                reason=f"{r.reason}, but {dm:.2f} m / {ddeg:.1f} deg from its registered neighbours moved by the "
                f"odometry (more than {max_m:g} m / {max_deg:g} deg)",
            )
        )
    return out


def write_sixdof(out: Path, stamps_ns: np.ndarray, results: Sequence[SixDofResult], loc: SixDofLocalizer) -> dict:
    """The 6-DoF poses of a run into ``out``: ``sixdof_tum.txt`` (``world_from_camera``, TUM, as the filter's),
    ``sixdof_poses.txt`` (``cam_from_world`` in the benchmark format, named as the queries) and ``sixdof.json``
    (each query's outcome). A query without a pose is left out of both pose files. Where the run joined the poses
    by the odometry (``SixDofConfig.smoothing``), ``sequence_tum.txt`` and ``sequence_poses.txt`` hold the pose
    graph's poses the same way. Returns the summary: queries and the accepted share. The seconds each query took
    are a run record (:func:`sixdof_timings`), not written here: the same inputs give these files to the byte."""
    stamps_ns = np.asarray(stamps_ns, np.int64)
    sequence = [r.sequence_world_from_cam for r in results]
    for prefix, poses in (
        ("sixdof", [(r.world_from_cam, r.cam_from_world) for r in results]),
        ("sequence", [(T, None if T is None else invert_pose(T)) for T in sequence]),
    ):
        posed = [k for k, (T, _) in enumerate(poses) if T is not None]
        if prefix == "sequence" and not posed:
            for name in ("sequence_tum.txt", "sequence_poses.txt"):
                (out / name).unlink(missing_ok=True)
            continue
        world_from_cam = np.array([poses[k][0] for k in posed], np.float64).reshape(-1, 4, 4)
        cam_from_world = np.array([poses[k][1] for k in posed], np.float64).reshape(-1, 4, 4)
        write_tum(out / f"{prefix}_tum.txt", stamps_ns[posed], world_from_cam)
        write_benchmark_poses(out / f"{prefix}_poses.txt", [results[k].name for k in posed], cam_from_world)
    accepted = sum(r.accepted for r in results)
    summary: dict[str, Any] = {
        "model": str(loc.folder),
        "queries": len(results),
        "accepted": accepted,
        "accepted_share": accepted / len(results) if results else None,
    }
    per_query = [
        {
            "name": r.name,
            "stamp_ns": int(stamp),
            "accepted": r.accepted,
            "reason": r.reason,
            "inliers": r.inliers,
            "matches": r.matches,
            "candidates": r.candidates,
            "position_std_m": _position_std(r),
        }
        for r, stamp in zip(results, np.asarray(stamps_ns, np.int64), strict=True)
    ]
    write_json(out / "sixdof.json", {**summary, "config": loc.cfg.model_dump(mode="json"), "per_query": per_query})
    return summary


def _position_std(r: SixDofResult) -> list[float] | None:
    """An accepted registration's position std (m) along the camera's x (right), y (down) and z (the view)."""
    if not r.accepted or r.covariance is None:
        return None
    return [round(float(v), 4) for v in np.sqrt(np.diag(r.covariance)[3:])]


def sixdof_timings(results: Sequence[SixDofResult]) -> dict[str, float | None]:
    """The 6-DoF run's times for its ``timings.json``: the median and the largest seconds a query took (its share of
    the batch's feature extraction, matching, RANSAC and any second attempt)."""
    seconds = np.array([r.seconds for r in results], np.float64)
    return {
        "sixdof_median_s_per_query": float(np.median(seconds)) if len(seconds) else None,
        "sixdof_max_s_per_query": float(seconds.max()) if len(seconds) else None,
    }


def remove_sixdof_outputs(out: Path) -> None:
    """A run without refinement removes the 6-DoF files an earlier run left in its folder: the folder then holds
    one run's outputs."""
    for name in SIXDOF_FILES:
        (out / name).unlink(missing_ok=True)


def _query_pixels(frame) -> np.ndarray:
    """A log frame's pixels as the 6-DoF localizer reads them: grey or RGB (a ``bgr8`` frame's channels turned)."""
    image = frame.image
    return image[..., ::-1] if frame.encoding == "bgr8" and image.ndim == 3 else image


def log_camera_odometry(
    lg, camera: str, stamps_ns: np.ndarray, progress: bool = False
) -> tuple[list[np.ndarray | None] | None, dict[str, Any]]:
    """The camera's motion between consecutive images of a log (``odometry[t]``: camera t-1 from camera t, None for
    the first and where the trajectory does not span both stamps), from the log's own trajectory as ``mapkit build``
    estimates it: kiss-icp on its LiDAR, else its pose stream, moved to the camera by the log's tf. With neither
    (monocular visual odometry has no metric scale the filter could move by) or where the trajectory cannot be made,
    ``(None, why)`` and an :class:`InputWarning` saying the filter runs without odometry."""
    import warnings

    from mapkit.core.config import TopicConfig, resolve_topics
    from mapkit.core.errors import InputWarning
    from mapkit.core.geometry import interpolate_poses
    from mapkit.mapping.trajectory import SensorMounts, TrajectoryConfig, choose_source, estimate_trajectory

    def without(why: str) -> tuple[None, dict[str, Any]]:
        warnings.warn(f"{lg.path}: odometry: {why}; the filter runs without odometry", InputWarning, stacklevel=3)
        return None, {"source": None, "why": why}

    try:
        cfg = TrajectoryConfig()
        source = choose_source(lg, cfg, resolve_topics(lg, TopicConfig()))
        if source == "camera":
            return without("no LiDAR and no pose stream (visual odometry from one camera has no metric scale)")
        traj = estimate_trajectory(lg, cfg, progress=progress)
        base_from_cam = SensorMounts.of(lg).base_from(traj.body_frame, camera, "camera")
    except InputError as e:
        return without(str(e))
    world_from_base, inside = interpolate_poses(traj.stamps_ns, traj.world_from_base, stamps_ns)
    cams: list[np.ndarray | None] = [None] * len(stamps_ns)
    for k, pose in zip(np.flatnonzero(inside), world_from_base, strict=True):
        cams[int(k)] = pose @ base_from_cam
    steps = odometry_steps(cams)
    return steps, {"source": traj.source, "steps": sum(s is not None for s in steps)}


@writes_workspace("out", within=True)
def localize_log(
    bundle: str | Path,
    log: str | Path,
    out: str | Path,
    config: str | Path | None = None,
    camera: str | None = None,
    progress: bool = True,
    overrides: dict | None = None,
) -> Path:
    """Run the localizer on the camera images of a drive log against a VLAD bundle; writes the
    filter's and retrieval's camera poses as TUM files, the resolved config and metrics. With
    ``odometry: true`` the filter moves by the log's own odometry (:func:`log_camera_odometry`). With
    ``refine: 6dof`` each query is then registered against the reference model (default: the
    bundle's source workspace's ``reference_model/``; the log must hold the camera's intrinsics),
    and :func:`write_sixdof`'s files join the others; with odometry, consecutive registered poses are checked
    against it and unregistered queries retried from a registered neighbour, as ``mapkit eval localize`` does."""

    cfg = load_config(LocalizeConfig, config, overrides)
    index = VladIndex.load(bundle)
    loc = open_reference_model(cfg, index.manifest.get("source_workspace")) if cfg.refine == "6dof" else None
    try:
        return _localize_log(index, Path(bundle), Path(log), Path(out), cfg, camera, progress, loc)
    finally:
        if loc is not None:
            loc.close()


def _localize_log(
    index: VladIndex,
    bundle: Path,
    log: Path,
    out: Path,
    cfg: LocalizeConfig,
    camera: str | None,
    progress: bool,
    loc: SixDofLocalizer | None,
) -> Path:
    with open_log(log) as lg:
        frames = [f for f in lg.records(StreamKind.IMAGE) if camera is None or f.camera == camera]
        if not frames:
            raise InputError(
                log, "no camera images" + (f" from camera {camera!r}" if camera else ""), field="topics.images"
            )
        cams = {f.camera for f in frames}
        if len(cams) > 1:
            raise InputError(
                log, f"images of {len(cams)} cameras ({sorted(cams)}): choose one with --camera", field="camera"
            )
        info = lg.camera_infos().get(frames[0].camera) if loc is not None else None
        if loc is not None and info is None:
            raise InputError(
                log,
                f"camera {frames[0].camera!r} has no intrinsics (camera_info): refine 6dof needs them",
                field="camera",
            )
        out.mkdir(parents=True, exist_ok=True)
        atomic_write_text(out / "config.yaml", dump_config(cfg))
        stamps = np.array([f.stamp_ns for f in frames], np.int64)
        t0 = time.perf_counter()
        odometry, odometry_info = (
            log_camera_odometry(lg, frames[0].camera, stamps, progress) if cfg.odometry else (None, None)
        )
        r = run_localizer(index, [f.image for f in frames], cfg, odometry, progress=progress)
        t1 = time.perf_counter()
        results = None
        if loc is not None:
            pixels = [_query_pixels(f) for f in frames]
            names = [str(s) for s in stamps]
            results = refine_sixdof(loc, index, r, pixels, [info] * len(frames), names, progress, odometry=odometry)
    write_run_trajectories(out, stamps, r)
    metrics: dict[str, Any] = {
        "bundle": str(bundle),
        "log": str(log),
        "queries": len(stamps),
        "frame": "workspace ENU of the bundle (world_from_camera)",
    }
    if odometry_info is not None:
        metrics["odometry"] = odometry_info
    if results is not None and loc is not None:
        metrics["sixdof"] = write_sixdof(out, stamps, results, loc)
    else:
        remove_sixdof_outputs(out)
    write_json(out / "metrics.json", metrics)
    timings: dict[str, Any] = {"filter_ms_per_step": 1000 * r.filter_s / len(stamps)}
    if results is not None:
        timings["sixdof_s_per_query"] = (time.perf_counter() - t1) / len(stamps)
        timings.update(sixdof_timings(results))
    write_timings(out, seconds=time.perf_counter() - t0, **timings)
    return out
