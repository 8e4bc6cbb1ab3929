"""Exact SIFT matching by matrix products gives COLMAP's brute-force matches: the same pairs in the same order,
ties and thresholds included, on descriptors made to test them and on every pair of a real model."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from mapkit.localization.descriptor_matching import nearest_two, sift_matches


def _colmap_like(rng: np.random.Generator, n: int) -> np.ndarray:
    """n descriptors as COLMAP stores RootSIFT: non-negative unit vectors times 512, rounded to bytes."""
    v = rng.gamma(0.5, size=(n, 128)) ** 0.5
    v *= 512.0 / np.linalg.norm(v, axis=1, keepdims=True)
    return np.clip(np.round(v), 0, 255).astype(np.uint8)


def _descriptor_sets(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Two sets sharing perturbed copies (matches at every distance up to the thresholds), with exact duplicates
    on both sides (ties: the ratio test must reject them) and more rows than one block of the product."""
    rng = np.random.default_rng(seed)
    a = _colmap_like(rng, 1300)
    b = _colmap_like(rng, 1100)
    shared = np.r_[np.arange(1200, 1250), rng.choice(1200, 650, replace=False)]
    noise = rng.normal(0, rng.uniform(1, 40, size=(700, 1)), size=(700, 128))
    b[:700] = np.clip(a[shared] + noise.round(), 0, 255).astype(np.uint8)
    b[700:720] = b[50:70]  # nearest in b twice
    a[1250:1300] = a[1200:1250]  # nearest in a twice
    return a, b


def _colmap(a: np.ndarray, b: np.ndarray, max_ratio: float, cross_check: bool) -> np.ndarray:
    options = pycolmap.FeatureMatchingOptions()
    options.num_threads = 1
    options.sift.cpu_brute_force_matcher = True
    options.sift.max_ratio = max_ratio
    options.sift.cross_check = cross_check
    matcher = pycolmap.FeatureMatcher.create(options, pycolmap.Device.cpu)
    kind = pycolmap.FeatureExtractorType.SIFT
    return np.asarray(
        matcher.match(None, pycolmap.FeatureDescriptors(kind, a), None, pycolmap.FeatureDescriptors(kind, b))
    )


@pytest.mark.parametrize("max_ratio", [0.8, 0.95])
@pytest.mark.parametrize("cross_check", [True, False])
def test_matches_are_colmaps_brute_force_matches(max_ratio, cross_check):
    a, b = _descriptor_sets(seed=3)
    ours = sift_matches(a, b, max_ratio=max_ratio, max_distance=0.7, cross_check=cross_check)
    theirs = _colmap(a, b, max_ratio, cross_check)
    assert len(theirs) > 200  # the sets do match, and the comparison below is not between two empty lists
    assert ours.dtype == np.uint32
    np.testing.assert_array_equal(ours, theirs)
    # a tie never passes the ratio test: the twins in b are nobody's match, those in a only one way
    assert not np.isin(ours[:, 1], np.r_[50:70, 700:720]).any()
    assert np.isin(ours[:, 0], np.arange(1200, 1300)).any() != cross_check


def test_nearest_two_are_the_two_largest_dot_products_of_each_row_and_column():
    a, b = _descriptor_sets(seed=5)
    dots = a.astype(np.int64) @ b.T.astype(np.int64)  # exact, the slow way
    (rows, col_arg), (cols, row_arg) = nearest_two(a, b), nearest_two(b, a)
    for side, d in ((rows, dots), (cols, dots.T)):
        top2 = np.sort(d, axis=1)[:, -2:]
        np.testing.assert_array_equal(side.arg, np.argmax(d, axis=1))  # the first of equals
        np.testing.assert_array_equal(side.best, top2[:, 1])
        np.testing.assert_array_equal(side.second, top2[:, 0])
    np.testing.assert_array_equal(col_arg, cols.arg)  # across blocks of rows, the first of equals too
    np.testing.assert_array_equal(row_arg, rows.arg)


def test_empty_and_single_descriptor_sets():
    a, b = _descriptor_sets(seed=7)
    assert sift_matches(a[:0], b).shape == (0, 2) and sift_matches(a, b[:0]).shape == (0, 2)
    np.testing.assert_array_equal(sift_matches(a[:1], b), _colmap(a[:1], b, 0.8, True))
    np.testing.assert_array_equal(sift_matches(a, b[:1]), _colmap(a, b[:1], 0.8, True))
