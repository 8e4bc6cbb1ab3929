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
    metrics.json    images encoded, database and training images, the vocabulary's sample, what the
                    PCA learned on (``pca``), the executor and its workers
    timings.json    wall-clock figures: seconds per step (vocabulary, encoding, PCA, index), images
                    encoded per second, the total

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
fewer training images than the paper's 4096 dimensions the PCA is capped at n - 1, and full
whitening in nearly as many dimensions as images makes the training images (usually the database)
all equidistant; ``vlad.whitening`` therefore defaults to power-law whitening, which keeps their
structure (:mod:`mapkit.retrieval.vlad`). ``python3 bench/bench_whitening.py WS`` measures the
recall of every whitening variant on a workspace.

Encoding is the expensive part (the bundle's ``timings.json`` gives its rate, ``images_encoded_per_s``).
It runs on an executor (:mod:`mapkit.core.executor`: this process, ``workers`` spawned processes, or
Ray) whose workers compute
the raw VLAD (16384-D; only the config and the small vocabulary are shipped to them, once per
worker), while the parent applies the PCA in batches, in input order; the vectors are the same bit
for bit whichever executor ran.

The code lives in four modules, imported one way: :mod:`~mapkit.retrieval.vlad_bundle` (the
bundle's format: file names, config, session image tables, database table) and
:mod:`~mapkit.retrieval.vlad_encoding` (images to vectors on an executor) below
:mod:`~mapkit.retrieval.vlad_build` (``build_vlad_index``) and :mod:`~mapkit.retrieval.vlad_index`
(``VladIndex``: load, query, add a session). This module gathers their public names.
"""

from __future__ import annotations

from mapkit.retrieval.vlad_build import _build_into, _rewrite_config, _uniform_subset, build_vlad_index, make_index
from mapkit.retrieval.vlad_bundle import (
    DATABASE_COLUMNS,
    DATABASE_CSV,
    ENCODER_DIR,
    FORMAT_VERSION,
    INDEX_FILE,
    VECTORS_FILE,
    IvfConfig,
    SessionImages,
    VladIndexConfig,
    _database_table,
    _same_frame,
    _write_database_csv,
    _write_index,
    read_database_csv,
    read_session_images,
    workspace_sessions,
)
from mapkit.retrieval.vlad_encoding import (
    _faiss_threads,
    _file_key,
    _map,
    _raw_task,
    _sample_task,
    encode_images,
    read_image,
)
from mapkit.retrieval.vlad_index import Hits, VladIndex

__all__ = [
    "FORMAT_VERSION",
    "DATABASE_COLUMNS",
    "DATABASE_CSV",
    "ENCODER_DIR",
    "INDEX_FILE",
    "VECTORS_FILE",
    "IvfConfig",
    "VladIndexConfig",
    "SessionImages",
    "Hits",
    "VladIndex",
    "build_vlad_index",
    "make_index",
    "encode_images",
    "read_image",
    "read_session_images",
    "workspace_sessions",
    "read_database_csv",
    # private helpers that evaluation, tests and benches reach for
    "_build_into",
    "_database_table",
    "_faiss_threads",
    "_file_key",
    "_map",
    "_raw_task",
    "_rewrite_config",
    "_same_frame",
    "_sample_task",
    "_uniform_subset",
    "_write_database_csv",
    "_write_index",
]
