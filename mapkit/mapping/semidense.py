"""Semi-dense mapping with known camera poses: high-gradient pixels triangulated from several frames.

This is the map-construction step of the semi-dense place-recognition pipeline (Sec. 3.1 of the
paper: "any system that tracks and triangulates points with nonzero image gradient", DSO or
LSD-SLAM), reduced to pure geometry because the poses are already known:

0. **Rotations** (:mod:`.pose_refine`, optional: ``refine_rotations``): each frame's camera rotation
   refined on its given position against corners tracked into the next frames (their epipolar distances,
   a sliding window), for poses whose rotations disagree with the images by tenths of a degree.
1. **Candidates** (:mod:`.semidense_candidates`, after DSO's candidate point selection: Engel,
   Koltun, Cremers, TPAMI 2018): pixels whose gradient beats a block-adaptive threshold, the
   strongest per ``cell_size`` cell, so texture-poor regions still get points.
2. **Epipolar search** and 3. **sub-pixel depth and uncertainty** (:mod:`.semidense_epipolar`,
   after the semi-dense depth filter of LSD-SLAM: Engel, Sturm, Cremers, ICCV 2013, and DSO's
   immature-point trace): each candidate is searched along its epipolar line in the neighbouring
   frames, nearest baseline first, full range and coarse to fine the first time, then within
   +-3 sigma of the estimate so far; the cost is 1 - ZNCC over DSO's 8-pixel pattern.
4. **Consistency** (here, :func:`map_keyframe`): a depth is kept when at least
   ``min_agreeing_frames`` frames (the keyframe plus neighbours whose own match lies within 3
   sigma) agree and its relative uncertainty is low (optionally also its inverse-depth sigma:
   ``max_sigma_inv_depth``, the depth filter's convergence); agreeing matches are fused by
   inverse variance, as in LSD-SLAM's depth observation update.
5. **Fusion** (:mod:`.semidense_fusion`): optionally a keyframe's depths first pass a
   multi-view geometric test (``min_consistent_views``) and a photometric one
   (``photometric_min_views``) against the keyframes around it, then a free-space test against a
   wider window (``free_space_window_keyframes``), which keep the streaks of wrong matches along
   viewing rays and the points floating in front of surfaces out of the map; points of nearby keyframes
   closer than ``fusion_radius_m`` are fused by greedy non-maximum suppression on the depth
   sigma; the survivor inherits the observations of those it absorbed, so every map point lists
   every frame that observed it (the references that the paper's place voting needs); an
   optional statistical outlier pass (``outlier_neighbours``) ends it.

This module holds the configuration, the results (:class:`KeyframePoints`, :class:`SemiDenseMap`
with its save/load), the per-keyframe driver :func:`map_keyframe`, the streaming
:func:`build_semidense_map` and the :func:`consistency` check, and re-exports the public names of
the step modules (``__all__``), so ``from mapkit.mapping.semidense import ...`` reaches all of them.

Everything is vectorised over candidates (numpy and ``cv2.remap``); there are no per-pixel Python
loops. Frames stream through a small window; no more than ``2 * neighbour_window_frames + 1``
images are held at once.

Frames and units: ``world_from_cam`` maps camera points (x right, y down, z forward, metres) into
the world; ``K`` is the 3x3 pinhole matrix of the (undistorted) images; inverse depth ``rho`` is
1/z in 1/m of the keyframe camera; frame ids are the caller's integers.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from itertools import pairwise
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field, model_validator

from mapkit.core.config import MapkitConfig, dump_config
from mapkit.core.errors import InputError
from mapkit.core.executor import Executor, get_executor
from mapkit.core.geometry import invert_pose, rotation_angle_rad, transform_points
from mapkit.core.runio import atomic_path, atomic_write_ply, atomic_write_text, progress_bar
from mapkit.mapping.pose_refine import RotationRefiner
from mapkit.mapping.semidense_candidates import PATTERN_DSO8, gradient_threshold, image_gradients, select_candidates
from mapkit.mapping.semidense_epipolar import _candidate_searcher, _Neighbour, _neighbour_geometry, _Pyramid, _Searcher
from mapkit.mapping.semidense_fusion import (
    SparseDepth,
    _Fuser,
    _ViewWindow,
    consistent_views,
    free_space_filter,
    greedy_nms,
    hidden_in_source,
    multi_view_filter,
    photometric_filter,
    photometric_ncc,
    statistical_inliers,
    visibility_views,
)

__all__ = [
    "KeyframePoints",
    "PATTERN_DSO8",
    "SemiDenseConfig",
    "SemiDenseMap",
    "build_semidense_map",
    "consistency",
    "consistent_views",
    "free_space_filter",
    "gradient_threshold",
    "greedy_nms",
    "hidden_in_source",
    "image_gradients",
    "map_keyframe",
    "multi_view_filter",
    "photometric_filter",
    "photometric_ncc",
    "select_candidates",
    "statistical_inliers",
    "visibility_views",
]


class SemiDenseConfig(MapkitConfig):
    """Parameters of semi-dense mapping; defaults from DSO and LSD-SLAM where they have one."""

    # --- candidate selection (DSO) ---
    block_size: int = Field(
        32,
        ge=4,
        description="Side (px) of the blocks whose median gradient sets the threshold (DSO candidate selection: "
        "32x32).",
    )
    gradient_threshold_add: float = Field(
        7.0,
        ge=0,
        description="Added to the block median of |gradient| (grey levels per px, central differences) to make the "
        "threshold (DSO: g_th = 7, setting_minGradHistAdd).",
    )
    cell_size: int = Field(
        2,
        ge=1,
        description="Keep the strongest candidate per cell of this side (px). DSO picks one per d x d cell with d "
        "tuned for ~2000 points; 2 keeps semi-dense density (LSD-SLAM uses every pixel) at a quarter of the cost.",
    )
    max_candidates: int | None = Field(
        None,
        ge=1,
        description="Keep at most this many candidates per keyframe (strongest gradient relative to threshold first); "
        "None = no cap.",
    )
    # --- epipolar search ---
    min_depth_m: float = Field(
        1.0,
        gt=0,
        description="Nearest depth searched (m), in the keyframe and every neighbour. A vehicle camera sees nothing "
        "closer than its own bonnet.",
    )
    max_depth_m: float = Field(
        100.0,
        gt=0,
        description="Farthest depth searched (m). Beyond ~100 m, baselines of a few metres cannot reach max_rel_sigma "
        "anyway.",
    )
    search_samples: int = Field(
        32,
        ge=8,
        description="Samples of the first (full-range) search along the epipolar line, at <= 1 px of the pyramid level "
        "it runs on.",
    )
    full_range_attempts: int = Field(
        1,
        ge=1,
        description="Full-range searches tried per candidate (nearest neighbours first) before giving it up; sky and "
        "repetitive texture would otherwise pay for a full search in every neighbour.",
    )
    prior_search_samples: int = Field(
        12, ge=5, description="Samples of a search within +-search_sigmas of an existing estimate."
    )
    pyramid_levels: int = Field(
        4,
        ge=1,
        le=6,
        description="Pyramid levels for coarse-to-fine search of long epipolar lines (level l samples every 2^l px); 4 "
        "covers lines up to 8*(search_samples-1) px at one level-pixel per sample.",
    )
    search_sigmas: float = Field(
        3.0,
        gt=0,
        description="Half-width (in sigmas) of the search around an existing estimate (LSD-SLAM: STEREO_EPL_VAR_FAC = "
        "2; 3 leaves slack for underestimated sigmas).",
    )
    min_search_half_width_px: float = Field(
        2.0,
        ge=0.5,
        description="A prior search covers at least +-this many pixels, so the cost curve has a shape to fit.",
    )
    min_epipolar_length_px: float = Field(
        2.0,
        ge=0,
        description="Skip a full-range search whose epipolar segment (whole depth range, inside the image) is shorter "
        "than this: no parallax (LSD-SLAM: MIN_EPL_LENGTH_SQUARED = 1^2 px; 2 px because the pattern itself spans 4).",
    )
    min_gradient_epipolar_cos: float = Field(
        0.3,
        ge=0,
        le=1,
        description="Skip a neighbour when |cos| of the angle between the image gradient and the epipolar line is "
        "below this: the line runs along the edge (LSD-SLAM MIN_EPL_ANGLE_SQUARED = 0.3^2).",
    )
    max_cost: float = Field(
        0.3, gt=0, le=2, description="Largest accepted 1 - ZNCC over the 8-pixel pattern (ZNCC >= 0.7)."
    )
    ambiguity_ratio: float | None = Field(
        None,
        gt=0,
        le=1,
        description="Second-best ratio test of a full-range search (as Lowe's ratio and LSD-SLAM's second-best check): "
        "ambiguous (rejected) when another local minimum, more than 2 level-pixels away, scores at least this fraction "
        "of the best's ZNCC. None = off (only ambiguity_margin).",
    )
    ambiguity_margin: float = Field(
        0.1,
        ge=0,
        description="A full-range search is ambiguous (rejected) when another local minimum, more than 2 level-pixels "
        "away, costs less than best + this (in 1 - ZNCC). LSD-SLAM asks the second-best SSD to be 1.5x the best; a "
        "ratio is meaningless for ZNCC costs near 0, hence a margin.",
    )
    image_noise_sigma: float = Field(
        4.0,
        gt=0,
        description="Image noise (grey levels) for the photometric part of the matching sigma (LSD-SLAM: "
        "cameraPixelNoise2 = 4^2).",
    )
    min_sigma_px: float = Field(
        0.25,
        gt=0,
        description="Floor of the matching sigma along the epipolar line (px): the usual limit of sub-pixel block "
        "matching (parabola bias, 'pixel locking').",
    )
    # --- acceptance ---
    min_agreeing_frames: int = Field(
        3,
        ge=2,
        description="Frames (keyframe + neighbours) whose matches agree within agree_sigmas; 3 = 'consistent across "
        "more than two frames'. 4 is measured in bench/semidense_kitti_clip.py --ablation: it cleans each keyframe's "
        "own depths, but with the fusion filters on the map itself hardly changes.",
    )
    agree_sigmas: float = Field(
        3.0,
        gt=0,
        description="Two inverse-depth estimates agree when they differ by at most this many combined sigmas (3: 99.7% "
        "of a Gaussian).",
    )
    max_rel_sigma: float = Field(
        0.02, gt=0, description="Largest accepted sigma(depth)/depth (= sigma(rho)/rho) of a fused point."
    )
    max_sigma_depth_m: float = Field(
        0.3,
        gt=0,
        description="Largest accepted sigma of depth (m); keeps far points out of a map whose accuracy goal is a "
        "median of 0.15 m.",
    )
    max_sigma_inv_depth: float | None = Field(
        None,
        gt=0,
        description="Depth-filter convergence: largest accepted sigma of inverse depth (1/m) after fusing a "
        "candidate's observations, before it enters the map (LSD-SLAM keeps a pixel's hypothesis out of use until its "
        "inverse-depth variance has shrunk; SVO's depth filter calls a seed converged below a fixed sigma). None = "
        "off.",
    )
    # --- keyframes and neighbours ---
    keyframe_spacing_m: float = Field(
        1.0, gt=0, description="A frame becomes a keyframe after this much motion since the last keyframe (m)."
    )
    keyframe_rotation_deg: float = Field(
        10.0, gt=0, description="... or after this much rotation since the last keyframe (deg)."
    )
    neighbour_window_frames: int = Field(
        3,
        ge=1,
        description="Neighbours are the frames up to this many before and after a keyframe (streaming window of 2n+1 "
        "images).",
    )
    min_baseline_m: float = Field(
        0.1, ge=0, description="Neighbours closer than this to the keyframe are not used (no parallax)."
    )
    max_baseline_m: float = Field(
        10.0, gt=0, description="Neighbours farther than this from the keyframe are not used (little overlap)."
    )
    # --- camera rotations refined against the images ---
    refine_rotations: bool = Field(
        False,
        description="Refine every frame's camera rotation on its given position before mapping: correspondences with "
        "the frames up to refine_max_gap_frames on (tracked corners, or SIFT: refine_matcher), their epipolar "
        "distances minimised (Huber) over a small rotation per frame, in a sliding window of refine_lag_frames either "
        "side (mapkit.mapping.pose_refine). For poses whose positions are right to millimetres between frames but "
        "whose rotations disagree with the images by tenths of a degree (post-processed GPS/INS: KITTI's given poses; "
        "an extrinsic rotation off). NOT for positions with centimetres of frame-to-frame noise (LiDAR odometry, a "
        "factor graph): the baseline's direction is then off by degrees and the rotations follow it; on the synthetic "
        "town it makes maps worse even on true poses (tiny-sunny, bench/map_error_budget.py --semidense: median to the "
        "true surfaces 0.087 -> 0.116 m; docs/accuracy.md). Off by default; the map's keyframe poses are the refined "
        "ones.",
    )
    refine_max_gap_frames: int = Field(
        3, ge=1, description="... frames matched with each frame, forward (3: the neighbour window)."
    )
    refine_lag_frames: int = Field(
        6,
        ge=1,
        description="... a frame's rotation is solved with this many frames before and after it, and handed to the "
        "mapper this many frames late (>= refine_max_gap_frames).",
    )
    refine_huber_px: float = Field(1.0, gt=0, description="... Huber scale (px) of the epipolar distances.")
    refine_prior_px: float = Field(
        1.0,
        gt=0,
        description="... weak prior at the given rotation: a correction of 1/f rad costs as much as this many px of "
        "epipolar distance (holds the roll about a straight drive, which the epipolar lines do not see).",
    )
    refine_anchor_px: float = Field(
        0.1,
        gt=0,
        description="... frames already handed on stay in the window held at their final rotations by a prior of this "
        "many px per 1/f rad: smaller ties the window's weakly seen common rotation to the frames before (consistent "
        "neighbours, but an offset carried along), larger lets it follow the given rotations (no offset carried, more "
        "jitter between windows). 0.1 chosen on the tiny town between 0.1 and 1.0 (tiny-sunny, estimated poses: median "
        "0.317 against 0.392 m); scored on the KITTI clip.",
    )
    refine_gate_px: float = Field(
        10.0,
        gt=0,
        description="... matches farther than this (px) from the epipolar lines of the given poses are left out (wrong "
        "matches on repeated texture; a rotation error of the size this corrects moves a line by a few px).",
    )
    refine_matcher: Literal["tracks", "sift"] = Field(
        "tracks",
        description="... how frames are matched: 'tracks' follows Shi-Tomasi corners from frame to frame (pyramidal "
        "Lucas-Kanade, forward-backward checked); 'sift' matches SIFT features by Lowe's ratio test. On the KITTI clip "
        "both give rotations as good (median distance of independent SIFT matches to the refined epipolar lines: "
        "frames 25-50, given 0.305 px, SIFT 0.207, tracks 0.204) and the tracks' refiner takes a tenth of SIFT's CPU "
        "time (python3 bench/rotation_refine_matchers.py).",
    )
    refine_features: int = Field(
        600, ge=50, description="... corners tracked per frame (tracks), or SIFT features per frame (sift)."
    )
    refine_lowe_ratio: float = Field(
        0.7,
        gt=0,
        le=1,
        description="... Lowe's ratio test of the matches (Lowe IJCV 2004: 0.8; 0.7 keeps fewer wrong matches on "
        "repeated facades).",
    )
    refine_min_matches: int = Field(
        30, ge=8, description="... a pair of frames with fewer matches is left out (the prior holds a frame with none)."
    )
    # --- fusion ---
    fusion_radius_m: float = Field(
        0.05,
        gt=0,
        description="No two map points closer than this (m): the better-measured point absorbs the other's "
        "observations. Below the 0.15 m accuracy goal.",
    )
    fusion_window_keyframes: int = Field(
        10,
        ge=1,
        description="A point stays open for fusion until this many keyframes pass without it absorbing a new "
        "observation.",
    )
    # --- outlier rejection at fusion ---
    min_consistent_views: int = Field(
        0,
        ge=0,
        description="Multi-view geometric consistency (as COLMAP's depth-map fusion filters): a keyframe depth enters "
        "the map only where at least this many other keyframes within consistency_window_keyframes have their own "
        "depth within consistency_rel_tol at its reprojection. 0 = off (the default; 1 with the defaults below is the "
        "setting chosen on the clip's first half, and with free_space_window_keyframes = 25 the recommended one: "
        "configs/build/clean-maps.yaml).",
    )
    consistency_rel_tol: float = Field(
        0.06,
        gt=0,
        description="Relative depth tolerance |z - z_other| / z_other of the multi-view consistency test (COLMAP: "
        "filter_max_depth_diff = 0.01 on dense depth maps; 0.06 chosen on the first half of the KITTI clip, where "
        "0.01-0.06 were tried).",
    )
    consistency_pixel_radius: float = Field(
        1.5,
        gt=0,
        description="A reprojected depth is compared with the other keyframe's depths within this radius (px): "
        "semi-dense candidates are one per cell, so the same edge may sit a pixel off.",
    )
    min_agree_over_conflict: float = Field(
        2.0,
        ge=0,
        description="... and only where the agreeing views number at least this times the views whose depths there "
        "contradict it (stability-based fusion, Merrell et al. ICCV 2007: support against free-space violations and "
        "occlusions; 2 chosen on the first half of the KITTI clip among 0, 1, 1.5, 2). 0 = agreement alone decides.",
    )
    consistency_window_keyframes: int = Field(
        12,
        ge=1,
        description="Keyframes before and after a keyframe that vote on its depths; a keyframe enters fusion this many "
        "keyframes late (memory: 2n+1 sparse depth images).",
    )
    photometric_min_views: int = Field(
        0,
        ge=0,
        description="Photometric consistency (as DSO's point activation and COLMAP's photometric term): a keyframe "
        "depth enters the map only where at least this many other keyframes within consistency_window_keyframes that "
        "see it unoccluded show its patch with NCC >= photometric_ncc_min, and they number at least "
        "photometric_min_agree_over_conflict times those whose NCC falls below. 0 = off (measured alone it cleans less "
        "than the geometric test at the same point count on the KITTI clip: bench/semidense_kitti_clip.py --ablation).",
    )
    photometric_ncc_min: float = Field(
        0.5,
        ge=-1,
        le=1,
        description="... NCC of the (2 photometric_patch_radius + 1)^2 patch, lifted at the depth (fronto-parallel) "
        "and sampled in the other keyframe, that counts as agreement (0.5 chosen on the first half of the KITTI clip "
        "among 0.5, 0.7, 0.8: the setting with the lowest 90th percentile that keeps half the points).",
    )
    photometric_min_agree_over_conflict: float = Field(
        1.0,
        ge=0,
        description="... agreeing keyframes at least this times the disagreeing ones (1 chosen on the first half of "
        "the KITTI clip among 0.5, 1, 2).",
    )
    photometric_patch_radius: int = Field(
        2,
        ge=1,
        le=5,
        description="Half-side (px) of the patch the photometric test compares: 2 = 5x5, the extent of DSO's 8-pixel "
        "pattern.",
    )
    free_space_window_keyframes: int = Field(
        0,
        ge=0,
        description="Visibility test after the geometric and photometric ones (free-space carving as in TSDF fusion; "
        "Merrell et al.'s stability-based fusion, ICCV 2007): a depth is rejected when more than "
        "free_space_max_violations of the keyframes up to this many before and after it either see through it (it "
        "floats in front of a surface their checked depths hold at its reprojection) or saw a surface that would hide "
        "it in its own keyframe. 0 = off; 25 (twice the consistency window: the clip's 26-frame first half is too "
        "short to choose it on) is the setting measured. Keyframes enter fusion this many keyframes later again "
        "(memory: 2n+1 sparse keyframe depths).",
    )
    free_space_max_violations: int = Field(
        0,
        ge=0,
        description="... violating keyframes tolerated (0: one violation rejects; chosen on the first half of the "
        "KITTI clip among 0, 1, 2).",
    )
    outlier_neighbours: int = Field(
        0,
        ge=0,
        description="Final statistical outlier pass over the fused map (open3d remove_statistical_outlier): neighbours "
        "whose mean distance is compared. 0 = off.",
    )
    outlier_std_ratio: float = Field(
        2.0,
        gt=0,
        description="... a point goes when its mean neighbour distance exceeds the map's mean by this many standard "
        "deviations (the PCL/open3d tutorial value).",
    )

    @model_validator(mode="after")
    def _check(self) -> SemiDenseConfig:
        if self.max_depth_m <= self.min_depth_m:
            raise ValueError(f"max_depth_m ({self.max_depth_m}) must exceed min_depth_m ({self.min_depth_m})")
        if self.max_baseline_m <= self.min_baseline_m:
            raise ValueError("max_baseline_m must exceed min_baseline_m")
        if self.refine_lag_frames < self.refine_max_gap_frames:
            raise ValueError(
                f"refine_lag_frames ({self.refine_lag_frames}) must be at least refine_max_gap_frames "
                f"({self.refine_max_gap_frames})"
            )
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

    def depth_image(self, shape: tuple[int, int], dtype=np.float64) -> np.ndarray:
        """(H, W) depth (m) at the accepted pixels, NaN elsewhere."""
        img = np.full(shape, np.nan, dtype)
        img[self.pixels_uv[:, 1], self.pixels_uv[:, 0]] = self.depth
        return img

    def select(self, keep: np.ndarray) -> KeyframePoints:
        """The points where ``keep`` (N,) is true."""
        return KeyframePoints(
            self.pixels_uv[keep],
            self.inv_depth[keep],
            self.sigma_inv_depth[keep],
            self.intensity[keep],
            self.neighbour_ids,
            self.agreed[keep],
            self.frame_id,
            dict(self.stats),
        )


def map_size(points: int, keyframe_world_from_cam: np.ndarray) -> dict:
    """A map's size as its stats report it: points, keyframes, the keyframes' path (m) and points per 100 m of it
    (None on a path of zero length)."""
    K = np.asarray(keyframe_world_from_cam, np.float64).reshape(-1, 4, 4)
    path_m = float(np.linalg.norm(np.diff(K[:, :3, 3], axis=0), axis=1).sum()) if len(K) > 1 else 0.0
    return {
        "points": int(points),
        "keyframes": int(len(K)),
        "keyframe_path_m": path_m,
        "points_per_100m": points / path_m * 100.0 if path_m > 0 else None,
    }


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
    config: SemiDenseConfig | None = None
    #: every frame the map was built from, keyframe or not: (T,) ids and their stamps, so that a
    #: frame's pose can be interpolated between keyframes over time (absent in maps saved before)
    frame_ids: np.ndarray | None = None
    frame_stamps_ns: np.ndarray | None = None
    #: points each outlier filter of the fusion removed, by name (not saved: the build's metrics hold it)
    rejected: dict = field(default_factory=dict)
    #: what the rotation refinement did (frames, corrections, epipolar distances before and after; not saved either)
    pose_refinement: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return int(len(self.points_world))

    def select(self, keep: np.ndarray) -> SemiDenseMap:
        """The map restricted to the points where ``keep`` (N,) is true, with their observations."""
        keep = np.asarray(keep, bool)
        c = self.obs_counts
        sel_obs = np.repeat(keep, c)
        return replace(
            self,
            points_world=self.points_world[keep],
            intensity=self.intensity[keep],
            sigma_depth=self.sigma_depth[keep],
            source_keyframe=self.source_keyframe[keep],
            obs_indptr=np.r_[0, np.cumsum(c[keep])].astype(np.int64),
            obs_frame_ids=self.obs_frame_ids[sel_obs],
            rejected=dict(self.rejected),
            pose_refinement=dict(self.pose_refinement),
        )

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
        return {
            **map_size(len(self), self.keyframe_world_from_cam),
            "observations": int(c.sum()),
            "obs_per_point_median": float(np.median(c)) if len(c) else None,
            "sigma_depth_median_m": float(np.median(self.sigma_depth)) if len(c) else None,
            **({"rejected": dict(self.rejected)} if self.rejected else {}),
            **({"pose_refinement": dict(self.pose_refinement)} if self.pose_refinement else {}),
        }

    def save(self, folder: str | Path, frame=None) -> Path:
        """Write ``points.ply`` (binary, float64 xyz, grey colour), ``observations.npz`` and
        ``config.yaml`` into ``folder``, each file atomically. Returns ``folder``. ``frame``: the
        :class:`~mapkit.core.geodesy.LocalFrame` whose ENU the points are in, stated in the PLY header."""
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        grey = np.repeat(self.intensity.astype(np.float64)[:, None] / 255.0, 3, axis=1)
        atomic_write_ply(folder / "points.ply", self.points_world, grey, frame=frame)
        frames: dict[str, Any] = (  # Any: numpy's stub would match these arrays to savez's allow_pickle too
            {}
            if self.frame_ids is None
            else {
                "frame_ids": np.asarray(self.frame_ids, np.int64),
                "frame_stamps_ns": np.asarray(self.frame_stamps_ns, np.int64),
            }
        )
        with atomic_path(folder / "observations.npz") as tmp, open(tmp, "wb") as f:
            np.savez(
                f,
                obs_indptr=self.obs_indptr,
                obs_frame_ids=self.obs_frame_ids,
                source_keyframe=self.source_keyframe,
                sigma_depth=self.sigma_depth,
                intensity=self.intensity,
                keyframe_ids=self.keyframe_ids,
                keyframe_stamps_ns=self.keyframe_stamps_ns,
                keyframe_world_from_cam=self.keyframe_world_from_cam,
                K=self.K,
                image_size_wh=np.asarray(self.image_size_wh, np.int64),
                **frames,
            )
        if self.config is not None:
            atomic_write_text(folder / "config.yaml", dump_config(self.config))
        return folder

    @classmethod
    def load(cls, folder: str | Path) -> SemiDenseMap:
        import open3d as o3d
        import yaml

        folder = Path(folder)
        for name in ("points.ply", "observations.npz"):
            if not (folder / name).is_file():
                raise InputError(folder / name, "no such file (not a semi-dense map folder?)")
        # open3d's stub asks for an os.PathLike; it reads a str path as well
        ply = o3d.io.read_point_cloud(str(folder / "points.ply"), format="ply")  # type: ignore[arg-type]
        pts = np.asarray(ply.points, np.float64)
        with np.load(folder / "observations.npz") as z:
            d = {k: z[k] for k in z.files}
        if len(d["obs_indptr"]) != len(pts) + 1:
            raise InputError(
                folder / "observations.npz", f"{len(d['obs_indptr']) - 1} points, but points.ply has {len(pts)}"
            )
        cfg = None
        if (folder / "config.yaml").is_file():
            cfg = SemiDenseConfig.model_validate(yaml.safe_load((folder / "config.yaml").read_text()))
        w, h = (int(x) for x in d["image_size_wh"])
        return cls(
            points_world=pts,
            intensity=d["intensity"],
            sigma_depth=d["sigma_depth"],
            source_keyframe=d["source_keyframe"],
            obs_indptr=d["obs_indptr"],
            obs_frame_ids=d["obs_frame_ids"],
            keyframe_ids=d["keyframe_ids"],
            keyframe_stamps_ns=d["keyframe_stamps_ns"],
            keyframe_world_from_cam=d["keyframe_world_from_cam"],
            K=d["K"],
            image_size_wh=(w, h),
            config=cfg,
            frame_ids=d.get("frame_ids"),
            frame_stamps_ns=d.get("frame_stamps_ns"),
        )


# --- one keyframe ------------------------------------------------------------------------------------------


def _accepted(rho: np.ndarray, sigma: np.ndarray, agreed: np.ndarray, cfg: SemiDenseConfig) -> np.ndarray:
    """Candidates whose depth enough frames agree on, inside the depth range and sharp enough."""
    rho_min, rho_max = 1.0 / cfg.max_depth_m, 1.0 / cfg.min_depth_m
    n_frames = 1 + agreed.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return (
            np.isfinite(rho)
            & (n_frames >= cfg.min_agreeing_frames)
            & (rho >= rho_min)
            & (rho <= rho_max)
            & (sigma <= cfg.max_rel_sigma * rho)
            & (sigma <= cfg.max_sigma_depth_m * rho**2)
            & (sigma <= (np.inf if cfg.max_sigma_inv_depth is None else cfg.max_sigma_inv_depth))
        )


def map_keyframe(
    ref_image: np.ndarray,
    ref_world_from_cam: np.ndarray,
    neighbours: Sequence[tuple[np.ndarray, np.ndarray]],
    K: np.ndarray,
    cfg: SemiDenseConfig | None = None,
    *,
    frame_id: int = -1,
    neighbour_ids: Sequence[int] | None = None,
    ref_pyramid: _Pyramid | None = None,
    neighbour_pyramids: Sequence[_Pyramid] | None = None,
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
    ref_pyr, nb_pyrs = _pyramids(ref_image, neighbours, cfg, ref_pyramid, neighbour_pyramids)

    u, v, g, searcher = _candidate_searcher(ref_image, ref_pyr, cfg)
    geoms = [_neighbour_geometry(i, ref_world_from_cam, T, K) for i, (_, T) in enumerate(neighbours)]
    geoms = [n for n in geoms if cfg.min_baseline_m <= n.baseline_m <= cfg.max_baseline_m]
    geoms.sort(key=lambda n: n.baseline_m)  # nearest first: short lines, then sharpen

    est = _DepthEstimates.empty(len(u), len(neighbours))
    n_searched = n_full = n_prior = 0
    for nb in geoms:
        usable = _gradient_along_line(nb, u, v, g) >= cfg.min_gradient_epipolar_cos
        has = np.isfinite(est.rho)
        tgt = nb_pyrs[nb.index]
        # no estimate yet: full-range search with the ambiguity test
        ia = np.nonzero(usable & ~has & (est.attempts < cfg.full_range_attempts))[0]
        n_full += len(ia)
        if len(ia):
            est.search_full_range(searcher, ia, nb, tgt, cfg)
        # estimate so far: search within +-search_sigmas, then fuse where it agrees (LSD-SLAM-style update)
        ib = np.nonzero(usable & has)[0]
        n_prior += len(ib)
        if len(ib):
            est.search_near_estimate(searcher, ib, nb, tgt, cfg)
        n_searched += 1

    sigma = np.sqrt(est.var)
    keep = _accepted(est.rho, sigma, est.agreed, cfg)
    intensity = np.clip(ref_image[v[keep], u[keep]], 0, 255).astype(np.uint8)
    return KeyframePoints(
        pixels_uv=np.column_stack([u[keep], v[keep]]).astype(np.int32),
        inv_depth=est.rho[keep],
        sigma_inv_depth=sigma[keep],
        intensity=intensity,
        neighbour_ids=ids,
        agreed=est.agreed[keep],
        frame_id=int(frame_id),
        stats={
            "candidates": int(len(u)),
            "with_estimate": int(np.isfinite(est.rho).sum()),
            "accepted": int(keep.sum()),
            "neighbours_searched": n_searched,
            "full_range_searches": n_full,
            "prior_searches": n_prior,
        },
    )


def _pyramids(
    ref_image: np.ndarray,
    neighbours: Sequence[tuple[np.ndarray, np.ndarray]],
    cfg: SemiDenseConfig,
    ref_pyramid: _Pyramid | None,
    neighbour_pyramids: Sequence[_Pyramid] | None,
) -> tuple[_Pyramid, list[_Pyramid]]:
    """The keyframe's pyramid and its neighbours' (those given, else built), all of one image shape."""
    ref_pyr = ref_pyramid or _Pyramid(ref_image, cfg.pyramid_levels)
    nb_pyrs = (
        list(neighbour_pyramids)
        if neighbour_pyramids is not None
        else [_Pyramid(img, cfg.pyramid_levels) for img, _ in neighbours]
    )
    for (_img, _), pyr in zip(neighbours, nb_pyrs, strict=True):
        if pyr.shape != ref_pyr.shape:
            raise ValueError(f"neighbour image shape {pyr.shape} differs from the keyframe's {ref_pyr.shape}")
    return ref_pyr, nb_pyrs


def _gradient_along_line(nb: _Neighbour, u: np.ndarray, v: np.ndarray, g: np.ndarray) -> np.ndarray:
    """|cos| of the angle between each candidate's gradient ``g`` and its epipolar line towards neighbour ``nb``
    (0 where undefined): a pixel whose gradient runs across its line cannot be placed along it."""
    # the epipolar line in the keyframe runs from the epipole through the pixel
    e = nb.epipole_h
    line = np.column_stack([u * e[2] - e[0], v * e[2] - e[1]])
    with np.errstate(invalid="ignore", divide="ignore"):
        cos = np.abs((line * g).sum(1)) / (np.linalg.norm(line, axis=1) * np.linalg.norm(g, axis=1))
    return np.nan_to_num(cos)


@dataclass
class _DepthEstimates:
    """Each candidate's depth filter over the neighbours searched so far."""

    rho: np.ndarray  # (N,) inverse depth (1/m), NaN while there is no estimate
    var: np.ndarray  # (N,) its variance
    agreed: np.ndarray  # (N, neighbours) bool: the neighbours whose match agreed
    attempts: np.ndarray  # (N,) full-range searches tried

    @classmethod
    def empty(cls, n_candidates: int, n_neighbours: int) -> _DepthEstimates:
        return cls(
            np.full(n_candidates, np.nan),
            np.full(n_candidates, np.inf),
            np.zeros((n_candidates, n_neighbours), bool),
            np.zeros(n_candidates, np.int64),
        )

    def search_full_range(
        self, searcher: _Searcher, idx: np.ndarray, nb: _Neighbour, tgt: _Pyramid, cfg: SemiDenseConfig
    ) -> None:
        """The candidates ``idx`` (no estimate yet) searched over the whole depth range, with the ambiguity test;
        a match becomes their estimate."""
        rho_min, rho_max = 1.0 / cfg.max_depth_m, 1.0 / cfg.min_depth_m
        r = searcher.trace(
            idx, np.full(len(idx), rho_min), np.full(len(idx), rho_max), nb, tgt, cfg.search_samples, True
        )
        self.attempts[idx[r.searched]] += 1  # a line outside this neighbour's view is no attempt
        k = idx[r.ok]
        self.rho[k], self.var[k] = r.rho[r.ok], r.sigma_rho[r.ok] ** 2
        self.agreed[k, nb.index] = True

    def search_near_estimate(
        self, searcher: _Searcher, idx: np.ndarray, nb: _Neighbour, tgt: _Pyramid, cfg: SemiDenseConfig
    ) -> None:
        """The candidates ``idx`` searched within ``search_sigmas`` of their estimate; a match that agrees with it
        (within ``agree_sigmas``) is fused into it by inverse variance."""
        rho_min, rho_max = 1.0 / cfg.max_depth_m, 1.0 / cfg.min_depth_m
        rho, var = self.rho, self.var
        sd = np.sqrt(var[idx])
        lo = np.clip(rho[idx] - cfg.search_sigmas * sd, rho_min, rho_max)
        hi = np.clip(rho[idx] + cfg.search_sigmas * sd, rho_min, rho_max)
        r = searcher.trace(idx, lo, hi, nb, tgt, cfg.prior_search_samples, False)
        s2 = r.sigma_rho**2
        agree = r.ok & (np.abs(r.rho - rho[idx]) <= cfg.agree_sigmas * np.sqrt(var[idx] + s2))
        k = idx[agree]
        w_old, w_new = 1.0 / var[k], 1.0 / s2[agree]
        rho[k] = (rho[k] * w_old + r.rho[agree] * w_new) / (w_old + w_new)
        var[k] = 1.0 / (w_old + w_new)
        self.agreed[k, nb.index] = True


