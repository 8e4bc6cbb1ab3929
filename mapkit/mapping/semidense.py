"""Semi-dense mapping with known camera poses: high-gradient pixels triangulated from several frames.

This is the map-construction step of the semi-dense place-recognition pipeline (Sec. 3.1 of the
paper: "any system that tracks and triangulates points with nonzero image gradient", DSO or
LSD-SLAM), reduced to pure geometry because the poses are already known:

1. **Candidates** (DSO: Engel, Koltun, Cremers, TPAMI 2018, "candidate point selection"; its
   ``PixelSelector``): the image is split into 32x32 blocks; a pixel is a candidate when its
   gradient exceeds the block's median gradient plus 7 (thresholds smoothed over 3x3 blocks), so
   texture-poor regions still get points; the strongest pixel per ``cell_size`` cell is kept.
2. **Epipolar search** (the semi-dense depth filter of LSD-SLAM: Engel, Sturm, Cremers, ICCV 2013,
   "Semi-dense visual odometry for a monocular camera"; DSO's immature-point trace): each
   candidate is searched along its epipolar line in the neighbouring frames, nearest baseline
   first. The first search covers the whole inverse-depth range, coarse to fine on an image
   pyramid (so that a long line is sampled at <= 1 pixel of the level it is searched on); every
   later search only covers +-3 sigma of the estimate so far and sharpens it, as in LSD-SLAM's
   inverse-depth filter. The cost is 1 - ZNCC over DSO's 8-pixel pattern, warped to the target
   under a fronto-parallel assumption, so it is blind to exposure changes between frames.
3. **Sub-pixel and uncertainty**: a parabola on the cost curve gives the minimum and the
   curvature; the pixel error along the line is the curvature term for ``image_noise_sigma``
   added in quadrature to a quarter-pixel floor, and is mapped to inverse depth by the line's
   pixels per unit inverse depth. Ambiguous searches (a second local minimum almost as good),
   short lines (small parallax) and lines along the gradient's edge are rejected.
4. **Consistency**: a depth is kept when at least ``min_agreeing_frames`` frames (the keyframe
   plus neighbours whose own match lies within 3 sigma) agree and its relative uncertainty is low.
5. **Fusion**: points of nearby keyframes closer than ``fusion_radius_m`` are fused by greedy
   non-maximum suppression on the depth sigma; the surviving (best-measured) point inherits the
   observations of those it absorbed, so every map point lists every frame that observed it (the
   references that the paper's place voting needs).

Everything is vectorised over candidates (numpy and ``cv2.remap``); there are no per-pixel Python
loops. Frames stream through a small window; no more than ``2 * neighbour_window_frames + 1``
images are held at once.

Frames and units: ``world_from_cam`` maps camera points (x right, y down, z forward, metres) into
the world; ``K`` is the 3x3 pinhole matrix of the (undistorted) images; inverse depth ``rho`` is
1/z in 1/m of the keyframe camera; frame ids are the caller's integers.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Optional, Sequence

import cv2
import numpy as np
from pydantic import Field, model_validator
from scipy.ndimage import uniform_filter
from scipy.spatial import cKDTree

from mapkit.core.config import MapkitConfig, dump_config
from mapkit.core.errors import InputError
from mapkit.core.executor import Executor, get_executor
from mapkit.core.geometry import invert_pose, rotation_angle_rad, transform_points
from mapkit.core.runio import atomic_path, atomic_write_ply, atomic_write_text, progress_bar

#: DSO's residual pattern (``PATTERNP = staticPattern[8]`` in DSO's settings): 8 pixels around
#: the candidate, a diamond of radius 2, offsets (du, dv) in pixels.
PATTERN_DSO8 = np.array([(0, -2), (-1, -1), (1, -1), (-2, 0), (0, 0), (2, 0), (-1, 1), (0, 2)], np.float64)
_PATTERN_RADIUS = 2
_BAD_COST = 4.0  # any cost above the worst ZNCC cost (2): marks invalid samples
_CHUNK = 4096  # candidates per vectorised block: bounds memory at ~100 MB for 32 samples x 8 taps


class SemiDenseConfig(MapkitConfig):
    """Parameters of semi-dense mapping; defaults from DSO and LSD-SLAM where they have one."""

    # --- candidate selection (DSO) ---
    block_size: int = Field(32, ge=4, description="Side (px) of the blocks whose median gradient sets the threshold (DSO candidate selection: 32x32).")
    gradient_threshold_add: float = Field(7.0, ge=0, description="Added to the block median of |gradient| (grey levels per px, central differences) to make the threshold (DSO: g_th = 7, setting_minGradHistAdd).")
    cell_size: int = Field(2, ge=1, description="Keep the strongest candidate per cell of this side (px). DSO picks one per d x d cell with d tuned for ~2000 points; 2 keeps semi-dense density (LSD-SLAM uses every pixel) at a quarter of the cost.")
    max_candidates: Optional[int] = Field(None, ge=1, description="Keep at most this many candidates per keyframe (strongest gradient relative to threshold first); None = no cap.")
    # --- epipolar search ---
    min_depth_m: float = Field(1.0, gt=0, description="Nearest depth searched (m), in the keyframe and every neighbour. A vehicle camera sees nothing closer than its own bonnet.")
    max_depth_m: float = Field(100.0, gt=0, description="Farthest depth searched (m). Beyond ~100 m, baselines of a few metres cannot reach max_rel_sigma anyway.")
    search_samples: int = Field(32, ge=8, description="Samples of the first (full-range) search along the epipolar line, at <= 1 px of the pyramid level it runs on.")
    full_range_attempts: int = Field(1, ge=1, description="Full-range searches tried per candidate (nearest neighbours first) before giving it up; sky and repetitive texture would otherwise pay for a full search in every neighbour.")
    prior_search_samples: int = Field(12, ge=5, description="Samples of a search within +-search_sigmas of an existing estimate.")
    pyramid_levels: int = Field(4, ge=1, le=6, description="Pyramid levels for coarse-to-fine search of long epipolar lines (level l samples every 2^l px); 4 covers lines up to 8*(search_samples-1) px at one level-pixel per sample.")
    search_sigmas: float = Field(3.0, gt=0, description="Half-width (in sigmas) of the search around an existing estimate (LSD-SLAM: STEREO_EPL_VAR_FAC = 2; 3 leaves slack for underestimated sigmas).")
    min_search_half_width_px: float = Field(2.0, ge=0.5, description="A prior search covers at least +-this many pixels, so the cost curve has a shape to fit.")
    min_epipolar_length_px: float = Field(2.0, ge=0, description="Skip a full-range search whose epipolar segment (whole depth range, inside the image) is shorter than this: no parallax (LSD-SLAM: MIN_EPL_LENGTH_SQUARED = 1^2 px; 2 px because the pattern itself spans 4).")
    min_gradient_epipolar_cos: float = Field(0.3, ge=0, le=1, description="Skip a neighbour when |cos| of the angle between the image gradient and the epipolar line is below this: the line runs along the edge (LSD-SLAM MIN_EPL_ANGLE_SQUARED = 0.3^2).")
    max_cost: float = Field(0.3, gt=0, le=2, description="Largest accepted 1 - ZNCC over the 8-pixel pattern (ZNCC >= 0.7).")
    ambiguity_margin: float = Field(0.1, ge=0, description="A full-range search is ambiguous (rejected) when another local minimum, more than 2 level-pixels away, costs less than best + this (in 1 - ZNCC). LSD-SLAM asks the second-best SSD to be 1.5x the best; a ratio is meaningless for ZNCC costs near 0, hence a margin.")
    image_noise_sigma: float = Field(4.0, gt=0, description="Image noise (grey levels) for the photometric part of the matching sigma (LSD-SLAM: cameraPixelNoise2 = 4^2).")
    min_sigma_px: float = Field(0.25, gt=0, description="Floor of the matching sigma along the epipolar line (px): the usual limit of sub-pixel block matching (parabola bias, 'pixel locking').")
    # --- acceptance ---
    min_agreeing_frames: int = Field(3, ge=2, description="Frames (keyframe + neighbours) whose matches agree within agree_sigmas; 3 = 'consistent across more than two frames'.")
    agree_sigmas: float = Field(3.0, gt=0, description="Two inverse-depth estimates agree when they differ by at most this many combined sigmas (3: 99.7% of a Gaussian).")
    max_rel_sigma: float = Field(0.02, gt=0, description="Largest accepted sigma(depth)/depth (= sigma(rho)/rho) of a fused point.")
    max_sigma_depth_m: float = Field(0.3, gt=0, description="Largest accepted sigma of depth (m); keeps far points out of a map whose accuracy goal is a median of 0.15 m.")
    # --- keyframes and neighbours ---
    keyframe_spacing_m: float = Field(1.0, gt=0, description="A frame becomes a keyframe after this much motion since the last keyframe (m).")
    keyframe_rotation_deg: float = Field(10.0, gt=0, description="... or after this much rotation since the last keyframe (deg).")
    neighbour_window_frames: int = Field(3, ge=1, description="Neighbours are the frames up to this many before and after a keyframe (streaming window of 2n+1 images).")
    min_baseline_m: float = Field(0.1, ge=0, description="Neighbours closer than this to the keyframe are not used (no parallax).")
    max_baseline_m: float = Field(10.0, gt=0, description="Neighbours farther than this from the keyframe are not used (little overlap).")
    # --- fusion ---
    fusion_radius_m: float = Field(0.05, gt=0, description="No two map points closer than this (m): the better-measured point absorbs the other's observations. Below the 0.15 m accuracy goal.")
    fusion_window_keyframes: int = Field(10, ge=1, description="A point stays open for fusion until this many keyframes pass without it absorbing a new observation.")

    @model_validator(mode="after")
    def _check(self) -> "SemiDenseConfig":
        if self.max_depth_m <= self.min_depth_m:
            raise ValueError(f"max_depth_m ({self.max_depth_m}) must exceed min_depth_m ({self.min_depth_m})")
        if self.max_baseline_m <= self.min_baseline_m:
            raise ValueError("max_baseline_m must exceed min_baseline_m")
        return self


# --- results ---------------------------------------------------------------------------------------

@dataclass
class KeyframePoints:
    """The accepted depths of one keyframe: pixel, inverse depth, sigma and who agreed."""

    pixels_uv: np.ndarray  # (N, 2) int32, column and row in the keyframe image
    inv_depth: np.ndarray  # (N,) float64, 1/z (1/m) in the keyframe camera
    sigma_inv_depth: np.ndarray  # (N,) float64
    intensity: np.ndarray  # (N,) uint8, keyframe grey value
    neighbour_ids: np.ndarray  # (K,) int64, frame ids of the neighbours searched
    agreed: np.ndarray  # (N, K) bool, which neighbours' matches agreed with the fused depth
    frame_id: int = -1
    stats: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return int(len(self.inv_depth))

    @property
    def depth(self) -> np.ndarray:
        return 1.0 / self.inv_depth

    @property
    def sigma_depth(self) -> np.ndarray:
        """First-order sigma of depth (m): sigma(rho) / rho^2."""
        return self.sigma_inv_depth / self.inv_depth**2

    def points_cam(self, K: np.ndarray) -> np.ndarray:
        uv1 = np.column_stack([self.pixels_uv.astype(np.float64), np.ones(len(self))])
        return (uv1 @ np.linalg.inv(K).T) / self.inv_depth[:, None]

    def points_world(self, K: np.ndarray, world_from_cam: np.ndarray) -> np.ndarray:
        return transform_points(world_from_cam, self.points_cam(K))

    def depth_image(self, shape: tuple[int, int]) -> np.ndarray:
        """(H, W) float64 depth (m) at the accepted pixels, NaN elsewhere."""
        img = np.full(shape, np.nan)
        img[self.pixels_uv[:, 1], self.pixels_uv[:, 0]] = self.depth
        return img


@dataclass
class SemiDenseMap:
    """A fused semi-dense point map; each point lists every frame that observed it (CSR)."""

    points_world: np.ndarray  # (N, 3) float64
    intensity: np.ndarray  # (N,) uint8
    sigma_depth: np.ndarray  # (N,) float32, m, along the source keyframe's ray
    source_keyframe: np.ndarray  # (N,) int64, frame id of the keyframe whose estimate the point is
    obs_indptr: np.ndarray  # (N+1,) int64
    obs_frame_ids: np.ndarray  # (M,) int64, sorted within each point
    keyframe_ids: np.ndarray  # (F,) int64
    keyframe_stamps_ns: np.ndarray  # (F,) int64
    keyframe_world_from_cam: np.ndarray  # (F, 4, 4)
    K: np.ndarray  # (3, 3)
    image_size_wh: tuple[int, int]
    config: Optional[SemiDenseConfig] = None
    #: every frame the map was built from, keyframe or not: (T,) ids and their stamps, so that a
    #: frame's pose can be interpolated between keyframes over time (absent in maps saved before)
    frame_ids: Optional[np.ndarray] = None
    frame_stamps_ns: Optional[np.ndarray] = None

    def __len__(self) -> int:
        return int(len(self.points_world))

    def observations(self, i: int) -> np.ndarray:
        """Frame ids that observed point ``i``."""
        return self.obs_frame_ids[self.obs_indptr[i] : self.obs_indptr[i + 1]]

    @property
    def obs_counts(self) -> np.ndarray:
        return np.diff(self.obs_indptr)

    def obs_point_index(self) -> np.ndarray:
        """(M,) point index of each entry of ``obs_frame_ids``."""
        return np.repeat(np.arange(len(self)), self.obs_counts)

    def stats(self) -> dict:
        c = self.obs_counts
        path_m = float(np.linalg.norm(np.diff(self.keyframe_world_from_cam[:, :3, 3], axis=0), axis=1).sum()) if len(self.keyframe_ids) > 1 else 0.0
        return {
            "points": len(self),
            "keyframes": int(len(self.keyframe_ids)),
            "keyframe_path_m": path_m,
            "points_per_100m": len(self) / path_m * 100.0 if path_m > 0 else None,
            "observations": int(c.sum()),
            "obs_per_point_median": float(np.median(c)) if len(c) else None,
            "sigma_depth_median_m": float(np.median(self.sigma_depth)) if len(c) else None,
        }

    def save(self, folder: str | Path, frame=None) -> Path:
        """Write ``points.ply`` (binary, float64 xyz, grey colour), ``observations.npz`` and
        ``config.yaml`` into ``folder``, each file atomically. Returns ``folder``. ``frame``: the
        :class:`~mapkit.core.geodesy.LocalFrame` whose ENU the points are in, stated in the PLY header."""
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        grey = np.repeat(self.intensity.astype(np.float64)[:, None] / 255.0, 3, axis=1)
        atomic_write_ply(folder / "points.ply", self.points_world, grey, frame=frame)
        with atomic_path(folder / "observations.npz") as tmp:
            with open(tmp, "wb") as f:
                np.savez(
                    f,
                    obs_indptr=self.obs_indptr, obs_frame_ids=self.obs_frame_ids, source_keyframe=self.source_keyframe,
                    sigma_depth=self.sigma_depth, intensity=self.intensity, keyframe_ids=self.keyframe_ids,
                    keyframe_stamps_ns=self.keyframe_stamps_ns, keyframe_world_from_cam=self.keyframe_world_from_cam,
                    K=self.K, image_size_wh=np.asarray(self.image_size_wh, np.int64),
                    **({} if self.frame_ids is None else {"frame_ids": np.asarray(self.frame_ids, np.int64),
                                                          "frame_stamps_ns": np.asarray(self.frame_stamps_ns, np.int64)}),
                )
        if self.config is not None:
            atomic_write_text(folder / "config.yaml", dump_config(self.config))
        return folder

    @classmethod
    def load(cls, folder: str | Path) -> "SemiDenseMap":
        import open3d as o3d
        import yaml

        folder = Path(folder)
        for name in ("points.ply", "observations.npz"):
            if not (folder / name).is_file():
                raise InputError(folder / name, "no such file (not a semi-dense map folder?)")
        pts = np.asarray(o3d.io.read_point_cloud(str(folder / "points.ply"), format="ply").points, np.float64)
        with np.load(folder / "observations.npz") as z:
            d = {k: z[k] for k in z.files}
        if len(d["obs_indptr"]) != len(pts) + 1:
            raise InputError(folder / "observations.npz", f"{len(d['obs_indptr']) - 1} points, but points.ply has {len(pts)}")
        cfg = None
        if (folder / "config.yaml").is_file():
            cfg = SemiDenseConfig.model_validate(yaml.safe_load((folder / "config.yaml").read_text()))
        return cls(
            points_world=pts, intensity=d["intensity"], sigma_depth=d["sigma_depth"], source_keyframe=d["source_keyframe"],
            obs_indptr=d["obs_indptr"], obs_frame_ids=d["obs_frame_ids"], keyframe_ids=d["keyframe_ids"],
            keyframe_stamps_ns=d["keyframe_stamps_ns"], keyframe_world_from_cam=d["keyframe_world_from_cam"],
            K=d["K"], image_size_wh=tuple(int(x) for x in d["image_size_wh"]), config=cfg,
            frame_ids=d.get("frame_ids"), frame_stamps_ns=d.get("frame_stamps_ns"),
        )


# --- candidate selection ---------------------------------------------------------------------------

def image_gradients(gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Central-difference gradients (grey levels per pixel) as DSO computes them; 0 on the border."""
    img = np.asarray(gray, np.float32)
    gx = np.zeros_like(img)
    gy = np.zeros_like(img)
    gx[:, 1:-1] = 0.5 * (img[:, 2:] - img[:, :-2])
    gy[1:-1, :] = 0.5 * (img[2:, :] - img[:-2, :])
    return gx, gy


