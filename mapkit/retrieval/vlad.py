"""MCVL's observation encoder (Sec. III-B): dense RootSIFT, VLAD, PCA-whitening, L2.

Pieces, each usable alone:

- ``rootsift``: L1-normalise each SIFT vector, then take elementwise square roots (Arandjelovic
  and Zisserman, CVPR 2012), so that Euclidean distances compare descriptors by the Hellinger
  kernel.
- ``fit_vocabulary``: K visual words by k-means (faiss) on a uniform sample of descriptors.
- ``vlad``: every descriptor is assigned to its nearest word and the residuals are summed per
  word (Jegou et al., CVPR 2010), giving a K x 128 = 16384-D vector. Pooling ``"sum"`` is the
  paper's text (plain sum pooling, then L2); ``"intra"`` is the authors' released code (each
  word's block L2-normalised, then the whole vector: Arandjelovic and Zisserman, CVPR 2013).
- ``PcaWhitening``: PCA learned on training VLADs, whitening and L2 (the paper's [33], Jegou and
  Chum, ECCV 2012), to 4096 dimensions. Full whitening (each direction divided by its standard
  deviation) is the paper's; it needs a training set much larger than the output dimension, which
  [33] and the authors' code learn on a separate, large image set. Learned on n <= dim images it
  keeps n - 1 directions and maps its n training vectors to the corners of a regular simplex: all
  equidistant (squared distance 2n/(n-1) after L2), so a database it was learned on returns only
  ties, and a query's coordinates along the noise directions of the last components are scaled
  up the most. ``whitening`` therefore offers the two usual regularised forms as well: power-law
  whitening (eigenvalues to the power -alpha/2: the shrinkage exponent ``s`` of the PCA-whitening in
  the code of Tolias, Jenicek and Chum's HOW, ECCV 2020, whose s = 1 is full whitening and s = 0
  plain PCA; the default here, at alpha = 0.5) and eigenvalue shrinkage (a fraction of the mean
  eigenvalue added before the inverse square root, as a covariance shrunk towards a scaled
  identity does: Ledoit and Wolf, J. Multivariate Anal. 2004).
- ``VladEncoder``: all of the above behind ``fit`` / ``encode`` / ``save`` / ``load``.

The encoder's hot path never holds a whole image's descriptors: dense SIFT is produced in
blocks of ~2000 frames (``mapkit.retrieval.dsift.iter_histogram_blocks``) and each block is normalised,
assigned and summed while it is in cache. Everything is float32; there are no per-descriptor
Python loops.
"""

from __future__ import annotations

import json
import math
import warnings
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import scipy.linalg
import scipy.sparse
from pydantic import Field, ValidationError

from mapkit.core.config import MapkitConfig
from mapkit.core.errors import ConfigError, InputError, InputWarning
from mapkit.core.runio import atomic_path, atomic_write_text
from mapkit.retrieval.dsift import (
    DESCRIPTOR_DIM,
    DsiftConfig,
    StepTimer,
    iter_histogram_blocks,
    null_timer,
    prepare_image,
)

Pooling = Literal["sum", "intra"]
Whitening = Literal["full", "power", "shrinkage"]
_TINY = np.float32(1e-12)
_ASSIGN_BLOCK = 4096  # descriptors per assignment block: the (block, K) score matrix stays in cache
_RANK_TOL = 1e-6  # PCA: variances below this fraction of the largest are numerically zero