# --- the map of a drive ---------------------------------------------------------------------------------


@dataclass
class _Buffered:
    frame_id: int
    stamp_ns: int
    image: np.ndarray
    world_from_cam: np.ndarray
    is_keyframe: bool
    pyramid: _Pyramid | None = None


@dataclass
class _KeyframeTask:
    """One keyframe's work: its image and pose, its neighbours', and (in this process) their pyramids."""

    frame_id: int
    stamp_ns: int
    image: np.ndarray
    world_from_cam: np.ndarray
    neighbours: list[tuple[np.ndarray, np.ndarray]]
    neighbour_ids: list[int]
    pyramid: _Pyramid | None = None
    neighbour_pyramids: list[_Pyramid] | None = None


@dataclass
class _Checked:
    """A mapped keyframe waiting for the keyframes that vote on its depths (and voting on theirs)."""

    frame_id: int
    world_from_cam: np.ndarray
    points: KeyframePoints
    # own depths: (H, W) float32, NaN elsewhere, while voting; sparse while carving
    depth: np.ndarray | SparseDepth | None
    image: np.ndarray | None = None  # (H, W) grey keyframe image, for the photometric test
    xyz: np.ndarray | None = None  # (N, 3) world points of ``points``, once they passed the voting filters

    # what each stage asks of a keyframe, which the stage before gave it when the test that asks is on
    @property
    def dense_depth(self) -> np.ndarray:
        assert isinstance(self.depth, np.ndarray), "a voting keyframe has a dense depth image"
        return self.depth

    @property
    def sparse_depth(self) -> SparseDepth:
        assert isinstance(self.depth, SparseDepth), "a carving keyframe has sparse depths"
        return self.depth

    @property
    def grey(self) -> np.ndarray:
        assert self.image is not None, "a keyframe of the photometric test has its image"
        return self.image

    @property
    def points_xyz(self) -> np.ndarray:
        assert self.xyz is not None, "a voted keyframe has its world points"
        return self.xyz


