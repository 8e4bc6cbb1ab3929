"""Hand-crafted structure descriptors of semi-dense patches: NBLD and M2DP, plus PCA to 25 dims.

Sec. 3.3.1 of the semi-dense place-recognition paper evaluates two descriptors that need no
surface normals (semi-dense clouds are too thin for them):

- **NBLD**, neighbour-binary landmark density (Cieslewski et al., ICRA 2016, "Point cloud
  descriptors for place recognition using sparse visual information"): a vertical cylinder cut
  into ``n_radial`` rings, ``n_azimuth`` sectors and ``n_vertical`` layers; the density of a
  cell is its point count over its volume; each cell contributes three bits, "denser than the
  next cell outwards / counter-clockwise / upwards".
- **M2DP**, multiview 2D projection (He, Wang, Zhang, IROS 2016): the points are projected onto
  ``p * q`` planes through the keypoint; on each plane a polar grid of ``l`` rings and ``t``
  sectors counts them; the (p q) x (l t) count matrix is summarised by its first left and right
  singular vectors. :func:`m2dp_reference` is M2DP of a whole cloud exactly as the authors'
  ``M2DP.m`` computes it (checked against its output on a KITTI scan); the patch descriptor
  differs from it in three settings of ``M2DPConfig`` (grid radius, in-plane axes, frame), and
  with ``M2DPConfig.authors()`` it computes the reference on each patch.

Both work on many patches at once: the points of all patches (CSR, as in ``mapkit.places.patches``)
are binned in a few vectorised passes and counted with one call per block of patches for NBLD
(``np.bincount``) and one per patch for M2DP (``cv2.calcHist`` over ~60 planes x 162 bins, on
bin ids made by OpenCV's SIMD passes), and M2DP's leading singular pairs come from one batched
power iteration over a few hundred patches. ``describe`` chains extraction, yaw normalisation and a
descriptor; ``DescriptorPCA`` projects descriptors to 25 dimensions before matching ("all of the
above descriptors are projected down to a 25-dimensional space via PCA", Sec. 5.2).

Defaults and their sources: NBLD's domain (r = 10 m, h = 20 m) is the semi-dense paper's (Fig. 6
caption); its subdivisions (8 sectors, 3 rings, 4 layers) are mapkit's choice, the NBLD paper's
values not being at hand. M2DP's p = 4, q = 16, l = 8, t = 16 (192 dimensions) are those of the
original paper and its reference code; its default radius, the domain's 10 m, is mapkit's
choice (the semi-dense paper does not state it; the authors' code takes the farthest point).
Points are binned in float32: a point within ~1e-6 rad or ~1e-6 m of a bin edge may fall on
either side, as it may in any implementation.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
from pydantic import Field, model_validator
from scipy.spatial import cKDTree

from mapkit.core.config import MapkitConfig
from mapkit.core.errors import InputError
from mapkit.places.patches import (
    M2DP_DOMAIN,
    NBLD_DOMAIN,
    PatchDomain,
    extract_patches,
    gather_local,
    keypoint_blocks,
    patch_blocks,
    xy_tree,
    yaw_normalise_patches,
)

_NBLD_CHUNK_POINTS = 1 << 16  # patch points per block (NBLD works on ~10 arrays of this length)
_NBLD_CHUNK_PATCHES = 1 << 14  # ... and patches per block (bounds the bincount output)
_M2DP_CHUNK_POINTS = (
    1 << 12
)  # patch points per block; x 61 planes: float32 work arrays of ~1 MiB (larger blocks: no faster)
_M2DP_CHUNK_PATCHES = 256  # ... and patches per block and per batched singular-vector solve
_M2DP_FRAME_POINTS = (
    1 << 18
)  # patch points per block put into the PCA frame / scaled at once (float64 temporaries of ~10 MiB)
_M2DP_PCA_LOOP_POINTS = 256  # patches of at least this many points get their PCA frame one at a time


class NBLDConfig(MapkitConfig):
    """NBLD (Cieslewski et al. 2016) on the domain of the semi-dense paper."""

    domain: PatchDomain = Field(
        NBLD_DOMAIN,
        description="Finite vertical cylinder; r = 10 m, h = 20 m from the semi-dense paper (Fig. 6 caption).",
    )
    n_azimuth: int = Field(
        8,
        ge=2,
        description="Azimuthal sectors n_a, from the patch x-axis counter-clockwise (mapkit's choice: 45 deg sectors).",
    )
    n_radial: int = Field(3, ge=1, description="Rings n_r of equal width (mapkit's choice).")
    # 8 x 3 x 8 = 192 cells: a patch of 500-3000 points has ~3-15 points per cell on average
    n_vertical: int = Field(
        8,
        ge=1,
        description="Layers n_z of equal height: 2.5 m layers (mapkit's choice, measured: the paper "
        "gives no counts). Chosen on the tiny town's 3 pairs (mean AUC 0.199 against 0.154 with 4 layers; "
        "8x2x2 0.125, 8x3x6 0.098, 16x3x8 0.171); on the demo's 8 pairs, not used to choose, held-out mean "
        "AUC 0.308 against 0.217 with 4 layers, all places 0.179 against 0.127. Facades and trees differ by "
        "height more than by azimuth at this radius.",
    )

    @model_validator(mode="after")
    def _check(self) -> NBLDConfig:
        if self.domain.kind != "cylinder":
            raise ValueError(f"NBLD needs a finite cylinder domain, got {self.domain.kind}")
        return self

    @property
    def dim(self) -> int:
        return 3 * self.n_radial * self.n_azimuth * self.n_vertical


class M2DPConfig(MapkitConfig):
    """M2DP (He et al. 2016); the counts are those of the original paper and code.

    Three settings say how a patch is put onto the planes' polar grids; the authors' ``M2DP.m``
    (written for a whole scan) and mapkit's patch descriptor differ in each of them:

    - ``radius``: the outer radius of the grid. ``domain`` is the patch domain's radius r, a
      fixed metric grid for every patch (the semi-dense paper's infinite cylinder of radius r,
      Sec. 3.3.1); points whose projection lies beyond r are left out. ``farthest`` is the
      distance of the patch's farthest point from the origin of its frame, as ``M2DP.m`` takes it,
      so that every point lands on the grid and the grid scales with the patch.
    - ``normalise_axes``: the in-plane x-axis of each plane is the projection of the frame's
      x-axis onto the plane; normalised (metric in-plane coordinates), or left at its length
      sqrt(1 - n_x^2) as ``M2DP.m`` leaves it (its y-axis, normal x x-axis, has the same length).
    - ``frame``: ``yaw`` describes the patch in its yaw-normalised frame about the keypoint
      (Sec. 3.2); ``pca`` first centres it on its mean and rotates it onto its principal axes
      (x the first, y the second; each axis signed so that its largest coefficient is positive,
      MATLAB's ``pca`` convention), as ``M2DP.m`` does for rotation invariance.

    The defaults are mapkit's patch descriptor (domain radius, normalised axes, yaw frame), chosen
    by place-recognition AUC: on the demo's 8 session pairs (all places; ``mapkit eval places``)
    mean AUC 0.257 with the defaults, 0.150 with the farthest-point radius, 0.081 with all three
    of ``M2DP.m``'s settings; on the tiny town's 3 pairs, not used to choose, 0.148 / 0.132 /
    0.032. The authors' settings describe a whole scan; on a 10 m patch the farthest point moves
    the grid with every outlier and the PCA frame flips between similar patches.
    :meth:`authors` gives the settings of ``M2DP.m``, with which :func:`m2dp_patches` computes
    :func:`m2dp_reference` on each patch.
    """

    domain: PatchDomain = Field(
        M2DP_DOMAIN,
        description="Infinite vertical cylinder; r = 10 m (the semi-dense paper leaves r open). "
        "It bounds the patch in any case; with radius = domain it is also the grid's radius.",
    )
    n_plane_azimuths: int = Field(
        4, ge=1, description="p: plane-normal azimuths, linearly spaced over [-pi/2, pi/2] (M2DP default 4)."
    )
    n_plane_elevations: int = Field(
        16, ge=1, description="q: plane-normal elevations, linearly spaced over [0, pi/2] (M2DP default 16)."
    )
    n_radial: int = Field(
        8, ge=1, description="l: rings per plane, outer radii r * (i / l)^2 as in the original (M2DP default 8)."
    )
    n_angular: int = Field(16, ge=1, description="t: sectors per plane over [-pi, pi) (M2DP default 16).")
    radius: Literal["domain", "farthest"] = Field(
        "domain",
        description="Grid radius r: the patch domain's radius, points beyond it left out (default; the semi-dense "
        "paper's domain), or the distance of the patch's farthest point, every point on the grid (M2DP.m).",
    )
    normalise_axes: bool = Field(
        True,
        description="Normalise each plane's in-plane axes (default: metric in-plane coordinates), or leave them at "
        "length sqrt(1 - n_x^2) as M2DP.m does.",
    )
    frame: Literal["yaw", "pca"] = Field(
        "yaw",
        description="The patch's yaw-normalised frame about its keypoint (default, Sec. 3.2 of the semi-dense paper), "
        "or centred on its mean and rotated onto its principal axes (M2DP.m).",
    )
    max_points: int | None = Field(
        None,
        ge=16,
        description="Thin each patch to about this many points before describing it (thin_patches: a fixed "
        "pseudo-random choice of map points); None = every point, as M2DP and the semi-dense paper do (default). "
        "M2DP's cost is linear in the points; the singular vectors barely move when a dense patch is thinned.",
    )

    @model_validator(mode="after")
    def _check(self) -> M2DPConfig:
        if self.domain.kind == "cube":
            raise ValueError("M2DP needs a cylinder domain (its polar grid has the cylinder's radius)")
        return self

    @classmethod
    def authors(cls, **overrides) -> M2DPConfig:
        """The settings of the authors' ``M2DP.m``: farthest-point radius, unnormalised in-plane
        axes, centred PCA frame (``overrides``: any other field, e.g. the domain)."""
        return cls(**{"radius": "farthest", "normalise_axes": False, "frame": "pca", **overrides})

    @property
    def n_planes(self) -> int:
        return self.n_plane_azimuths * self.n_plane_elevations

    @property
    def dim(self) -> int:
        return self.n_planes + self.n_radial * self.n_angular


class StructureDescriptorConfig(MapkitConfig):
    """Hand-crafted structure descriptors of Sec. 3.3.1 and their PCA (Sec. 5.2)."""

    keypoint_fraction: float = Field(
        0.05,
        gt=0,
        le=1,
        description="Fraction of map points drawn as keypoints by the caller of describe() (Sec. 3.2: a random five "
        "percent).",
    )
    nbld: NBLDConfig = Field(default_factory=NBLDConfig, description="NBLD parameters.")
    m2dp: M2DPConfig = Field(default_factory=M2DPConfig, description="M2DP parameters.")
    pca_dim: int = Field(25, ge=1, description="Dimensions kept by PCA before matching (Sec. 5.2: 25).")


# --- NBLD -------------------------------------------------------------------------------------------


def nbld_cell_volumes(cfg: NBLDConfig) -> np.ndarray:
    """(n_radial,) volume (m^3) of one cell of each ring: annular sector times layer height."""
    radius, height = cfg.domain.radius, cfg.domain.height
    assert radius is not None and height is not None  # NBLDConfig's domain is a finite cylinder
    edges = np.linspace(0.0, radius, cfg.n_radial + 1)
    return math.pi * np.diff(edges**2) / cfg.n_azimuth * (height / cfg.n_vertical)


def nbld_counts(points_normalised: np.ndarray, indptr: np.ndarray, cfg: NBLDConfig | None = None) -> np.ndarray:
    """(M, n_radial, n_azimuth, n_vertical) point counts of the NBLD cells of each patch.

    Ring i covers radii [i, i + 1) * r / n_r; sector j azimuths [j, j + 1) * 2 pi / n_a counted
    from the normalised x-axis towards +y; layer k heights -h/2 + [k, k + 1) * h / n_z. Points on
    the outer boundary (r or h/2 exactly) fall into the last cell; points outside are left out.
    Points on the axis (the keypoint itself) have no azimuth and count in sector 0.
    """
    cfg = cfg or NBLDConfig()
    pts = _as_points(points_normalised)
    indptr = np.asarray(indptr, np.int64)
    m = len(indptr) - 1
    nr, na, nz = cfg.n_radial, cfg.n_azimuth, cfg.n_vertical
    assert cfg.domain.radius is not None and cfg.domain.height is not None  # a finite cylinder (NBLDConfig)
    R, H = float(cfg.domain.radius), float(cfg.domain.height)
    cells = nr * na * nz
    out = np.zeros((m, nr, na, nz), np.int64)
    # float32 / int32 throughout: numpy's float64 arctan2 is not vectorised, and the narrower
    # types halve the memory traffic of these ~20 passes
    for k0, k1 in patch_blocks(
        indptr, _NBLD_CHUNK_POINTS, min(_NBLD_CHUNK_PATCHES, (1 << 31) // cells)
    ):  # int32 cell ids
        a, b = indptr[k0], indptr[k1]
        x, y, z = np.ascontiguousarray(pts[a:b].T, dtype=np.float32)
        rho2 = x * x
        rho2 += y * y
        keep = rho2 <= np.float32(R * R)
        keep &= np.abs(z) <= np.float32(H / 2)
        ir = (np.sqrt(rho2) * np.float32(nr / R)).astype(np.int32)
        np.minimum(ir, nr - 1, out=ir)  # rho = r exactly
        # atan2(-y, -x) + pi is the azimuth in [0, 2 pi]
        az = np.arctan2(np.negative(y), np.negative(x))
        az += np.float32(math.pi)
        az *= np.float32(na / (2 * math.pi))
        ia = az.astype(np.int32)
        np.minimum(ia, na - 1, out=ia)  # azimuth 2 pi exactly
        ia[rho2 == 0] = 0  # the keypoint itself: atan2 of signed zeros is any of 0, +-pi
        z += np.float32(H / 2)
        z *= np.float32(nz / H)
        iz = z.astype(np.int32)
        np.minimum(iz, nz - 1, out=iz)  # z = h / 2 exactly
        flat = np.repeat(np.arange(k1 - k0, dtype=np.int32) * cells, np.diff(indptr[k0 : k1 + 1]))
        ir *= na * nz
        ia *= nz
        flat += ir
        flat += ia
        flat += iz
        out[k0:k1] = np.bincount(flat[keep], minlength=(k1 - k0) * cells).reshape(k1 - k0, nr, na, nz)
    return out


def nbld_bits_from_counts(counts: np.ndarray, cfg: NBLDConfig | None = None) -> np.ndarray:
    """(M, 3, n_r, n_a, n_z) uint8 NBLD bits from cell counts (M, n_r, n_a, n_z).

    Channel 0 (radial): the cell is denser than the cell of the next ring outwards; the outer
    ring is compared with 0 (beyond the domain nothing is known, as in ``density_comparison``).
    Channel 1 (azimuthal): denser than the next sector counter-clockwise, wrapping around.
    Channel 2 (vertical): denser than the layer above; the top layer is compared with 0.
    Comparisons are strict, so two equally dense (e.g. empty) cells give 0.
    """
    cfg = cfg or NBLDConfig()
    d = np.asarray(counts, np.float64) / nbld_cell_volumes(cfg)[None, :, None, None]
    out = np.empty((d.shape[0], 3) + d.shape[1:], np.uint8)
    outward = np.zeros_like(d)
    outward[:, :-1] = d[:, 1:]
    out[:, 0] = d > outward
    out[:, 1] = d > np.roll(d, -1, axis=2)
    up = np.zeros_like(d)
    up[..., :-1] = d[..., 1:]
    out[:, 2] = d > up
    return out


def nbld_patches(
    points_normalised: np.ndarray, indptr: np.ndarray, cfg: NBLDConfig | None = None, packed: bool = False
) -> np.ndarray:
    """NBLD of many yaw-normalised patches: (M, 3 n_r n_a n_z) float32 0/1, or packed uint8.

    Bit order is that of :func:`nbld_bits_from_counts` flattened in C order (channel, ring,
    sector, layer). ``packed`` returns ``np.packbits`` bytes per row (Hamming matching); the float
    form is what PCA and L2 matching take.
    """
    cfg = cfg or NBLDConfig()
    bits = nbld_bits_from_counts(nbld_counts(points_normalised, indptr, cfg), cfg).reshape(len(indptr) - 1, -1)
    return np.packbits(bits, axis=1) if packed else bits.astype(np.float32)


# --- M2DP -------------------------------------------------------------------------------------------


def _plane_axes(p: int, q: int, normalise: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normals and in-plane x- and y-axes (each (p q, 3)) of the M2DP planes, azimuth-major."""
    az = np.linspace(-math.pi / 2, math.pi / 2, p)
    el = np.linspace(0.0, math.pi / 2, q)
    a_grid, e_grid = np.meshgrid(az, el, indexing="ij")
    a, e = a_grid.ravel(), e_grid.ravel()
    normal = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], axis=1)
    ax = np.array([1.0, 0.0, 0.0]) - normal[:, :1] * normal
    short = np.linalg.norm(ax, axis=1) < 1e-9
    ax[short] = np.array([0.0, 1.0, 0.0]) - normal[short, 1:2] * normal[short]
    if normalise:
        ax /= np.linalg.norm(ax, axis=1, keepdims=True)
    ay = np.cross(normal, ax)
    return normal, ax, ay


