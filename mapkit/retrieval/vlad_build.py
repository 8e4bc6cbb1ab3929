"""Building the VLAD bundle of a workspace (``mapkit index vlad``): learn the encoder on the
training sessions, encode every database image, index the vectors and write the bundle.

The vocabulary's descriptor sample is drawn evenly from up to ``max_vocabulary_images`` training
images (a uniform sample of each image's RootSIFT descriptors, seeded per image), so it does not
depend on the number of workers. The PCA learns from up to ``max_training_images`` of them; the
training images' raw VLADs are kept and reused for those that are also database images, so every
image is encoded once. By default the training sessions are the database sessions, so the PCA
learns on the database itself, usually on fewer images than the 4096 dimensions of MCVL Sec. IV-A:
the dimension is then n - 1 and ``vlad.whitening`` must be regularised (the default, 'power')
rather than full, which would make the database images equidistant (see :mod:`mapkit.retrieval.vlad`).
Sessions beyond the database named in ``train_sessions`` give the PCA images the database does not
hold, and so, with ``training_frames: true``, do the frames a build kept beside each training
session's database (``imagedb.training_frames``). The manifest's ``vlad.pca`` (and ``metrics.json``'s
``pca``) records what it learned on. The bundle is written into a partial folder and renamed into
place (:func:`mapkit.core.bundle.building`). See :mod:`mapkit.retrieval.index_vlad` for the layout.
"""

from __future__ import annotations

import json
import math
import os
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mapkit import __version__
from mapkit.core.blas import openblas_kernels
from mapkit.core.bundle import MANIFEST, building, copy_file, is_finished, read_manifest, write_manifest
from mapkit.core.config import dump_config, load_config
from mapkit.core.errors import ConfigError, InputError, InputWarning
from mapkit.core.executor import Executor, get_executor
from mapkit.core.geodesy import LocalFrame
from mapkit.core.runio import atomic_write_text, config_hash, sha256_file, verify_file, write_json, write_timings
from mapkit.core.workspace import Workspace
from mapkit.core.writers import writes_workspace
from mapkit.retrieval.vlad import PcaWhitening, VladEncoder, kmeans, whitening_parameters
from mapkit.retrieval.vlad_bundle import (
    _QUERY_TIME_FIELDS,
    DATABASE_CSV,
    ENCODER_DIR,
    FORMAT_VERSION,
    INDEX_FILE,
    SessionImages,
    VladIndexConfig,
    _database_table,
    _write_database_csv,
    _write_index,
    read_session_images,
    read_vectors,
)
from mapkit.retrieval.vlad_encoding import _PCA_BATCH, _faiss_threads, _map, _raw_task, _sample_task, encode_images

Ref = tuple[str, int]  # (session, row of its image table; rows past its end are its training frames)


def _uniform_subset(n: int, size: int, seed: int, salt: int) -> np.ndarray:
    """Sorted indices of a uniform random subset of ``min(n, size)`` of ``range(n)``."""
    if n <= size:
        return np.arange(n)
    return np.sort(np.random.default_rng([seed, salt]).choice(n, size, replace=False))


# --------------------------------------------------------------------------- inputs


