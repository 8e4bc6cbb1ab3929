"""The deployable VLAD image-retrieval index of a workspace (MCVL's observation encoder, Sec. III-B).

``build_vlad_index`` learns the encoder (vocabulary, then PCA-whitening) on the images of the
training sessions only, encodes every database image and writes a self-describing bundle;
``VladIndex.load`` reads it back, verifies it, and answers queries: the top R = 20 database images
(MCVL Sec. IV-A) with their poses, and the measurement ``z_t`` of Sec. III-B (mean shift over the
retrieved translations, :func:`mapkit.retrieval.measurement.mean_shift_measurement`).

Bundle layout (``WORKSPACE/indexes/vlad`` by default)::

    manifest.json   format_version, created, mapkit version, build hash, resolved config, source
                    workspace, sessions (image counts, pose source, table checksum), frame/CRS,
                    index kind and dimensions, and the sha256 and size of every other file
    config.yaml     the resolved VladIndexConfig
    encoder/        VladEncoder.save: vocabulary, PCA-whitening, VladConfig
    index.faiss     faiss index over the database vectors; row i of database.csv is faiss id i
    vectors.npy     (N, D) float32 database vectors; IVF bundles only (see below)
    database.csv    DATABASE_COLUMNS: entry id, session, image, stamp, camera pose in the local ENU
                    frame (x, y, z, qw, qx, qy, qz, world_from_cam), UTM and WGS84 position
    metrics.json    timings (images encoded per second, per step)

``vectors.npy`` is written for IVF bundles only. A flat index stores the exact float32 vectors
itself (``index.reconstruct_n`` gives them back), so a second copy would double the bundle for
nothing; an IVF-PQ index keeps only lossy codes, and retraining its coarse quantizer or codebooks
(a new ``nlist`` or ``pq_m``, or a much grown database) needs the exact vectors, so IVF bundles
keep them. Either way an index of another kind can be made without re-encoding a single image.

Writes are atomic at the level of the bundle: it is built in ``.<name>.partial-<pid>`` beside the
output and renamed into place last, so a folder at the output path is always a finished bundle
and an interrupted build leaves only a partial folder (removed by the next build once its process
is gone). Re-running with the same config and the same inputs (session tables) returns at once.
``add_session`` writes the grown bundle the same way.

The vocabulary's descriptor sample is drawn evenly from up to ``max_vocabulary_images`` training
images (a uniform sample of each image's RootSIFT descriptors, seeded per image), so it does not
depend on the number of workers. The PCA learns from up to ``max_training_images`` of them. With
fewer training images than the paper's 4096 dimensions the PCA is capped at n - 1, and whitening
in nearly as many dimensions as images flattens the differences between the training images
(which are usually the database): on the 8-session demo (684 training images, 683-D) recall@1/5/20
within 25 m was 0.38/0.62/0.83 whitened, against 0.46/0.69/0.88 with ``vlad.pca_dim: 256``.

Encoding is the expensive part (~0.27 s per 640x480 image and core). It runs on an executor
(:mod:`mapkit.core.executor`: this process, ``workers`` spawned processes, or Ray) whose workers compute
the raw VLAD (16384-D; only the config and the small vocabulary are shipped to them, once per
worker), while the parent applies the PCA in batches, in input order; the vectors are the same bit
for bit whichever executor ran.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import math
import os
import time
import warnings
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Iterator, Literal, Optional, Sequence

import cv2
import numpy as np
from pydantic import Field

from mapkit import __version__
from mapkit.core.config import MapkitConfig, dump_config, load_config
from mapkit.core.errors import ConfigError, InputError, InputWarning
from mapkit.core.executor import Executor, TaskError, get_executor
from mapkit.core.geodesy import LocalFrame, read_workspace_frame
from mapkit.mapping.imagedb import images_world_from_cam, read_images_csv
from mapkit.core.geometry import matrix_to_quat_wxyz
from mapkit.multisession.align import aligned_sessions
from mapkit.core.bundle import MANIFEST, building, is_finished, link_or_copy, read_manifest, write_manifest
from mapkit.retrieval.measurement import Measurement, mean_shift_measurement
from mapkit.core.runio import atomic_path, atomic_write_text, config_hash, sha256_file, write_json
from mapkit.retrieval.vlad import VladConfig, VladEncoder, kmeans

FORMAT_VERSION = 1
DATABASE_CSV = "database.csv"
INDEX_FILE = "index.faiss"
VECTORS_FILE = "vectors.npy"
ENCODER_DIR = "encoder"

DATABASE_COLUMNS = [
    "entry_id", "session", "image_id", "stamp_ns", "camera", "image",
    "x_m", "y_m", "z_m", "qw", "qx", "qy", "qz",
    "easting_m", "northing_m", "up_m", "lat_deg", "lon_deg", "alt_m", "utm_epsg",
]

#: settings that change neither the vectors nor the index: a new value rewrites the config, no rebuild
_QUERY_TIME_FIELDS = {"workers", "top_k", "mean_shift_bandwidth_m"}
_PCA_BATCH = 256  # raw VLADs (64 KiB each at K = 128) projected per matrix product


# --------------------------------------------------------------------------- configuration


class IvfConfig(MapkitConfig):
    """Inverted-file index for large databases (faiss IndexIVFFlat, or IndexIVFPQ with ``pq_m``)."""

    nlist: Optional[int] = Field(
        None, ge=1,
        description="Inverted lists (coarse centroids). None = 4 sqrt(N) (faiss's guideline); always capped at N / 39 so that "
        "k-means has the 39 training points per list faiss asks for.",
    )
    nprobe: int = Field(
        16, ge=1,
        description="Lists visited per query. With 1024 lists over 100k 4096-D vectors on one core: 14 ms per query and recall@20 "
        "0.999 of the exact top-20, against 107 ms exact (bench/bench_vlad_query.py, road-clustered synthetic vectors).",
    )
    pq_m: Optional[int] = Field(
        None, ge=1,
        description="None = IVF-Flat (exact distances inside the visited lists). m = IVF-PQ with m sub-quantizers (m bytes per "
        "vector at 8 bits; must divide the dimension): for city scale, at a recall cost measured by the benchmark.",
    )
    pq_bits: int = Field(8, ge=1, le=16, description="Bits per PQ sub-quantizer code.")
    max_training_vectors: int = Field(
        200_000, ge=1, description="The coarse quantizer (and PQ) train on a uniform sample of at most this many database vectors."
    )


class VladIndexConfig(MapkitConfig):
    """The VLAD retrieval index; defaults are MCVL's (Sec. III-B, IV-A) where the paper gives one."""

    vlad: VladConfig = Field(default_factory=VladConfig, description="The observation encoder (see mapkit.retrieval.vlad).")
    train_sessions: Optional[list[str]] = Field(
        None, description="Sessions whose images train the vocabulary and PCA. None = the database sessions. Never the query sessions.",
    )
    database_sessions: Optional[list[str]] = Field(None, description="Sessions whose images are indexed. None = every session in the workspace.")
    prefer_aligned_poses: bool = Field(
        True,
        description="Take camera poses from WORKSPACE/align (multi-session refinement) for sessions it finished, else from the "
        "session's GPS-aligned imagedb.",
    )
    index: Literal["flat", "ivf"] = Field("flat", description="'flat': exact search (faiss IndexFlatL2); 'ivf': approximate, for city scale.")
    ivf: IvfConfig = Field(default_factory=IvfConfig, description="IVF settings (used when index = 'ivf').")
    top_k: int = Field(20, ge=1, description="Images retrieved per query, R (MCVL Sec. IV-A: 20).")
    mean_shift_bandwidth_m: float = Field(5.0, gt=0, description="Radius of the flat mean-shift kernel over retrieved translations (m; the authors' code: 5).")
    max_training_images: int = Field(
        5000, ge=2,
        description="PCA trains on a uniform sample of at most this many training images (not in the paper; the 4096-D PCA of "
        "Sec. IV-A needs more than 4096; fewer cap the dimension at n - 1).",
    )
    max_vocabulary_images: int = Field(
        250, ge=1,
        description="The k-means descriptor sample (vlad.kmeans_max_descriptors) is drawn evenly from at most this many of the "
        "training images (not in the paper; ~800 descriptors per image at the defaults).",
    )
    workers: int = Field(1, ge=1, description="Processes encoding images (1 = in this process).")
    seed: int = Field(0, description="Seed of the image subsamples.")