def _map_keyframe_task(
    shared: tuple[np.ndarray, SemiDenseConfig], t: _KeyframeTask
) -> tuple[int, int, np.ndarray, KeyframePoints]:
    K, cfg = shared
    pts = map_keyframe(
        t.image,
        t.world_from_cam,
        t.neighbours,
        K,
        cfg,
        frame_id=t.frame_id,
        neighbour_ids=t.neighbour_ids,
        ref_pyramid=t.pyramid,
        neighbour_pyramids=t.neighbour_pyramids,
    )
    return t.frame_id, t.stamp_ns, t.world_from_cam, pts


def _checked_frame(
    frame_id: int, gray, world_from_cam, image_shape: tuple[int, int] | None
) -> tuple[np.ndarray, np.ndarray]:
    """(grey image, pose) of one input frame, or an error naming the frame: a (H, W) image of the
    first frame's shape and a finite 4x4 pose."""
    gray = np.asarray(gray)
    T = np.asarray(world_from_cam, np.float64)
    if gray.ndim != 2:
        raise InputError(None, f"frame {frame_id}: expected a (H, W) grey image, got shape {gray.shape}")
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise InputError(None, f"frame {frame_id}: world_from_cam must be a finite 4x4 matrix")
    if image_shape is not None and gray.shape != image_shape:
        raise InputError(
            None, f"frame {frame_id}: image shape {gray.shape} differs from the first frame's {image_shape}"
        )
    return gray, T