class VladConfig(MapkitConfig):
    """Parameters of the VLAD observation encoder; defaults are MCVL's (Sec. III-B, IV-A)."""

    dsift: DsiftConfig = Field(default_factory=DsiftConfig, description="Dense SIFT (see mapkit.retrieval.dsift).")
    num_words: int = Field(128, ge=1, description="Vocabulary size K (MCVL Sec. IV-A: 128; VLAD is K x 128 = 16384-D).")
    pooling: Pooling = Field(
        "sum",
        description="'sum': residuals summed per word, then L2 (the paper's text, Sec. III-B); 'intra': each word's "
        "block L2-normalised, then L2 (the authors' released code).",
    )
    pca_dim: int = Field(
        4096, ge=1, description="Output dimension after PCA (MCVL Sec. IV-A: 4096); capped at n_train - 1."
    )
    whiten: bool = Field(
        True, description="Whiten after PCA (MCVL Sec. III-B/IV-A: PCA, whitening, L2); False = plain PCA."
    )
    whitening: Whitening = Field(
        "power",
        description="How principal components are scaled: 'full' = 1/sqrt(eigenvalue) (the paper's [33], sound when "
        "PCA learns on many more images than its dimension, from a separate set); 'power' = "
        "eigenvalue^(-whitening_power/2) (power-law whitening: HOW's shrinkage exponent, Tolias et al., ECCV 2020); "
        "'shrinkage' = 1/sqrt(eigenvalue + whitening_shrinkage x mean kept eigenvalue) (Ledoit-Wolf style). Default "
        "'power': learned on the database itself (n images, n - 1 dimensions), full whitening makes the database "
        "images all equidistant. Tiny town, PCA on the database sessions, each session in turn the queries (209), "
        "recall@1/5/20 within 25 m (bench/bench_whitening.py): full 0.297/0.742/0.919, power 0.5 0.411/0.852/0.938, "
        "shrinkage 1 0.402/0.823/0.933.",
    )
    whitening_power: float = Field(
        0.5,
        ge=0,
        le=1,
        description="alpha of 'power' whitening: 1 = full whitening, 0 = plain PCA. 0.5 halves the full scaling's "
        "range in log terms; on the tiny town 0.25 (recall@1 0.459) and plain PCA (0.455) edged it (0.411), within the "
        "+-0.034 standard error of 209 queries, and 0.75 trailed (0.364): 0.5 keeps part of the damping of dominant "
        "components the paper whitens for.",
    )
    whitening_shrinkage: float = Field(
        1.0,
        ge=0,
        description="Fraction of the mean kept eigenvalue added to every eigenvalue by 'shrinkage' whitening.",
    )
    kmeans_max_descriptors: int = Field(
        200_000,
        ge=1,
        description="k-means trains on a uniform random sample of at most this many RootSIFT descriptors of the "
        "training images (not in the paper; ~1500 per word).",
    )
    kmeans_iterations: int = Field(25, ge=1, description="k-means iterations (faiss's default; not in the paper).")
    seed: int = Field(0, description="Seed of the descriptor sample and of k-means.")


# --------------------------------------------------------------------------- RootSIFT