def _chosen_sessions(ws: Workspace, cfg: VladIndexConfig) -> tuple[list[str], list[str]]:
    """(database sessions, training sessions): the config's, checked against the workspace's image databases."""
    if not ws.sessions_dir.is_dir():
        raise InputError(ws.sessions_dir, "not a workspace (no sessions/ folder): run mapkit build first")
    available = ws.sessions_with_images()
    unscaled = {n: u for n in available if (u := _pose_units(ws, n)) != "m"}
    if unscaled and cfg.database_sessions is None:
        warnings.warn(
            f"{ws.sessions_dir}: session(s) {sorted(unscaled)} left out of the index: their image poses are in "
            "arbitrary units (camera-only, not georeferenced), and the index's radii and the localizer are in metres",
            InputWarning,
            stacklevel=3,
        )
    db_names = (
        list(cfg.database_sessions)
        if cfg.database_sessions is not None
        else [n for n in available if n not in unscaled]
    )
    train_names = list(cfg.train_sessions) if cfg.train_sessions is not None else db_names
    for field, names in (("database_sessions", db_names), ("train_sessions", train_names)):
        missing = [n for n in names if n not in available]
        if missing:
            raise InputError(
                ws.sessions_dir,
                f"no image database for session(s) {missing}; the workspace has {available}",
                field=field,
            )
        if len(set(names)) != len(names):
            raise ConfigError(f"{field} lists a session twice: {names}")
    bad = [n for n in db_names if n in unscaled]
    if bad:
        raise InputError(
            ws.sessions_dir,
            f"session(s) {bad} have image poses in {unscaled[bad[0]]}; a database needs poses in "
            "metres (georeference them: GPS over a longer stretch)",
            field="database_sessions",
        )
    if not db_names:
        why = (
            f"the image poses of {sorted(unscaled)} are in arbitrary units"
            if unscaled
            else "a log without images, or `imagedb: false`, builds none"
        )
        raise InputError(
            ws.sessions_dir, f"no session with a metric image database to index ({why})", field="database_sessions"
        )
    if not train_names:
        raise ConfigError("train_sessions is empty: the vocabulary and PCA need training images")
    return db_names, train_names


def _pose_units(ws: Workspace, name: str) -> str:
    """The units of a session's image poses as its build recorded them ("m" when it recorded none:
    databases built before the field existed were all metric)."""
    path = ws.session(name).imagedb / "metrics.json"
    try:
        return str(json.loads(path.read_text()).get("pose_units", "m"))
    except (OSError, ValueError):
        return "m"


def _read_sessions(
    ws: Workspace, cfg: VladIndexConfig, db_names: list[str], train_names: list[str]
) -> dict[str, SessionImages]:
    """The image tables of the database and training sessions; fails before any bundle is written
    when there is nothing to index or to learn from."""
    sessions = {n: read_session_images(ws, n, cfg.prefer_aligned_poses) for n in dict.fromkeys(db_names + train_names)}
    for (
        n,
        s,
    ) in sessions.items():  # an image table edited since its stage wrote it is refused, naming the stage to re-run
        verify_file(
            s.csv_path, "mapkit align" if ws.align_dir in Path(s.csv_path).parents else f"mapkit build (session {n})"
        )
        if s.training_csv is not None and cfg.training_frames and n in train_names:
            verify_file(s.training_csv, f"mapkit build (session {n})")
    for field, names, least in (("database_sessions", db_names, 1), ("train_sessions", train_names, 2)):
        n_images = sum(len(sessions[n]) for n in names)
        if n_images < least:
            raise InputError(
                ws.sessions_dir,
                f"{n_images} image(s) in the image databases of {field} {names} (at least {least} "
                "needed): rebuild them with a longer drive or a smaller imagedb.min_spacing_m, or name other sessions",
                field=field,
            )
    return sessions


def _build_hash(
    cfg: VladIndexConfig,
    db_names: list[str],
    train_names: list[str],
    sessions: dict[str, SessionImages],
    frame: LocalFrame | None,
) -> str:
    """What the bundle's vectors and index depend on: the config (not its query-time settings), the
    sessions and their tables (by checksum), the frame."""
    inputs = {n: [s.pose_source, sha256_file(s.csv_path)] for n, s in sessions.items()}
    for n in train_names:  # the training frames count only where they are learned from: bundles without any stay valid
        training_csv = sessions[n].training_csv
        if cfg.training_frames and training_csv is not None and sessions[n].training_paths:
            inputs[n].append(sha256_file(training_csv))
    return config_hash(
        {
            "format_version": FORMAT_VERSION,
            "config": cfg.model_dump(mode="json", exclude=_QUERY_TIME_FIELDS),
            "database": db_names,
            "train": train_names,
            "tables": inputs,
            "frame": None if frame is None else frame.to_dict(),
        }
    )