def m2dp_planes(cfg: M2DPConfig | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normals and in-plane axes (each (p q, 3)) of the M2DP planes, azimuth-major.

    Plane (i, j) has the normal (cos e_j cos a_i, cos e_j sin a_i, sin e_j) with azimuth a_i and
    elevation e_j (row ``i q + j`` of the signature matrix, the original's loop order). Its
    in-plane x-axis is the projection of the frame's x-axis onto the plane, x - (x . n) n, of
    length sqrt(1 - n_x^2); with ``cfg.normalise_axes`` (the default) it is normalised, so that
    the in-plane coordinates are metric and a fixed grid radius means the same on every plane.
    The authors' code leaves it unnormalised (``normalise_axes=False``), which shrinks the
    coordinates on the planes facing x. Its y-axis is normal x x-axis (of the same length). Where
    the x-axis is the normal itself (azimuth 0 and elevation 0, absent from any even p, as the
    default p = 4) the frame's y-axis is projected instead (the authors' code would get a zero axis).
    """
    cfg = cfg or M2DPConfig()
    return _plane_axes(cfg.n_plane_azimuths, cfg.n_plane_elevations, cfg.normalise_axes)


def m2dp_pca_frame(points: np.ndarray, indptr: np.ndarray) -> np.ndarray:
    """(n, 3) float64 points of each patch centred on the patch's mean and rotated onto its
    principal axes: coordinates along the first, second and third principal axis.

    This is the rotation invariance of the authors' ``M2DP.m`` (centre on the mean, then
    MATLAB's ``pca``), batched over patches: the 3 x 3 scatter matrices' eigenvectors come from
    one stacked ``np.linalg.eigh``. Each axis is signed so that its coefficient of largest
    magnitude is positive (MATLAB's and Octave's ``pca`` convention; a tie keeps the sign). The
    third axis is the third principal axis so signed, not the cross product of the first two, as
    in ``M2DP.m``: the frame may be a reflection. Patches of at least 256 points are centred,
    summed and rotated one at a time (BLAS on each; the Python loop costs little per point),
    smaller ones all at once (``np.bincount``); which way a patch goes depends on its size only,
    so a patch gets the same frame, to the last bit, alone or among others.
    """
    pts = _as_points(points)
    indptr = np.asarray(indptr, np.int64)
    counts = np.diff(indptr)
    m = len(counts)
    centred = np.empty_like(pts)
    out = np.empty_like(pts)
    S = np.zeros((m, 3, 3))
    big = np.flatnonzero(counts >= _M2DP_PCA_LOOP_POINTS)
    small = np.flatnonzero((counts > 0) & (counts < _M2DP_PCA_LOOP_POINTS))
    ones = np.ones(int(counts.max(initial=0)))
    for k in big:
        a, b = indptr[k], indptr[k + 1]
        c = np.subtract(
            pts[a:b], (ones[: b - a] @ pts[a:b]) / (b - a), out=centred[a:b]
        )  # a dot: ~10x numpy's mean(axis=0) on (n, 3)
        np.matmul(c.T, c, out=S[k])
    if len(small):
        cs = counts[small]
        sel = np.repeat(counts < _M2DP_PCA_LOOP_POINTS, counts)
        pid = np.repeat(np.arange(len(small)), cs)
        c = pts[sel]
        c -= np.stack([np.bincount(pid, c[:, i], minlength=len(small)) for i in range(3)], axis=1)[pid] / cs[pid, None]
        for i in range(3):
            for j in range(i, 3):
                S[small, i, j] = S[small, j, i] = np.bincount(pid, c[:, i] * c[:, j], minlength=len(small))
    V = np.linalg.eigh(S)[1][:, :, ::-1]  # columns by decreasing eigenvalue
    V *= np.where(V.max(axis=1) < -V.min(axis=1), -1.0, 1.0)[:, None, :]
    for k in big:
        a, b = indptr[k], indptr[k + 1]
        np.matmul(centred[a:b], V[k], out=out[a:b])
    if len(small):
        out[sel] = np.einsum("ni,nij->nj", c, np.repeat(V[small], cs, axis=0))
    return out


def m2dp_reference_signature(points_xyz: np.ndarray, p: int = 4, q: int = 16, l: int = 8, t: int = 16) -> np.ndarray:  # noqa: E741 (l: the number of lines, the M2DP paper's symbol)
    """(p q, l t) float64 point counts of one cloud on the M2DP planes, as the authors' ``M2DP.m``.

    The cloud is centred on its mean and rotated onto its principal axes (:func:`m2dp_pca_frame`);
    the grid radius R is the distance of the farthest point from the mean; each plane's in-plane
    axes are x - (x . n) n and n x that, unnormalised. The bins are the authors': sector edges
    ``linspace(-pi, pi, t + 1)``, ring edges ``linspace(0, sqrt(R), l + 1)^2``, a value on an
    edge going to the bin above it and anything beyond the last edge to the last bin (their
    ``CountVote2D``). A point projected onto the mean exactly counts as angle 0 (``atan2(0, 0)``;
    numpy's ``arctan2`` of negative zeros would give +-pi). Counts are not divided by
    the number of points as in the original (the singular vectors do not depend on scale).
    Straightforward float64 numpy, one plane at a time: the reference the batched
    :func:`m2dp_patches` is tested against, not a fast path.
    """
    pts = _as_points(points_xyz)
    A = np.zeros((p * q, l * t))
    if not len(pts):
        return A
    d = m2dp_pca_frame(pts, np.array([0, len(pts)]))
    R = math.sqrt(float(np.max(np.einsum("ij,ij->i", d, d))))
    sector_edges = np.linspace(-math.pi, math.pi, t + 1)[1:t]
    ring_edges = (np.linspace(0.0, math.sqrt(R), l + 1) ** 2)[1:l]
    _, ax, ay = _plane_axes(p, q, normalise=False)
    for k in range(p * q):
        x, y = d @ ax[k], d @ ay[k]
        theta = np.arctan2(y, x)
        theta[(x == 0) & (y == 0)] = 0.0
        sector = np.searchsorted(sector_edges, theta, side="right")
        ring = np.searchsorted(ring_edges, np.hypot(x, y), side="right")
        A[k] = np.bincount(ring * t + sector, minlength=l * t)
    return A


def m2dp_reference(points_xyz: np.ndarray, p: int = 4, q: int = 16, l: int = 8, t: int = 16) -> np.ndarray:  # noqa: E741 (l: the number of lines, the M2DP paper's symbol)
    """M2DP (p q + l t,) float64 of one whole cloud exactly as the authors' ``M2DP.m`` computes it
    (He, Wang, Zhang, IROS 2016; signature matrix of :func:`m2dp_reference_signature`), [u1, v1]
    of a float64 SVD.

    The authors' signs are whatever their SVD returns; here, as in :func:`m2dp_patches`, the pair
    is signed so that v1 sums to >= 0 (both non-negative for a non-negative matrix). An empty
    cloud gives zeros. ``m2dp_patches`` with ``M2DPConfig.authors()`` computes the same on each
    patch (in float32).
    """
    A = m2dp_reference_signature(points_xyz, p, q, l, t)
    if not A.any():
        return np.zeros(p * q + l * t)
    U, _, Vt = np.linalg.svd(A)
    u, v = U[:, 0], Vt[0]
    return np.concatenate([u, v]) * (1.0 if v.sum() >= 0 else -1.0)


def m2dp_signature_matrices(
    points_normalised: np.ndarray, indptr: np.ndarray, cfg: M2DPConfig | None = None
) -> np.ndarray:
    """(M, p q, l t) float32 point counts of each patch on the M2DP planes' polar grids.

    On each plane, the in-plane angle theta in [-pi, pi] falls into sector
    floor((theta + pi) t / 2 pi) (theta = pi into the last one), and the in-plane distance rho
    into ring i when r (i / l)^2 <= rho < r ((i + 1) / l)^2, the original's concentric circles of
    radii r (i / l)^2. With ``cfg.radius == "domain"`` points with rho >= r lie outside the grid
    and are not counted (the grid ends at r, Sec. 3.3.1); with ``"farthest"`` r is the patch's
    farthest point, as in the original, and a point at rho >= r (only the farthest one, in a plane
    that holds it) counts in the last ring, as the original's ``CountVote2D`` counts it.
    A point at the origin of the frame (the keypoint, or the mean in the ``pca`` frame) has no
    angle; it counts as theta = 0 (as atan2(0, 0) = 0); in the ``farthest`` case a patch all of
    whose points are at the origin (R = 0) counts them in the last ring, as the original does.
    Column ``i t + j`` holds ring i, sector j, as in the original. The counts are not divided by
    the number of points as in the original code: the singular vectors do not depend on scale.
    """
    cfg = cfg or M2DPConfig()
    out = np.empty((len(indptr) - 1, cfg.n_planes, cfg.n_radial, cfg.n_angular), np.float32)
    plane_of = _m2dp_unique_planes(cfg)[1]
    for k0, k1, counts in _m2dp_signature_blocks(points_normalised, indptr, cfg):
        np.take(counts, plane_of, axis=1, out=out[k0:k1], mode="clip")
    return out.reshape(len(out), cfg.n_planes, -1)


def _m2dp_unique_planes(cfg: M2DPConfig) -> tuple[np.ndarray, np.ndarray]:
    """Rows of the distinct planes among :func:`m2dp_planes` (by in-plane axes) and, for each
    plane, the index of its distinct plane (at elevation pi/2 every azimuth gives the same one)."""
    _, ax, ay = m2dp_planes(cfg)
    _, first, plane_of = np.unique(np.round(np.hstack([ax, ay]), 12), axis=0, return_index=True, return_inverse=True)
    return first, plane_of.ravel()


def _m2dp_point_blocks(pts: np.ndarray, indptr: np.ndarray, cfg: M2DPConfig):
    """Yields ``(k0, k1, p, flat)``: the blocks of patches :func:`_m2dp_signature_blocks` bins at
    once, ``p`` their float32 points (n, 3) in the frame of ``cfg.frame`` and, with
    ``cfg.radius == "farthest"``, scaled by l^2 / R of their patch (with a fixed radius the scale
    is folded into the plane axes instead), and ``flat`` the rows of ``p`` in patches whose R is
    0 (None with a fixed radius). Frame and scale are computed in float64 over larger blocks
    (``_M2DP_FRAME_POINTS``), where numpy's per-call costs vanish."""
    if cfg.frame == "yaw" and cfg.radius == "domain":
        for k0, k1 in patch_blocks(indptr, _M2DP_CHUNK_POINTS, _M2DP_CHUNK_PATCHES):
            yield k0, k1, pts[indptr[k0] : indptr[k1]].astype(np.float32), None
        return
    for s0, s1 in patch_blocks(indptr, _M2DP_FRAME_POINTS):
        sp = indptr[s0 : s1 + 1] - indptr[s0]
        q = pts[indptr[s0] : indptr[s1]]
        if cfg.frame == "pca":
            q = m2dp_pca_frame(q, sp)
        flat = None
        if cfg.radius == "farthest":
            counts = np.diff(sp)
            full = np.flatnonzero(counts)
            R2 = np.zeros(len(counts))
            if len(full):
                R2[full] = np.maximum.reduceat(np.einsum("ij,ij->i", q, q), sp[full])
            R = np.sqrt(R2)
            scale = np.divide(float(cfg.n_radial**2), R, out=np.ones_like(R), where=R > 0)
            q = q * np.repeat(scale, counts)[:, None]
            flat = np.repeat(R == 0, counts)
        q = q.astype(np.float32)
        for k0, k1 in patch_blocks(sp, _M2DP_CHUNK_POINTS, _M2DP_CHUNK_PATCHES):
            a, b = sp[k0], sp[k1]
            yield s0 + k0, s0 + k1, q[a:b], None if flat is None else np.flatnonzero(flat[a:b])


def _m2dp_signature_blocks(points_normalised: np.ndarray, indptr: np.ndarray, cfg: M2DPConfig):
    """Yields ``(k0, k1, counts)``: the counts (k1 - k0, distinct planes, l, t) of a block of
    patches on the distinct planes of :func:`_m2dp_unique_planes` (a view, valid until the next
    block).

    Each block's points are first put into the frame of ``cfg.frame`` and, for the farthest-point
    radius, scaled to their patch's grid (:func:`_m2dp_point_blocks`). Every (point, plane) pair of
    a block of patches then gets a bin id (plane, ring, sector) in a few float32 / uint8 passes
    (ring and sector combined in one byte when a plane has at most 256 bins, as with the defaults;
    else in uint16), and the ids of each patch are counted at once. The element-wise passes are
    OpenCV's where numpy is slow or has no such operation (``cv2.magnitude``, ``cv2.sqrt``,
    ``cv2.convertScaleAbs`` that scales, offsets and rounds to uint8 in one pass, ``cv2.min``), and
    the counting is ``cv2.calcHist`` (twice as fast as ``np.bincount``, and float32 counts
    directly). Rounding stands in for flooring: ``round(v + 1/2) = floor(v + 1)`` except on a bin
    edge exactly. Sectors are counted in t + 2 columns, ``floor((theta + pi) t / 2 pi) + 1``: column
    0 only receives theta = -pi (the float32 -pi lies a hair below -pi) and column t + 1 only theta
    = pi; they are folded into sectors 0 and t - 1. Rings are clipped at ring l, which collects the
    points outside the grid and is dropped (at ring l - 1 for the farthest-point radius, which has
    no outside). Planes that coincide (at elevation pi/2 every azimuth gives the horizontal plane)
    are binned once.
    """
    pts = _as_points(points_normalised)
    indptr = np.asarray(indptr, np.int64)
    P, L, T = cfg.n_planes, cfg.n_radial, cfg.n_angular
    _, ax, ay = m2dp_planes(cfg)
    first = _m2dp_unique_planes(cfg)[0]
    Pu = len(first)
    cols = T + 2
    per_plane = (L + 1) * cols  # rings 0 .. l (outside), sector columns 0 .. t + 1
    _m2dp_check_bins(P, Pu, L, T)
    one_byte = per_plane <= 256
    farthest = cfg.radius == "farthest"
    # in-plane axes scaled by l^2 / r: the in-plane radius is then rho l^2 / r, whose square root
    # l sqrt(rho / r) is the ring coordinate (atan2 does not mind the common scale); with the
    # farthest-point radius the points carry their patch's scale instead
    assert cfg.domain.radius is not None  # M2DPConfig's domain is a cylinder
    axis_scale = 1.0 if farthest else L**2 / float(cfg.domain.radius)
    wx = np.ascontiguousarray(ax[first].T * axis_scale, np.float32)
    wy = np.ascontiguousarray(ay[first].T * axis_scale, np.float32)
    ring_cap = L - 1 if farthest else L
    centre_id = T // 2 + 1 + ((L - 1) * cols if farthest else 0)  # ring 0 (or l - 1 when R = 0), theta = 0
    cap = max(_M2DP_CHUNK_POINTS, int(np.diff(indptr).max(initial=0)))
    bx = np.empty((cap, Pu), np.float32)
    by = np.empty((cap, Pu), np.float32)
    b_theta = np.empty((cap, Pu), np.float32)
    b_ring = np.empty((cap, Pu), np.uint8)
    b_sector = np.empty((cap, Pu), np.uint8)
    b_ids = np.empty((cap, Pu), np.uint16)
    plane_off = np.empty((cap, Pu), np.uint16)
    plane_off[:] = np.arange(Pu, dtype=np.uint16) * per_plane
    dist2 = np.einsum("ij,ij->i", pts, pts)
    if not np.all(dist2 < 1e60):  # NaN, inf, or beyond float32's range once projected
        raise InputError(
            None, "M2DP patch points must be finite (and within 1e30 m of their keypoint)", field="points_normalised"
        )
    for k0, k1, p, flat in _m2dp_point_blocks(pts, indptr, cfg):
        a, b = indptr[k0], indptr[k1]
        n = int(b - a)
        x, y, theta, ring, sector, ids = bx[:n], by[:n], b_theta[:n], b_ring[:n], b_sector[:n], b_ids[:n]
        np.matmul(p, wx, out=x)
        np.matmul(p, wy, out=y)
        # sector column round(theta t / 2 pi + t / 2 + 1/2) = floor((theta + pi) t / 2 pi) + 1
        np.arctan2(y, x, out=theta)
        cv2.convertScaleAbs(theta, sector, T / (2 * math.pi), T / 2 + 0.5)
        cv2.magnitude(x, y, x)
        cv2.sqrt(x, x)
        cv2.convertScaleAbs(x, ring, 1.0, -0.5)  # |l sqrt(rho / r) - 1/2| rounded: the ring (saturates at 255)
        cv2.min(ring, ring_cap, ring)
        if one_byte:
            ring *= cols
            ring += sector
            np.copyto(ids, ring)  # then same-type adds: numpy's mixed uint8 + uint16 add is slower
        else:
            np.copyto(ids, ring)
            ids *= cols
            ids += sector
        ids += plane_off[:n]
        # a point at the origin of the frame is (+-0, +-0) on every plane, and atan2 of signed
        # zeros is any of 0, pi, -0, -pi: it is put where theta = 0 puts it (the original's
        # atan2(0, 0) = 0), on the innermost ring; where a whole patch is at the origin (R = 0
        # with the farthest-point radius) the original's ring edges are all 0 and it counts in
        # the last ring
        at_origin = np.flatnonzero(~p.any(axis=1))
        if len(at_origin):
            ids[at_origin] = plane_off[0] + T // 2 + 1
        if flat is not None and len(flat):
            ids[flat] = plane_off[0] + centre_id
        yield k0, k1, _m2dp_block_counts(ids, indptr[k0 : k1 + 1] - a, Pu, L, T)


def _m2dp_check_bins(P: int, Pu: int, L: int, T: int) -> None:
    """An InputError when the bin ids of :func:`_m2dp_signature_blocks` do not fit their types:
    rings 0 .. l and sector columns 0 .. t + 1 are uint8, bin ids over the ``Pu`` distinct planes uint16."""
    if L + 1 > 255 or T + 2 > 255 or Pu * (L + 1) * (T + 2) > 1 << 16:
        raise InputError(
            None,
            f"M2DP grid of {P} planes x {L} rings x {T} sectors is too fine (at most 254 rings and 253 sectors, "
            "65,536 bins over the distinct planes)",
            field="m2dp",
        )


def _m2dp_block_counts(ids: np.ndarray, indptr: np.ndarray, Pu: int, L: int, T: int) -> np.ndarray:
    """Counts (patches, Pu, l, t) of the bin ids of a block of patches, patch k's ids being
    ``ids[indptr[k]:indptr[k + 1]]``: counted by ``cv2.calcHist``, the outside ring dropped and
    the sector columns 0 and t + 1 (theta = -pi and pi) folded into sectors 0 and t - 1."""
    cols = T + 2
    n_bins = Pu * (L + 1) * cols
    H = np.empty((len(indptr) - 1, n_bins, 1), np.float32)
    for k in range(len(indptr) - 1):
        rows = ids[indptr[k] : indptr[k + 1]]
        if len(rows):
            cv2.calcHist([rows], [0], None, [n_bins], [0, n_bins], hist=H[k])
        else:
            H[k] = 0.0
    h = H.reshape(len(H), Pu, L + 1, cols)[:, :, :L]
    h[..., 1] += h[..., 0]
    h[..., T] += h[..., T + 1]
    return h[..., 1 : T + 1]


def leading_singular_vectors(A: np.ndarray, tol: float = 1e-6, max_iter: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """First left and right singular vectors (M, m) and (M, n) of a stack of matrices (M, m, n).

    Power iteration u <- A A^T u in float32, batched over the stack (each step multiplies the
    error by (s2 / s1)^2; for M2DP's count matrices s2 / s1 is typically ~0.4, so ten or so
    steps reach float32 precision), started from A's row sums, which for a non-negative matrix
    are already close to the Perron vector. The batched products are ``np.einsum``'s (three
    times as fast as ``np.matmul`` on stacks of vectors). Matrices not converged to ``tol``
    within ``max_iter`` steps (nearly equal first two singular values) are finished with an
    exact float64 SVD. Signs are fixed so that each right singular vector sums to >= 0 (for a
    non-negative A both vectors are then non-negative); an all-zero matrix gives zero vectors.
    """
    A = np.asarray(A, np.float32)
    m = len(A)
    u = A.sum(axis=2)
    norm = np.linalg.norm(u, axis=1)
    zero = ~(norm > 0)
    u[zero] = 1.0
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    active = np.flatnonzero(~zero)
    steps = 0
    while len(active) and steps < max_iter:
        Aa = A if len(active) == m else A[active]
        ua = u[active]
        for _ in range(4):
            prev = ua
            ua = np.einsum("kij,kj->ki", Aa, np.einsum("ki,kij->kj", ua, Aa))
            ua /= np.linalg.norm(ua, axis=1, keepdims=True)
        steps += 4
        u[active] = ua
        active = active[np.abs(ua - prev).max(axis=1) > tol]
    if len(active):
        U = np.linalg.svd(A[active].astype(np.float64))[0]
        u[active] = U[:, :, 0]
    v = np.einsum("ki,kij->kj", u, A)
    s = np.linalg.norm(v, axis=1, keepdims=True)
    v = np.divide(v, s, out=np.zeros_like(v), where=s > 0)
    u[zero] = 0.0
    sign = np.where(v.sum(axis=1) < 0, np.float32(-1.0), np.float32(1.0))[:, None]
    return u * sign, v * sign


def m2dp_patches(points_normalised: np.ndarray, indptr: np.ndarray, cfg: M2DPConfig | None = None) -> np.ndarray:
    """M2DP of many yaw-normalised patches: (M, p q + l t) float32, [u1, v1] as in the original.

    Grid radius, in-plane axes and frame as ``cfg`` sets them (:class:`M2DPConfig`); with
    ``M2DPConfig.authors()`` each row is :func:`m2dp_reference` of its patch, computed in float32
    (counts equal but for points within float32 precision of a bin edge; singular vectors to ~1e-6).
    """
    cfg = cfg or M2DPConfig()
    P, L, T = cfg.n_planes, cfg.n_radial, cfg.n_angular
    out = np.empty((len(indptr) - 1, cfg.dim), np.float32)
    plane_of = _m2dp_unique_planes(cfg)[1]
    # the singular vectors of a few hundred patches at a time: one batched iteration for all;
    # a block holds at most _M2DP_CHUNK_PATCHES patches, so the buffer never overflows
    buf = np.empty((2 * _M2DP_CHUNK_PATCHES, P, L, T), np.float32)
    start = 0
    for k0, k1, counts in _m2dp_signature_blocks(points_normalised, indptr, cfg):
        np.take(counts, plane_of, axis=1, out=buf[k0 - start : k1 - start], mode="clip")
        if k1 - start >= _M2DP_CHUNK_PATCHES or k1 == len(out):
            u, v = leading_singular_vectors(buf[: k1 - start].reshape(k1 - start, P, L * T))
            out[start:k1, :P] = u
            out[start:k1, P:] = v
            start = k1
    return out


def thin_patches(indptr: np.ndarray, indices: np.ndarray, max_points: int) -> tuple[np.ndarray, np.ndarray]:
    """CSR patches (``indptr``, map point ``indices``) thinned to about ``max_points`` points each.

    A patch of n > ``max_points`` points keeps each point with probability ``max_points / n``,
    decided by a fixed pseudo-random number of the map point (Knuth's multiplicative hash of its
    index): no random state, the same choice in any block or process, and of two overlapping
    patches the one thinned more keeps a subset of the common points the other keeps. The hash of
    consecutive indices is evenly spread, so the count kept is within a few points of ``max_points``.
    """
    indptr = np.asarray(indptr, np.int64)
    counts = np.diff(indptr)
    if not np.any(counts > max_points):
        return indptr, indices
    u = ((np.asarray(indices, np.uint64) * np.uint64(2654435761)) & np.uint64(0xFFFFFFFF)).astype(np.float64) * 2.0**-32
    keep = u < np.repeat(np.minimum(1.0, max_points / np.maximum(counts, 1)), counts)
    kept = np.bincount(np.repeat(np.arange(len(counts)), counts)[keep], minlength=len(counts))
    return np.concatenate([[0], np.cumsum(kept)]), np.asarray(indices)[keep]


# --- the whole chain ----------------------------------------------------------------------------------


def describe(
    kind: Literal["nbld", "m2dp"],
    points: np.ndarray,
    keypoints: np.ndarray,
    observer_dirs: np.ndarray,
    cfg: StructureDescriptorConfig | None = None,
    *,
    tree: cKDTree | None = None,
) -> np.ndarray:
    """Descriptors (M, D) float32 of the patches about ``keypoints`` (M, 3) in the map ``points``.

    Extracts each patch on the descriptor's domain (``mapkit.places.patches.extract_patches``),
    normalises its yaw towards ``observer_dirs`` (M, 2 or 3; the horizontal direction from each
    keypoint towards its first observer, see ``first_observer_positions``) and describes it
    (M2DP with ``frame="pca"`` then centres and rotates the yaw-normalised patch; the yaw decides
    nothing but the signs MATLAB's PCA convention picks).
    ``tree`` is ``mapkit.places.patches.xy_tree(points)``, built here if omitted. Keypoints are
    processed in blocks of ~0.5 M patch points, so memory stays bounded for any number of them
    and any map density.
    """
    cfg = cfg or StructureDescriptorConfig()
    if kind == "nbld":
        sub: NBLDConfig | M2DPConfig = cfg.nbld
    elif kind == "m2dp":
        sub = cfg.m2dp
    else:
        raise InputError(None, f"unknown structure descriptor {kind!r} (nbld or m2dp)", field="kind")
    points = _as_points(points)
    keypoints = _as_points(keypoints)
    observer_dirs = np.asarray(observer_dirs, np.float64).reshape(len(keypoints), -1)
    tree = xy_tree(points) if tree is None else tree
    out = np.empty((len(keypoints), sub.dim), np.float32)
    for k0, k1 in keypoint_blocks(tree, keypoints, sub.domain):
        indptr, indices = extract_patches(points, keypoints[k0:k1], sub.domain, tree)
        if kind == "m2dp" and cfg.m2dp.max_points is not None:
            indptr, indices = thin_patches(indptr, indices, cfg.m2dp.max_points)
        local = gather_local(points, keypoints[k0:k1], indptr, indices)
        _, normalised = yaw_normalise_patches(local, indptr, observer_dirs[k0:k1, :2])
        out[k0:k1] = (
            nbld_patches(normalised, indptr, cfg.nbld) if kind == "nbld" else m2dp_patches(normalised, indptr, cfg.m2dp)
        )
    return out


# --- PCA --------------------------------------------------------------------------------------------


class DescriptorPCA:
    """Mean-centred projection onto the leading principal axes of a descriptor set (Sec. 3.4)."""

    def __init__(self, mean: np.ndarray, components: np.ndarray, explained_variance: np.ndarray):
        self.mean = np.asarray(mean, np.float64)
        self.components = np.asarray(components, np.float64)  # (dim, D), orthonormal rows
        self.explained_variance = np.asarray(explained_variance, np.float64)  # (dim,)
        if (
            self.components.ndim != 2
            or self.components.shape[1] != len(self.mean)
            or len(self.explained_variance) != len(self.components)
        ):
            raise InputError(
                None,
                f"inconsistent PCA arrays: mean {self.mean.shape}, components {self.components.shape}, variance "
                f"{self.explained_variance.shape}",
            )

    @property
    def dim(self) -> int:
        return int(len(self.components))

    @classmethod
    def fit(cls, X: np.ndarray, dim: int = 25) -> DescriptorPCA:
        """Principal axes of descriptors ``X`` (n, D); each axis signed so that its largest
        coefficient is positive (a deterministic basis for a given X)."""
        X = np.asarray(X, np.float64)
        if X.ndim != 2 or len(X) < 2:
            raise InputError(
                None, f"PCA needs at least 2 descriptors as an (n, D) array, got shape {X.shape}", field="X"
            )
        if not 1 <= dim <= X.shape[1]:
            raise InputError(None, f"PCA dim must be in [1, {X.shape[1]}], got {dim}", field="dim")
        mean = X.mean(axis=0)
        Xc = X - mean
        # the D x D covariance: n is usually far larger than D (768 at most here)
        w, V = np.linalg.eigh(Xc.T @ Xc / (len(X) - 1))
        w, V = w[::-1][:dim], V[:, ::-1][:, :dim].T
        big = np.argmax(np.abs(V), axis=1)
        V *= np.where(V[np.arange(dim), big] < 0, -1.0, 1.0)[:, None]
        return cls(mean, V, np.maximum(w, 0.0))

    def transform(self, X: np.ndarray) -> np.ndarray:
        """(n, dim) float32 coordinates of descriptors ``X`` (n, D)."""
        X = np.asarray(X, np.float64)
        if X.ndim != 2 or X.shape[1] != len(self.mean):
            raise InputError(None, f"expected descriptors of shape (n, {len(self.mean)}), got {X.shape}", field="X")
        return ((X - self.mean) @ self.components.T).astype(np.float32)

    def inverse_transform(self, Y: np.ndarray) -> np.ndarray:
        """(n, D) reconstruction of PCA coordinates ``Y`` (n, dim)."""
        return np.asarray(Y, np.float64) @ self.components + self.mean

    def save(self, path: str | Path) -> Path:
        """Write ``mean``, ``components``, ``explained_variance`` into an ``.npz``; returns the path."""
        path = Path(path)
        with open(path, "wb") as f:
            np.savez(f, mean=self.mean, components=self.components, explained_variance=self.explained_variance)
        return path

    @classmethod
    def load(cls, path: str | Path) -> DescriptorPCA:
        path = Path(path)
        if not path.is_file():
            raise InputError(path, "no such PCA file")
        with np.load(path) as z:
            missing = {"mean", "components", "explained_variance"} - set(z.files)
            if missing:
                raise InputError(path, f"not a DescriptorPCA file (missing {', '.join(sorted(missing))})")
            return cls(z["mean"], z["components"], z["explained_variance"])


def _as_points(a: np.ndarray) -> np.ndarray:
    a = np.asarray(a, np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise InputError(None, f"expected points of shape (n, 3), got {a.shape}")
    return a