def gradient_threshold(grad_mag: np.ndarray, cfg: SemiDenseConfig) -> np.ndarray:
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


def select_candidates(gray: np.ndarray, cfg: SemiDenseConfig, border: int = _PATTERN_RADIUS + 1) -> tuple[np.ndarray, np.ndarray]:
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
    out = cv2.remap(img, fx.reshape(rows, cols), fy.reshape(rows, cols), cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
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
        imgs = [np.asarray(gray, np.float32) - 128.0]
        for _ in range(1, levels):
            imgs.append(cv2.pyrDown(imgs[-1]))
        offsets, x = [], 0
        for im in imgs:
            offsets.append(x)
            x += im.shape[1] + self.GAP
        self.atlas = np.full((imgs[0].shape[0] + self.GAP, x), np.nan, np.float32)
        for o, im in zip(offsets, imgs):
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


def _neighbour_geometry(index: int, ref_world_from_cam: np.ndarray, world_from_cam: np.ndarray, K: np.ndarray) -> _Neighbour:
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

    def __init__(self, ref_u: np.ndarray, ref_v: np.ndarray, ref_norm: np.ndarray, ref_std: np.ndarray, max_level: np.ndarray, cfg: SemiDenseConfig):
        self.u = ref_u.astype(np.float64)
        self.v = ref_v.astype(np.float64)
        self.ref_norm = ref_norm  # (M, L, P) zero-mean unit-norm pattern per level
        self.ref_std = ref_std  # (M,) grey-level std of the level-0 pattern
        self.max_level = max_level  # (M,) deepest level whose ref pattern lies inside the image
        self.cfg = cfg

    def trace(self, idx: np.ndarray, lo: np.ndarray, hi: np.ndarray, nb: _Neighbour, target: _Pyramid, samples: int, full_range: bool) -> _TraceResult:
        n = len(idx)
        out = _TraceResult(np.full(n, np.nan), np.full(n, np.inf), np.full(n, _BAD_COST), np.zeros(n, bool), np.zeros(n, bool))
        for s in range(0, n, _CHUNK):
            sl = slice(s, s + _CHUNK)
            r = self._trace_chunk(idx[sl], lo[sl], hi[sl], nb, target, samples, full_range)
            out.rho[sl], out.sigma_rho[sl], out.cost[sl], out.ok[sl], out.searched[sl] = r.rho, r.sigma_rho, r.cost, r.ok, r.searched
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
            far = np.abs(s_samples - s_samples[rows, best][:, None]) > 2.0 * (2.0 ** level)[:, None]
            second = np.where(interior & far, cost, _BAD_COST).min(axis=1)
            valid &= second >= best_cost + cfg.ambiguity_margin

        centre, h, (c_minus, c_zero, c_plus), valid = self._refine(
            idx, a, b, nb, target, P0, direction, L, valid, level, step, s_samples[rows, best],
            (cost[rows, np.maximum(best - 1, 0)], best_cost, cost[rows, np.minimum(best + 1, S - 1)]))

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
        mg = _PATTERN_RADIUS + 1.0
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
            valid &= L >= cfg.min_epipolar_length_px
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
            c_minus[t], c_zero[t], c_plus[t] = c[rt, np.maximum(j - 1, 0)], c[rt, j], c[rt, np.minimum(j + 1, len(offsets) - 1)]
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
        vals = cv2.remap(target.atlas, x, y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan).reshape(m, n, P)
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


# --- one keyframe ------------------------------------------------------------------------------------------

def _candidate_searcher(ref_image: np.ndarray, ref_pyr: _Pyramid, cfg: SemiDenseConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray, _Searcher]:
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


def _accepted(rho: np.ndarray, sigma: np.ndarray, agreed: np.ndarray, cfg: SemiDenseConfig) -> np.ndarray:
    """Candidates whose depth enough frames agree on, inside the depth range and sharp enough."""
    rho_min, rho_max = 1.0 / cfg.max_depth_m, 1.0 / cfg.min_depth_m
    n_frames = 1 + agreed.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return (
            np.isfinite(rho)
            & (n_frames >= cfg.min_agreeing_frames)
            & (rho >= rho_min) & (rho <= rho_max)
            & (sigma <= cfg.max_rel_sigma * rho)
            & (sigma <= cfg.max_sigma_depth_m * rho**2)
        )


def map_keyframe(
    ref_image: np.ndarray,
    ref_world_from_cam: np.ndarray,
    neighbours: Sequence[tuple[np.ndarray, np.ndarray]],
    K: np.ndarray,
    cfg: Optional[SemiDenseConfig] = None,
    *,
    frame_id: int = -1,
    neighbour_ids: Optional[Sequence[int]] = None,
    ref_pyramid: Optional[_Pyramid] = None,
    neighbour_pyramids: Optional[Sequence[_Pyramid]] = None,
) -> KeyframePoints:
    """Semi-dense depths of one keyframe from neighbouring frames of known pose.

    ``ref_image`` and each neighbour image are (H, W) grey images (uint8 or float); poses are
    ``world_from_cam`` 4x4. Returns the accepted candidates with inverse depth, sigma and the
    neighbours that agreed (a point needs ``cfg.min_agreeing_frames - 1`` of them).
    Pyramids may be passed in to reuse them across keyframes (``build_semidense_map`` does).
    """
    cfg = cfg or SemiDenseConfig()
    K = np.asarray(K, np.float64)
    ref_image = np.asarray(ref_image)
    if ref_image.ndim != 2:
        raise ValueError(f"map_keyframe needs a (H, W) grey image, got shape {ref_image.shape}")
    ids = np.asarray(neighbour_ids if neighbour_ids is not None else np.arange(len(neighbours)), np.int64)
    ref_pyr = ref_pyramid or _Pyramid(ref_image, cfg.pyramid_levels)
    nb_pyrs = list(neighbour_pyramids) if neighbour_pyramids is not None else [_Pyramid(img, cfg.pyramid_levels) for img, _ in neighbours]
    for (img, _), pyr in zip(neighbours, nb_pyrs):
        if pyr.shape != ref_pyr.shape:
            raise ValueError(f"neighbour image shape {pyr.shape} differs from the keyframe's {ref_pyr.shape}")

    u, v, g, searcher = _candidate_searcher(ref_image, ref_pyr, cfg)
    n_cand = len(u)

    geoms = [_neighbour_geometry(i, ref_world_from_cam, T, K) for i, (_, T) in enumerate(neighbours)]
    geoms = [n for n in geoms if cfg.min_baseline_m <= n.baseline_m <= cfg.max_baseline_m]
    geoms.sort(key=lambda n: n.baseline_m)  # nearest first: short lines, then sharpen

    rho_min, rho_max = 1.0 / cfg.max_depth_m, 1.0 / cfg.min_depth_m
    rho = np.full(n_cand, np.nan)
    var = np.full(n_cand, np.inf)
    agreed = np.zeros((n_cand, len(neighbours)), bool)
    attempts = np.zeros(n_cand, np.int64)
    n_searched = n_full = n_prior = 0
    for nb in geoms:
        # the epipolar line in the keyframe runs from the epipole through the pixel
        e = nb.epipole_h
        line = np.column_stack([u * e[2] - e[0], v * e[2] - e[1]])
        with np.errstate(invalid="ignore", divide="ignore"):
            cos = np.abs((line * g).sum(1)) / (np.linalg.norm(line, axis=1) * np.linalg.norm(g, axis=1))
        usable = np.nan_to_num(cos) >= cfg.min_gradient_epipolar_cos
        has = np.isfinite(rho)
        tgt = nb_pyrs[nb.index]
        # no estimate yet: full-range search with the ambiguity test
        ia = np.nonzero(usable & ~has & (attempts < cfg.full_range_attempts))[0]
        n_full += len(ia)
        if len(ia):
            r = searcher.trace(ia, np.full(len(ia), rho_min), np.full(len(ia), rho_max), nb, tgt, cfg.search_samples, True)
            attempts[ia[r.searched]] += 1  # a line outside this neighbour's view is no attempt
            k = ia[r.ok]
            rho[k], var[k] = r.rho[r.ok], r.sigma_rho[r.ok] ** 2
            agreed[k, nb.index] = True
        # estimate so far: search within +-search_sigmas, then fuse where it agrees (LSD-SLAM-style update)
        ib = np.nonzero(usable & has)[0]
        n_prior += len(ib)
        if len(ib):
            sd = np.sqrt(var[ib])
            lo = np.clip(rho[ib] - cfg.search_sigmas * sd, rho_min, rho_max)
            hi = np.clip(rho[ib] + cfg.search_sigmas * sd, rho_min, rho_max)
            r = searcher.trace(ib, lo, hi, nb, tgt, cfg.prior_search_samples, False)
            s2 = r.sigma_rho**2
            agree = r.ok & (np.abs(r.rho - rho[ib]) <= cfg.agree_sigmas * np.sqrt(var[ib] + s2))
            k = ib[agree]
            w_old, w_new = 1.0 / var[k], 1.0 / s2[agree]
            rho[k] = (rho[k] * w_old + r.rho[agree] * w_new) / (w_old + w_new)
            var[k] = 1.0 / (w_old + w_new)
            agreed[k, nb.index] = True
        n_searched += 1

    sigma = np.sqrt(var)
    keep = _accepted(rho, sigma, agreed, cfg)
    img = np.asarray(ref_image)
    intensity = np.clip(img[v[keep], u[keep]], 0, 255).astype(np.uint8)
    return KeyframePoints(
        pixels_uv=np.column_stack([u[keep], v[keep]]).astype(np.int32),
        inv_depth=rho[keep],
        sigma_inv_depth=sigma[keep],
        intensity=intensity,
        neighbour_ids=ids,
        agreed=agreed[keep],
        frame_id=int(frame_id),
        stats={
            "candidates": int(n_cand), "with_estimate": int(np.isfinite(rho).sum()), "accepted": int(keep.sum()),
            "neighbours_searched": n_searched, "full_range_searches": n_full, "prior_searches": n_prior,
        },
    )


# --- fusion --------------------------------------------------------------------------------------------------

def greedy_nms(points: np.ndarray, priority: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Keep points so that no two kept ones are within ``radius``, best (lowest) priority first.

    Returns ``keep`` (N,) bool and ``target`` (N,) int: the index of the kept point that each
    point merges into (itself when kept; the nearest kept point within ``radius`` otherwise).
    The result equals sequential greedy suppression in priority order, computed in parallel
    rounds: each round keeps every undecided point that beats all its undecided neighbours.
    """
    n = len(points)
    target = np.arange(n)
    if n == 0:
        return np.zeros(0, bool), target
    pairs = cKDTree(points).query_pairs(radius, output_type="ndarray")
    if len(pairs) == 0:
        return np.ones(n, bool), target
    rank = np.empty(n, np.int64)
    rank[np.lexsort((np.arange(n), priority))] = np.arange(n)
    i = np.concatenate([pairs[:, 0], pairs[:, 1]])
    j = np.concatenate([pairs[:, 1], pairs[:, 0]])
    order = np.argsort(i, kind="stable")
    i, j = i[order], j[order]
    starts = np.flatnonzero(np.r_[True, i[1:] != i[:-1]])
    nodes = i[starts]
    UNDECIDED, KEPT, SUPPRESSED = 0, 1, 2
    state = np.zeros(n, np.int8)
    isolated = np.ones(n, bool)
    isolated[nodes] = False
    state[isolated] = KEPT
    while True:
        und = state == UNDECIDED
        if not und.any():
            break
        nb_rank = np.where(und[j], rank[j], np.iinfo(np.int64).max)
        best_nb = np.full(n, np.iinfo(np.int64).max)
        best_nb[nodes] = np.minimum.reduceat(nb_rank, starts)
        newly = und & (rank < best_nb)
        state[newly] = KEPT
        hit = newly[i] & (state[j] == UNDECIDED)
        state[j[hit]] = SUPPRESSED
    keep = state == KEPT
    m = (state[i] == SUPPRESSED) & (state[j] == KEPT)
    si, kj = i[m], j[m]
    d = np.linalg.norm(points[si] - points[kj], axis=1)
    o = np.lexsort((d, si))
    si, kj = si[o], kj[o]
    first = np.r_[True, si[1:] != si[:-1]]
    target[si[first]] = kj[first]
    return keep, target


class _Fuser:
    """Streaming duplicate fusion: recent points stay open; old ones are finalised."""

    def __init__(self, radius: float, window: int):
        self.radius = radius
        self.window = window
        self.counter = 0
        self.open = self._empty()
        self.done: list[dict] = []

    @staticmethod
    def _empty() -> dict:
        return {
            "xyz": np.zeros((0, 3)), "sigma": np.zeros(0, np.float32), "intensity": np.zeros(0, np.uint8),
            "source": np.zeros(0, np.int64), "touched": np.zeros(0, np.int64),
            "obs_pt": np.zeros(0, np.int64), "obs_fid": np.zeros(0, np.int64),
        }

    def add(self, xyz, sigma, intensity, source_id: int, obs_pt, obs_fid) -> None:
        o = self.open
        n_old = len(o["xyz"])
        xyz_all = np.vstack([o["xyz"], xyz])
        sigma_all = np.concatenate([o["sigma"], sigma.astype(np.float32)])
        touched = np.concatenate([o["touched"], np.full(len(xyz), self.counter, np.int64)])
        keep, target = greedy_nms(xyz_all, sigma_all, self.radius)
        np.maximum.at(touched, target, touched.copy())
        new_index = np.cumsum(keep) - 1
        pt = new_index[target[np.concatenate([o["obs_pt"], obs_pt + n_old])]]
        fid = np.concatenate([o["obs_fid"], obs_fid])
        order = np.lexsort((fid, pt))  # unique (point, frame) pairs, sorted
        pt, fid = pt[order], fid[order]
        first = np.ones(len(pt), bool)  # also right when nothing is open and nothing came in
        first[1:] = (pt[1:] != pt[:-1]) | (fid[1:] != fid[:-1])
        pairs = np.column_stack([pt[first], fid[first]])
        merged = {
            "xyz": xyz_all[keep], "sigma": sigma_all[keep],
            "intensity": np.concatenate([o["intensity"], intensity])[keep],
            "source": np.concatenate([o["source"], np.full(len(xyz), source_id, np.int64)])[keep],
            "touched": touched[keep], "obs_pt": pairs[:, 0], "obs_fid": pairs[:, 1],
        }
        self.open = merged
        self.counter += 1
        self._finalise(self.counter - 1 - self.window)

    def _finalise(self, older_than: int) -> None:
        o = self.open
        old = o["touched"] < older_than
        if not old.any():
            return
        self.done.append(self._take(o, old))
        self.open = self._take(o, ~old)

    @staticmethod
    def _take(o: dict, sel: np.ndarray) -> dict:
        new_index = np.cumsum(sel) - 1
        m = sel[o["obs_pt"]]
        out = {k: o[k][sel] for k in ("xyz", "sigma", "intensity", "source", "touched")}
        out["obs_pt"] = new_index[o["obs_pt"][m]]
        out["obs_fid"] = o["obs_fid"][m]
        return out

    def finish(self) -> dict:
        self._finalise(np.iinfo(np.int64).max)
        parts = self.done or [self._empty()]
        offsets = np.cumsum([0] + [len(p["xyz"]) for p in parts])
        out = {k: np.concatenate([p[k] for p in parts]) for k in ("xyz", "sigma", "intensity", "source")}
        obs_pt = np.concatenate([p["obs_pt"] + off for p, off in zip(parts, offsets)])
        obs_fid = np.concatenate([p["obs_fid"] for p in parts])
        o = np.lexsort((obs_fid, obs_pt))
        out["obs_fid"] = obs_fid[o]
        out["indptr"] = np.r_[0, np.cumsum(np.bincount(obs_pt, minlength=len(out["xyz"])))].astype(np.int64)
        return out


# --- the map of a drive ---------------------------------------------------------------------------------

@dataclass
class _Buffered:
    frame_id: int
    stamp_ns: int
    image: np.ndarray
    world_from_cam: np.ndarray
    is_keyframe: bool
    pyramid: Optional[_Pyramid] = None


@dataclass
class _KeyframeTask:
    """One keyframe's work: its image and pose, its neighbours', and (in this process) their pyramids."""

    frame_id: int
    stamp_ns: int
    image: np.ndarray
    world_from_cam: np.ndarray
    neighbours: list[tuple[np.ndarray, np.ndarray]]
    neighbour_ids: list[int]
    pyramid: Optional[_Pyramid] = None
    neighbour_pyramids: Optional[list[_Pyramid]] = None


def _map_keyframe_task(shared: tuple[np.ndarray, SemiDenseConfig], t: _KeyframeTask) -> tuple[int, int, np.ndarray, KeyframePoints]:
    K, cfg = shared
    pts = map_keyframe(t.image, t.world_from_cam, t.neighbours, K, cfg, frame_id=t.frame_id, neighbour_ids=t.neighbour_ids,
                       ref_pyramid=t.pyramid, neighbour_pyramids=t.neighbour_pyramids)
    return t.frame_id, t.stamp_ns, t.world_from_cam, pts


def _checked_frame(frame_id: int, gray, world_from_cam, image_shape: Optional[tuple[int, int]]) -> tuple[np.ndarray, np.ndarray]:
    """(grey image, pose) of one input frame, or an error naming the frame: a (H, W) image of the
    first frame's shape and a finite 4x4 pose."""
    gray = np.asarray(gray)
    T = np.asarray(world_from_cam, np.float64)
    if gray.ndim != 2:
        raise InputError(None, f"frame {frame_id}: expected a (H, W) grey image, got shape {gray.shape}")
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise InputError(None, f"frame {frame_id}: world_from_cam must be a finite 4x4 matrix")
    if image_shape is not None and gray.shape != image_shape:
        raise InputError(None, f"frame {frame_id}: image shape {gray.shape} differs from the first frame's {image_shape}")
    return gray, T


def _is_keyframe(last_kf: Optional[np.ndarray], world_from_cam: np.ndarray, cfg: SemiDenseConfig) -> bool:
    """The first frame, and a frame that moved or turned enough since the last keyframe."""
    if last_kf is None:
        return True
    rel = invert_pose(last_kf) @ world_from_cam
    angle_deg = float(np.degrees(rotation_angle_rad(rel[:3, :3])))
    return bool(np.linalg.norm(rel[:3, 3]) >= cfg.keyframe_spacing_m or angle_deg >= cfg.keyframe_rotation_deg)


def build_semidense_map(
    frames: Iterable[tuple[int, int, np.ndarray, np.ndarray]],
    K: np.ndarray,
    cfg: Optional[SemiDenseConfig] = None,
    progress: bool = True,
    on_keyframe: Optional[Callable[[int, np.ndarray, KeyframePoints], None]] = None,
    executor: Optional[Executor] = None,
) -> SemiDenseMap:
    """Semi-dense map of a drive from ``(frame_id, stamp_ns, gray (H, W), world_from_cam 4x4)``.

    Frames stream through a window of ``2 * neighbour_window_frames + 1`` images: a keyframe
    (chosen by motion) is mapped once the frames after it have arrived, against the frames up to
    ``neighbour_window_frames`` before and after it. ``on_keyframe(frame_id, world_from_cam,
    points)`` is called with each keyframe's own accepted depths (e.g. for ``consistency``).

    Keyframes are mapped on ``executor`` (default: :func:`mapkit.core.executor.get_executor`), a few
    per worker at a time, and fused here in keyframe order, so the map is the same bit for bit on
    any executor. In this process the image pyramids are shared between neighbouring keyframes;
    workers elsewhere receive the images and build their own.
    """
    cfg = cfg or SemiDenseConfig()
    K = np.asarray(K, np.float64)
    executor = executor or get_executor()
    W = cfg.neighbour_window_frames
    fuser = _Fuser(cfg.fusion_radius_m, cfg.fusion_window_keyframes)
    kf_ids, kf_stamps, kf_poses = [], [], []
    all_ids, all_stamps = [], []
    image_shape: Optional[tuple[int, int]] = None
    total = len(frames) if hasattr(frames, "__len__") else None  # type: ignore[arg-type]
    bar = progress_bar(total, progress, desc="semi-dense", unit="frame")

    def task(window: deque[_Buffered], center: int) -> _KeyframeTask:
        kf = window[center]
        nbs = [f for k, f in enumerate(window) if k != center and abs(k - center) <= W]
        t = _KeyframeTask(kf.frame_id, kf.stamp_ns, kf.image, kf.world_from_cam, [(f.image, f.world_from_cam) for f in nbs],
                          [f.frame_id for f in nbs])
        if executor.in_process:  # a frame's pyramid serves every keyframe whose window holds it
            for f in (kf, *nbs):
                if f.pyramid is None:
                    f.pyramid = _Pyramid(f.image, cfg.pyramid_levels)
            t.pyramid, t.neighbour_pyramids = kf.pyramid, [f.pyramid for f in nbs]
        return t

    def keyframe_tasks() -> Iterator[_KeyframeTask]:
        nonlocal image_shape
        window: deque[_Buffered] = deque()
        last_kf: Optional[np.ndarray] = None
        for frame_id, stamp_ns, gray, world_from_cam in frames:
            bar.update(1)
            gray, T = _checked_frame(frame_id, gray, world_from_cam, image_shape)
            if image_shape is None:
                image_shape = gray.shape
            is_kf = _is_keyframe(last_kf, T, cfg)
            if is_kf:
                last_kf = T
            window.append(_Buffered(int(frame_id), int(stamp_ns), gray, T, bool(is_kf)))
            all_ids.append(int(frame_id))
            all_stamps.append(int(stamp_ns))
            del gray
            # the frame W places back now has all its neighbours
            if len(window) > W and window[-1 - W].is_keyframe:
                yield task(window, len(window) - 1 - W)
            while len(window) > 2 * W + 1:
                window.popleft()
        # keyframes among the last W frames: map with the frames that exist
        for k in range(max(len(window) - W, 0), len(window)):
            if window[k].is_keyframe:
                yield task(window, k)

    results = executor.map(_map_keyframe_task, keyframe_tasks(), shared=(K, cfg), desc="semi-dense keyframes",
                           label=lambda t: f"keyframe {t.frame_id}")
    try:
        for frame_id, stamp_ns, world_from_cam, pts in results:
            if on_keyframe is not None:
                on_keyframe(frame_id, world_from_cam, pts)
            kf_ids.append(frame_id)
            kf_stamps.append(stamp_ns)
            kf_poses.append(world_from_cam)
            obs_pt = np.concatenate([np.arange(len(pts)), np.nonzero(pts.agreed)[0]])
            obs_fid = np.concatenate([np.full(len(pts), frame_id, np.int64), pts.neighbour_ids[np.nonzero(pts.agreed)[1]]])
            fuser.add(pts.points_world(K, world_from_cam), pts.sigma_depth, pts.intensity, frame_id, obs_pt, obs_fid)
            if progress:
                bar.set_postfix(keyframes=len(kf_ids), points=len(fuser.open["xyz"]) + sum(len(d["xyz"]) for d in fuser.done))
    finally:
        results.close()
        bar.close()

    out = fuser.finish()
    h, w = image_shape if image_shape is not None else (0, 0)
    return SemiDenseMap(
        points_world=out["xyz"].astype(np.float64),
        intensity=out["intensity"].astype(np.uint8),
        sigma_depth=out["sigma"].astype(np.float32),
        source_keyframe=out["source"].astype(np.int64),
        obs_indptr=out["indptr"],
        obs_frame_ids=out["obs_fid"].astype(np.int64),
        keyframe_ids=np.asarray(kf_ids, np.int64),
        keyframe_stamps_ns=np.asarray(kf_stamps, np.int64),
        keyframe_world_from_cam=np.asarray(kf_poses, np.float64).reshape(-1, 4, 4),
        K=K,
        image_size_wh=(int(w), int(h)),
        config=cfg,
        frame_ids=np.asarray(all_ids, np.int64),
        frame_stamps_ns=np.asarray(all_stamps, np.int64),
    )


# --- cross-frame consistency -------------------------------------------------------------------------------

def consistency(
    sd_map: SemiDenseMap,
    keyframes: Iterable[tuple[int, np.ndarray, KeyframePoints]],
    *,
    max_pixel_distance: float = 1.0,
    baseline_bins_m: Sequence[float] = (0.0, 2.0, 5.0, 10.0, np.inf),
) -> dict:
    """How well map points agree with the depths other keyframes estimated on their own.

    Every map point is reprojected into every keyframe ``(frame_id, world_from_cam, points)``
    other than its source keyframe; where that keyframe has its own accepted depth at the nearest
    pixel (within ``max_pixel_distance``, chosen by image distance only, never by depth), the
    relative disagreement |z_map - z_own| / z_own is recorded. ``median_rel`` over all such pairs
    is the headline figure. Occlusion (the map point hidden behind what the keyframe sees) and
    chance hits on unrelated structure make the tail, and both grow with the distance between
    the two keyframes, hence the breakdown by that distance and by sign ("map nearer" than the
    keyframe's own depth violates free space; "map farther" is mostly occlusion).
    """
    K = sd_map.K
    w, h = sd_map.image_size_wh
    kf_centre = dict(zip(sd_map.keyframe_ids.tolist(), sd_map.keyframe_world_from_cam[:, :3, 3]))
    src_centre = np.array([kf_centre.get(int(s), np.full(3, np.nan)) for s in sd_map.source_keyframe]).reshape(-1, 3)
    signed: list[np.ndarray] = []
    baseline: list[np.ndarray] = []
    projected = 0
    frames_used = 0
    offsets = [(dx, dy) for dy in (-1, 0, 1) for dx in (-1, 0, 1)]
    for fid, world_from_cam, pts in keyframes:
        own = pts.depth_image((h, w))
        sel = np.nonzero(sd_map.source_keyframe != fid)[0]
        X = transform_points(invert_pose(world_from_cam), sd_map.points_world[sel])
        front = X[:, 2] > 1e-3
        sel, X = sel[front], X[front]
        uvw = X @ K.T
        x, y = uvw[:, 0] / uvw[:, 2], uvw[:, 1] / uvw[:, 2]
        inside = (x > -0.5) & (x < w - 0.5) & (y > -0.5) & (y < h - 0.5)
        sel, x, y, z = sel[inside], x[inside], y[inside], X[inside, 2]
        projected += len(z)
        if len(z) == 0:
            continue
        xi, yi = np.rint(x).astype(np.int64), np.rint(y).astype(np.int64)
        best_d2 = np.full(len(z), np.inf)
        best_z = np.full(len(z), np.nan)
        for dx, dy in offsets:
            cx, cy = xi + dx, yi + dy
            ok = (cx >= 0) & (cx < w) & (cy >= 0) & (cy < h)
            zz = np.full(len(z), np.nan)
            zz[ok] = own[cy[ok], cx[ok]]
            d2 = (cx - x) ** 2 + (cy - y) ** 2
            better = np.isfinite(zz) & (d2 <= max_pixel_distance**2) & (d2 < best_d2)
            best_d2[better], best_z[better] = d2[better], zz[better]
        m = np.isfinite(best_z)
        if m.any():
            signed.append((z[m] - best_z[m]) / best_z[m])
            baseline.append(np.linalg.norm(src_centre[sel[m]] - world_from_cam[:3, 3], axis=1))
            frames_used += 1
    r = np.concatenate(signed) if signed else np.zeros(0)
    b = np.concatenate(baseline) if baseline else np.zeros(0)
    out: dict[str, Any] = {"pairs": int(len(r)), "frames": frames_used, "projected": int(projected)}
    if len(r) == 0:
        return {**out, "median_rel": None}
    a = np.abs(r)
    out.update(
        hit_rate=len(r) / projected,
        median_rel=float(np.median(a)),
        p75_rel=float(np.percentile(a, 75)),
        p90_rel=float(np.percentile(a, 90)),
        frac_below_5pct=float(np.mean(a < 0.05)),
        frac_map_nearer_5pct=float(np.mean(r < -0.05)),
        frac_map_farther_5pct=float(np.mean(r > 0.05)),
        by_keyframe_distance_m=[
            {"from_m": float(lo), "to_m": float(hi) if np.isfinite(hi) else None, "pairs": int(sel.sum()),
             "median_rel": float(np.median(a[sel])) if sel.any() else None,
             "frac_below_5pct": float(np.mean(a[sel] < 0.05)) if sel.any() else None}
            for lo, hi in zip(baseline_bins_m[:-1], baseline_bins_m[1:])
            for sel in [(b >= lo) & (b < hi)]
        ],
    )
    return out