def _is_keyframe(last_kf: np.ndarray | None, world_from_cam: np.ndarray, cfg: SemiDenseConfig) -> bool:
    """The first frame, and a frame that moved or turned enough since the last keyframe."""
    if last_kf is None:
        return True
    rel = invert_pose(last_kf) @ world_from_cam
    angle_deg = float(np.degrees(rotation_angle_rad(rel[:3, :3])))
    return bool(np.linalg.norm(rel[:3, 3]) >= cfg.keyframe_spacing_m or angle_deg >= cfg.keyframe_rotation_deg)


def build_semidense_map(
    frames: Iterable[tuple[int, int, np.ndarray, np.ndarray]],
    K: np.ndarray,
    cfg: SemiDenseConfig | None = None,
    progress: bool = True,
    on_keyframe: Callable[[int, np.ndarray, KeyframePoints], None] | None = None,
    executor: Executor | None = None,
    on_fused: Callable[[int, np.ndarray, KeyframePoints], None] | None = None,
) -> SemiDenseMap:
    """Semi-dense map of a drive from ``(frame_id, stamp_ns, gray (H, W), world_from_cam 4x4)``.

    Frames stream through a window of ``2 * neighbour_window_frames + 1`` images: a keyframe
    (chosen by motion) is mapped once the frames after it have arrived, against the frames up to
    ``neighbour_window_frames`` before and after it. ``on_keyframe(frame_id, world_from_cam,
    points)`` is called with each keyframe's own accepted depths (e.g. for ``consistency``), and
    ``on_fused`` (same arguments) with those of them that passed the fusion's outlier tests (multi-view,
    photometric, free space) and entered fusion (all of them when the tests are off), a keyframe's
    filtered depth map.

    Keyframes are mapped on ``executor`` (default: :func:`mapkit.core.executor.get_executor`), a few
    per worker at a time, and fused here in keyframe order, so the map is the same bit for bit on
    any executor. In this process the image pyramids are shared between neighbouring keyframes;
    workers elsewhere receive the images and build their own.
    """
    cfg = cfg or SemiDenseConfig()
    K = np.asarray(K, np.float64)
    executor = executor or get_executor()
    total = len(frames) if hasattr(frames, "__len__") else None  # type: ignore[arg-type]
    refiner = _rotation_refiner(K, cfg)
    if refiner is not None:
        frames = refiner.stream(frames)
    bar = progress_bar(total, progress, desc="semi-dense", unit="frame")
    window = _FrameWindow(cfg, bar, share_pyramids=executor.in_process)
    fusion = _KeyframeFusion(K, cfg, on_fused)
    keyframes: list[tuple[int, int, np.ndarray]] = []  # (frame id, stamp, world_from_cam) of each keyframe, in order
    results = executor.map(
        _map_keyframe_task,
        window.keyframe_tasks(frames),
        shared=(K, cfg),
        desc="semi-dense keyframes",
        label=lambda t: f"keyframe {t.frame_id}",
    )
    try:
        for frame_id, stamp_ns, world_from_cam, pts in results:
            if on_keyframe is not None:
                on_keyframe(frame_id, world_from_cam, pts)
            keyframes.append((frame_id, stamp_ns, world_from_cam))
            assert window.image_shape is not None  # the first frame's, set before any keyframe is mapped
            image = window.keyframe_images.pop(frame_id) if fusion.check_photo else None
            fusion.push(frame_id, world_from_cam, pts, window.image_shape, image)
            if progress:
                bar.set_postfix(keyframes=len(keyframes), points=fusion.points())
        fusion.flush()
    finally:
        results.close()
        bar.close()
    sd_map = _assembled_map(fusion, keyframes, window, K, cfg, refiner)
    if cfg.outlier_neighbours > 0:
        keep = statistical_inliers(sd_map.points_world, cfg.outlier_neighbours, cfg.outlier_std_ratio)
        sd_map = sd_map.select(keep)
        sd_map.rejected["statistical"] = int((~keep).sum())
    return sd_map


