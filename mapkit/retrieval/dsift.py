"""Dense SIFT computed the way VLFeat's ``vl_dsift``/``vl_phow`` do: whole maps, not patch by patch.

The observation encoder of MCVL (Sec. III-B of the paper) starts from SIFT descriptors computed
densely "at 4 different scales with region width of 16, 24, 32 and 40, over a grid with spacing
of 2 pixels" (Sec. IV-A). A region of width ``w`` is 4x4 spatial bins of ``w / 4`` pixels, so
the bin sizes are 4, 6, 8 and 10: exactly the defaults of VLFeat's ``vl_phow``, which this module
follows (Vedaldi and Fulkerson, "VLFeat", 2008):

1. **Pre-smoothing** per scale by a Gaussian of sigma = bin size / ``magnif`` (``vl_phow``:
   magnif 6).
2. **Gradient** by central differences (one-sided on the border, as ``vl_dsift``), its modulus
   and angle.
3. **Orientation channels**: the angle is interpolated linearly into 8 bins, each pixel adding
   its gradient modulus to the two nearest bins.
4. **Spatial binning**: each channel is filtered by the triangular (bilinear) kernel of the bin
   size, separably; this is SIFT's bilinear spatial interpolation done once for every
   descriptor. The filtered maps are only needed where bin centres fall, a lattice of spacing
   gcd(bin size, step) (2 px at the defaults), so the maps are decimated to it after the row pass.
5. **Sampling**: a descriptor is the 16 bin-centre values of the 8 channels, read from the
   decimated maps by strided slices (one copy per bin, for a whole block of frames at once),
   weighted by a Gaussian window over the 4x4 bins (SIFT's window; see *Modes* below).
6. **Normalisation** as SIFT: L2, clamp at 0.2, L2 again.

Modes (``DsiftConfig.mode``) differ only in the window of step 5 and in a contrast threshold:

- ``"mapkit"``: the window is a Gaussian of sigma 2 bins (half the descriptor width, Lowe 2004
  and OpenCV) evaluated at the 16 bin centres; every frame keeps its descriptor.
- ``"phow"``: ``vl_phow``'s defaults, i.e. ``vl_dsift`` in its fast mode with window size 1.5.
  The fast mode bins with the flat triangular kernel (as step 4) and then scales each spatial bin
  by the *mean* of a Gaussian of sigma 1.5 bins over the bin's support (the 2 s - 1 pixel offsets
  of the triangle, s the bin size), not by its value at the centre. ``vl_phow`` then zeroes every
  descriptor whose contrast is below 0.005, the contrast being VLFeat's frame "norm": the sum of
  the windowed histogram, with triangles of unit height, divided by the frame's area
  ``(3 s + 1)^2`` pixels (grey levels in [0, 1]). On KITTI frame 0 at
  640x480 this zeroes ~21% of the descriptors and the output matches VLFeat's at median cosine
  > 0.9999 (tests/test_dsift.py), against ~0.997 for ``"mapkit"``.

Geometry (also VLFeat's): a frame is kept when all 16 of its bin centres lie on image pixels, so
a frame of bin size ``s`` spans ``3 s + 1`` pixels between its outer bin centres; the outer half
bins read border-replicated pixels (VLFeat pads "by continuity"). Scales share their frame
centres as in ``vl_phow``: the first bin centre of bin size ``s`` is at ``floor(1.5 (s_max - s))``.
At 640x480 and the defaults this yields 279,838 frames, as VLFeat does.

Descriptor layout (OpenCV's and Lowe's): index ``(row_bin * 4 + col_bin) * 8 + orientation``,
rows from the top of the image, orientation ``o`` covering angles ``o * 45`` degrees measured
counter-clockwise from +x in the upright image (y pointing up). Frames are upright: no dominant
orientation is assigned. Keypoints are ``(x, y)`` centres in pixels of the input image, pixel
``(row, col)`` having its centre at ``(col, row)`` as OpenCV's ``KeyPoint``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, field
from typing import Literal, NamedTuple

import cv2
import numpy as np
from pydantic import Field, field_validator

from mapkit.core.config import MapkitConfig
from mapkit.core.errors import InputError

NUM_SPATIAL_BINS = 4  # per side (SIFT: 4x4)
NUM_ORIENTATIONS = 8  # SIFT: 8
DESCRIPTOR_DIM = NUM_SPATIAL_BINS * NUM_SPATIAL_BINS * NUM_ORIENTATIONS  # 128
_TINY = np.float32(1e-12)  # below any real descriptor norm; keeps flat patches at zero
_BLOCK_DESCRIPTORS = 2048  # frames per block: 1 MiB of float32 descriptors, stays in L2 cache


class DsiftConfig(MapkitConfig):
    """Dense SIFT parameters; defaults are MCVL's (Sec. IV-A) and VLFeat ``vl_phow``'s."""

    region_widths: list[int] = Field(
        [16, 24, 32, 40],
        description="Descriptor region widths (px), one per scale; 4x4 bins of width/4 px each (MCVL Sec. IV-A: 16, "
        "24, 32, 40; = vl_phow Sizes 4 6 8 10).",
    )
    step: int = Field(
        2, ge=1, description="Grid spacing (px) of the frame centres (MCVL Sec. IV-A: 2; vl_phow Step 2)."
    )
    magnif: float | None = Field(
        6.0,
        gt=0,
        description="Each scale is pre-smoothed by a Gaussian of sigma = bin size / magnif (vl_phow Magnif 6); None = "
        "no smoothing.",
    )
    window_sigma_bins: float | None = Field(
        2.0,
        gt=0,
        description="Sigma of the Gaussian window over the 4x4 bins, in bins (SIFT: half the descriptor width = 2, as "
        "in Lowe 2004 and OpenCV); None = flat window. Mode 'mapkit' only (vl_phow's window is mode 'phow').",
    )
    mode: Literal["mapkit", "phow"] = Field(
        "mapkit",
        description="'mapkit': Gaussian window of sigma window_sigma_bins sampled at the bin centres, no contrast "
        "threshold (Lowe 2004, OpenCV). 'phow': VLFeat vl_phow's defaults (Vedaldi and Fulkerson 2008; the extractor "
        "of the MCVL authors): vl_dsift fast mode, each bin weighted by the mean of a Gaussian window of sigma "
        "phow_window_size bins over the bin, and descriptors of contrast below phow_contrast_threshold zeroed; "
        "window_sigma_bins is then unused. Default 'mapkit' by measured recall@1 within 25 m (VLAD, power whitening): "
        "no consistent gain from 'phow' (demo, half resolution: clear 0.90 -> 0.98, night 0.11 -> 0.14, snowy 0.17 -> "
        "0.39; full resolution: night 0.25 -> 0.07, snowy 0.40 -> 0.35; tiny town night: half 0.42 -> 0.37, full 0.28 "
        "-> 0.36): its contrast threshold zeroes the descriptors of under-exposed images.",
    )
    phow_window_size: float = Field(
        1.5, gt=0, description="Mode 'phow': sigma of the Gaussian window, in bins (vl_phow WindowSize 1.5)."
    )
    phow_contrast_threshold: float | None = Field(
        0.005,
        ge=0,
        description="Mode 'phow': descriptors whose contrast (VLFeat's frame norm: windowed histogram mass per pixel "
        "of the frame, grey levels in [0, 1]) is below this are zeroed (vl_phow ContrastThreshold 0.005); None = keep "
        "all.",
    )
    clamp: float = Field(
        0.2, gt=0, le=1, description="SIFT normalisation: L2, clamp at this value, L2 again (Lowe 2004: 0.2)."
    )
    half_resolution: bool = Field(
        False,
        description="Halve the image (area average) before extracting. False = the paper's text (Sec. IV-A); the "
        "authors' released code halves the image (then region widths are in half-resolution pixels).",
    )

    @field_validator("region_widths")
    @classmethod
    def _widths_are_4_bins(cls, v: list[int]) -> list[int]:
        if not v:
            raise ValueError("at least one region width is needed")
        bad = [w for w in v if w < NUM_SPATIAL_BINS or w % NUM_SPATIAL_BINS]
        if bad:
            raise ValueError(f"region widths must be positive multiples of {NUM_SPATIAL_BINS} (4x4 bins), got {bad}")
        return v

    @property
    def bin_sizes(self) -> list[int]:
        return [w // NUM_SPATIAL_BINS for w in self.region_widths]


class DenseSift(NamedTuple):
    keypoints_xy: np.ndarray  # (N, 2) float32, frame centres in input-image pixels
    scale_index: np.ndarray  # (N,) int8, index into DsiftConfig.region_widths
    descriptors: np.ndarray  # (N, 128) float32, SIFT-normalised


@dataclass(frozen=True)
class ScaleGrid:
    """Frames of one scale: first bin centre (x0, y0) of the first frame, counts and spacing (px)."""

    scale_index: int
    bin_size: int
    x0: int
    y0: int
    num_x: int
    num_y: int
    step: int

    @property
    def count(self) -> int:
        return self.num_x * self.num_y

    def centres_xy(self, row0: int = 0, row1: int | None = None) -> np.ndarray:
        """(n, 2) float32 frame centres of frame rows ``row0:row1`` (row-major, as the descriptors)."""
        row1 = self.num_y if row1 is None else row1
        half = 1.5 * self.bin_size  # centre of the 4 bin centres
        xs = self.x0 + half + self.step * np.arange(self.num_x, dtype=np.float32)
        ys = self.y0 + half + self.step * np.arange(row0, row1, dtype=np.float32)
        out = np.empty((len(ys), len(xs), 2), np.float32)
        out[:, :, 0] = xs
        out[:, :, 1] = ys[:, None]
        return out.reshape(-1, 2)


@dataclass
class StepTimer:
    """Wall time per named step, summed over calls (the per-step breakdown of the benchmark)."""

    seconds: dict[str, float] = field(default_factory=dict)

    @contextmanager
    def __call__(self, step: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[step] = self.seconds.get(step, 0.0) + time.perf_counter() - t0


def null_timer(step: str):
    """The timer that times nothing (default of every ``timer`` argument)."""
    return nullcontext()


def to_gray_float(image: np.ndarray, what: str = "image") -> np.ndarray:
    """Grey levels in [0, 1] as contiguous float32 from a uint8/uint16 grey, BGR or BGRA image.

    Float input is taken as grey levels in [0, 1] already.
    """
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[2] in (3, 4):
        code = cv2.COLOR_BGR2GRAY if image.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        if image.dtype not in (np.uint8, np.uint16, np.float32):
            image = image.astype(np.float32)
        image = cv2.cvtColor(image, code)
    elif image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim != 2:
        raise InputError(None, f"{what}: expected a grey (H, W) or BGR (H, W, 3) image, got shape {image.shape}")
    if image.dtype == np.uint8:
        return image.astype(np.float32) * np.float32(1 / 255)
    if image.dtype == np.uint16:
        return image.astype(np.float32) * np.float32(1 / 65535)
    if np.issubdtype(image.dtype, np.floating):
        return np.ascontiguousarray(image, dtype=np.float32)
    raise InputError(None, f"{what}: unsupported pixel type {image.dtype} (uint8, uint16 or float in [0, 1])")


def prepare_image(image: np.ndarray, cfg: DsiftConfig) -> tuple[np.ndarray, float, float]:
    """The float32 grey image dense SIFT runs on, and (scale, shift) mapping its pixel coordinates back
    to the input's: ``x_input = scale * x + shift``."""
    gray = to_gray_float(image)
    if not cfg.half_resolution:
        return gray, 1.0, 0.0
    h, w = gray.shape
    h2, w2 = max(1, h // 2), max(1, w // 2)
    # an even crop makes INTER_AREA an exact 2x2 average: half-res pixel i has its centre at 2i + 0.5
    half = cv2.resize(gray[: 2 * h2, : 2 * w2], (w2, h2), interpolation=cv2.INTER_AREA)
    return half, 2.0, 0.5


def scale_grids(shape_hw: tuple[int, int], cfg: DsiftConfig) -> list[ScaleGrid]:
    """The frames of every scale on an image of ``shape_hw`` (after any halving), VLFeat's geometry."""
    h, w = shape_hw
    sizes = cfg.bin_sizes
    s_max = max(sizes)
    span = NUM_SPATIAL_BINS - 1  # bin-centre spans of a frame: (4 - 1) * bin size
    grids = []
    for i, s in enumerate(sizes):
        off = math.floor(1.5 * (s_max - s))  # vl_phow: all scales share frame centres
        nx = (w - 1 - off - span * s) // cfg.step + 1
        ny = (h - 1 - off - span * s) // cfg.step + 1
        grids.append(ScaleGrid(i, s, off, off, max(nx, 0), max(ny, 0), cfg.step))
    return grids


def _triangle_kernel(bin_size: int) -> np.ndarray:
    """Bilinear weights of one bin: (s - |t|) / s^2 for |t| < s; unit sum."""
    t = np.arange(-bin_size + 1, bin_size, dtype=np.float32)
    return ((bin_size - np.abs(t)) / np.float32(bin_size * bin_size)).astype(np.float32)


def _gradient(gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Central differences, one-sided on the border (vl_dsift); y pointing down."""
    gx = cv2.Sobel(gray, cv2.CV_32F, 1, 0, ksize=1, scale=0.5, borderType=cv2.BORDER_REPLICATE)
    gy = cv2.Sobel(gray, cv2.CV_32F, 0, 1, ksize=1, scale=0.5, borderType=cv2.BORDER_REPLICATE)
    # replicated border gives half the one-sided difference there
    gx[:, 0] *= 2
    gx[:, -1] *= 2
    gy[0] *= 2
    gy[-1] *= 2
    return gx, gy


def binned_maps(gray: np.ndarray, grid: ScaleGrid, magnif: float | None) -> tuple[np.ndarray, int]:
    """Spatially binned orientation maps of one scale, decimated to the bin-centre lattice.

    Returns ``(maps, g)``: ``maps[o, r, c]`` (planar, float32) is orientation ``o`` binned around
    pixel ``(y0 % g + g r, x0 % g + g c)``, with ``g = gcd(bin size, step)``.
    """
    s = grid.bin_size
    smoothed = cv2.GaussianBlur(gray, (0, 0), s / magnif, borderType=cv2.BORDER_REPLICATE) if magnif else gray
    gx, gy = _gradient(smoothed)
    np.negative(gy, out=gy)  # angles counter-clockwise with y up (OpenCV's and Lowe's convention)
    magnitude, angle = cv2.cartToPolar(gx, gy)
    bin_pos = angle
    bin_pos *= np.float32(NUM_ORIENTATIONS / (2 * np.pi))  # in [0, 8]
    g = math.gcd(s, grid.step)
    kernel = _triangle_kernel(s)
    kx, ky = kernel[None, :], kernel[:, None]
    h, w = gray.shape
    maps = np.empty((NUM_ORIENTATIONS, len(range(grid.y0 % g, h, g)), len(range(grid.x0 % g, w, g))), np.float32)
    for o in range(NUM_ORIENTATIONS):
        # linear interpolation of the angle between the two nearest of the 8 bins:
        # weight max(0, 1 - |bin_pos - o|), bin 0 also taking the wrap-around from bin_pos in (7, 8)
        weight = np.subtract(bin_pos, o)
        np.abs(weight, out=weight)
        np.subtract(1, weight, out=weight)
        np.maximum(weight, 0, out=weight)
        if o == 0:
            wrap = np.subtract(bin_pos, NUM_ORIENTATIONS - 1)
            np.maximum(wrap, 0, out=wrap)
            weight += wrap
        weight *= magnitude
        # separable bilinear binning; columns are decimated between the passes
        rows = cv2.filter2D(weight, -1, kx, borderType=cv2.BORDER_REPLICATE)
        rows = np.ascontiguousarray(rows[:, grid.x0 % g :: g])
        maps[o] = cv2.filter2D(rows, -1, ky, borderType=cv2.BORDER_REPLICATE)[grid.y0 % g :: g]
    return maps, g


def _window_weights(sigma_bins: float | None) -> np.ndarray:
    """(16,) Gaussian weight of each spatial bin (value at the bin centre), row-major."""
    if sigma_bins is None:
        return np.ones(NUM_SPATIAL_BINS * NUM_SPATIAL_BINS, np.float32)
    u = np.arange(NUM_SPATIAL_BINS) - (NUM_SPATIAL_BINS - 1) / 2
    w1 = np.exp(-0.5 * (u / sigma_bins) ** 2)
    return np.outer(w1, w1).ravel().astype(np.float32)


def _bin_mean_window_weights(bin_size: int, sigma_bins: float) -> np.ndarray:
    """(16,) weight of each spatial bin: the mean of the Gaussian window over the bin (vl_dsift fast mode).

    The mean is taken at the ``2 s - 1`` integer offsets the bin's triangle covers around its
    centre, unweighted (the window multiplies the bin after the flat triangular binning, so the
    triangle's own weights do not enter). Depends on the bin size through this sampling.
    """
    s = bin_size
    centres = s * (np.arange(NUM_SPATIAL_BINS) - (NUM_SPATIAL_BINS - 1) / 2)  # bin centres from the frame centre, px
    offsets = np.arange(-s + 1, s)
    w1 = np.exp(-0.5 * ((offsets[None, :] + centres[:, None]) / (sigma_bins * s)) ** 2).mean(axis=1)
    return np.outer(w1, w1).ravel().astype(np.float32)


def bin_weights(cfg: DsiftConfig, bin_size: int) -> np.ndarray:
    """(16,) window weight of each spatial bin (row-major) for the mode of ``cfg``."""
    if cfg.mode == "phow":
        return _bin_mean_window_weights(bin_size, cfg.phow_window_size)
    return _window_weights(cfg.window_sigma_bins)


def _low_contrast_frames(
    maps: np.ndarray, grid: ScaleGrid, g: int, weights: np.ndarray, threshold: float
) -> np.ndarray:
    """(num_y, num_x) bool: frames of ``grid`` whose contrast (VLFeat's frame norm) is below ``threshold``.

    A frame's contrast is the sum of its windowed histogram, so the 8 orientation maps are summed
    first and each frame reads 16 values instead of 128; the whole grid at once, in 16 array
    operations (per block they would cost more in calls than in arithmetic).
    """
    s = grid.bin_size
    mass = maps.sum(axis=0)
    hb, hs = s // g, grid.step // g
    bx, by = grid.x0 // g, grid.y0 // g
    nx, ny = grid.num_x, grid.num_y
    contrast = np.zeros((ny, nx), np.float32)
    term = np.empty_like(contrast)
    for i in range(NUM_SPATIAL_BINS):
        r = by + i * hb
        for j in range(NUM_SPATIAL_BINS):
            c = bx + j * hb
            np.multiply(
                mass[r : r + (ny - 1) * hs + 1 : hs, c : c + (nx - 1) * hs + 1 : hs],
                weights[i * NUM_SPATIAL_BINS + j],
                out=term,
            )
            contrast += term
    # VLFeat bins with triangles of unit height, s^2 times this module's unit-integral ones, and
    # divides by the frame's area (3 s + 1)^2: a gradient mass per pixel, comparable across scales
    contrast *= np.float32(s * s / ((NUM_SPATIAL_BINS - 1) * s + 1) ** 2)
    return contrast < threshold


class HistogramBlock(NamedTuple):
    grid: ScaleGrid
    row0: int  # first frame row of the block
    row1: int
    histograms: np.ndarray  # (n, 128) float32 windowed, not normalised; a view of a reused buffer


def iter_histogram_blocks(
    gray: np.ndarray, cfg: DsiftConfig, block_descriptors: int = _BLOCK_DESCRIPTORS, timer=null_timer
) -> Iterator[HistogramBlock]:
    """Raw (windowed, unnormalised) SIFT histograms of every frame, scale by scale, in row blocks.

    ``gray`` is the float32 image of ``prepare_image``. The block's array is overwritten by the next block:
    copy what must outlive it. ``timer`` (a ``StepTimer``) receives the time of ``maps``, ``sample`` and, in
    mode ``"phow"``, ``contrast``.
    In mode ``"phow"`` the histograms of frames below the contrast threshold are zero.
    """
    threshold = cfg.phow_contrast_threshold if cfg.mode == "phow" else None
    for grid in scale_grids(gray.shape, cfg):
        if grid.count == 0:
            continue
        weights = bin_weights(cfg, grid.bin_size)
        with timer("maps"):
            maps, g = binned_maps(gray, grid, cfg.magnif)
        # in lattice units: bin spacing, frame step, first bin centre
        hb, hs = grid.bin_size // g, grid.step // g
        bx, by = grid.x0 // g, grid.y0 // g
        nx = grid.num_x
        rows_per_block = max(1, min(grid.num_y, block_descriptors // nx))
        # bins-major buffer: every copy below moves a run of nx floats; one transpose per frame row
        # then gives the (frames, 128) layout (far faster than copying 8 floats at a time into it)
        by_bin = np.empty((rows_per_block, NUM_SPATIAL_BINS * NUM_SPATIAL_BINS, NUM_ORIENTATIONS, nx), np.float32)
        by_frame = np.empty((rows_per_block, nx, DESCRIPTOR_DIM), np.float32)
        if threshold:
            with timer("contrast"):
                low_contrast = _low_contrast_frames(maps, grid, g, weights, threshold)
        for row0 in range(0, grid.num_y, rows_per_block):
            row1 = min(grid.num_y, row0 + rows_per_block)
            n = row1 - row0
            with timer("sample"):
                for i in range(NUM_SPATIAL_BINS):
                    r = by + i * hb + row0 * hs
                    rows = maps[:, r : r + (n - 1) * hs + 1 : hs].transpose(1, 0, 2)  # (n, 8, cols)
                    for j in range(NUM_SPATIAL_BINS):
                        c = bx + j * hb
                        k = i * NUM_SPATIAL_BINS + j
                        np.multiply(rows[:, :, c : c + (nx - 1) * hs + 1 : hs], weights[k], out=by_bin[:n, k])
                for r in range(n):  # dst is contiguous and of the right shape: cv2 writes into it
                    cv2.transpose(by_bin[r].reshape(DESCRIPTOR_DIM, nx), by_frame[r])
            histograms = by_frame[:n].reshape(n * nx, DESCRIPTOR_DIM)
            if threshold:
                with timer("contrast"):
                    histograms[low_contrast[row0:row1].ravel()] = 0
            yield HistogramBlock(grid, row0, row1, histograms)


def sift_normalize(histograms: np.ndarray, clamp: float = 0.2, out: np.ndarray | None = None) -> np.ndarray:
    """SIFT normalisation of rows: L2, clamp at ``clamp``, L2 again (Lowe 2004). Zero rows stay zero."""
    if out is None:
        out = np.array(histograms, dtype=np.float32, copy=True)
    elif out is not histograms:
        np.copyto(out, histograms)
    norm = np.sqrt(np.einsum("ij,ij->i", out, out))
    out /= np.maximum(norm, _TINY)[:, None]
    np.minimum(out, np.float32(clamp), out=out)
    norm = np.sqrt(np.einsum("ij,ij->i", out, out))
    out /= np.maximum(norm, _TINY)[:, None]
    return out


def dense_sift(image: np.ndarray, cfg: DsiftConfig | None = None) -> DenseSift:
    """Dense SIFT of a grey or BGR image: keypoints (N, 2) xy, scale index (N,), descriptors (N, 128).

    Scales come one after the other (in ``cfg.region_widths`` order), each row-major over its grid.
    At 640x480 the full default set is ~143 MB of descriptors; ``iter_histogram_blocks`` streams.
    """
    cfg = cfg or DsiftConfig()
    gray, scale, shift = prepare_image(image, cfg)
    grids = scale_grids(gray.shape, cfg)
    total = sum(gr.count for gr in grids)
    keypoints = np.empty((total, 2), np.float32)
    scale_index = np.empty(total, np.int8)
    descriptors = np.empty((total, DESCRIPTOR_DIM), np.float32)
    starts = np.cumsum([0] + [gr.count for gr in grids])
    for blk in iter_histogram_blocks(gray, cfg):
        a = starts[blk.grid.scale_index] + blk.row0 * blk.grid.num_x
        b = a + len(blk.histograms)
        sift_normalize(blk.histograms, cfg.clamp, out=descriptors[a:b])
    for gr, a, b in zip(grids, starts[:-1], starts[1:], strict=True):
        keypoints[a:b] = gr.centres_xy()
        scale_index[a:b] = gr.scale_index
    if scale != 1.0:
        keypoints *= np.float32(scale)
        keypoints += np.float32(shift)
    return DenseSift(keypoints, scale_index, descriptors)


def opencv_keypoint_size(region_width: float) -> float:
    """``KeyPoint.size`` for which OpenCV's SIFT descriptor covers ``region_width`` pixels.

    OpenCV (``calcSIFTDescriptor``) makes a spatial bin ``3 * sigma`` wide with sigma =
    ``size / 2`` at octave 0, so its 4 bins span ``4 * 1.5 * size``: size = width / 6.
    """
    return region_width / 6.0
