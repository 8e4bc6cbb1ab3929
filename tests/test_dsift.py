"""Dense SIFT against OpenCV's SIFT and VLFeat's ``vl_phow``, its frame geometry, and gradients of known direction."""

from __future__ import annotations

import math
from pathlib import Path

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


def frame_contrast(histograms: np.ndarray, bin_size: int) -> np.ndarray:
    """(n,) VLFeat's contrast ("norm" of a ``vl_dsift`` frame) of raw histograms of one bin size, frame by
    frame: VLFeat bins with triangles of unit height, ``s^2`` times mapkit's unit-integral ones, and
    divides the histogram's sum by the frame's area ``(3 s + 1)^2`` (4 spatial bins of ``s`` pixels)."""
    span = 3 * bin_size + 1
    return histograms.sum(axis=1, dtype=np.float64) * bin_size * bin_size / (span * span)


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
            cv2.rectangle(
                img,
                (int(x), int(y)),
                (int(x + rng.integers(8, 30)), int(y + rng.integers(8, 30))),
                float(rng.uniform(0, 255)),
                -1,
            )
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


@pytest.mark.parametrize(
    "theta, bins",
    [
        (0.0, {0: 1.0}),
        (45.0, {1: 1.0}),
        (90.0, {2: 1.0}),
        (270.0, {6: 1.0}),
        (22.5, {0: 0.5, 1: 0.5}),
        (337.5, {7: 0.5, 0: 0.5}),
    ],
)
def test_a_ramp_puts_its_energy_in_the_bins_of_its_direction(theta, bins):
    cfg = DsiftConfig(magnif=None, region_widths=[16, 24])  # no smoothing: the gradient is exact to the border
    _, _, desc = dense_sift(ramp(theta), cfg)
    per_orientation = desc.reshape(len(desc), 16, 8).sum(axis=1)
    share = per_orientation / per_orientation.sum(axis=1, keepdims=True)
    expected = np.zeros(8)
    for b, v in bins.items():
        expected[b] = v
    np.testing.assert_allclose(share, np.broadcast_to(expected, share.shape), atol=1e-3)


@pytest.mark.parametrize("mode", ["mapkit", "phow"])
def test_sift_normalisation_and_blocks_agree(mode):
    img = textured_image(3)
    cfg = DsiftConfig(mode=mode)
    _, _, desc = dense_sift(img, cfg)
    norms = np.linalg.norm(desc, axis=1)
    kept = norms > 0
    if mode == "phow":  # vl_phow zeroes the flat parts of the texture, and only those
        assert 0 < (~kept).sum() < len(desc) // 2
    else:
        assert kept.all()
    np.testing.assert_allclose(norms[kept], 1.0, atol=1e-5)
    gray, _, _ = prepare_image(img, cfg)
    blocks = [sift_normalize(b.histograms) for b in iter_histogram_blocks(gray, cfg, block_descriptors=500)]
    np.testing.assert_allclose(np.concatenate(blocks), desc, atol=1e-6)


def test_phow_zeroes_exactly_the_frames_below_the_contrast_threshold():
    img = textured_image(6)
    cfg = DsiftConfig(mode="phow")
    gray, _, _ = prepare_image(img, cfg)
    unthresholded = cfg.model_copy(update={"phow_contrast_threshold": None})
    contrast = np.concatenate(
        [frame_contrast(b.histograms, b.grid.bin_size) for b in iter_histogram_blocks(gray, unthresholded)]
    )
    zeroed = ~dense_sift(img, cfg).descriptors.any(axis=1)
    near = np.abs(contrast / cfg.phow_contrast_threshold - 1) < 1e-4  # float summation order may tip these
    assert zeroed.any() and not zeroed.all()
    np.testing.assert_array_equal(zeroed[~near], (contrast < cfg.phow_contrast_threshold)[~near])


def test_phow_window_at_bin_size_1_is_the_bin_centre_window():
    # a bin of 1 px covers a single offset: its mean window is the window at its centre, so vl_dsift's
    # fast mode and the sampled window of mode "mapkit" must agree when given the same sigma
    img = textured_image(5)
    phow = DsiftConfig(region_widths=[4], mode="phow", phow_window_size=1.5, phow_contrast_threshold=None)
    sampled = DsiftConfig(region_widths=[4], window_sigma_bins=1.5)
    np.testing.assert_allclose(dense_sift(img, phow).descriptors, dense_sift(img, sampled).descriptors, atol=1e-6)
    # at larger bins the mean over the bin is lower than the value at the centre (the peak of a concave Gaussian top)
    wide_phow = dense_sift(img, phow.model_copy(update={"region_widths": [40]})).descriptors
    wide_sampled = dense_sift(img, sampled.model_copy(update={"region_widths": [40]})).descriptors
    assert np.abs(wide_phow - wide_sampled).max() > 1e-3