def _rotation_refiner(K: np.ndarray, cfg: SemiDenseConfig) -> RotationRefiner | None:
    """The streaming rotation refinement the config asks for (``refine_rotations``), or None."""
    if not cfg.refine_rotations:
        return None
    return RotationRefiner(
        K,
        max_gap=cfg.refine_max_gap_frames,
        lag=cfg.refine_lag_frames,
        huber_px=cfg.refine_huber_px,
        prior_px=cfg.refine_prior_px,
        anchor_px=cfg.refine_anchor_px,
        gate_px=cfg.refine_gate_px,
        matcher=cfg.refine_matcher,
        features=cfg.refine_features,
        lowe_ratio=cfg.refine_lowe_ratio,
        min_matches=cfg.refine_min_matches,
        min_baseline_m=cfg.min_baseline_m,
    )


class _FrameWindow:
    """The frames of a drive streamed through a window of ``2 * neighbour_window_frames + 1`` images, turned into
    keyframe tasks (:meth:`keyframe_tasks`). Records every frame's id and stamp, the first frame's image shape,
    and (with the photometric test on) each keyframe's image until the fusion takes it."""

    def __init__(self, cfg: SemiDenseConfig, bar, share_pyramids: bool):
        self.cfg = cfg
        self.bar = bar  # counts the frames read
        self.share_pyramids = share_pyramids  # tasks run in this process: a frame's pyramid is built once
        self.image_shape: tuple[int, int] | None = None
        self.frame_ids: list[int] = []
        self.frame_stamps_ns: list[int] = []
        self.keyframe_images: dict[int, np.ndarray] = {}  # keyframe images on their way to the photometric test

    def keyframe_tasks(self, frames: Iterable[tuple[int, int, np.ndarray, np.ndarray]]) -> Iterator[_KeyframeTask]:
        """A task per keyframe, once the frames after it have arrived (at the end, with the frames that exist)."""
        W = self.cfg.neighbour_window_frames
        window: deque[_Buffered] = deque()
        last_kf: np.ndarray | None = None
        for frame_id, stamp_ns, gray, world_from_cam in frames:
            self.bar.update(1)
            gray, T = _checked_frame(frame_id, gray, world_from_cam, self.image_shape)
            if self.image_shape is None:
                self.image_shape = gray.shape
            is_kf = _is_keyframe(last_kf, T, self.cfg)
            if is_kf:
                last_kf = T
            window.append(_Buffered(int(frame_id), int(stamp_ns), gray, T, bool(is_kf)))
            self.frame_ids.append(int(frame_id))
            self.frame_stamps_ns.append(int(stamp_ns))
            del gray
            # the frame W places back now has all its neighbours
            if len(window) > W and window[-1 - W].is_keyframe:
                yield self._task(window, len(window) - 1 - W)
            while len(window) > 2 * W + 1:
                window.popleft()
        # keyframes among the last W frames: map with the frames that exist
        for k in range(max(len(window) - W, 0), len(window)):
            if window[k].is_keyframe:
                yield self._task(window, k)

    def _task(self, window: deque[_Buffered], center: int) -> _KeyframeTask:
        kf = window[center]
        nbs = [f for k, f in enumerate(window) if k != center and abs(k - center) <= self.cfg.neighbour_window_frames]
        t = _KeyframeTask(
            kf.frame_id,
            kf.stamp_ns,
            kf.image,
            kf.world_from_cam,
            [(f.image, f.world_from_cam) for f in nbs],
            [f.frame_id for f in nbs],
        )
        if self.cfg.photometric_min_views > 0:
            self.keyframe_images[kf.frame_id] = kf.image
        if self.share_pyramids:  # a frame's pyramid serves every keyframe whose window holds it
            t.pyramid, t.neighbour_pyramids = self._pyramid(kf), [self._pyramid(f) for f in nbs]
        return t

    def _pyramid(self, f: _Buffered) -> _Pyramid:
        if f.pyramid is None:
            f.pyramid = _Pyramid(f.image, self.cfg.pyramid_levels)
        return f.pyramid