# --------------------------------------------------------------------------- workspace sessions


@dataclass
class SessionImages:
    """One session's database images as the workspace gives them."""

    name: str
    pose_source: Literal["align", "imagedb"]
    csv_path: Path
    table: dict[str, np.ndarray]
    image_paths: list[Path]  # readable paths
    workspace_paths: list[str]  # relative to the workspace, as written to database.csv
    world_from_cam: np.ndarray  # (n, 4, 4) local ENU

    def __len__(self) -> int:
        return len(self.image_paths)


def workspace_sessions(workspace: str | Path) -> list[str]:
    """Names of the sessions of a workspace that have an image database, sorted."""
    sdir = Path(workspace) / "sessions"
    if not sdir.is_dir():
        return []
    return sorted(p.name for p in sdir.iterdir() if (p / "imagedb" / "images.csv").is_file())


def read_session_images(workspace: str | Path, name: str, prefer_aligned: bool = True) -> SessionImages:
    """A session's image table: the aligned one (``align/sessions/<name>/images.csv``) when the
    alignment finished and holds the session, else ``sessions/<name>/imagedb/images.csv``."""
    ws = Path(workspace)
    imagedb_csv = ws / "sessions" / name / "imagedb" / "images.csv"
    align_csv = ws / "align" / "sessions" / name / "images.csv"
    if prefer_aligned and name in aligned_sessions(ws) and align_csv.is_file():
        csv_path, source = align_csv, "align"
    elif imagedb_csv.is_file():
        csv_path, source = imagedb_csv, "imagedb"
    else:
        raise InputError(imagedb_csv, f"session {name!r} has no image database (run mapkit build)")
    table = read_images_csv(csv_path)
    paths = [csv_path.parent / p for p in table["image"]]
    rel = [os.path.relpath(p, ws) for p in paths]
    return SessionImages(name, source, csv_path, table, paths, rel, images_world_from_cam(table))


# --------------------------------------------------------------------------- encoding (parallel)


