"""Encoding images into VLAD vectors on an executor: what building a VLAD bundle
(:mod:`mapkit.retrieval.vlad_build`) and querying one (:mod:`mapkit.retrieval.vlad_index`) share.

Encoding is the expensive part (~0.27 s per 640x480 image and core). Workers compute the raw VLAD
(16384-D; only the config and the small vocabulary are shipped to them, once per worker), while
the parent applies the PCA in batches, in input order; the vectors are the same bit for bit
whichever executor ran.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Sequence
from pathlib import Path

import cv2
import numpy as np

from mapkit.core.errors import InputError
from mapkit.core.executor import Executor, TaskError, get_executor
from mapkit.core.fingerprint import sha256_file
from mapkit.retrieval.vlad import VladEncoder

_PCA_BATCH = 256  # raw VLADs (64 KiB each at K = 128) projected per matrix product


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
        yield from executor.map(
            fn,
            items,
            shared=shared,
            progress=progress and len(items) > 0,
            desc=desc,
            unit="img",
            label=lambda item: str(item[0] if isinstance(item, tuple) else item),
        )
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
    """A cache key of an image file: its resolved path, size and content hash (not its mtime, so that
    the same images written again give the same cache)."""
    p = Path(path).resolve()
    return f"{p}|{p.stat().st_size}|{sha256_file(p)[:16]}"


def encode_images(
    encoder: VladEncoder,
    paths: Sequence[str | Path],
    workers: int = 1,
    progress: bool = False,
    desc: str = "encode",
    executor: Executor | None = None,
) -> np.ndarray:
    """(n, D) float32 encodings of image files (dense RootSIFT, VLAD, PCA-whitening, L2).

    Runs on ``executor``, else on the process-wide default (:func:`mapkit.core.executor.get_executor`),
    else in ``workers`` local processes; the result is the same bit for bit on any of them.
    """
    executor = executor or get_executor(workers)
    assert encoder.pca is not None, "the encoder has no PCA: fit or load it first"
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
