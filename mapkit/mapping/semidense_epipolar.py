"""Epipolar line search of keyframe candidates in neighbouring frames, and its image pyramid.

Steps 2 and 3 of the semi-dense mapper (:mod:`mapkit.mapping.semidense`):

2. **Epipolar search** (the semi-dense depth filter of LSD-SLAM: Engel, Sturm, Cremers, ICCV 2013,
   "Semi-dense visual odometry for a monocular camera", its stereo-based depth map update; DSO's
   immature-point trace, "candidate point tracking" in Engel, Koltun, Cremers, TPAMI 2018): each
   candidate is searched along its epipolar line in the neighbouring frames, nearest baseline
   first. The first search covers the whole inverse-depth range, coarse to fine on an image
   pyramid (so that a long line is sampled at <= 1 pixel of the level it is searched on); every
   later search only covers +-3 sigma of the estimate so far and sharpens it, as in LSD-SLAM's
   inverse-depth filter. The cost is 1 - ZNCC over DSO's 8-pixel pattern, warped to the target
   under a fronto-parallel assumption, so it is blind to exposure changes between frames.
3. **Sub-pixel and uncertainty** (after LSD-SLAM's disparity-error model): a parabola on the cost
   curve gives the minimum and the curvature; the pixel error along the line is the curvature
   term for ``image_noise_sigma`` added in quadrature to a quarter-pixel floor, and is mapped to
   inverse depth by the line's pixels per unit inverse depth. Ambiguous searches (a second local
   minimum within ``ambiguity_margin`` of the best cost, or, with ``ambiguity_ratio``, scoring that
   fraction of the best ZNCC: the second-best ratio test) and short lines (small parallax) are
   rejected here; lines along the gradient's edge are skipped by ``map_keyframe`` before searching.

Here live the pyramid atlas (:class:`_Pyramid`), the geometry of a neighbour
(:func:`_neighbour_geometry`), the vectorised searcher (:class:`_Searcher`) and its setup for a
keyframe's candidates (:func:`_candidate_searcher`); which neighbour is searched when, and how the
results are fused per candidate, is ``map_keyframe``'s business (:mod:`mapkit.mapping.semidense`).
Everything is vectorised over candidates (numpy and ``cv2.remap``). The config is typed against
:class:`SearchParams`, the fields read here, so that this module need not import ``semidense``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import cv2
import numpy as np

from mapkit.core.geometry import invert_pose
from mapkit.mapping.semidense_candidates import (
    PATTERN_DSO8,
    PATTERN_RADIUS,
    CandidateParams,
    image_gradients,
    select_candidates,
)

_BAD_COST = 4.0  # any cost above the worst ZNCC cost (2): marks invalid samples
_CHUNK = 4096  # candidates per vectorised block: bounds memory at ~100 MB for 32 samples x 8 taps


class SearchParams(CandidateParams, Protocol):
    """The fields of ``SemiDenseConfig`` that the epipolar search reads (besides candidate selection's)."""

    pyramid_levels: int
    min_depth_m: float
    min_search_half_width_px: float
    min_epipolar_length_px: float
    max_cost: float
    ambiguity_margin: float
    ambiguity_ratio: float | None
    image_noise_sigma: float
    min_sigma_px: float


# --- image pyramid sampled in one remap call ---------------------------------------------------------


def _remap(img: np.ndarray, mx: np.ndarray, my: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``img`` at float positions of any shape (cv2.remap caps rows/cols < 32767)."""
    shape = mx.shape
    n = int(mx.size)
    if n == 0:
        return np.zeros(shape, np.float32)
    cols = min(n, 8192)
    rows = -(-n // cols)
    fx = np.empty(rows * cols, np.float32)
    fy = np.empty(rows * cols, np.float32)
    fx[:n] = mx.ravel()
    fy[:n] = my.ravel()
    fx[n:] = fy[n:] = -1e4
    out = cv2.remap(
        img,
        fx.reshape(rows, cols),
        fy.reshape(rows, cols),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=np.nan,
    )
    return out.ravel()[:n].reshape(shape)


class _Pyramid:
    """Gaussian pyramid (cv2.pyrDown) packed side by side in one float32 atlas.

    Level-l pixel i sits at level-0 coordinate 2^l * i (pyrDown keeps the even pixels), so a
    level-0 position x maps to x / 2^l. One remap call samples any mix of levels. The levels are
    separated by NaN bands (and the atlas is NaN outside): a bilinear sample that touches a pixel
    outside its level is NaN, so validity needs no per-sample bounds test. Values are stored
    minus 128 so that sums of squares in float32 keep their precision.
    """

    GAP = 16  # NaN band (px) between levels: wider than any pattern tap can stray off its level

    def __init__(self, gray: np.ndarray, levels: int):
        imgs: list[np.ndarray] = [np.asarray(gray, np.float32) - 128.0]
        for _ in range(1, levels):
            imgs.append(cv2.pyrDown(imgs[-1]))
        offsets, x = [], 0
        for im in imgs:
            offsets.append(x)
            x += im.shape[1] + self.GAP
        self.atlas = np.full((imgs[0].shape[0] + self.GAP, x), np.nan, np.float32)
        for o, im in zip(offsets, imgs, strict=True):
            self.atlas[: im.shape[0], o : o + im.shape[1]] = im
        self.offset_x = np.array(offsets, np.float64)
        self.scale = 0.5 ** np.arange(levels)
        self.shape = imgs[0].shape
        self.levels = levels

    def sample(self, x: np.ndarray, y: np.ndarray, level: np.ndarray) -> np.ndarray:
        """Values (NaN where invalid) at level-0 positions ``x, y`` on pyramid ``level`` (broadcast)."""
        s = self.scale[level]
        xl, yl = np.broadcast_arrays(x * s + self.offset_x[level], y * s)
        return _remap(self.atlas, xl.astype(np.float32), yl.astype(np.float32))


def _normalise_patterns(vals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Zero-mean, unit-norm patterns along the last axis, and their norms."""
    c = vals - vals.mean(axis=-1, keepdims=True)
    norm = np.sqrt((c * c).sum(axis=-1, keepdims=True))
    return c / np.maximum(norm, 1e-6), norm[..., 0]


# --- epipolar geometry and search -----------------------------------------------------------------------


@dataclass(frozen=True)
class _Neighbour:
    """Geometry of one neighbour relative to the keyframe: K X_k ~ KRKi [u v 1] + rho K t."""

    index: int  # position in the caller's neighbour list
    KRKi: np.ndarray
    Kt: np.ndarray
    epipole_h: np.ndarray  # the neighbour's centre projected into the keyframe (homogeneous)
    baseline_m: float
    pattern_da: np.ndarray  # (P, 3): change of K R K^-1 [u v 1] per pattern offset (level 0)


def _neighbour_geometry(
    index: int, ref_world_from_cam: np.ndarray, world_from_cam: np.ndarray, K: np.ndarray
) -> _Neighbour:
    cam_from_ref = invert_pose(world_from_cam) @ ref_world_from_cam
    R, t = cam_from_ref[:3, :3], cam_from_ref[:3, 3]
    centre_in_ref = -R.T @ t
    KRKi = K @ R @ np.linalg.inv(K)
    return _Neighbour(index, KRKi, K @ t, K @ centre_in_ref, float(np.linalg.norm(t)), PATTERN_DSO8 @ KRKi[:, :2].T)


@dataclass
class _TraceResult:
    rho: np.ndarray
    sigma_rho: np.ndarray
    cost: np.ndarray
    ok: np.ndarray
    searched: np.ndarray  # the line lay in the image and was long enough to search


def _project(a: np.ndarray, b: np.ndarray, rho: np.ndarray) -> np.ndarray:
    """Pixel of inverse depth ``rho`` on the ray ``a`` (K R K^-1 x), ``b`` = K t; shapes broadcast."""
    h = a + rho[..., None] * b
    return h[..., :2] / h[..., 2:3]


class _Searcher:
    """Searches one set of candidates of one keyframe along epipolar lines of one neighbour."""

    def __init__(
        self,
        ref_u: np.ndarray,
        ref_v: np.ndarray,
        ref_norm: np.ndarray,
        ref_std: np.ndarray,
        max_level: np.ndarray,
        cfg: SearchParams,
    ):
        self.u = ref_u.astype(np.float64)
        self.v = ref_v.astype(np.float64)
        self.ref_norm = ref_norm  # (M, L, P) zero-mean unit-norm pattern per level
        self.ref_std = ref_std  # (M,) grey-level std of the level-0 pattern
        self.max_level = max_level  # (M,) deepest level whose ref pattern lies inside the image
        self.cfg = cfg

    def trace(
        self,
        idx: np.ndarray,
        lo: np.ndarray,
        hi: np.ndarray,
        nb: _Neighbour,
        target: _Pyramid,
        samples: int,
        full_range: bool,
    ) -> _TraceResult:
        n = len(idx)
        out = _TraceResult(
            np.full(n, np.nan), np.full(n, np.inf), np.full(n, _BAD_COST), np.zeros(n, bool), np.zeros(n, bool)
        )
        for s in range(0, n, _CHUNK):
            sl = slice(s, s + _CHUNK)
            r = self._trace_chunk(idx[sl], lo[sl], hi[sl], nb, target, samples, full_range)
            out.rho[sl], out.sigma_rho[sl], out.cost[sl], out.ok[sl], out.searched[sl] = (
                r.rho,
                r.sigma_rho,
                r.cost,
                r.ok,
                r.searched,
            )
        return out

    def _trace_chunk(self, idx, lo, hi, nb: _Neighbour, target: _Pyramid, S: int, full_range: bool) -> _TraceResult:
        cfg = self.cfg
        m = len(idx)
        u, v = self.u[idx], self.v[idx]
        a = np.column_stack([u, v, np.ones(m)]) @ nb.KRKi.T  # (m, 3)
        b = nb.Kt
        P0, direction, L, valid = self._segment(a, b, lo, hi, target.shape, full_range)
        searched = valid.copy()

        # coarse search: S samples, on the pyramid level where a step is <= 1 level-pixel
        step = L / (S - 1)
        level = np.clip(np.ceil(np.log2(np.maximum(step, 1e-9))), 0, self.max_level[idx]).astype(np.int64)
        s_samples = step[:, None] * np.arange(S)[None, :]
        cost = self._costs(idx, a, b, nb.pattern_da, P0, direction, s_samples, level, target)
        best = np.argmin(cost, axis=1)
        rows = np.arange(m)
        best_cost = cost[rows, best]
        valid &= (best > 0) & (best < S - 1) & (best_cost < _BAD_COST)
        if full_range:
            # a second local minimum, beyond 2 level-pixels, nearly as good: ambiguous
            interior = np.zeros_like(cost, dtype=bool)
            interior[:, 1:-1] = (cost[:, 1:-1] <= cost[:, :-2]) & (cost[:, 1:-1] <= cost[:, 2:])
            far = np.abs(s_samples - s_samples[rows, best][:, None]) > 2.0 * (2.0**level)[:, None]
            second = np.where(interior & far, cost, _BAD_COST).min(axis=1)
            valid &= second >= best_cost + cfg.ambiguity_margin
            if cfg.ambiguity_ratio is not None:  # ZNCC = 1 - cost; no second minimum scores -3
                valid &= (1.0 - second) < cfg.ambiguity_ratio * (1.0 - best_cost)

        centre, h, (c_minus, c_zero, c_plus), valid = self._refine(
            idx,
            a,
            b,
            nb,
            target,
            P0,
            direction,
            L,
            valid,
            level,
            step,
            s_samples[rows, best],
            (cost[rows, np.maximum(best - 1, 0)], best_cost, cost[rows, np.minimum(best + 1, S - 1)]),
        )

        # sub-pixel: parabola through the three costs around the minimum
        curv = c_minus - 2.0 * c_zero + c_plus
        valid &= curv > 1e-9
        with np.errstate(divide="ignore", invalid="ignore"):
            delta = np.clip(0.5 * (c_minus - c_plus) / curv, -0.5, 0.5)
        s_best = centre + delta * h
        cost_min = c_zero - 0.25 * (c_minus - c_plus) * delta
        valid &= cost_min <= cfg.max_cost
        p_best = P0 + s_best[:, None] * direction
        rho = self._rho_at(a, b, p_best, direction)
        valid &= np.isfinite(rho) & (rho > 0)
        # sigma along the line: curvature term for image noise (ZNCC cost, see module docstring)
        # in quadrature with a floor; then pixels -> inverse depth
        kappa = np.where(curv > 0, curv, np.nan) / (h * h)  # d^2 cost / ds^2 (1/px^2)
        P = PATTERN_DSO8.shape[0]
        ratio = cfg.image_noise_sigma / np.maximum(self.ref_std[idx], 1e-3)
        sigma_px = np.sqrt(cfg.min_sigma_px**2 + ratio**2 * 2.0 / (P * kappa))
        J = self._pixels_per_rho(a, b, np.where(valid, rho, 1.0))
        sigma_rho = sigma_px / np.maximum(J, 1e-12)
        valid &= np.isfinite(sigma_rho)
        return _TraceResult(np.where(valid, rho, np.nan), np.where(valid, sigma_rho, np.inf), cost_min, valid, searched)

    def _segment(self, a, b, lo, hi, shape: tuple[int, int], full_range: bool):
        """The searchable part of each candidate's epipolar line in the target: (start P0, unit
        direction, length L in px, valid). A line is valid when its inverse-depth range is in front
        of both cameras, it crosses the image with the pattern inside, and (full range) it is long
        enough to show parallax; invalid lines get finite placeholders."""
        cfg = self.cfg
        m = len(a)
        lo, hi = lo.astype(np.float64).copy(), hi.astype(np.float64).copy()

        # a prior search spans at least +-min_search_half_width_px around its centre
        if not full_range:
            mid = 0.5 * (lo + hi)
            J = self._pixels_per_rho(a, b, mid)
            half = np.maximum(0.5 * (hi - lo), cfg.min_search_half_width_px / np.maximum(J, 1e-9))
            lo, hi = np.maximum(mid - half, 1e-6), mid + half
        # depth in the neighbour >= min_depth: a_z + rho (b_z - zmin) >= 0 (times rho > 0)
        c1 = b[2] - cfg.min_depth_m
        if c1 > 0:
            lo = np.maximum(lo, -a[:, 2] / c1)
        elif c1 < 0:
            hi = np.minimum(hi, a[:, 2] / -c1)
        valid = (hi > lo) & (a[:, 2] + hi * b[2] > 0)
        p_lo, p_hi = _project(a, b, lo), _project(a, b, hi)
        # clip the segment to the image (Liang-Barsky), keeping the pattern inside
        H, W = shape
        d = p_hi - p_lo
        t0, t1 = np.zeros(m), np.ones(m)
        mg = PATTERN_RADIUS + 1.0
        with np.errstate(divide="ignore", invalid="ignore"):
            for k, lim_lo, lim_hi in ((0, mg, W - 1 - mg), (1, mg, H - 1 - mg)):
                p, dk = p_lo[:, k], d[:, k]
                for q, r in ((-dk, p - lim_lo), (dk, lim_hi - p)):
                    tt = r / q
                    t0 = np.where(q < 0, np.maximum(t0, tt), t0)
                    t1 = np.where(q > 0, np.minimum(t1, tt), t1)
                    valid &= ~((q == 0) & (r < 0))
        valid &= np.isfinite(p_lo).all(1) & np.isfinite(p_hi).all(1) & (t1 > t0)
        P0 = p_lo + t0[:, None] * d
        P1 = p_lo + t1[:, None] * d
        seg = P1 - P0
        L = np.linalg.norm(seg, axis=1)
        valid &= L > 1e-3
        if full_range:
            valid &= cfg.min_epipolar_length_px <= L
        direction = seg / np.maximum(L, 1e-9)[:, None]
        P0[~valid], direction[~valid], L[~valid] = 0.0, 1.0, 1.0  # keep the arithmetic finite
        return P0, direction, L, valid

    def _refine(self, idx, a, b, nb: _Neighbour, target: _Pyramid, P0, direction, L, valid, level, step, centre, costs):
        """Coarse to fine around the coarse minimum ``centre``: halve the step (and the pyramid level)
        until level 0 and <= 0.5 px. Returns (centre, final step h, the costs at centre - h, centre,
        centre + h, valid): a minimum that runs off the refined window is not valid."""
        c_minus, c_zero, c_plus = (c.copy() for c in costs)
        centre, level, valid = centre.copy(), level.copy(), valid.copy()
        h = step.copy()
        todo = valid & ((level > 0) | (step > 0.5))
        offsets = np.arange(-3, 4, dtype=np.float64)
        while todo.any():
            t = np.nonzero(todo)[0]
            level[t] = np.maximum(level[t] - 1, 0)
            h[t] *= 0.5
            s_ref = np.clip(centre[t, None] + h[t, None] * offsets[None, :], 0.0, L[t, None])
            c = self._costs(idx[t], a[t], b, nb.pattern_da, P0[t], direction[t], s_ref, level[t], target)
            j = np.argmin(c, axis=1)
            rt = np.arange(len(t))
            edge = (j == 0) | (j == len(offsets) - 1)
            centre[t] = s_ref[rt, j]
            c_minus[t], c_zero[t], c_plus[t] = (
                c[rt, np.maximum(j - 1, 0)],
                c[rt, j],
                c[rt, np.minimum(j + 1, len(offsets) - 1)],
            )
            valid[t[edge]] = False
            todo[t] = valid[t] & ((level[t] > 0) | (h[t] > 0.5))
        return centre, h, (c_minus, c_zero, c_plus), valid

    @staticmethod
    def _pixels_per_rho(a: np.ndarray, b: np.ndarray, rho: np.ndarray) -> np.ndarray:
        """|d pixel / d rho| on the epipolar line: d/drho (A + rho B)/(C + rho D) = (BC - AD)/(C + rho D)^2."""
        den = (a[:, 2] + rho * b[2]) ** 2
        dx = (b[0] * a[:, 2] - a[:, 0] * b[2]) / den
        dy = (b[1] * a[:, 2] - a[:, 1] * b[2]) / den
        return np.hypot(dx, dy)

    @staticmethod
    def _rho_at(a: np.ndarray, b: np.ndarray, p: np.ndarray, direction: np.ndarray) -> np.ndarray:
        """Inverse depth of a pixel on the epipolar line, from the better-conditioned coordinate."""
        with np.errstate(divide="ignore", invalid="ignore"):
            rx = (a[..., 0] - p[..., 0] * a[..., 2]) / (p[..., 0] * b[2] - b[0])
            ry = (a[..., 1] - p[..., 1] * a[..., 2]) / (p[..., 1] * b[2] - b[1])
        use_x = np.abs(direction[..., 0]) >= np.abs(direction[..., 1])
        return np.where(use_x, rx, ry)

    def _costs(self, idx, a, b, pattern_da, P0, direction, s, level, target: _Pyramid) -> np.ndarray:
        """1 - ZNCC of the warped 8-pixel pattern at line positions ``s`` (m, n) on ``level`` (m,).

        The pattern's rays (keyframe pattern scaled to the level) are taken at the sample's inverse
        depth, i.e. a fronto-parallel patch: tap = (A + rho B) / (C + rho D), with the level scale
        and the atlas offset folded into A and B. Numerators and denominators of all taps come out
        of one batched matrix product [rho, 1] @ [[B], [A]], and the ZNCC sums out of two more,
        which is several times faster than broadcasting; all (m, n, P) arrays are float32.
        """
        f32 = np.float32
        m, n = s.shape
        P = pattern_da.shape[0]
        centre = P0[:, None, :] + s[..., None] * direction[:, None, :]  # (m, n, 2)
        rho = self._rho_at(a[:, None, :], b, centre, direction[:, None, :])  # (m, n)
        bad = ~np.isfinite(rho)
        R1 = np.empty((m, n, 2), f32)
        R1[..., 0] = np.where(bad, 0.0, rho)
        R1[..., 1] = 1.0
        sc = target.scale[level]  # (m,)
        ox = target.offset_x[level]
        ap = a[:, None, :] + (1.0 / sc)[:, None, None] * pattern_da[None]  # (m, P, 3) pattern rays
        C = np.empty((m, 2, 3 * P), f32)
        C[:, 0, :P] = (b[0] * sc + ox * b[2])[:, None]
        C[:, 1, :P] = ap[..., 0] * sc[:, None] + ox[:, None] * ap[..., 2]
        C[:, 0, P : 2 * P] = (b[1] * sc)[:, None]
        C[:, 1, P : 2 * P] = ap[..., 1] * sc[:, None]
        C[:, 0, 2 * P :] = b[2]
        C[:, 1, 2 * P :] = ap[..., 2]
        Hm = np.matmul(R1, C)  # (m, n, 3P): x-numerator, y-numerator, denominator
        # a sample on the neighbour's focal plane projects to infinity: it lands outside the image,
        # remap returns NaN there and the cost rejects it, so the division warning is noise
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = np.reciprocal(Hm[..., 2 * P :])
            x = np.multiply(Hm[..., :P], inv).reshape(m, n * P)
            y = np.multiply(Hm[..., P : 2 * P], inv, out=inv).reshape(m, n * P)
        vals = cv2.remap(
            target.atlas, x, y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan
        ).reshape(m, n, P)
        # ZNCC; the keyframe pattern is zero-mean and unit-norm, so only the target's sums are needed
        Wt = np.empty((m, P, 2), f32)
        Wt[..., 0] = self.ref_norm[idx, level]
        Wt[..., 1] = 1.0
        dot_sum = np.matmul(vals, Wt)  # (m, n, 2)
        sq = np.matmul(np.square(vals), np.ones((P, 1), f32))[..., 0]
        sm = dot_sum[..., 1]
        var = np.maximum(sq - sm * sm / f32(P), f32(1e-6))
        cost = 1.0 - dot_sum[..., 0] / np.sqrt(var)
        cost[bad | ~np.isfinite(cost)] = _BAD_COST
        return cost


# --- a keyframe's candidates, ready to search ------------------------------------------------------------


def _candidate_searcher(
    ref_image: np.ndarray, ref_pyr: _Pyramid, cfg: SearchParams
) -> tuple[np.ndarray, np.ndarray, np.ndarray, _Searcher]:
    """The keyframe's candidates (u, v), their gradients (N, 2), and a searcher holding their
    patterns on every pyramid level (a candidate searches only levels whose pattern is inside)."""
    u, v = select_candidates(ref_image, cfg)
    gx, gy = image_gradients(ref_image)
    g = np.column_stack([gx[v, u], gy[v, u]]).astype(np.float64)
    levels = np.arange(cfg.pyramid_levels)
    offs = PATTERN_DSO8[None, :, :] * (2.0**levels)[:, None, None]  # (L, P, 2)
    px = (u[:, None, None] + offs[None, :, :, 0]).astype(np.float32)
    py = (v[:, None, None] + offs[None, :, :, 1]).astype(np.float32)
    ref_vals = ref_pyr.sample(px, py, levels[None, :, None])
    level_ok = np.isfinite(ref_vals).all(axis=2)
    max_level = np.where(level_ok.all(axis=1), cfg.pyramid_levels - 1, np.argmin(level_ok, axis=1) - 1).astype(np.int64)
    ref_norm, norms = _normalise_patterns(np.nan_to_num(ref_vals))
    ref_std = norms[:, 0] / math.sqrt(PATTERN_DSO8.shape[0])
    return u, v, g, _Searcher(u, v, ref_norm.astype(np.float32), ref_std, np.maximum(max_level, 0), cfg)