class _KeyframeFusion:
    """The fusion's outlier tests and the fuser, fed mapped keyframes in order (:meth:`push`, then :meth:`flush`).

    A keyframe enters the multi-view and photometric tests once the keyframes after it that vote have arrived,
    then the free-space test once those after it that carve have passed the first two, then the fuser.
    ``rejected`` counts the points each test removed."""

    def __init__(
        self,
        K: np.ndarray,
        cfg: SemiDenseConfig,
        on_fused: Callable[[int, np.ndarray, KeyframePoints], None] | None,
    ):
        self.K = K
        self.cfg = cfg
        self.on_fused = on_fused
        self.check_views = cfg.min_consistent_views > 0
        self.check_photo = cfg.photometric_min_views > 0
        self.check_free = cfg.free_space_window_keyframes > 0
        self.voting: _ViewWindow[_Checked] = _ViewWindow(
            cfg.consistency_window_keyframes if self.check_views or self.check_photo else 0
        )
        self.carving: _ViewWindow[_Checked] = _ViewWindow(cfg.free_space_window_keyframes)
        self.rejected = {
            name: 0
            for name, on in (
                ("multi_view", self.check_views),
                ("photometric", self.check_photo),
                ("free_space", self.check_free),
            )
            if on
        }
        self.fuser = _Fuser(cfg.fusion_radius_m, cfg.fusion_window_keyframes)
        self.image_shape: tuple[int, int] | None = None

    def points(self) -> int:
        """Points fused so far."""
        return len(self.fuser.open["xyz"]) + sum(len(d["xyz"]) for d in self.fuser.done)

    def push(
        self,
        frame_id: int,
        world_from_cam: np.ndarray,
        pts: KeyframePoints,
        image_shape: tuple[int, int],
        image: np.ndarray | None,
    ) -> None:
        """A mapped keyframe (``image``: its grey image, for the photometric test); fuses those it makes ready."""
        self.image_shape = image_shape
        depth = pts.depth_image(image_shape, np.float32) if self.check_views or self.check_photo else None
        for ready in self.voting.push(_Checked(frame_id, world_from_cam, pts, depth, image)):
            for item, others in self._vote(*ready):
                self._fuse(item, others)

    def flush(self) -> None:
        """Fuse the keyframes still waiting for their voters and carvers."""
        for ready in self.voting.flush():
            for item, others in self._vote(*ready):
                self._fuse(item, others)
        for item, others in self.carving.flush():
            self._fuse(item, others)

    def _vote(self, item: _Checked, others: list[_Checked]) -> Iterator[tuple[_Checked, list[_Checked]]]:
        """The multi-view and photometric tests of ``item`` against the keyframes around it; yields the keyframes
        that the free-space window releases."""
        cfg, K = self.cfg, self.K
        pts = item.points
        keep = np.ones(len(pts), bool)
        if self.check_views:
            keep = multi_view_filter(
                pts.points_world(K, item.world_from_cam),
                [(o.world_from_cam, o.dense_depth) for o in others],
                K,
                min_views=cfg.min_consistent_views,
                min_agree_over_conflict=cfg.min_agree_over_conflict,
                rel_tol=cfg.consistency_rel_tol,
                pixel_radius=cfg.consistency_pixel_radius,
            )
            self.rejected["multi_view"] += int((~keep).sum())
        if self.check_photo:
            sub = np.nonzero(keep)[0]
            ok = photometric_filter(
                item.world_from_cam,
                item.grey,
                pts.pixels_uv[sub],
                pts.depth[sub],
                [(o.world_from_cam, o.grey, o.dense_depth) for o in others],
                K,
                min_views=cfg.photometric_min_views,
                ncc_min=cfg.photometric_ncc_min,
                min_agree_over_conflict=cfg.photometric_min_agree_over_conflict,
                patch_radius=cfg.photometric_patch_radius,
                rel_tol=cfg.consistency_rel_tol,
                pixel_radius=cfg.consistency_pixel_radius,
            )
            self.rejected["photometric"] += int((~ok).sum())
            keep[sub[~ok]] = False
        pts = pts.select(keep) if not keep.all() else pts
        sparse = None
        if self.check_free:
            assert self.image_shape is not None  # the first frame's, set before any keyframe is mapped
            sparse = SparseDepth(pts.pixels_uv, pts.depth, self.image_shape)
        checked = _Checked(
            item.frame_id, item.world_from_cam, pts, sparse, xyz=pts.points_world(K, item.world_from_cam)
        )
        yield from self.carving.push(checked)

    def _fuse(self, item: _Checked, others: list[_Checked]) -> None:
        """The free-space test of ``item`` against the keyframes around it, then its points into the fuser."""
        cfg = self.cfg
        pts, world_from_cam, xyz = item.points, item.world_from_cam, item.points_xyz
        if self.check_free:
            assert self.image_shape is not None  # the first frame's, set before any keyframe is mapped
            keep = free_space_filter(
                world_from_cam,
                pts.pixels_uv,
                pts.depth,
                xyz,
                [(o.world_from_cam, o.sparse_depth, o.points_xyz) for o in others],
                self.K,
                self.image_shape,
                rel_tol=cfg.consistency_rel_tol,
                pixel_radius=cfg.consistency_pixel_radius,
                max_violations=cfg.free_space_max_violations,
            )
            self.rejected["free_space"] += int((~keep).sum())
            pts, xyz = pts.select(keep), xyz[keep]
        if self.on_fused is not None:
            self.on_fused(item.frame_id, world_from_cam, pts)
        obs_pt = np.concatenate([np.arange(len(pts)), np.nonzero(pts.agreed)[0]])
        obs_fid = np.concatenate(
            [np.full(len(pts), item.frame_id, np.int64), pts.neighbour_ids[np.nonzero(pts.agreed)[1]]]
        )
        self.fuser.add(xyz, pts.sigma_depth, pts.intensity, item.frame_id, obs_pt, obs_fid)


