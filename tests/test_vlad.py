"""RootSIFT, VLAD, PCA-whitening and the VLAD encoder on hand-computed cases and synthetic places."""

from __future__ import annotations

import json
import warnings

import cv2
import numpy as np
import pytest
from test_dsift import textured_image

from mapkit.core.errors import InputError, InputWarning
from mapkit.retrieval.dsift import DsiftConfig, dense_sift
from mapkit.retrieval.vlad import (
    PcaWhitening,
    VladAccumulator,
    VladConfig,
    VladEncoder,
    rootsift,
    vlad,
    whitening_scales,
)

SMALL = dict(
    dsift=DsiftConfig(region_widths=[16, 24]), num_words=16, kmeans_max_descriptors=20_000, kmeans_iterations=10
)


def test_rootsift_rows_are_unit_and_give_the_hellinger_kernel(rng):
    a = rng.random((20, 128)).astype(np.float32)
    b = rng.random((20, 128)).astype(np.float32)
    a[3] = 0
    ra, rb = rootsift(a), rootsift(b)
    norms = np.linalg.norm(ra, axis=1)
    np.testing.assert_allclose(np.delete(norms, 3), 1.0, atol=1e-6)
    assert np.all(ra[3] == 0)
    a_l1 = a / np.maximum(a.sum(1, keepdims=True), 1e-30)
    b_l1 = b / b.sum(1, keepdims=True)
    hellinger = np.sqrt(a_l1 * b_l1).sum(1)
    np.testing.assert_allclose((ra * rb).sum(1), hellinger, atol=1e-6)


def test_vlad_of_a_hand_built_case():
    centroids = np.array([[0, 0, 0], [2, 0, 0]], np.float32)
    desc = np.array([[0, 1, 0], [0, 0, 2], [2, 1, 0], [3, 0, 0]], np.float32)
    # words: 0, 0, 1, 1; residual sums: (0, 1, 2) and (1, 1, 0)
    np.testing.assert_array_equal(VladAccumulator(centroids).assign(desc), [0, 0, 1, 1])
    expected_sum = np.array([0, 1, 2, 1, 1, 0]) / np.sqrt(7)
    np.testing.assert_allclose(vlad(desc, centroids, "sum"), expected_sum, atol=1e-6)
    expected_intra = np.concatenate([np.array([0, 1, 2]) / np.sqrt(5), np.array([1, 1, 0]) / np.sqrt(2)]) / np.sqrt(2)
    np.testing.assert_allclose(vlad(desc, centroids, "intra"), expected_intra, atol=1e-6)
    assert vlad(desc, centroids).dtype == np.float32


def test_assignment_is_the_nearest_centroid(rng):
    desc = rng.random((6000, 128)).astype(np.float32)
    centroids = rng.random((32, 128)).astype(np.float32)
    d2 = (
        (desc.astype(np.float64) ** 2).sum(1)[:, None]
        - 2 * desc.astype(np.float64) @ centroids.T.astype(np.float64)
        + (centroids.astype(np.float64) ** 2).sum(1)
    )
    best = d2.argmin(1)
    got = VladAccumulator(centroids).assign(desc)
    # float32 ties aside, the chosen word is as near as the best one
    np.testing.assert_allclose(d2[np.arange(len(desc)), got], d2[np.arange(len(desc)), best], rtol=1e-5)


@pytest.mark.parametrize("n, dim_in, dim", [(60, 300, 20), (400, 40, 25)])  # Gram trick (n < D), covariance (n > D)
def test_whitened_training_vectors_have_identity_covariance(rng, n, dim_in, dim):
    mixing = rng.standard_normal((dim_in, dim_in)) * np.linspace(3, 0.1, dim_in)
    x = (rng.standard_normal((n, dim_in)) @ mixing.T + 5).astype(np.float32)
    pca = PcaWhitening.fit(x, dim)
    y = pca.project(x)
    assert y.shape == (n, dim)
    np.testing.assert_allclose(np.cov(y, rowvar=False), np.eye(dim), atol=2e-3)
    np.testing.assert_allclose(y.mean(0), 0, atol=1e-3)
    assert np.all(np.diff(pca.variances) <= 0)
    np.testing.assert_allclose(np.linalg.norm(pca.transform(x), axis=1), 1.0, atol=1e-5)
    # unwhitened: orthonormal directions keeping the variances
    plain = PcaWhitening.fit(x, dim, whiten=False)
    np.testing.assert_allclose(plain.projection @ plain.projection.T, np.eye(dim), atol=1e-4)
    np.testing.assert_allclose(np.var(plain.project(x), axis=0, ddof=1), plain.variances, rtol=1e-3)