def read_image(path: str | Path) -> np.ndarray:
    """An image as stored (grey or BGR uint8), as the encoder takes it."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(path, "cannot read this image")
    if img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    return img


def _raw_task(encoder: VladEncoder, path: str) -> np.ndarray:
    """(K * 128,) raw VLAD of an image file: what workers compute (the PCA stays in the parent)."""
    return encoder.encode_raw(read_image(path))


def _sample_task(encoder: VladEncoder, args: tuple[str, int, int, int]) -> np.ndarray:
    """A uniform sample of ``size`` RootSIFT descriptors of one image, seeded by ``(seed, index)``."""
    from mapkit.retrieval.dsift import iter_histogram_blocks, prepare_image
    from mapkit.retrieval.vlad import _rootsift_from_histograms, _UniformSample  # the encoder's own sampling, per image

    path, size, seed, index = args
    cfg = encoder.cfg
    sample = _UniformSample(size, np.random.default_rng([seed, index]))
    gray, _, _ = prepare_image(read_image(path), cfg.dsift)
    for blk in iter_histogram_blocks(gray, cfg.dsift):
        sample.add(_rootsift_from_histograms(blk.histograms, cfg.dsift.clamp))
    return sample.result()


def _map(fn, items: Sequence, encoder: VladEncoder, executor: Executor, progress: bool, desc: str) -> Iterator:
    """``fn(encoder, item)`` over ``items`` in order on ``executor``; only the encoder's config and
    vocabulary travel to workers (never the PCA, up to 256 MiB at 4096-D).

    An input error of one image (unreadable, too small) is raised as that image's InputError: it
    names the file already.
    """
    shared = VladEncoder(encoder.cfg, encoder.vocabulary)
    try:
        yield from executor.map(fn, items, shared=shared, progress=progress and len(items) > 0, desc=desc, unit="img",
                                label=lambda item: str(item[0] if isinstance(item, tuple) else item))
    except TaskError as exc:
        if isinstance(exc.cause, InputError) and exc.cause.path is not None:
            raise exc.cause from None
        raise


@contextlib.contextmanager
def _faiss_threads(n: int) -> Iterator[None]:
    """faiss (OpenMP) on ``n`` threads for a while. k-means of 200k descriptors into 128 words took
    24 s on 2 threads and 5 s on 1 on this shared 2-core machine (OpenMP barriers spin)."""
    import faiss

    before = faiss.omp_get_max_threads()
    faiss.omp_set_num_threads(n)
    try:
        yield
    finally:
        faiss.omp_set_num_threads(before)


def _file_key(path: str | Path) -> str:
    p = Path(path).resolve()
    st = p.stat()
    return f"{p}|{st.st_size}|{st.st_mtime_ns}"


def encode_images(
    encoder: VladEncoder, paths: Sequence[str | Path], workers: int = 1, progress: bool = False, desc: str = "encode",
    executor: Optional[Executor] = None,
) -> np.ndarray:
    """(n, D) float32 encodings of image files (dense RootSIFT, VLAD, PCA-whitening, L2).

    Runs on ``executor``, else on the process-wide default (:func:`mapkit.core.executor.get_executor`),
    else in ``workers`` local processes; the result is the same bit for bit on any of them.
    """
    executor = executor or get_executor(workers)
    out = np.zeros((len(paths), encoder.pca.dim), np.float32)
    for rows, raw in _batched(_map(_raw_task, [str(p) for p in paths], encoder, executor, progress, desc), _PCA_BATCH):
        out[rows] = encoder.pca.transform(raw)
    return out


def _batched(raws: Iterator[np.ndarray], size: int) -> Iterator[tuple[slice, np.ndarray]]:
    buf: list[np.ndarray] = []
    start = 0
    for r in raws:
        buf.append(r)
        if len(buf) == size:
            yield slice(start, start + size), np.stack(buf)
            start += size
            buf = []
    if buf:
        yield slice(start, start + len(buf)), np.stack(buf)


# --------------------------------------------------------------------------- building




def _uniform_subset(n: int, size: int, seed: int, salt: int) -> np.ndarray:
    """Sorted indices of a uniform random subset of ``min(n, size)`` of ``range(n)``."""
    if n <= size:
        return np.arange(n)
    return np.sort(np.random.default_rng([seed, salt]).choice(n, size, replace=False))


def build_vlad_index(
    workspace: str | Path,
    out: str | Path | None = None,
    config: VladIndexConfig | str | Path | None = None,
    overrides: Optional[dict] = None,
    progress: bool = True,
    executor: Optional[Executor] = None,
) -> Path:
    """Build the VLAD index bundle of ``workspace``; returns its folder (default ``WORKSPACE/indexes/vlad``).

    Images are encoded on ``executor``, else on the process-wide default executor, else in
    ``workers`` local processes (:func:`mapkit.core.executor.get_executor`); the bundle's vectors do not
    depend on which.

    The vocabulary and PCA learn from training-session images only; every database image is
    encoded once (the training subsample's raw VLADs are kept for the PCA and reused). Skips when
    the bundle at ``out`` was built from the same config and session tables.
    """
    t_start = time.perf_counter()
    ws = Path(workspace)
    cfg = load_config(VladIndexConfig, config, overrides)
    out = Path(out) if out is not None else ws / "indexes" / "vlad"
    if not (ws / "sessions").is_dir():
        raise InputError(ws / "sessions", "not a workspace (no sessions/ folder): run mapkit build first")
    available = workspace_sessions(ws)
    db_names = list(cfg.database_sessions) if cfg.database_sessions is not None else available
    train_names = list(cfg.train_sessions) if cfg.train_sessions is not None else db_names
    for field, names in (("database_sessions", db_names), ("train_sessions", train_names)):
        missing = [n for n in names if n not in available]
        if missing:
            raise InputError(ws / "sessions", f"no image database for session(s) {missing}; the workspace has {available}", field=field)
        if len(set(names)) != len(names):
            raise ConfigError(f"{field} lists a session twice: {names}")
    if not db_names:
        raise InputError(ws / "sessions", "no session with an image database to index", field="database_sessions")
    if not train_names:
        raise ConfigError("train_sessions is empty: the vocabulary and PCA need training images")

    frame = read_workspace_frame(ws)
    sessions = {n: read_session_images(ws, n, cfg.prefer_aligned_poses) for n in dict.fromkeys(db_names + train_names)}
    for field, names, least in (("database_sessions", db_names, 1), ("train_sessions", train_names, 2)):
        n_images = sum(len(sessions[n]) for n in names)
        if n_images < least:  # nothing to index or to learn from: fail before any bundle is written
            raise InputError(ws / "sessions", f"{n_images} image(s) in the image databases of {field} {names} (at least {least} "
                             "needed): rebuild them with a longer drive or a smaller imagedb.min_spacing_m, or name other sessions",
                             field=field)
    inputs = {n: [s.pose_source, sha256_file(s.csv_path)] for n, s in sessions.items()}
    build_hash = config_hash({"format_version": FORMAT_VERSION, "config": cfg.model_dump(mode="json", exclude=_QUERY_TIME_FIELDS),
                              "database": db_names, "train": train_names, "tables": inputs,
                              "frame": None if frame is None else frame.to_dict()})
    if is_finished(out, build_hash, FORMAT_VERSION):
        if json.loads((out / MANIFEST).read_text())["config"] != cfg.model_dump(mode="json"):
            _rewrite_config(out, cfg)  # only query-time settings differ: nothing to encode again
        return out
    if out.exists() and not (out / MANIFEST).is_file() and any(out.iterdir()):
        raise InputError(out, "exists and is not a VLAD index bundle (no manifest.json): refusing to replace it")

    with building(out) as tmp:
        metrics, manifest = _build_into(tmp, ws, cfg, sessions, db_names, train_names, frame, build_hash, progress,
                                        executor or get_executor(cfg.workers))
        metrics["seconds_total"] = time.perf_counter() - t_start
        write_json(tmp / "metrics.json", metrics)
        write_manifest(tmp, manifest)  # last: it checksums every other file
    return out


def _build_into(tmp: Path, ws: Path, cfg: VladIndexConfig, sessions: dict[str, SessionImages], db_names: list[str],
                train_names: list[str], frame: Optional[LocalFrame], build_hash: str, progress: bool,
                executor: Executor) -> tuple[dict, dict]:
    """Learn, encode and write everything but metrics.json and the manifest into ``tmp``; returns both."""
    timings: dict[str, float] = {}
    # training images: every image of the training sessions, uniformly subsampled
    train_refs = [(n, i) for n in train_names for i in range(len(sessions[n]))]
    if len(train_refs) < 2:
        raise InputError(sessions[train_names[0]].csv_path, f"{len(train_refs)} training image(s): the PCA needs at least 2", field="train_sessions")
    train_sel = [train_refs[i] for i in _uniform_subset(len(train_refs), cfg.max_training_images, cfg.seed, 1)]
    vocab_sel = [train_sel[i] for i in _uniform_subset(len(train_sel), cfg.max_vocabulary_images, cfg.seed, 2)]
    path_of = lambda ref: str(sessions[ref[0]].image_paths[ref[1]])  # noqa: E731

    # 1. vocabulary: k-means on descriptors drawn evenly from the vocabulary images
    t0 = time.perf_counter()
    per_image = math.ceil(cfg.vlad.kmeans_max_descriptors / len(vocab_sel))
    tasks = [(path_of(r), per_image, cfg.vlad.seed, k) for k, r in enumerate(vocab_sel)]
    sample = np.concatenate(list(_map(_sample_task, tasks, VladEncoder(cfg.vlad), executor, progress, "descriptors")))
    with _faiss_threads(1):
        vocabulary = kmeans(sample, cfg.vlad.num_words, cfg.vlad.kmeans_iterations, cfg.vlad.seed)
    timings["vocabulary_s"] = time.perf_counter() - t0
    n_descriptors = len(sample)
    del sample

    # 2. PCA-whitening on the raw VLADs of the training images
    t0 = time.perf_counter()
    encoder = VladEncoder(cfg.vlad, vocabulary)
    raw_train = np.zeros((len(train_sel), encoder.raw_dim), np.float32)
    for i, r in enumerate(_map(_raw_task, [path_of(r) for r in train_sel], encoder, executor, progress, "train VLAD")):
        raw_train[i] = r
    timings["encode_training_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    encoder.fit_pca(raw_train)
    timings["pca_s"] = time.perf_counter() - t0

    # 3. database: reuse the training raws, encode the rest
    t0 = time.perf_counter()
    db_refs = [(n, i) for n in db_names for i in range(len(sessions[n]))]
    if not db_refs:
        raise InputError(sessions[db_names[0]].csv_path, "the database sessions hold no image", field="database_sessions")
    vectors = np.zeros((len(db_refs), encoder.pca.dim), np.float32)
    row_of_train = {r: k for k, r in enumerate(train_sel)}
    reused = [j for j, r in enumerate(db_refs) if r in row_of_train]
    for a in range(0, len(reused), _PCA_BATCH):
        js = reused[a : a + _PCA_BATCH]
        vectors[js] = encoder.pca.transform(raw_train[[row_of_train[db_refs[j]] for j in js]])
    del raw_train
    todo = [j for j, r in enumerate(db_refs) if r not in row_of_train]
    vectors[todo] = encode_images(encoder, [path_of(db_refs[j]) for j in todo], progress=progress, desc="database", executor=executor)
    timings["encode_database_s"] = time.perf_counter() - t0
    n_encoded = len(train_sel) + len(todo)

    # 4. index
    t0 = time.perf_counter()
    index, index_info = make_index(vectors, cfg)
    timings["index_s"] = time.perf_counter() - t0

    # 5. files (manifest last)
    encoder.save(tmp / ENCODER_DIR)
    _write_index(tmp, index, vectors if cfg.index == "ivf" else None)
    table = _database_table(db_names, sessions, frame)
    _write_database_csv(tmp / DATABASE_CSV, table)
    atomic_write_text(tmp / "config.yaml", dump_config(cfg))
    encode_s = timings["encode_training_s"] + timings["encode_database_s"]
    metrics = {
        "images_encoded": n_encoded,
        "images_encoded_per_s": n_encoded / encode_s if encode_s > 0 else None,
        "database_images": len(db_refs),
        "database_images_reused_from_training": len(reused),
        "training_images": len(train_sel),
        "vocabulary_images": len(vocab_sel),
        "vocabulary_descriptors": n_descriptors,
        "executor": executor.kind,
        "workers": executor.workers,
        **timings,
    }
    train_count = {n: sum(1 for r in train_sel if r[0] == n) for n in train_names}
    manifest = {
        "format_version": FORMAT_VERSION,
        "kind": "mapkit VLAD index",
        "created": _now(),
        "mapkit_version": __version__,
        "build_hash": build_hash,
        "config": cfg.model_dump(mode="json"),
        "source_workspace": str(ws.resolve()),
        "frame": None if frame is None else frame.to_dict(),
        "database_sessions": db_names,
        "train_sessions": train_names,
        "sessions": {
            n: {
                "images": len(s) if n in db_names else 0,
                "training_images": train_count.get(n, 0),
                "database": n in db_names,
                "training": n in train_names,
                "pose_source": s.pose_source,
                "images_csv": os.path.relpath(s.csv_path, ws),
                "images_csv_sha256": sha256_file(s.csv_path),
            }
            for n, s in sessions.items()
        },
        "added_sessions": [],
        "vlad": {"raw_dim": encoder.raw_dim, "dim": encoder.pca.dim, "pca_dim_requested": cfg.vlad.pca_dim,
                 "training_images": len(train_sel), "vocabulary_images": len(vocab_sel)},
        "index": index_info,
        "entries": len(db_refs),
    }
    return metrics, manifest


def make_index(vectors: np.ndarray, cfg: VladIndexConfig):
    """A faiss index over (N, D) float32 vectors, and its description for the manifest."""
    import faiss

    n, d = vectors.shape
    if cfg.index == "flat":
        index = faiss.IndexFlatL2(d)
        index.add(vectors)
        return index, {"kind": "flat", "faiss": "IndexFlatL2", "dim": d, "metric": "squared L2", "ntotal": int(index.ntotal)}
    ivf = cfg.ivf
    cap = max(1, n // 39)
    nlist = min(ivf.nlist or max(1, round(4 * math.sqrt(n))), cap)
    if ivf.nlist is not None and nlist < ivf.nlist:
        warnings.warn(f"IVF nlist capped from {ivf.nlist} to {nlist}: {n} database vectors (39 per list)", InputWarning, stacklevel=3)
    quantizer = faiss.IndexFlatL2(d)
    if ivf.pq_m is None:
        index = faiss.IndexIVFFlat(quantizer, d, nlist, faiss.METRIC_L2)
        kind = "IndexIVFFlat"
    else:
        if d % ivf.pq_m:
            raise ConfigError(f"ivf.pq_m = {ivf.pq_m} does not divide the vector dimension {d}")
        if n < 2**ivf.pq_bits:
            raise ConfigError(f"IVF-PQ with {ivf.pq_bits}-bit codes needs at least {2 ** ivf.pq_bits} database vectors, got {n}")
        index = faiss.IndexIVFPQ(quantizer, d, nlist, ivf.pq_m, ivf.pq_bits)
        kind = "IndexIVFPQ"
    train = vectors[_uniform_subset(n, ivf.max_training_vectors, cfg.seed, 3)]
    index.train(np.ascontiguousarray(train))
    index.add(vectors)
    index.nprobe = min(ivf.nprobe, nlist)
    info = {"kind": "ivf", "faiss": kind, "dim": d, "metric": "squared L2", "ntotal": int(index.ntotal), "nlist": nlist,
            "nprobe": int(index.nprobe), "pq_m": ivf.pq_m, "pq_bits": ivf.pq_bits if ivf.pq_m else None}
    return index, info


def _write_index(folder: Path, index, vectors: Optional[np.ndarray]) -> None:
    import faiss

    faiss.write_index(index, str(folder / INDEX_FILE))
    if vectors is not None:
        np.save(folder / VECTORS_FILE, np.ascontiguousarray(vectors, np.float32))


def _database_table(names: list[str], sessions: dict[str, SessionImages], frame: Optional[LocalFrame], first_id: int = 0) -> dict[str, Any]:
    cols: dict[str, list] = {c: [] for c in DATABASE_COLUMNS}
    T_all = []
    for n in names:
        s = sessions[n]
        cols["session"] += [n] * len(s)
        cols["image_id"] += list(s.table["image_id"])
        cols["stamp_ns"] += list(s.table["stamp_ns"])
        cols["camera"] += list(s.table["camera"])
        cols["image"] += s.workspace_paths
        T_all.append(s.world_from_cam)
    T = np.concatenate(T_all) if T_all else np.zeros((0, 4, 4))
    n_all = len(T)
    xyz = T[:, :3, 3]
    q = matrix_to_quat_wxyz(T[:, :3, :3]) if n_all else np.zeros((0, 4))
    if frame is not None and n_all:
        lat, lon, alt = frame.enu_to_geodetic(xyz)
        utm = frame.enu_to_utm(xyz)
        epsg = int(frame.utm_epsg)
    else:
        lat = lon = alt = np.full(n_all, np.nan)
        utm = np.full((n_all, 3), np.nan)
        epsg = 0
    out: dict[str, Any] = {
        "entry_id": np.arange(first_id, first_id + n_all, dtype=np.int64),
        "session": np.asarray(cols["session"], dtype=object),
        "image_id": np.asarray(cols["image_id"], np.int64),
        "stamp_ns": np.asarray(cols["stamp_ns"], np.int64),
        "camera": np.asarray(cols["camera"], dtype=object),
        "image": np.asarray(cols["image"], dtype=object),
        "x_m": xyz[:, 0], "y_m": xyz[:, 1], "z_m": xyz[:, 2],
        "qw": q[:, 0], "qx": q[:, 1], "qy": q[:, 2], "qz": q[:, 3],
        "easting_m": utm[:, 0], "northing_m": utm[:, 1], "up_m": utm[:, 2],
        "lat_deg": np.asarray(lat, np.float64), "lon_deg": np.asarray(lon, np.float64), "alt_m": np.asarray(alt, np.float64),
        "utm_epsg": np.full(n_all, epsg, np.int64),
    }
    return out


_FORMATS = {"x_m": ".4f", "y_m": ".4f", "z_m": ".4f", "qw": ".9f", "qx": ".9f", "qy": ".9f", "qz": ".9f",
            "easting_m": ".4f", "northing_m": ".4f", "up_m": ".4f", "lat_deg": ".9f", "lon_deg": ".9f", "alt_m": ".4f"}


def _write_database_csv(path: Path, table: dict[str, Any]) -> None:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(DATABASE_COLUMNS)
    for i in range(len(table["entry_id"])):
        w.writerow([format(table[c][i], _FORMATS[c]) if c in _FORMATS else table[c][i] for c in DATABASE_COLUMNS])
    atomic_write_text(path, buf.getvalue())


def read_database_csv(path: str | Path) -> dict[str, np.ndarray]:
    """The bundle's database table as columns (numbers as arrays, names and paths as object arrays)."""
    path = Path(path)
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        missing = [c for c in DATABASE_COLUMNS if c not in (reader.fieldnames or [])]
        if missing:
            raise InputError(path, f"header lacks {missing}", field="header")
        rows = list(reader)
    out: dict[str, np.ndarray] = {}
    for c in DATABASE_COLUMNS:
        vals = [r[c] for r in rows]
        if c in ("session", "camera", "image"):
            out[c] = np.asarray(vals, dtype=object)
        elif c in ("entry_id", "image_id", "stamp_ns", "utm_epsg"):
            out[c] = np.asarray([int(v) for v in vals], np.int64)
        else:
            out[c] = np.asarray([float(v) for v in vals], np.float64)
    return out


def _concat_tables(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    return {c: np.concatenate([np.asarray(a[c]), np.asarray(b[c])]) for c in DATABASE_COLUMNS}


# --------------------------------------------------------------------------- bundle plumbing


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def _rewrite_config(out: Path, cfg: VladIndexConfig) -> None:
    """A copy of the bundle (hard links) with a new config.yaml and manifest config, swapped in."""
    with building(out) as tmp:
        for p in out.rglob("*"):
            rel = p.relative_to(out)
            if p.is_file() and rel.as_posix() not in (MANIFEST, "config.yaml"):
                link_or_copy(p, tmp / rel)
        atomic_write_text(tmp / "config.yaml", dump_config(cfg))
        manifest = json.loads((out / MANIFEST).read_text())
        manifest["config"] = cfg.model_dump(mode="json")
        manifest["modified"] = _now()
        write_manifest(tmp, manifest)


# --------------------------------------------------------------------------- the loaded index


@dataclass(frozen=True, eq=False)
class Hits:
    """The database images retrieved for one query, best first.

    ``distances`` are squared L2 between unit vectors (0 to 4); ``world_from_cam`` (k, 4, 4) are
    camera poses in the bundle's local ENU frame; ``utm_enh`` (k, 3) easting, northing (m) and
    ellipsoidal height; ``lat_lon_alt`` (k, 3) WGS84 degrees and metres.
    """

    ids: np.ndarray
    distances: np.ndarray
    world_from_cam: np.ndarray
    utm_enh: np.ndarray
    lat_lon_alt: np.ndarray
    sessions: list[str]
    images: list[str]
    image_ids: np.ndarray
    stamps_ns: np.ndarray

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def translations(self) -> np.ndarray:
        """(k, 3) camera positions in the local ENU frame (m)."""
        return self.world_from_cam[:, :3, 3]


class VladIndex:
    """A loaded VLAD bundle: encode images, retrieve the top-k database images, measure the pose."""

    def __init__(self, path: Path, manifest: dict, cfg: VladIndexConfig, encoder: VladEncoder, index, database: dict[str, np.ndarray]):
        self.path = Path(path)
        self.manifest = manifest
        self.cfg = cfg
        self.encoder = encoder
        self.index = index
        self.database = database
        self.world_from_cam = images_world_from_cam(database)
        self.frame = LocalFrame.from_dict(manifest["frame"]) if manifest.get("frame") else None

    # ---- loading

    @classmethod
    def load(cls, path: str | Path, verify: bool = True) -> "VladIndex":
        """Read a bundle; checks its format version and (``verify``) every file's sha256."""
        import faiss

        path = Path(path)
        mpath = path / MANIFEST
        manifest = read_manifest(path, "VLAD index", FORMAT_VERSION,
                                 (DATABASE_CSV, INDEX_FILE, f"{ENCODER_DIR}/{VladEncoder.MODEL_FILE}"), verify)
        try:
            cfg = VladIndexConfig.model_validate(manifest["config"])
        except Exception as exc:  # noqa: BLE001 - pydantic's error, reported against the manifest
            raise InputError(mpath, f"invalid config ({exc})", field="config") from None
        encoder = VladEncoder.load(path / ENCODER_DIR)
        index = faiss.read_index(str(path / INDEX_FILE))
        if hasattr(index, "nprobe") and manifest.get("index", {}).get("nprobe"):
            index.nprobe = int(manifest["index"]["nprobe"])
        database = read_database_csv(path / DATABASE_CSV)
        n = len(database["entry_id"])
        if index.ntotal != n or not np.array_equal(database["entry_id"], np.arange(n)):
            raise InputError(path / DATABASE_CSV, f"{n} rows (ids 0..n-1 expected) for an index of {index.ntotal} vectors", field="entry_id")
        if encoder.pca is None or index.d != encoder.pca.dim:
            raise InputError(path / INDEX_FILE, f"index dimension {index.d} differs from the encoder's", field="dim")
        return cls(path, manifest, cfg, encoder, index, database)

    # ---- facts

    def __len__(self) -> int:
        return int(self.index.ntotal)

    @property
    def dim(self) -> int:
        return int(self.index.d)

    @property
    def database_sessions(self) -> list[str]:
        return [n for n, s in self.manifest["sessions"].items() if s.get("database")]

    @property
    def train_sessions(self) -> list[str]:
        return [n for n, s in self.manifest["sessions"].items() if s.get("training")]

    # ---- queries

    def encode(self, image: np.ndarray | str | Path) -> np.ndarray:
        """(D,) float32 unit vector of an image (array or file)."""
        if isinstance(image, (str, Path)):
            image = read_image(image)
        return self.encoder.encode(np.asarray(image))

    def _as_vector(self, image_or_vector) -> np.ndarray:
        if isinstance(image_or_vector, (str, Path)):
            return self.encode(image_or_vector)
        a = np.asarray(image_or_vector)
        if a.ndim == 1 and a.dtype.kind == "f":
            if len(a) != self.dim:
                raise InputError(None, f"query vector has {len(a)} dimensions, the index {self.dim}", field="dim")
            return a.astype(np.float32)
        return self.encode(a)

    def search(self, vectors: np.ndarray, k: Optional[int] = None) -> tuple[np.ndarray, np.ndarray]:
        """Batch search: (distances (n, k) squared L2, ids (n, k)); ids -1 pad when k > len(self)."""
        q = np.ascontiguousarray(np.atleast_2d(vectors), np.float32)
        if q.shape[1] != self.dim:
            raise InputError(None, f"query vectors have {q.shape[1]} dimensions, the index {self.dim}", field="dim")
        return self.index.search(q, int(k or self.cfg.top_k))

    def hits(self, ids: np.ndarray, distances: np.ndarray) -> Hits:
        """The database rows of retrieved ``ids`` (padding ids < 0 dropped)."""
        keep = np.asarray(ids) >= 0
        ids, distances = np.asarray(ids)[keep].astype(np.int64), np.asarray(distances)[keep]
        db = self.database
        return Hits(
            ids=ids,
            distances=distances,
            world_from_cam=self.world_from_cam[ids],
            utm_enh=np.stack([db["easting_m"][ids], db["northing_m"][ids], db["up_m"][ids]], axis=1),
            lat_lon_alt=np.stack([db["lat_deg"][ids], db["lon_deg"][ids], db["alt_m"][ids]], axis=1),
            sessions=[str(s) for s in db["session"][ids]],
            images=[str(s) for s in db["image"][ids]],
            image_ids=db["image_id"][ids],
            stamps_ns=db["stamp_ns"][ids],
        )

    def encode_files(self, paths: Sequence[str | Path], progress: bool = False, desc: str = "encode",
                     cache_dir: str | Path | None = None, workers: Optional[int] = None) -> np.ndarray:
        """(n, D) encodings of image files, on the run's executor (see :func:`encode_images`).

        With ``cache_dir``, encodings are kept in ``encodings-<build hash>.npz`` there, keyed by
        each file's resolved path, size and mtime, and only the files not found are encoded: two
        evaluations of the same images (localization and place recognition) encode them once.
        ``workers`` (default: the bundle's setting) applies when no run-wide executor is set.
        """
        workers = self.cfg.workers if workers is None else workers
        if cache_dir is None:
            return encode_images(self.encoder, paths, workers, progress, desc)
        cache = Path(cache_dir) / f"encodings-{self.manifest.get('build_hash', 'x')}.npz"
        keys = [_file_key(p) for p in paths]
        have: dict[str, np.ndarray] = {}
        if cache.is_file():
            try:
                with np.load(cache, allow_pickle=False) as z:
                    if z["vectors"].shape[1:] == (self.dim,):
                        have = dict(zip(z["keys"].tolist(), z["vectors"]))
            except (OSError, KeyError, ValueError):
                have = {}  # unreadable: encode again, the file is replaced below
        todo = sorted({k: i for i, k in enumerate(keys) if k not in have}.values())
        if todo:
            vec = encode_images(self.encoder, [paths[i] for i in todo], workers, progress, desc)
            have.update({keys[i]: v for i, v in zip(todo, vec)})
            with atomic_path(cache) as tmp, open(tmp, "wb") as f:
                np.savez(f, keys=np.array(list(have)), vectors=np.stack(list(have.values())).astype(np.float32))
        out = np.zeros((len(paths), self.dim), np.float32)
        for i, k in enumerate(keys):
            out[i] = have[k]
        return out

    def query(self, image_or_vector, k: Optional[int] = None) -> Hits:
        """The top ``k`` (default ``top_k`` = 20) database images of an image, image file or encoded vector."""
        dist, ids = self.search(self._as_vector(image_or_vector)[None], k)
        return self.hits(ids[0], dist[0])

    def measurement(self, image_or_vector, k: Optional[int] = None) -> Measurement:
        """MCVL's measurement z_t (Sec. III-B): mean shift over the top-k translations, the largest
        cluster's mean translation and rotation (camera pose, local ENU)."""
        return self.measurement_from_hits(self.query(image_or_vector, k))

    def measurement_from_hits(self, hits: Hits) -> Measurement:
        if len(hits) == 0:
            raise InputError(self.path, "the index is empty: no measurement")
        return mean_shift_measurement(hits.translations, hits.world_from_cam[:, :3, :3], bandwidth=self.cfg.mean_shift_bandwidth_m)

    def vectors(self) -> np.ndarray:
        """(N, D) float32 database vectors: from vectors.npy, or reconstructed exactly from a flat index."""
        p = self.path / VECTORS_FILE
        if p.is_file():
            return np.load(p)
        return self.index.reconstruct_n(0, self.index.ntotal)

    # ---- growing

    def add_session(self, workspace: str | Path, name: str, progress: bool = False, executor: Optional[Executor] = None) -> "VladIndex":
        """Append a session's images (encoded with this bundle's vocabulary and PCA, not relearned).

        The grown bundle is written beside this one and renamed into place; ``self`` then holds it.
        """
        ws = Path(workspace)
        mpath = self.path / MANIFEST
        if name in self.manifest["sessions"] and self.manifest["sessions"][name].get("database"):
            raise InputError(mpath, f"session {name!r} is already in the index", field="sessions")
        frame = read_workspace_frame(ws)
        mine = self.manifest.get("frame")
        if (frame is None) != (mine is None) or (frame is not None and not _same_frame(frame, LocalFrame.from_dict(mine))):
            raise InputError(ws / "origin.json", "the workspace's local frame differs from the bundle's: its poses would not match", field="frame")
        s = read_session_images(ws, name, self.cfg.prefer_aligned_poses)
        t0 = time.perf_counter()
        new = encode_images(self.encoder, [str(p) for p in s.image_paths], self.cfg.workers, progress, f"add {name}", executor)
        encode_s = time.perf_counter() - t0
        table = _database_table([name], {name: s}, frame, first_id=len(self))
        database = _concat_tables(self.database, table)

        import faiss

        index = faiss.clone_index(self.index)
        index.add(new)
        with building(self.path) as tmp:
            rewritten = {MANIFEST, INDEX_FILE, VECTORS_FILE, DATABASE_CSV, "metrics.json"}
            for p in self.path.rglob("*"):
                rel = p.relative_to(self.path)
                if p.is_file() and rel.as_posix() not in rewritten:
                    link_or_copy(p, tmp / rel)
            vectors = np.concatenate([np.load(self.path / VECTORS_FILE), new]) if (self.path / VECTORS_FILE).is_file() else None
            _write_index(tmp, index, vectors)
            _write_database_csv(tmp / DATABASE_CSV, database)
            metrics = json.loads((self.path / "metrics.json").read_text()) if (self.path / "metrics.json").is_file() else {}
            metrics.setdefault("added_sessions", {})[name] = {"images": len(s), "encode_s": encode_s,
                                                              "images_encoded_per_s": len(s) / encode_s if encode_s > 0 else None}
            write_json(tmp / "metrics.json", metrics)
            manifest = json.loads(json.dumps(self.manifest))
            manifest["sessions"][name] = {
                "images": len(s), "training_images": 0, "database": True, "training": False, "pose_source": s.pose_source,
                "images_csv": os.path.relpath(s.csv_path, ws), "images_csv_sha256": sha256_file(s.csv_path),
                "source_workspace": str(ws.resolve()),
            }
            manifest["database_sessions"] = list(manifest["database_sessions"]) + [name]
            manifest["added_sessions"] = list(manifest.get("added_sessions", [])) + [{"session": name, "added": _now(), "images": len(s)}]
            manifest["entries"] = int(index.ntotal)
            manifest["index"]["ntotal"] = int(index.ntotal)
            manifest["modified"] = _now()
            write_manifest(tmp, manifest)
        self.manifest, self.index, self.database = manifest, index, database
        self.world_from_cam = images_world_from_cam(database)
        return self


def _same_frame(a: LocalFrame, b: LocalFrame) -> bool:
    return (abs(a.lat0_deg - b.lat0_deg) < 1e-9 and abs(a.lon0_deg - b.lon0_deg) < 1e-9 and abs(a.alt0_m - b.alt0_m) < 1e-4
            and int(a.utm_epsg) == int(b.utm_epsg))


__all__ = [
    "FORMAT_VERSION", "DATABASE_COLUMNS", "IvfConfig", "VladIndexConfig", "SessionImages", "Hits", "VladIndex",
    "build_vlad_index", "make_index", "encode_images", "read_image", "read_session_images", "workspace_sessions",
    "aligned_sessions", "read_database_csv",
]