def _assembled_map(
    fusion: _KeyframeFusion,
    keyframes: list[tuple[int, int, np.ndarray]],
    window: _FrameWindow,
    K: np.ndarray,
    cfg: SemiDenseConfig,
    refiner: RotationRefiner | None,
) -> SemiDenseMap:
    """The map of the fused points, its keyframes (id, stamp, world_from_cam) and every frame read."""
    out = fusion.fuser.finish()
    h, w = window.image_shape if window.image_shape is not None else (0, 0)
    return SemiDenseMap(
        points_world=out["xyz"].astype(np.float64),
        intensity=out["intensity"].astype(np.uint8),
        sigma_depth=out["sigma"].astype(np.float32),
        source_keyframe=out["source"].astype(np.int64),
        obs_indptr=out["indptr"],
        obs_frame_ids=out["obs_fid"].astype(np.int64),
        keyframe_ids=np.asarray([k[0] for k in keyframes], np.int64),
        keyframe_stamps_ns=np.asarray([k[1] for k in keyframes], np.int64),
        keyframe_world_from_cam=np.asarray([k[2] for k in keyframes], np.float64).reshape(-1, 4, 4),
        K=K,
        image_size_wh=(int(w), int(h)),
        config=cfg,
        frame_ids=np.asarray(window.frame_ids, np.int64),
        frame_stamps_ns=np.asarray(window.frame_stamps_ns, np.int64),
        rejected=fusion.rejected,
        pose_refinement=refiner.report() if refiner is not None else {},
    )


# --- cross-frame consistency -------------------------------------------------------------------------------


@dataclass
class _Pairs:
    """(map point, other keyframe) pairs of :func:`consistency`, one entry each."""

    point: np.ndarray  # (P,) index of the map point
    frame_id: np.ndarray  # (P,) the other keyframe
    signed_rel: np.ndarray  # (P,) (z_map - z_own) / z_own
    baseline_m: np.ndarray  # (P,) distance between the point's source keyframe and the other one
    own_depth: np.ndarray  # (P,) z_own (m)
    own_pixel: np.ndarray  # (P,) row * W + column of the other keyframe's depth that was compared
    projected: int  # map points that projected into another keyframe's image


def _pairs(
    sd_map: SemiDenseMap, keyframes: Iterable[tuple[int, np.ndarray, KeyframePoints]], max_pixel_distance: float
) -> _Pairs:
    """Every map point reprojected into every keyframe but its source, against that keyframe's own
    depth at the nearest pixel (within ``max_pixel_distance``, chosen by image distance only)."""
    K = sd_map.K
    w, h = sd_map.image_size_wh
    kf_centre = dict(zip(sd_map.keyframe_ids.tolist(), sd_map.keyframe_world_from_cam[:, :3, 3], strict=True))
    src_centre = np.array([kf_centre.get(int(s), np.full(3, np.nan)) for s in sd_map.source_keyframe]).reshape(-1, 3)
    parts: dict[str, list[np.ndarray]] = {
        k: [] for k in ("point", "frame_id", "signed_rel", "baseline_m", "own_depth", "own_pixel")
    }
    projected = 0
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
        best_px = np.full(len(z), -1, np.int64)
        for dx, dy in offsets:
            cx, cy = xi + dx, yi + dy
            ok = (cx >= 0) & (cx < w) & (cy >= 0) & (cy < h)
            zz = np.full(len(z), np.nan)
            zz[ok] = own[cy[ok], cx[ok]]
            d2 = (cx - x) ** 2 + (cy - y) ** 2
            better = np.isfinite(zz) & (d2 <= max_pixel_distance**2) & (d2 < best_d2)
            best_d2[better], best_z[better], best_px[better] = d2[better], zz[better], (cy * w + cx)[better]
        m = np.isfinite(best_z)
        if m.any():
            parts["point"].append(sel[m])
            parts["frame_id"].append(np.full(int(m.sum()), int(fid), np.int64))
            parts["signed_rel"].append((z[m] - best_z[m]) / best_z[m])
            parts["baseline_m"].append(np.linalg.norm(src_centre[sel[m]] - world_from_cam[:3, 3], axis=1))
            parts["own_depth"].append(best_z[m])
            parts["own_pixel"].append(best_px[m])
    cat = {
        k: np.concatenate(v) if v else np.zeros(0, np.int64 if k in ("point", "frame_id", "own_pixel") else np.float64)
        for k, v in parts.items()
    }
    return _Pairs(**cat, projected=projected)