def test_pca_dimension_is_capped_by_the_training_set(rng):
    x = rng.standard_normal((10, 50)).astype(np.float32)
    with pytest.warns(InputWarning, match="capped from 32 to 9"):
        pca = PcaWhitening.fit(x, 32)
    assert pca.dim == 9
    with pytest.raises(InputError):
        PcaWhitening.fit(x[:1], 4)


def test_whitening_scales_of_each_form():
    lam = np.array([4.0, 1.0])
    np.testing.assert_allclose(whitening_scales(lam), [0.5, 1.0])  # full: 1 / sqrt(lambda)
    np.testing.assert_allclose(whitening_scales(lam, power=0.5), [4**-0.25, 1.0])
    np.testing.assert_allclose(whitening_scales(lam, power=0.0), [1.0, 1.0])  # plain PCA
    np.testing.assert_allclose(whitening_scales(lam, shrinkage=1.0), [6.5**-0.5, 3.5**-0.5])  # + 1 x mean 2.5


@pytest.mark.parametrize("n, dim_in", [(60, 300), (400, 40)])
def test_power_whitened_training_variances_are_the_eigenvalues_to_one_minus_alpha(rng, n, dim_in):
    x = (rng.standard_normal((n, dim_in)) * np.linspace(3, 0.1, dim_in) + 2).astype(np.float32)
    pca = PcaWhitening.fit(x, 20, power=0.5)
    y = pca.project(x)
    # directions scaled by lambda^(-1/4): the variance along each becomes lambda^(1/2)
    np.testing.assert_allclose(np.var(y, axis=0, ddof=1), pca.variances**0.5, rtol=2e-3)
    np.testing.assert_allclose(
        np.cov(y, rowvar=False), np.diag(pca.variances**0.5), atol=2e-3 * pca.variances[0] ** 0.5
    )
    assert pca.describe() == {"dim": 20, "training_vectors": n, "whitening": "power", "power": 0.5, "shrinkage": 0.0}


def places_with_background(seed: int, places: int = 20, dim: int = 400):
    """VLAD-like synthetic vectors with known structure, fewer than their dimension: a common mean,
    4 'background' directions with a random weight per image (the bursty part whitening damps),
    a place signal, and per-visit noise. Returns (database: 2 visits of every place, stacked by
    visit; queries: a third, held-out visit)."""
    rng = np.random.default_rng(seed)
    background = np.linalg.qr(rng.standard_normal((dim, 4)))[0]
    place = 0.1 * rng.standard_normal((places, dim))  # norm ~2
    mean = rng.standard_normal(dim)

    def visit() -> np.ndarray:
        weights = 0.5 * rng.standard_normal((places, 4))
        return (mean + weights @ background.T + place + 0.05 * rng.standard_normal((places, dim))).astype(np.float32)

    return np.concatenate([visit(), visit()]), visit()


def test_full_whitening_on_its_own_n_vectors_makes_them_equidistant_regularised_does_not():
    """Fully whitened in the n - 1 dimensions they span, n vectors are the corners of a regular
    simplex, so after L2 every pair is at squared distance 2n / (n - 1) and the database the PCA
    learned on, searched against itself, returns only ties (684 images: all at 2.0029). Regularised
    whitening keeps the structure."""
    db, _ = places_with_background(0)
    n, places = len(db), len(db) // 2
    same_place = np.r_[np.arange(places) + places, np.arange(places)]
    with pytest.warns(InputWarning, match="capped from 4096 to 39"):
        full = PcaWhitening.fit(db, 4096)
    y = full.transform(db)
    sq = ((y[:, None] - y[None]) ** 2).sum(-1)[~np.eye(n, dtype=bool)]
    np.testing.assert_allclose(sq, 2 * n / (n - 1), rtol=1e-4)
    for kw in (dict(power=0.5), dict(shrinkage=1.0)):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", InputWarning)
            pca = PcaWhitening.fit(db, 4096, **kw)
        y = pca.transform(db)
        sq = ((y[:, None] - y[None]) ** 2).sum(-1)
        np.fill_diagonal(sq, np.inf)
        pairs = sq[np.isfinite(sq)]
        assert pairs.std() / pairs.mean() > 0.05, kw
        # every database image searched against the others finds its other visit, not a tie
        np.testing.assert_array_equal(sq.argmin(axis=1), same_place)
        second = np.sort(sq, axis=1)[:, 1]
        assert np.all(second - sq.min(axis=1) > 0.01), kw


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_regularised_whitening_fitted_on_fewer_vectors_than_dimensions_ranks_held_out_queries(seed):
    db, queries = places_with_background(seed)
    places = len(queries)
    for kw in (dict(power=0.5), dict(shrinkage=1.0)):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", InputWarning)
            pca = PcaWhitening.fit(db, 4096, **kw)  # 40 vectors of 400 dimensions: 39 kept
        assert pca.dim == len(db) - 1
        d = ((pca.transform(queries)[:, None] - pca.transform(db)[None]) ** 2).sum(-1)
        np.testing.assert_array_equal(d.argmin(axis=1) % places, np.arange(places))


