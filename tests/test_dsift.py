"""Dense SIFT against OpenCV's SIFT, its frame geometry, and gradients of known direction."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from mapkit.core.errors import InputError
from mapkit.retrieval.dsift import (
    DESCRIPTOR_DIM,
    DsiftConfig,
    dense_sift,
    iter_histogram_blocks,
    opencv_keypoint_size,
    prepare_image,
    scale_grids,
    sift_normalize,
)


def textured_image(seed: int, h: int = 120, w: int = 160) -> np.ndarray:
    """uint8 grey texture: noise at three scales plus a few filled shapes (edges and corners)."""
    rng = np.random.default_rng(seed)
    img = np.zeros((h, w), np.float32)
    for sigma, amp in ((1.0, 0.3), (3.0, 1.0), (8.0, 2.0)):
        layer = cv2.GaussianBlur(rng.standard_normal((h, w)).astype(np.float32), (0, 0), sigma)
        img += amp * layer / layer.std()
    img = (img - img.min()) / (img.max() - img.min()) * 200 + 20
    for _ in range(6):
        x, y = rng.integers(0, w), rng.integers(0, h)
        if rng.random() < 0.5:
            cv2.rectangle(img, (int(x), int(y)), (int(x + rng.integers(8, 30)), int(y + rng.integers(8, 30))), float(rng.uniform(0, 255)), -1)
        else:
            cv2.circle(img, (int(x), int(y)), int(rng.integers(4, 15)), float(rng.uniform(0, 255)), -1)
    return np.clip(img, 0, 255).astype(np.uint8)


def ramp(theta_deg: float, h: int = 60, w: int = 70) -> np.ndarray:
    """Float image whose gradient points at ``theta_deg`` counter-clockwise from +x (y up)."""
    t = math.radians(theta_deg)
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    return (0.5 + 0.004 * (x * math.cos(t) - y * math.sin(t))).astype(np.float32)  # rows grow downwards


@pytest.mark.parametrize("step", [2, 3])  # step 3: bin-centre lattices of spacing 1 and 3 px
def test_matches_opencv_sift_at_the_same_upright_keypoints(step):
    img = textured_image(1)
    cfg = DsiftConfig(step=step)
    kp, scale, desc = dense_sift(img, cfg)
    rng = np.random.default_rng(0)
    sift = cv2.SIFT_create()
    cosines = []
    for si, width in enumerate(cfg.region_widths):
        pick = rng.choice(np.flatnonzero(scale == si), 50, replace=False)
        kps = [cv2.KeyPoint(float(x), float(y), opencv_keypoint_size(width), 0) for x, y in kp[pick]]
        kps_out, ref = sift.compute(img, kps)
        assert len(kps_out) == len(pick)
        np.testing.assert_allclose([k.pt for k in kps_out], kp[pick], atol=1e-4)
        ours = desc[pick]
        cosines.append((ours * ref).sum(1) / np.linalg.norm(ours, axis=1) / np.linalg.norm(ref, axis=1))
    cosines = np.concatenate(cosines)
    assert np.median(cosines) >= 0.9, np.median(cosines)


def test_frames_fit_the_image_on_a_shared_grid():
    h, w = 83, 97
    cfg = DsiftConfig(step=3)
    kp, scale, desc = dense_sift(np.zeros((h, w), np.uint8), cfg)
    assert desc.shape == (len(kp), DESCRIPTOR_DIM) and len(scale) == len(kp)
    assert np.all(desc == 0)  # a flat image has no gradient: zero descriptors, no NaN
    first_centre = None
    for si, s in enumerate(cfg.bin_sizes):
        xy = kp[scale == si]
        xs, ys = np.unique(xy[:, 0]), np.unique(xy[:, 1])
        assert len(xy) == len(xs) * len(ys)
        assert np.all(np.diff(xs) == cfg.step) and np.all(np.diff(ys) == cfg.step)
        # every bin centre on a pixel, and one more step would leave the image
        half = 1.5 * s
        assert xs.min() - half >= 0 and xs.max() + half <= w - 1 < xs.max() + half + cfg.step
        assert ys.min() - half >= 0 and ys.max() + half <= h - 1 < ys.max() + half + cfg.step
        if first_centre is None:
            first_centre = (xs[0], ys[0])
        assert (xs[0], ys[0]) == first_centre  # scales share centres (vl_phow)


def test_frame_count_at_640x480_is_vlfeats():
    # vl_phow(Sizes 4 6 8 10, Step 2) on a 640x480 image returns 279,838 frames
    assert sum(g.count for g in scale_grids((480, 640), DsiftConfig())) == 279_838


def test_half_resolution_keypoints_are_in_input_pixels():
    img = textured_image(2)
    cfg = DsiftConfig(region_widths=[16], half_resolution=True)
    kp, _, _ = dense_sift(img[:, :-1], cfg)  # odd width: the last column is dropped
    grid = scale_grids((60, 79), cfg)[0]  # the halved image is 79 x 60
    np.testing.assert_allclose(kp, 2 * grid.centres_xy() + 0.5)


@pytest.mark.parametrize("theta, bins", [(0.0, {0: 1.0}), (45.0, {1: 1.0}), (90.0, {2: 1.0}), (270.0, {6: 1.0}), (22.5, {0: 0.5, 1: 0.5}), (337.5, {7: 0.5, 0: 0.5})])
def test_a_ramp_puts_its_energy_in_the_bins_of_its_direction(theta, bins):
    cfg = DsiftConfig(magnif=None, region_widths=[16, 24])  # no smoothing: the gradient is exact to the border
    _, _, desc = dense_sift(ramp(theta), cfg)
    per_orientation = desc.reshape(len(desc), 16, 8).sum(axis=1)
    share = per_orientation / per_orientation.sum(axis=1, keepdims=True)
    expected = np.zeros(8)
    for b, v in bins.items():
        expected[b] = v
    np.testing.assert_allclose(share, np.broadcast_to(expected, share.shape), atol=1e-3)


def test_sift_normalisation_and_blocks_agree():
    img = textured_image(3)
    cfg = DsiftConfig()
    _, _, desc = dense_sift(img, cfg)
    np.testing.assert_allclose(np.linalg.norm(desc, axis=1), 1.0, atol=1e-5)
    gray, _, _ = prepare_image(img, cfg)
    blocks = [sift_normalize(b.histograms) for b in iter_histogram_blocks(gray, cfg, block_descriptors=500)]
    np.testing.assert_allclose(np.concatenate(blocks), desc, atol=1e-6)


def test_bgr_input_is_converted_to_grey():
    img = textured_image(4)
    bgr = np.dstack([img, img, img])
    np.testing.assert_allclose(dense_sift(bgr).descriptors, dense_sift(img).descriptors, atol=1e-6)


def test_bad_inputs_are_reported():
    with pytest.raises(InputError):
        dense_sift(np.zeros((10, 10, 2), np.uint8))
    with pytest.raises(InputError):
        dense_sift(np.zeros((10, 10), np.int32))
    with pytest.raises(ValueError):  # pydantic: widths must be 4 bins of whole pixels
        DsiftConfig(region_widths=[18])
    with pytest.raises(ValueError):  # unknown keys are errors
        DsiftConfig(stepp=2)