def _figures(r: np.ndarray) -> dict:
    """Headline figures of signed relative disagreements ``r``."""
    a = np.abs(r)
    if len(r) == 0:
        return {"pairs": 0, "median_rel": None}
    return {
        "pairs": int(len(r)),
        "median_rel": float(np.median(a)),
        "p75_rel": float(np.percentile(a, 75)),
        "p90_rel": float(np.percentile(a, 90)),
        "frac_below_5pct": float(np.mean(a < 0.05)),
        "frac_map_nearer_5pct": float(np.mean(r < -0.05)),
        "frac_map_farther_5pct": float(np.mean(r > 0.05)),
    }


def consistency(
    sd_map: SemiDenseMap,
    keyframes: Iterable[tuple[int, np.ndarray, KeyframePoints]],
    *,
    max_pixel_distance: float = 1.0,
    baseline_bins_m: Sequence[float] = (0.0, 2.0, 5.0, 10.0, np.inf),
    depth_bins_m: Sequence[float] = (0.0, 5.0, 10.0, 20.0, 40.0, np.inf),
    verified: Iterable[tuple[int, np.ndarray, KeyframePoints]] | None = None,
    min_confirming: int = 2,
    keyframe_bins: Sequence[float] | None = None,
) -> dict:
    """How well map points agree with the depths other keyframes estimated on their own.

    Every map point is reprojected into every keyframe ``(frame_id, world_from_cam, points)``
    other than its source keyframe; where that keyframe has its own accepted depth at the nearest
    pixel (within ``max_pixel_distance``, chosen by image distance only, never by depth), the
    relative disagreement |z_map - z_own| / z_own is recorded. ``median_rel`` over all such pairs
    is the headline figure. Occlusion (the map point hidden behind what the keyframe sees) and
    chance hits on unrelated structure make the tail, and both grow with the distance between
    the two keyframes, hence the breakdown by that distance and by sign ("map nearer" than the
    keyframe's own depth violates free space; "map farther" is mostly occlusion), and by the
    keyframe's own depth (``by_depth_m``: far depths are measured with less parallax).

    ``verified``: each keyframe's depths that passed a multi-view test (same ids; e.g. what
    ``build_semidense_map`` hands ``on_fused`` with ``min_consistent_views`` on). Then the pairs
    where the map lies more than 5 % farther are told apart (``farther_causes``, shares of all
    pairs): ``reference_unverified``, the keyframe's own depth there is one its multi-view test
    rejected (the reference, not the map, is suspect); ``occluded``, that depth is verified and
    the map point agrees within 5 % with the verified depths of at least ``min_confirming`` other
    keyframes (two surfaces both seen from several keyframes, the nearer hiding the farther: the
    keyframe could not see the point); ``unexplained``, the rest. ``verified_reference`` holds the
    figures against the verified depths alone, and ``verified_visible`` the same without the
    occluded pairs.

    ``keyframe_bins``: edges ``[from, to)`` of frame ids; then ``by_source_keyframe`` (the map point's
    keyframe in the range) and ``by_reference_keyframe`` (the keyframe whose own depth is compared in
    the range) break the figures down along the drive, each bin with its farther pairs told apart
    (``farther_causes``, shares of the bin's pairs) when ``verified`` is given: where a drive's figure
    comes from, and whether the map or the reference depths are to blame there.
    """
    p = _pairs(sd_map, keyframes, max_pixel_distance)
    out: dict[str, Any] = {
        "pairs": int(len(p.signed_rel)),
        "frames": int(len(np.unique(p.frame_id))),
        "projected": p.projected,
    }
    if len(p.signed_rel) == 0:
        return {**out, "median_rel": None}
    r = p.signed_rel
    out.update(
        hit_rate=len(r) / p.projected,
        **{k: v for k, v in _figures(r).items() if k != "pairs"},
        by_keyframe_distance_m=_binned(r, p.baseline_m, baseline_bins_m),
        by_depth_m=_binned(r, p.own_depth, depth_bins_m),
    )
    if keyframe_bins is not None:
        src_fid = sd_map.source_keyframe[p.point]
        out["by_source_keyframe"] = _binned(r, src_fid, keyframe_bins, unit="frame")
        out["by_reference_keyframe"] = _binned(r, p.frame_id, keyframe_bins, unit="frame")
    if verified is not None:
        _add_farther_causes(
            out,
            sd_map,
            p,
            list(verified),
            max_pixel_distance,
            min_confirming,
            baseline_bins_m,
            keyframe_bins is not None,
        )
    return out


def _add_farther_causes(
    out: dict,
    sd_map: SemiDenseMap,
    p: _Pairs,
    verified: list[tuple[int, np.ndarray, KeyframePoints]],
    max_pixel_distance: float,
    min_confirming: int,
    baseline_bins_m: Sequence[float],
    by_keyframe: bool,
) -> None:
    """:func:`consistency`'s figures against the ``verified`` depths, added to ``out``: ``farther_causes`` (of
    the pairs ``p``; with ``by_keyframe`` also in each bin of ``by_source_keyframe`` and
    ``by_reference_keyframe``), ``verified_reference`` and ``verified_visible``."""
    w, _ = sd_map.image_size_wh
    ver_pixels = {
        int(fid): set((pts.pixels_uv[:, 1].astype(np.int64) * w + pts.pixels_uv[:, 0]).tolist())
        for fid, _, pts in verified
    }
    v = _pairs(sd_map, verified, max_pixel_distance)
    confirming = np.bincount(v.point[np.abs(v.signed_rel) <= 0.05], minlength=len(sd_map))

    def occluded(pairs: _Pairs, ref_verified: np.ndarray) -> np.ndarray:
        return (pairs.signed_rel > 0.05) & ref_verified & (confirming[pairs.point] >= min_confirming)

    ref_ok = np.array(
        [px in ver_pixels.get(int(f), ()) for f, px in zip(p.frame_id.tolist(), p.own_pixel.tolist(), strict=True)],
        bool,
    )
    farther = p.signed_rel > 0.05
    occ = occluded(p, ref_ok)
    out["farther_causes"] = {
        "reference_unverified": float(np.mean(farther & ~ref_ok)),
        "occluded": float(np.mean(occ)),
        "unexplained": float(np.mean(farther & ref_ok & ~occ)),
        "min_confirming": min_confirming,
    }
    if by_keyframe:
        src_fid = sd_map.source_keyframe[p.point]
        for key, fid in (("by_source_keyframe", src_fid), ("by_reference_keyframe", p.frame_id)):
            for b in out[key]:
                sel = (fid >= b["from_frame"]) & (fid < (np.inf if b["to_frame"] is None else b["to_frame"]))
                n = max(int(sel.sum()), 1)
                b["farther_causes"] = {
                    "reference_unverified": float((sel & farther & ~ref_ok).sum() / n),
                    "occluded": float((sel & occ).sum() / n),
                    "unexplained": float((sel & farther & ref_ok & ~occ).sum() / n),
                }
    occ_v = occluded(v, np.ones(len(v.signed_rel), bool))
    out["verified_reference"] = _figures(v.signed_rel)
    out["verified_visible"] = {
        **_figures(v.signed_rel[~occ_v]),
        "by_keyframe_distance_m": _binned(v.signed_rel[~occ_v], v.baseline_m[~occ_v], baseline_bins_m),
    }


def _binned(signed_rel: np.ndarray, key: np.ndarray, bins: Sequence[float], unit: str = "m") -> list[dict]:
    """Disagreement figures of the pairs whose ``key`` lies in each ``[from, to)`` of ``bins`` (keys
    ``from_<unit>``, ``to_<unit>``)."""
    out = []
    for lo, hi in pairwise(bins):
        sel = (key >= lo) & (key < hi)
        a, r = np.abs(signed_rel[sel]), signed_rel[sel]
        some = bool(sel.any())
        out.append(
            {
                f"from_{unit}": float(lo),
                f"to_{unit}": float(hi) if np.isfinite(hi) else None,
                "pairs": int(sel.sum()),
                "median_rel": float(np.median(a)) if some else None,
                "p90_rel": float(np.percentile(a, 90)) if some else None,
                "frac_below_5pct": float(np.mean(a < 0.05)) if some else None,
                "frac_map_farther_5pct": float(np.mean(r > 0.05)) if some else None,
            }
        )
    return out