def test_encoder_config_chooses_the_whitening(rng):
    x = rng.standard_normal((30, 64)).astype(np.float32)
    # the 8 largest eigenvalues of the training covariance, and each form's scale of its direction written out
    lam = np.sort(np.linalg.eigvalsh(np.cov(x.astype(np.float64), rowvar=False)))[::-1][:8]
    scales = {"full": lam**-0.5, "power": lam**-0.25, "shrinkage": (lam + 2.0 * lam.mean()) ** -0.5}
    for whitening, power, shrinkage in (("full", 1.0, 0.0), ("power", 0.5, 0.0), ("shrinkage", 1.0, 2.0)):
        enc = VladEncoder(VladConfig(pca_dim=8, whitening=whitening, whitening_shrinkage=2.0, **SMALL))
        pca = enc.fit_pca(x)
        assert (pca.power, pca.shrinkage, pca.n_train) == (power, shrinkage, 30)
        np.testing.assert_allclose(pca.variances, lam, rtol=1e-5)
        np.testing.assert_allclose(np.linalg.norm(pca.projection, axis=1), scales[whitening], rtol=1e-4)
    assert VladConfig().whitening == "power" and VladConfig().whitening_power == 0.5
    # a saved state without the whitening's power and shrinkage loads as fully whitened
    state = PcaWhitening.fit(x, 8).state_dict()
    bare = {k: state[k] for k in ("mean", "projection", "variances", "whiten")}
    assert PcaWhitening.from_state_dict(bare).describe()["whitening"] == "full"


def shifted_and_brighter(
    img: np.ndarray, dx: int = 3, dy: int = 2, gain: float = 1.1, offset: float = 15
) -> np.ndarray:
    m = np.float32([[1, 0, dx], [0, 1, dy]])
    moved = cv2.warpAffine(img, m, (img.shape[1], img.shape[0]), borderMode=cv2.BORDER_REFLECT)
    return np.clip(moved.astype(np.float32) * gain + offset, 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def fitted() -> VladEncoder:
    train = [textured_image(100 + i) for i in range(12)]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # 12 images, 8 dims: nothing is capped
        return VladEncoder(VladConfig(pca_dim=8, **SMALL)).fit(train)


def test_encoder_retrieves_the_same_place_among_distractors(fitted):
    database = [textured_image(i) for i in range(8)]
    db = np.stack([fitted.encode(im) for im in database])
    assert db.shape == (8, 8) and db.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(db, axis=1), 1.0, atol=1e-5)
    for place in (2, 5):
        q = fitted.encode(shifted_and_brighter(database[place]))
        dist = np.linalg.norm(db - q, axis=1)
        assert dist.argmin() == place, dist


@pytest.mark.parametrize("pooling", ["sum", "intra"])
def test_fused_encoder_equals_the_composition_of_its_steps(fitted, pooling):
    enc = VladEncoder(fitted.cfg.model_copy(update={"pooling": pooling}), fitted.vocabulary, fitted.pca)
    img = textured_image(7)
    _, _, desc = dense_sift(img, enc.cfg.dsift)
    expected = vlad(rootsift(desc), enc.vocabulary, pooling)
    got = enc.encode_raw(img)
    assert got.shape == (16 * 128,) and got.dtype == np.float32
    np.testing.assert_allclose(got, expected, atol=2e-5)


def test_save_load_round_trip_encodes_identically(fitted, tmp_path):
    fitted.save(tmp_path / "enc")
    loaded = VladEncoder.load(tmp_path / "enc")
    assert loaded.cfg == fitted.cfg
    assert json.loads((tmp_path / "enc" / "config.json").read_text())["pooling"] == "sum"
    img = textured_image(9)
    np.testing.assert_array_equal(loaded.encode(img), fitted.encode(img))


def test_encoder_errors_are_reported(fitted, tmp_path):
    with pytest.raises(TypeError):
        VladEncoder(VladConfig(**SMALL)).fit(iter([textured_image(0)]))
    with pytest.raises(InputError):
        VladEncoder.load(tmp_path / "nothing-here")
    with pytest.raises(InputError):
        fitted.encode(np.zeros((12, 12), np.uint8))  # no 4x4-bin frame of either scale fits
