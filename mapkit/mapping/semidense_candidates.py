"""Candidate pixels of a keyframe: image gradients, the region-adaptive threshold, one pixel per cell.

Step 1 of the semi-dense mapper (:mod:`mapkit.mapping.semidense`), after DSO's candidate point
selection (Engel, Koltun, Cremers, TPAMI 2018, "candidate point selection" under point management;
its ``PixelSelector``): the image is split into 32x32 blocks; a pixel is a candidate when its
gradient exceeds the block's median gradient plus 7 (thresholds smoothed over 3x3 blocks), so
texture-poor regions still get points; the strongest pixel per ``cell_size`` cell is kept. Also
holds DSO's 8-pixel residual pattern, which the epipolar search (:mod:`.semidense_epipolar`)
matches and whose radius sets the border candidates keep from the image edge.

The functions take the mapper's :class:`~mapkit.mapping.semidense.SemiDenseConfig`; they are typed
against :class:`CandidateParams`, the fields they read, so that this module need not import
``semidense`` (which imports it).
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
from scipy.ndimage import uniform_filter

#: DSO's residual pattern (``PATTERNP = staticPattern[8]`` in DSO's settings): 8 pixels around
#: the candidate, a diamond of radius 2, offsets (du, dv) in pixels.
PATTERN_DSO8 = np.array([(0, -2), (-1, -1), (1, -1), (-2, 0), (0, 0), (2, 0), (-1, 1), (0, 2)], np.float64)
PATTERN_RADIUS = 2  # the pattern's half-width (px): candidates and searched lines keep this off the border


class CandidateParams(Protocol):
    """The fields of ``SemiDenseConfig`` that candidate selection reads."""

    block_size: int
    gradient_threshold_add: float
    cell_size: int
    max_candidates: int | None


def image_gradients(gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Central-difference gradients (grey levels per pixel) as DSO computes them; 0 on the border."""
    img = np.asarray(gray, np.float32)
    gx = np.zeros_like(img)
    gy = np.zeros_like(img)
    gx[:, 1:-1] = 0.5 * (img[:, 2:] - img[:, :-2])
    gy[1:-1, :] = 0.5 * (img[2:, :] - img[:-2, :])
    return gx, gy


def gradient_threshold(grad_mag: np.ndarray, cfg: CandidateParams) -> np.ndarray:
    """Per-pixel threshold: block median of |gradient| + g_th, smoothed over 3x3 blocks (DSO)."""
    H, W = grad_mag.shape
    bs = cfg.block_size
    nby, nbx = -(-H // bs), -(-W // bs)
    # partial blocks on the right and bottom borders are completed by reflection
    padded = np.pad(grad_mag.astype(np.float32), ((0, nby * bs - H), (0, nbx * bs - W)), mode="symmetric")
    blocks = padded.reshape(nby, bs, nbx, bs).transpose(0, 2, 1, 3).reshape(nby, nbx, bs * bs)
    med = np.median(blocks, axis=2) + cfg.gradient_threshold_add
    smoothed = uniform_filter(med, size=3, mode="nearest")
    return np.repeat(np.repeat(smoothed, bs, axis=0), bs, axis=1)[:H, :W].astype(np.float32)


def select_candidates(
    gray: np.ndarray, cfg: CandidateParams, border: int = PATTERN_RADIUS + 1
) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (u, v) whose gradient beats the region-adaptive threshold, one per ``cell_size`` cell."""
    gx, gy = image_gradients(gray)
    mag = np.hypot(gx, gy)
    ratio = mag / gradient_threshold(mag, cfg)
    ratio[:border, :] = 0
    ratio[-border:, :] = 0
    ratio[:, :border] = 0
    ratio[:, -border:] = 0
    H, W = mag.shape
    cs = cfg.cell_size
    if cs == 1:
        v, u = np.nonzero(ratio > 1.0)
        score = ratio[v, u]
    else:
        ny, nx = -(-H // cs), -(-W // cs)
        padded = np.zeros((ny * cs, nx * cs), np.float32)
        padded[:H, :W] = ratio
        cells = padded.reshape(ny, cs, nx, cs).transpose(0, 2, 1, 3).reshape(ny, nx, cs * cs)
        best = np.argmax(cells, axis=2)
        score = np.take_along_axis(cells, best[..., None], axis=2)[..., 0]
        cy, cx = np.nonzero(score > 1.0)
        k = best[cy, cx]
        v, u = cy * cs + k // cs, cx * cs + k % cs
        score = score[cy, cx]
    if cfg.max_candidates is not None and len(u) > cfg.max_candidates:
        keep = np.sort(np.argsort(-score, kind="stable")[: cfg.max_candidates])
        u, v = u[keep], v[keep]
    return u.astype(np.int32), v.astype(np.int32)