@writes_workspace("workspace")
def build_vlad_index(
    workspace: str | Path,
    out: str | Path | None = None,
    config: VladIndexConfig | str | Path | None = None,
    overrides: dict | None = None,
    progress: bool = True,
    executor: Executor | None = None,
    reuse: str | Path | None = None,
) -> Path:
    """Build the VLAD index bundle of ``workspace``; returns its folder (default ``WORKSPACE/indexes/vlad``).

    Images are encoded on ``executor``, else on the process-wide default executor, else in
    ``workers`` local processes (:func:`mapkit.core.executor.get_executor`); the bundle's vectors do not
    depend on which.

    The vocabulary and PCA learn from training-session images only; every database image is
    encoded once (the training subsample's raw VLADs are kept for the PCA and reused). Skips when
    the bundle at ``out`` was built from the same config and session tables.

    ``reuse``: a finished bundle of the same workspace built with the same config but for the
    whitening (``vlad.whiten``, ``whitening``, ``whitening_power``, ``whitening_shrinkage``): its
    vocabulary, PCA and database vectors are taken and only re-scaled, with no image encoded again.
    Exact, since the whitening only scales the principal directions and every vector is L2-normalised
    last (:meth:`~mapkit.retrieval.vlad.PcaWhitening.rewhitened`). A bundle built from anything else
    is refused, naming it.
    """
    t_start = time.perf_counter()
    ws = Workspace(workspace)
    cfg = load_config(VladIndexConfig, config, overrides)
    out = Path(out) if out is not None else ws.vlad_index
    db_names, train_names = _chosen_sessions(ws, cfg)
    frame = ws.frame()
    sessions = _read_sessions(ws, cfg, db_names, train_names)
    build_hash = _build_hash(cfg, db_names, train_names, sessions, frame)
    if is_finished(out, build_hash, FORMAT_VERSION):
        if json.loads((out / MANIFEST).read_text())["config"] != cfg.model_dump(mode="json"):
            _rewrite_config(out, cfg)  # only query-time settings differ: nothing to encode again
        return out
    if out.exists() and not (out / MANIFEST).is_file() and any(out.iterdir()):
        raise InputError(out, "exists and is not a VLAD index bundle (no manifest.json): refusing to replace it")

    with building(out) as tmp:
        metrics, manifest = _build_into(
            tmp,
            ws,
            cfg,
            sessions,
            db_names,
            train_names,
            frame,
            build_hash,
            progress,
            executor or get_executor(cfg.workers),
            None if reuse is None else Path(reuse),
        )
        timings = metrics.pop("timings")
        write_json(tmp / "metrics.json", metrics)
        write_timings(tmp, **timings, seconds_total=time.perf_counter() - t_start)
        write_manifest(tmp, manifest)  # last: it checksums every other file
    return out


# --------------------------------------------------------------------------- the steps of a build


@dataclass
class _Learned:
    """The encoder learned on the training images, with what the database step reuses and the metrics report."""

    encoder: VladEncoder
    train_sel: list[Ref]  # the PCA's training images
    raw_train: np.ndarray  # (len(train_sel), raw_dim) float32, their raw VLADs
    vocab_images: int
    vocab_descriptors: int