# --- VLFeat vl_phow's output on a real KITTI frame (../shared/data/vlfeat-phow-reference) ------------------

PHOW_REFERENCE = (
    Path(__file__).resolve().parents[2] / "shared" / "data" / "vlfeat-phow-reference" / "phow_kitti000000_640x480.npz"
)


def vlfeat_layout(desc: np.ndarray) -> np.ndarray:
    """mapkit descriptors in VLFeat's orientation order: mapkit's bin o is VLFeat's (-o) mod 8 (opposite senses)."""
    out = np.empty_like(desc)
    out.reshape(-1, 16, 8)[:, :, [(-o) % 8 for o in range(8)]] = desc.reshape(-1, 16, 8)
    return out


def row_cosines(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return (a * b).sum(1) / np.maximum(np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1), 1e-12)


@pytest.fixture(scope="module")
def phow_reference():
    """VLFeat's vl_phow on KITTI frame 0 at 640x480 (every 37th frame kept); skipped when absent."""
    if not PHOW_REFERENCE.is_file():
        pytest.skip(f"VLFeat reference not found at {PHOW_REFERENCE} (expected ../shared/data beside the project)")
    with np.load(PHOW_REFERENCE) as z:
        return {k: z[k] for k in z.files}


@pytest.mark.realdata
def test_phow_mode_reproduces_vlfeat_phow(phow_reference):
    ref = phow_reference
    cfg = DsiftConfig(mode="phow")
    kp, scale, desc = dense_sift(ref["image"], cfg)
    # the same frames, in the same order (bin size, then rows, then columns)
    assert np.bincount(scale, minlength=4).tolist() == ref["counts_per_size"].tolist()
    idx = ref["index"]
    np.testing.assert_array_equal(kp[idx], ref["frames"][:, :2])
    np.testing.assert_array_equal(np.asarray(cfg.bin_sizes)[scale[idx]], ref["frames"][:, 3])
    ours = vlfeat_layout(desc[idx])
    # the contrast threshold zeroes the same descriptors (~21% of them)
    zero_ours, zero_ref = ~ours.any(axis=1), ~ref["descriptors"].any(axis=1)
    assert 0.15 < zero_ref.mean() < 0.3
    assert (zero_ours == zero_ref).mean() >= 0.999, (
        f"zero masks differ on {(zero_ours != zero_ref).sum()} of {len(idx)} frames"
    )
    kept = ~zero_ours & ~zero_ref
    assert np.median(row_cosines(ours[kept], ref["descriptors"][kept])) >= 0.9999
    # without the threshold every frame agrees, not only the median
    no_thr = vlfeat_layout(
        dense_sift(ref["image"], cfg.model_copy(update={"phow_contrast_threshold": None})).descriptors[idx]
    )
    cos = row_cosines(no_thr, ref["descriptors_no_threshold"])
    assert np.median(cos) >= 0.9999 and cos.min() >= 0.999, (np.median(cos), cos.min())


@pytest.mark.realdata
def test_phow_contrast_is_vlfeats_frame_norm(phow_reference):
    ref = phow_reference
    cfg = DsiftConfig(mode="phow", phow_contrast_threshold=None)
    gray, _, _ = prepare_image(ref["image"], cfg)
    contrast = np.concatenate([frame_contrast(b.histograms, b.grid.bin_size) for b in iter_histogram_blocks(gray, cfg)])
    np.testing.assert_allclose(contrast[ref["index"]], ref["frames"][:, 2], rtol=2e-3, atol=1e-6)


@pytest.mark.realdata
def test_default_mode_differs_from_vlfeat_only_by_its_window(phow_reference):
    # mode "mapkit" (sigma 2 bins at the bin centres, no threshold) is close to vl_phow but measurably not it
    ref = phow_reference
    desc = dense_sift(ref["image"], DsiftConfig()).descriptors[ref["index"]]
    cos = row_cosines(vlfeat_layout(desc), ref["descriptors_no_threshold"])
    assert 0.99 <= np.median(cos) < 0.9995, np.median(cos)
    assert np.all(np.any(desc, axis=1))  # no contrast threshold


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
