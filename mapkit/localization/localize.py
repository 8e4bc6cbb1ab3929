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
"""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field, field_validator

from mapkit.core.config import MapkitConfig, dump_config, load_config
from mapkit.core.errors import InputError
from mapkit.core.runio import atomic_path, atomic_write_text, progress_bar, sha256_file, write_json, write_timings
from mapkit.core.types import StreamKind
from mapkit.core.writers import writes_workspace
from mapkit.io import open_log
from mapkit.io.trajectory import write_tum
from mapkit.localization.mcl import FORWARD_CAMERA_ROTATION, CameraMount, MclConfig, MonteCarloLocalizer
from mapkit.retrieval.index_vlad import VladIndex
from mapkit.retrieval.measurement import PoseHypotheses, mean_shift_measurement

Row4 = tuple[float, float, float, float]


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
        description="Beyond the paper: drive the motion model by the query session's own trajectory "
        "(its relative camera motion between queries, turned into the base's through base_from_camera) instead "
        "of eqs. 1-2. Sets mcl.odometry.enabled.",
    )
    seed: int = Field(0, description="Seed of the particle filter.")

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


@writes_workspace("out", within=True)
def localize_log(
    bundle: str | Path,
    log: str | Path,
    out: str | Path,
    config: str | Path | None = None,
    camera: str | None = None,
    progress: bool = True,
) -> Path:
    """Run the localizer on the camera images of a drive log against a VLAD bundle; writes the
    filter's and retrieval's camera poses as TUM files, the resolved config and metrics."""

    cfg = load_config(LocalizeConfig, config)
    index = VladIndex.load(bundle)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "config.yaml", dump_config(cfg))
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
        stamps = np.array([f.stamp_ns for f in frames], np.int64)
        t0 = time.perf_counter()
        r = run_localizer(index, [f.image for f in frames], cfg, progress=progress)
    write_run_trajectories(out, stamps, r)
    write_json(
        out / "metrics.json",
        {
            "bundle": str(bundle),
            "log": str(log),
            "queries": len(stamps),
            "frame": "workspace ENU of the bundle (world_from_camera)",
        },
    )
    write_timings(out, seconds=time.perf_counter() - t0, filter_ms_per_step=1000 * r.filter_s / len(stamps))
    return out