def _learn_encoder(
    cfg: VladIndexConfig,
    sessions: dict[str, SessionImages],
    train_names: list[str],
    executor: Executor,
    progress: bool,
    timings: dict[str, float],
) -> _Learned:
    """1. vocabulary (k-means on descriptors drawn evenly from the vocabulary images), 2. PCA-whitening
    on the raw VLADs of the training images (every image of the training sessions, uniformly subsampled):
    their database images and, with ``training_frames``, the frames kept beside the database."""
    train_sel, vocab_sel = _training_selection(cfg, sessions, train_names)
    t0 = time.perf_counter()
    per_image = math.ceil(cfg.vlad.kmeans_max_descriptors / len(vocab_sel))
    tasks = [(_path_of(sessions, r), per_image, cfg.vlad.seed, k) for k, r in enumerate(vocab_sel)]
    sample = np.concatenate(list(_map(_sample_task, tasks, VladEncoder(cfg.vlad), executor, progress, "descriptors")))
    with _faiss_threads(1):
        vocabulary = kmeans(sample, cfg.vlad.num_words, cfg.vlad.kmeans_iterations, cfg.vlad.seed)
    timings["vocabulary_s"] = time.perf_counter() - t0
    n_descriptors = len(sample)
    del sample

    t0 = time.perf_counter()
    encoder = VladEncoder(cfg.vlad, vocabulary)
    raw_train = np.zeros((len(train_sel), encoder.raw_dim), np.float32)
    paths = [_path_of(sessions, r) for r in train_sel]
    for i, r in enumerate(_map(_raw_task, paths, encoder, executor, progress, "train VLAD")):
        raw_train[i] = r
    timings["encode_training_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputWarning)  # the cap is reported once, below, with what to do about it
        encoder.fit_pca(raw_train)
    timings["pca_s"] = time.perf_counter() - t0
    _warn_small_pca(cfg, encoder, len(train_sel))
    return _Learned(encoder, train_sel, raw_train, len(vocab_sel), n_descriptors)


def _training_selection(
    cfg: VladIndexConfig, sessions: dict[str, SessionImages], train_names: list[str]
) -> tuple[list[Ref], list[Ref]]:
    """The PCA's training images and, among them, the vocabulary's: uniform, seeded subsets (the same on every run)."""
    extra = {n: len(sessions[n].training_paths) if cfg.training_frames else 0 for n in train_names}
    train_refs = [(n, i) for n in train_names for i in range(len(sessions[n]) + extra[n])]
    if len(train_refs) < 2:
        raise InputError(
            sessions[train_names[0]].csv_path,
            f"{len(train_refs)} training image(s): the PCA needs at least 2",
            field="train_sessions",
        )
    train_sel = [train_refs[i] for i in _uniform_subset(len(train_refs), cfg.max_training_images, cfg.seed, 1)]
    return train_sel, [train_sel[i] for i in _uniform_subset(len(train_sel), cfg.max_vocabulary_images, cfg.seed, 2)]


_WHITENING_FIELDS = ("whiten", "whitening", "whitening_power", "whitening_shrinkage")


def _rewhiten(
    reuse: Path,
    cfg: VladIndexConfig,
    sessions: dict[str, SessionImages],
    db_names: list[str],
    train_names: list[str],
    frame: LocalFrame | None,
    timings: dict[str, float],
) -> tuple[_Learned, np.ndarray]:
    """The encoder and database vectors of the bundle ``reuse`` under ``cfg``'s whitening (see ``build_vlad_index``)."""
    t0 = time.perf_counter()
    manifest = read_manifest(
        reuse, "VLAD index", FORMAT_VERSION, (DATABASE_CSV, INDEX_FILE, f"{ENCODER_DIR}/{VladEncoder.MODEL_FILE}"), True
    )
    old = VladIndexConfig.model_validate(manifest["config"])
    as_old = cfg.model_copy(
        update={"vlad": cfg.vlad.model_copy(update={k: getattr(old.vlad, k) for k in _WHITENING_FIELDS})}
    )
    if manifest.get("added_sessions") or manifest.get("build_hash") != _build_hash(
        as_old, db_names, train_names, sessions, frame
    ):
        raise InputError(
            reuse / MANIFEST,
            "was built from other sessions, images or settings than this index's (only the whitening "
            "may differ); build this one from the images instead",
            field="reuse",
        )
    encoder = VladEncoder.load(reuse / ENCODER_DIR)
    assert encoder.pca is not None  # a bundle's encoder is saved with its PCA
    pca, ratio = encoder.pca.rewhitened(cfg.vlad.whiten, *whitening_parameters(cfg.vlad))
    vectors = read_vectors(reuse)  # read_manifest above checked every listed file's sha256
    train_sel, vocab_sel = _training_selection(cfg, sessions, train_names)
    old_metrics = reuse / "metrics.json"
    n_desc = json.loads(old_metrics.read_text()).get("vocabulary_descriptors", 0) if old_metrics.is_file() else 0
    learned = _Learned(
        VladEncoder(cfg.vlad, encoder.vocabulary, pca),
        train_sel,
        np.zeros((0, encoder.raw_dim), np.float32),
        len(vocab_sel),
        n_desc,
    )
    timings["rewhiten_s"] = time.perf_counter() - t0
    return learned, PcaWhitening.rescale(vectors, ratio)


def _warn_small_pca(cfg: VladIndexConfig, encoder: VladEncoder, n_train: int) -> None:
    """Say when the PCA learned on fewer images than the dimension asked for, and what that does to
    full whitening (MCVL's [33] learns it on a separate, much larger set)."""
    assert encoder.pca is not None  # called after fit_pca
    dim = encoder.pca.dim
    if dim >= cfg.vlad.pca_dim:
        return
    note = (
        f"PCA dimension capped from {cfg.vlad.pca_dim} to {dim}: {n_train} training images (name more train_sessions "
        "or raise max_training_images for more)"
    )
    if cfg.vlad.whiten and cfg.vlad.whitening == "full" and dim >= n_train - 1:
        note += (
            "; full whitening in n - 1 dimensions makes the n training images equidistant (a database learned on "
            "returns ties): vlad.whitening 'power' or 'shrinkage' regularises it"
        )
    warnings.warn(note, InputWarning, stacklevel=5)  # the caller of build_vlad_index


def _encode_database(
    learned: _Learned,
    sessions: dict[str, SessionImages],
    db_names: list[str],
    executor: Executor,
    progress: bool,
    timings: dict[str, float],
) -> tuple[np.ndarray, int, int]:
    """3. (N, D) vectors of the database images: the training raws projected again, the rest encoded.
    Returns (vectors, images reused from training, images encoded here)."""
    t0 = time.perf_counter()
    encoder = learned.encoder
    assert encoder.pca is not None  # the learned (or re-whitened) encoder has its PCA
    db_refs = [(n, i) for n in db_names for i in range(len(sessions[n]))]
    if not db_refs:
        raise InputError(
            sessions[db_names[0]].csv_path, "the database sessions hold no image", field="database_sessions"
        )
    vectors = np.zeros((len(db_refs), encoder.pca.dim), np.float32)
    row_of_train = {r: k for k, r in enumerate(learned.train_sel)}
    reused = [j for j, r in enumerate(db_refs) if r in row_of_train]
    for a in range(0, len(reused), _PCA_BATCH):
        js = reused[a : a + _PCA_BATCH]
        vectors[js] = encoder.pca.transform(learned.raw_train[[row_of_train[db_refs[j]] for j in js]])
    learned.raw_train = np.zeros(
        (0, encoder.raw_dim), np.float32
    )  # up to 64 KiB per training image: freed before encoding more
    todo = [j for j, r in enumerate(db_refs) if r not in row_of_train]
    vectors[todo] = encode_images(
        encoder, [_path_of(sessions, db_refs[j]) for j in todo], progress=progress, desc="database", executor=executor
    )
    timings["encode_database_s"] = time.perf_counter() - t0
    return vectors, len(reused), len(todo)


def _path_of(sessions: dict[str, SessionImages], ref: Ref) -> str:
    return str(sessions[ref[0]].path(ref[1]))


def _build_into(
    tmp: Path,
    ws: Workspace,
    cfg: VladIndexConfig,
    sessions: dict[str, SessionImages],
    db_names: list[str],
    train_names: list[str],
    frame: LocalFrame | None,
    build_hash: str,
    progress: bool,
    executor: Executor,
    reuse: Path | None = None,
) -> tuple[dict, dict]:
    """Learn, encode (or re-whiten ``reuse``'s) and write everything but metrics.json and the manifest into
    ``tmp``; returns both."""
    timings: dict[str, float] = {}
    if reuse is None:
        learned = _learn_encoder(cfg, sessions, train_names, executor, progress, timings)
        vectors, n_reused, n_todo = _encode_database(learned, sessions, db_names, executor, progress, timings)
    else:
        learned, vectors = _rewhiten(reuse, cfg, sessions, db_names, train_names, frame, timings)
        n_reused, n_todo = len(vectors), 0
        timings.update(encode_training_s=0.0, encode_database_s=0.0)

    # 4. index
    t0 = time.perf_counter()
    index, index_info = make_index(vectors, cfg)
    timings["index_s"] = time.perf_counter() - t0

    # 5. files (the caller writes metrics.json and the manifest last)
    encoder = learned.encoder
    encoder.save(tmp / ENCODER_DIR)
    _write_index(tmp, index, vectors if cfg.index == "ivf" else None)
    _write_database_csv(tmp / DATABASE_CSV, _database_table(db_names, sessions, frame))
    atomic_write_text(tmp / "config.yaml", dump_config(cfg))
    n_train, n_encoded = len(learned.train_sel), (len(learned.train_sel) if reuse is None else 0) + n_todo
    encode_s = timings["encode_training_s"] + timings["encode_database_s"]
    metrics = {
        "images_encoded": n_encoded,
        "database_images": len(vectors),
        "database_images_reused_from_training": n_reused,
        "training_images": n_train,
        "vocabulary_images": learned.vocab_images,
        "vocabulary_descriptors": learned.vocab_descriptors,
        "pca": _pca_record(cfg, learned, sessions, db_names),
        "executor": executor.kind,
        "workers": executor.workers,
        **({"rewhitened_from": str(reuse)} if reuse is not None else {}),
        # a run record, not a result: the caller moves it to timings.json
        "timings": {**timings, "images_encoded_per_s": n_encoded / encode_s if encode_s > 0 else None},
    }
    return metrics, _manifest(
        ws, cfg, sessions, db_names, train_names, frame, build_hash, learned, index_info, len(vectors)
    )


def _manifest(
    ws: Workspace,
    cfg: VladIndexConfig,
    sessions: dict[str, SessionImages],
    db_names: list[str],
    train_names: list[str],
    frame: LocalFrame | None,
    build_hash: str,
    learned: _Learned,
    index_info: dict,
    entries: int,
) -> dict:
    """The bundle's manifest, without the file checksums (``write_manifest`` adds them)."""
    encoder = learned.encoder
    assert encoder.pca is not None  # the learned (or re-whitened) encoder has its PCA
    train_count = {n: sum(1 for r in learned.train_sel if r[0] == n) for n in train_names}
    return {
        "format_version": FORMAT_VERSION,
        "kind": "mapkit VLAD index",
        "mapkit_version": __version__,
        "build_hash": build_hash,
        "config": cfg.model_dump(mode="json"),
        "source_workspace": str(ws.root.resolve()),
        "frame": None if frame is None else frame.to_dict(),
        "database_sessions": db_names,
        "train_sessions": train_names,
        # each database session's camera mount (base_from_camera), so that a localizer can put its
        # filter on the vehicle pose the way the database was recorded
        "camera_mounts": {n: mount.tolist() for n in db_names if (mount := sessions[n].base_from_camera) is not None},
        "sessions": {
            n: {
                "images": len(s) if n in db_names else 0,
                "training_images": train_count.get(n, 0),
                "database": n in db_names,
                "training": n in train_names,
                "pose_source": s.pose_source,
                "images_csv": os.path.relpath(s.csv_path, ws.root),
                "images_csv_sha256": sha256_file(s.csv_path),
            }
            for n, s in sessions.items()
        },
        "added_sessions": [],
        "vlad": {
            "raw_dim": encoder.raw_dim,
            "dim": encoder.pca.dim,
            "pca_dim_requested": cfg.vlad.pca_dim,
            "training_images": len(learned.train_sel),
            "vocabulary_images": learned.vocab_images,
            "pca": _pca_record(cfg, learned, sessions, db_names),
        },
        "index": index_info,
        "entries": entries,
        # the kernel each OpenBLAS ran: k-means breaks ties on the last bits of its products, so another kernel
        # learns another vocabulary from the same images (mapkit.core.blas)
        "openblas": openblas_kernels(),
    }


# --------------------------------------------------------------------------- the index and the config


def _pca_record(
    cfg: VladIndexConfig, learned: _Learned, sessions: dict[str, SessionImages], db_names: list[str]
) -> dict:
    """What the PCA-whitening learned on and how it scales its directions, for the manifest and metrics:
    training vectors per session, how many of them are database images and how many training frames,
    output dimension (asked for and got: at most n - 1), whitening (mode, power, shrinkage)."""
    pca = learned.encoder.pca
    assert pca is not None  # the learned (or re-whitened) encoder has its PCA
    per_session: dict[str, int] = {}
    in_database = training_frames = 0
    for name, row in learned.train_sel:
        per_session[name] = per_session.get(name, 0) + 1
        is_frame = row >= len(sessions[name])
        training_frames += is_frame
        in_database += name in db_names and not is_frame
    n = len(learned.train_sel)
    return {
        **pca.describe(),
        "training_vectors": n,
        "dim_requested": cfg.vlad.pca_dim,
        "rank_limited": pca.dim >= n - 1,
        "training_sessions": per_session,
        "training_vectors_in_database": in_database,
        "training_vectors_from_training_frames": training_frames,
    }


def make_index(vectors: np.ndarray, cfg: VladIndexConfig):
    """A faiss index over (N, D) float32 vectors, and its description for the manifest."""
    import faiss

    n, d = vectors.shape
    if cfg.index == "flat":
        index = faiss.IndexFlatL2(d)
        index.add(vectors)
        return index, {
            "kind": "flat",
            "faiss": "IndexFlatL2",
            "dim": d,
            "metric": "squared L2",
            "ntotal": int(index.ntotal),
        }
    ivf = cfg.ivf
    cap = max(1, n // 39)
    nlist = min(ivf.nlist or max(1, round(4 * math.sqrt(n))), cap)
    if ivf.nlist is not None and nlist < ivf.nlist:
        warnings.warn(
            f"IVF nlist capped from {ivf.nlist} to {nlist}: {n} database vectors (39 per list)",
            InputWarning,
            stacklevel=3,
        )
    quantizer = faiss.IndexFlatL2(d)
    ivf_index: faiss.IndexIVF
    if ivf.pq_m is None:
        ivf_index = faiss.IndexIVFFlat(quantizer, d, nlist, faiss.METRIC_L2)
        kind = "IndexIVFFlat"
    else:
        if d % ivf.pq_m:
            raise ConfigError(f"ivf.pq_m = {ivf.pq_m} does not divide the vector dimension {d}")
        if n < 2**ivf.pq_bits:
            raise ConfigError(
                f"IVF-PQ with {ivf.pq_bits}-bit codes needs at least {2**ivf.pq_bits} database vectors, got {n}"
            )
        ivf_index = faiss.IndexIVFPQ(quantizer, d, nlist, ivf.pq_m, ivf.pq_bits)
        kind = "IndexIVFPQ"
    train = vectors[_uniform_subset(n, ivf.max_training_vectors, cfg.seed, 3)]
    ivf_index.train(np.ascontiguousarray(train))
    ivf_index.add(vectors)
    ivf_index.nprobe = min(ivf.nprobe, nlist)
    info = {
        "kind": "ivf",
        "faiss": kind,
        "dim": d,
        "metric": "squared L2",
        "ntotal": int(ivf_index.ntotal),
        "nlist": nlist,
        "nprobe": int(ivf_index.nprobe),
        "pq_m": ivf.pq_m,
        "pq_bits": ivf.pq_bits if ivf.pq_m else None,
    }
    return ivf_index, info


def _rewrite_config(out: Path, cfg: VladIndexConfig) -> None:
    """A copy of the bundle with a new config.yaml and manifest config, swapped in."""
    with building(out) as tmp:
        for p in out.rglob("*"):
            rel = p.relative_to(out)
            if p.is_file() and rel.as_posix() not in (MANIFEST, "config.yaml"):
                copy_file(p, tmp / rel)
        atomic_write_text(tmp / "config.yaml", dump_config(cfg))
        manifest = json.loads((out / MANIFEST).read_text())
        manifest["config"] = cfg.model_dump(mode="json")
        write_manifest(tmp, manifest)


__all__ = ["build_vlad_index", "make_index"]