def rootsift(desc: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """RootSIFT of rows: L1-normalise, then elementwise square root (zero rows stay zero).

    Rows must be non-negative (SIFT histograms). The result rows have unit L2 norm.
    """
    desc = np.asarray(desc, dtype=np.float32)
    if out is None:
        out = desc.copy()
    elif out is not desc:
        np.copyto(out, desc)
    l1 = out.sum(axis=1, dtype=np.float32)
    out /= np.maximum(l1, _TINY)[:, None]
    np.sqrt(out, out=out)
    return out


def _rootsift_from_histograms(hist: np.ndarray, clamp: float) -> np.ndarray:
    """``rootsift(sift_normalize(hist, clamp))`` in place, in four passes instead of eight.

    SIFT's L2 / clamp / L2 followed by an L1 normalisation equals clamping at ``clamp * ||h||_2``
    and one L1 normalisation: the positive scalings in between cancel.
    """
    norm = np.sqrt(np.einsum("ij,ij->i", hist, hist))
    norm *= np.float32(clamp)
    np.minimum(hist, norm[:, None], out=hist)
    l1 = hist @ np.ones(hist.shape[1], np.float32)
    np.sqrt(hist, out=hist)
    hist *= (1.0 / np.sqrt(np.maximum(l1, _TINY))).astype(np.float32)[:, None]
    return hist


# --------------------------------------------------------------------------- VLAD


class VladAccumulator:
    """Per-word sums of descriptors and counts, fed block by block; ``result`` pools them into VLAD."""

    def __init__(self, centroids: np.ndarray):
        self.centroids = np.ascontiguousarray(centroids, dtype=np.float32)
        if self.centroids.ndim != 2:
            raise InputError(None, f"centroids must be (K, d), got shape {self.centroids.shape}")
        k, d = self.centroids.shape
        self._centroids_t = np.ascontiguousarray(self.centroids.T)
        self._half_sq_norms = (0.5 * np.einsum("ij,ij->i", self.centroids, self.centroids)).astype(np.float32)
        self.sums = np.zeros((k, d), np.float32)
        self.counts = np.zeros(k, np.int64)

    def assign(self, desc: np.ndarray) -> np.ndarray:
        """Index of the nearest word of each row: argmax of x.c - ||c||^2 / 2 (= argmin ||x - c||^2)."""
        scores = desc @ self._centroids_t
        scores -= self._half_sq_norms
        return scores.argmax(axis=1)

    def add(self, desc: np.ndarray, timer=null_timer) -> None:
        """Accumulate float32 (n, d) rows (a block that fits in cache: ~4k rows)."""
        n = len(desc)
        if n == 0:
            return
        with timer("assign"):
            words = self.assign(desc)
        with timer("aggregate"):
            # one-hot (K x n) in CSC form, built without sorting: column i holds a 1 at row words[i]
            onehot = scipy.sparse.csc_matrix(
                (np.ones(n, np.float32), words, np.arange(n + 1)), shape=(len(self.sums), n)
            )
            self.sums += onehot @ desc
            self.counts += np.bincount(words, minlength=len(self.counts))

    def add_many(self, desc: np.ndarray, timer=null_timer) -> None:
        for a in range(0, len(desc), _ASSIGN_BLOCK):
            self.add(np.ascontiguousarray(desc[a : a + _ASSIGN_BLOCK], dtype=np.float32), timer)

    def result(self, pooling: Pooling = "sum") -> np.ndarray:
        """The (K * d,) float32 VLAD: residual sums per word, pooled and L2-normalised."""
        residuals = self.sums - self.counts[:, None].astype(np.float32) * self.centroids
        if pooling == "intra":
            residuals /= np.maximum(np.linalg.norm(residuals, axis=1), _TINY)[:, None]
        elif pooling != "sum":
            raise ConfigError(f"pooling must be 'sum' or 'intra', got {pooling!r}")
        v = residuals.ravel()
        v /= max(np.float32(np.linalg.norm(v)), _TINY)
        return v


def vlad(desc: np.ndarray, centroids: np.ndarray, pooling: Pooling = "sum") -> np.ndarray:
    """VLAD of descriptors (n, d) on a vocabulary (K, d): a (K * d,) float32 unit vector.

    ``pooling="sum"``: residuals x - c(x) summed per word, then L2 (MCVL's text). ``"intra"``:
    each word's sum L2-normalised first (the authors' code). No descriptors give the zero vector.
    """
    desc = np.asarray(desc, dtype=np.float32)
    acc = VladAccumulator(centroids)
    if desc.ndim != 2 or desc.shape[1] != acc.centroids.shape[1]:
        raise InputError(None, f"descriptors must be (n, {acc.centroids.shape[1]}), got shape {desc.shape}")
    acc.add_many(desc)
    return acc.result(pooling)


# --------------------------------------------------------------------------- vocabulary


class _UniformSample:
    """A uniform sample without replacement of at most ``size`` rows from a stream of blocks.

    Every row gets a uniform random key; the sample is the rows with the ``size`` smallest keys
    (bottom-k sampling), kept exactly while the stream is read, with at most 2 x size rows held.
    """

    def __init__(self, size: int, rng: np.random.Generator):
        self.size = size
        self.rng = rng
        self.threshold = 1.0
        self._keys: list[np.ndarray] = []
        self._rows: list[np.ndarray] = []
        self._held = 0

    def add(self, rows: np.ndarray) -> None:
        keys = self.rng.random(len(rows))
        keep = keys < self.threshold
        if keep.any():
            self._keys.append(keys[keep])
            self._rows.append(rows[keep])  # a copy: blocks are reused buffers
            self._held += int(keep.sum())
            if self._held > 2 * self.size:
                self._shrink()

    def _shrink(self) -> None:
        keys = np.concatenate(self._keys)
        rows = np.concatenate(self._rows)
        if len(keys) > self.size:
            best = np.argpartition(keys, self.size - 1)[: self.size]
            keys, rows = keys[best], rows[best]
            self.threshold = float(keys.max())
        self._keys, self._rows, self._held = [keys], [rows], len(keys)

    def result(self) -> np.ndarray:
        if not self._rows:
            return np.zeros((0, 0), np.float32)
        self._shrink()
        return self._rows[0]


def kmeans(samples: np.ndarray, k: int, iterations: int = 25, seed: int = 0) -> np.ndarray:
    """(k, d) float32 centroids of ``samples`` by faiss k-means, on all the given samples."""
    import faiss

    samples = np.ascontiguousarray(samples, dtype=np.float32)
    if len(samples) < k:
        raise InputError(None, f"k-means needs at least {k} descriptors (one per word), got {len(samples)}")
    km = faiss.Kmeans(
        samples.shape[1],
        k,
        niter=iterations,
        seed=seed,
        verbose=False,
        max_points_per_centroid=math.ceil(len(samples) / k) + 1,
    )
    km.train(samples)
    return np.ascontiguousarray(km.centroids, dtype=np.float32)


# --------------------------------------------------------------------------- PCA-whitening


@dataclass
class PcaWhitening:
    """y = L2( W (x - mean) ): W's rows are principal directions, each scaled by a function of the
    training variance along it (see :func:`whitening_scales`). Serialisable as plain arrays
    (``state_dict``).

    ``power`` and ``shrinkage`` say how the directions were scaled (power 1, shrinkage 0: full
    whitening, the paper's); ``n_train`` how many vectors the PCA learned from (0: not recorded).
    """

    mean: np.ndarray  # (D,) float32
    projection: np.ndarray  # (d, D) float32
    variances: np.ndarray  # (d,) float64, training variance along each direction (descending)
    whiten: bool
    power: float = 1.0
    shrinkage: float = 0.0
    n_train: int = 0

    def __post_init__(self) -> None:
        self.mean = np.ascontiguousarray(self.mean, dtype=np.float32)
        self.projection = np.ascontiguousarray(self.projection, dtype=np.float32)
        self.variances = np.asarray(self.variances, dtype=np.float64)
        self._bias = (self.projection.astype(np.float64) @ self.mean.astype(np.float64)).astype(np.float32)

    @property
    def dim(self) -> int:
        return self.projection.shape[0]

    @classmethod
    def fit(
        cls, vectors: np.ndarray, dim: int, whiten: bool = True, power: float = 1.0, shrinkage: float = 0.0
    ) -> PcaWhitening:
        """Learn from training vectors (n, D). ``dim`` is capped at the rank n - 1 with a warning.

        ``power`` (alpha) and ``shrinkage`` (beta) regularise the whitening (see
        :func:`whitening_scales`); the defaults are full whitening, which equalises the distances
        between the training vectors when ``dim`` reaches n - 1 (use the regularised forms then).

        With n < D the eigenvectors come from the n x n Gram matrix (the D x D covariance of
        16384-D VLADs would be 1 GiB), else from the covariance.
        """
        x = np.asarray(vectors, dtype=np.float32)
        if x.ndim != 2 or len(x) < 2:
            raise InputError(None, f"PCA needs at least 2 training vectors (n, D), got shape {x.shape}")
        if not 0.0 <= power <= 1.0 or shrinkage < 0:
            raise ConfigError(f"whitening power must be in [0, 1] and shrinkage >= 0, got {power} and {shrinkage}")
        n, big_d = x.shape
        cap = min(dim, n - 1, big_d)
        if cap < dim:
            warnings.warn(
                f"PCA dimension capped from {dim} to {cap}: {n} training vectors of dimension {big_d}",
                InputWarning,
                stacklevel=2,
            )
        mean = x.mean(axis=0, dtype=np.float64).astype(np.float32)
        xc = x - mean
        if n <= big_d:
            gram = (xc @ xc.T).astype(np.float64)
            evals, evecs = np.linalg.eigh(gram)  # ascending
            evals, evecs = evals[::-1][:cap], evecs[:, ::-1][:, :cap]
            keep = evals > _RANK_TOL * max(evals[0], np.finfo(np.float64).tiny)
            evals, evecs = evals[keep], evecs[:, keep]
            # direction u = X^T v / sqrt(lambda) for Gram eigenpair (lambda, v); unit norm
            directions = (xc.T @ (evecs / np.sqrt(evals)).astype(np.float32)).T
        else:
            cov = (xc.T @ xc).astype(np.float64)
            evals, evecs = scipy.linalg.eigh(cov, subset_by_index=[big_d - cap, big_d - 1])
            evals, evecs = evals[::-1], evecs[:, ::-1]
            keep = evals > _RANK_TOL * max(evals[0], np.finfo(np.float64).tiny)
            evals, evecs = evals[keep], evecs[:, keep]
            directions = evecs.T.astype(np.float32)
        if len(evals) < cap:
            warnings.warn(
                f"PCA dimension capped from {cap} to {len(evals)}: the training vectors span only that many dimensions",
                InputWarning,
                stacklevel=2,
            )
        # deterministic signs: the largest-magnitude coordinate of each direction is positive
        flip = np.sign(directions[np.arange(len(directions)), np.abs(directions).argmax(axis=1)])
        directions *= flip[:, None]
        variances = evals / (n - 1)
        if whiten:
            directions *= whitening_scales(variances, power, shrinkage).astype(np.float32)[:, None]
        else:
            power, shrinkage = 0.0, 0.0
        return cls(mean, directions, variances, whiten, float(power), float(shrinkage), n)

    def project(self, x: np.ndarray) -> np.ndarray:
        """W (x - mean) for one (D,) vector or rows (n, D), without the final L2."""
        x = np.asarray(x, dtype=np.float32)
        return x @ self.projection.T - self._bias if x.ndim == 2 else self.projection @ x - self._bias

    def transform(self, x: np.ndarray) -> np.ndarray:
        """L2-normalised projection of one (D,) vector or rows (n, D)."""
        y = self.project(x)
        norm = np.linalg.norm(y, axis=-1, keepdims=True)
        y /= np.maximum(norm, _TINY)
        return y

    def rewhitened(self, whiten: bool, power: float = 1.0, shrinkage: float = 0.0) -> tuple[PcaWhitening, np.ndarray]:
        """The same PCA with another whitening, and the factor (d,) that takes this one's outputs to
        the new one's before the L2 (:meth:`rescale`). Exact: the whitening only scales the principal
        directions, and the L2 at the end removes the scale of a whole vector."""
        if not 0.0 <= power <= 1.0 or shrinkage < 0:
            raise ConfigError(f"whitening power must be in [0, 1] and shrinkage >= 0, got {power} and {shrinkage}")
        if not whiten:
            power, shrinkage = 0.0, 0.0  # plain PCA: every scale 1, as whitening_scales gives for alpha = 0
        ratio = whitening_scales(self.variances, power, shrinkage) / whitening_scales(
            self.variances, self.power, self.shrinkage
        )
        projection = (self.projection.astype(np.float64) * ratio[:, None]).astype(np.float32)
        return PcaWhitening(
            self.mean, projection, self.variances, whiten, float(power), float(shrinkage), self.n_train
        ), ratio

    @staticmethod
    def rescale(vectors: np.ndarray, ratio: np.ndarray) -> np.ndarray:
        """Outputs of one whitening (n, d), unit rows, as another's: scaled per direction by ``ratio``, then L2
        again."""
        y = np.asarray(vectors, np.float64) * ratio
        y /= np.maximum(np.linalg.norm(y, axis=1, keepdims=True), _TINY)
        return y.astype(np.float32)

    def state_dict(self) -> dict[str, np.ndarray]:
        return {
            "mean": self.mean,
            "projection": self.projection,
            "variances": self.variances,
            "whiten": np.array(self.whiten),
            "power": np.array(self.power),
            "shrinkage": np.array(self.shrinkage),
            "n_train": np.array(self.n_train),
        }

    @classmethod
    def from_state_dict(cls, state: dict[str, np.ndarray]) -> PcaWhitening:
        """Arrays of ``state_dict``; encoders saved before the regularised whitening (no ``power``) were fully
        whitened."""
        whiten = bool(state["whiten"])
        power = float(state["power"]) if "power" in state else (1.0 if whiten else 0.0)
        return cls(
            state["mean"],
            state["projection"],
            state["variances"],
            whiten,
            power,
            float(state.get("shrinkage", 0.0)),
            int(state.get("n_train", 0)),
        )

    def describe(self) -> dict:
        """What the whitening is, for a manifest: dimension, training vectors, how directions were scaled."""
        mode = (
            "none"
            if not self.whiten
            else "full"
            if self.power == 1.0 and self.shrinkage == 0.0
            else "shrinkage"
            if self.shrinkage > 0
            else "power"
        )
        return {
            "dim": self.dim,
            "training_vectors": self.n_train,
            "whitening": mode,
            "power": self.power,
            "shrinkage": self.shrinkage,
        }


def whitening_scales(variances: np.ndarray, power: float = 1.0, shrinkage: float = 0.0) -> np.ndarray:
    """Scale of each principal direction: (lambda_i + beta * mean(lambda)) ** (-alpha / 2).

    alpha = 1, beta = 0 is full whitening (MCVL's [33], Jegou and Chum, ECCV 2012): unit variance
    along every kept direction, which also gives full weight to the last, least reliable ones.
    alpha < 1 is power-law whitening (HOW's shrinkage exponent, Tolias et al., ECCV 2020): the
    spread of the scales is the full one to the power alpha, so large components are still
    damped (the paper's aim: down-weight bursty, co-occurring background words) but small ones are
    not blown up. beta > 0 adds a fraction of the mean kept eigenvalue before the inverse square
    root, as whitening with a covariance shrunk towards a scaled identity does (Ledoit and Wolf,
    2004): directions with much less than the mean variance are scaled like the mean. Either keeps
    the whitened training vectors from all being equidistant when the PCA keeps n - 1 directions.
    Only ratios matter: the encoder L2-normalises after projecting.
    """
    lam = np.asarray(variances, np.float64)
    if len(lam) == 0:
        return lam
    return (lam + shrinkage * lam.mean()) ** (-power / 2)


def whitening_parameters(cfg: VladConfig) -> tuple[float, float]:
    """(power alpha, shrinkage beta) of :func:`whitening_scales` for a config's ``whitening``."""
    if cfg.whitening == "full":
        return 1.0, 0.0
    if cfg.whitening == "power":
        return float(cfg.whitening_power), 0.0
    return 1.0, float(cfg.whitening_shrinkage)


# --------------------------------------------------------------------------- encoder


class VladEncoder:
    """Image -> MCVL observation vector: dense RootSIFT, VLAD, PCA-whitening, L2.

    ``fit`` learns the vocabulary and then the PCA from training images; ``encode`` maps a uint8
    grey or BGR image to a unit ``(pca.dim,)`` float32 vector (``cfg.pca_dim`` unless capped by
    too few training images). ``encode_raw`` stops before the PCA.
    """

    MODEL_FILE = "vlad_encoder.npz"
    CONFIG_FILE = "config.json"

    def __init__(
        self,
        cfg: VladConfig | None = None,
        vocabulary: np.ndarray | None = None,
        pca: PcaWhitening | None = None,
    ):
        self.cfg = cfg or VladConfig()
        self.vocabulary = None if vocabulary is None else np.ascontiguousarray(vocabulary, dtype=np.float32)
        self.pca = pca
        if self.vocabulary is not None and self.vocabulary.shape != (self.cfg.num_words, DESCRIPTOR_DIM):
            raise ConfigError(
                f"vocabulary has shape {self.vocabulary.shape}, config wants ({self.cfg.num_words}, {DESCRIPTOR_DIM})"
            )

    @property
    def raw_dim(self) -> int:
        return self.cfg.num_words * DESCRIPTOR_DIM

    # ---- training

    def fit(self, images: Iterable[np.ndarray], progress: bool = False) -> VladEncoder:
        """Learn the vocabulary, then the PCA-whitening, from ``images`` (read twice: pass a list or
        another re-iterable collection, not a one-shot iterator)."""
        if iter(images) is images:
            raise TypeError(
                "fit reads the images twice: pass a list or another re-iterable collection, not an iterator"
            )
        self.fit_vocabulary(images, progress=progress)
        raw = np.stack([self.encode_raw(im) for im in _progress(images, progress, "VLAD")])
        self.fit_pca(raw)
        return self

    def fit_vocabulary(self, images: Iterable[np.ndarray], progress: bool = False) -> np.ndarray:
        """k-means vocabulary on a uniform sample of the RootSIFT descriptors of ``images``."""
        sample = _UniformSample(self.cfg.kmeans_max_descriptors, np.random.default_rng(self.cfg.seed))
        for im in _progress(images, progress, "descriptors"):
            gray, _, _ = prepare_image(im, self.cfg.dsift)
            for blk in iter_histogram_blocks(gray, self.cfg.dsift):
                sample.add(_rootsift_from_histograms(blk.histograms, self.cfg.dsift.clamp))
        self.vocabulary = kmeans(sample.result(), self.cfg.num_words, self.cfg.kmeans_iterations, self.cfg.seed)
        return self.vocabulary

    def fit_pca(self, raw_vlads: np.ndarray) -> PcaWhitening:
        """PCA (+ whitening, as ``cfg.whitening`` says) on training VLADs (n, K * 128) from ``encode_raw``."""
        power, shrinkage = whitening_parameters(self.cfg)
        self.pca = PcaWhitening.fit(
            raw_vlads, self.cfg.pca_dim, whiten=self.cfg.whiten, power=power, shrinkage=shrinkage
        )
        return self.pca

    # ---- encoding

    def encode_raw(self, image: np.ndarray, timer: StepTimer | None = None) -> np.ndarray:
        """(K * 128,) float32 VLAD of an image, before PCA. ``timer`` collects per-step seconds."""
        if self.vocabulary is None:
            raise ConfigError("the encoder has no vocabulary: fit or load it first")
        step = timer or null_timer
        with step("prepare"):
            gray, _, _ = prepare_image(image, self.cfg.dsift)
        acc = VladAccumulator(self.vocabulary)
        for blk in iter_histogram_blocks(gray, self.cfg.dsift, timer=step):
            with step("rootsift"):
                desc = _rootsift_from_histograms(blk.histograms, self.cfg.dsift.clamp)
            acc.add(desc, step)
        if acc.counts.sum() == 0:
            raise InputError(
                None,
                f"image of shape {gray.shape} is smaller than the largest descriptor region "
                f"({max(self.cfg.dsift.region_widths)} px): no dense SIFT frame fits",
            )
        with step("pool"):
            return acc.result(self.cfg.pooling)

    def encode(self, image: np.ndarray, timer: StepTimer | None = None) -> np.ndarray:
        """(pca.dim,) float32 unit vector of an image: VLAD, PCA-whitening, L2."""
        if self.pca is None:
            raise ConfigError("the encoder has no PCA: fit or load it first")
        raw = self.encode_raw(image, timer)
        with (timer or null_timer)("pca"):
            return self.pca.transform(raw)

    # ---- persistence

    def save(self, folder: str | Path) -> Path:
        """Write ``vlad_encoder.npz`` (vocabulary, PCA arrays) and ``config.json`` into ``folder``."""
        if self.vocabulary is None:
            raise ConfigError("nothing to save: the encoder has no vocabulary")
        folder = Path(folder)
        arrays = {"vocabulary": self.vocabulary}
        if self.pca is not None:
            arrays.update({f"pca_{k}": v for k, v in self.pca.state_dict().items()})
        with atomic_path(folder / self.MODEL_FILE) as tmp, open(tmp, "wb") as f:
            # mypy matches **arrays against savez's allow_pickle: bool; no key here is allow_pickle
            np.savez(f, **arrays)  # type: ignore[arg-type]
        atomic_write_text(folder / self.CONFIG_FILE, self.cfg.model_dump_json(indent=2) + "\n")
        return folder

    @classmethod
    def load(cls, folder: str | Path) -> VladEncoder:
        folder = Path(folder)
        cfg_path, model_path = folder / cls.CONFIG_FILE, folder / cls.MODEL_FILE
        for p in (cfg_path, model_path):
            if not p.is_file():
                raise InputError(p, "missing: not a saved VLAD encoder folder")
        try:
            cfg = VladConfig.model_validate(json.loads(cfg_path.read_text()))
        except (ValidationError, json.JSONDecodeError) as exc:
            raise ConfigError(f"{cfg_path}: not a valid VLAD config ({exc})") from None
        with np.load(model_path, allow_pickle=False) as z:
            if "vocabulary" not in z.files:
                raise InputError(model_path, "no vocabulary array", field="vocabulary")
            vocabulary = z["vocabulary"]
            pca_state = {k[4:]: z[k] for k in z.files if k.startswith("pca_")}
        pca = PcaWhitening.from_state_dict(pca_state) if pca_state else None
        return cls(cfg, vocabulary, pca)


def _progress(items: Iterable, enabled: bool, desc: str) -> Iterable:
    if not enabled:
        return items
    from tqdm import tqdm

    return tqdm(items, desc=desc, unit="img")
