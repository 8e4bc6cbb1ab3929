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
  singular vectors.

Both work on many patches at once: the points of all patches (CSR, as in ``mapkit.patches``)
are binned with ``np.bincount`` (one call per block of patches for NBLD, one per patch for
M2DP's ~60 planes x 136 bins), and M2DP's leading singular pairs come from one batched power
iteration over a few hundred patches. ``describe`` chains extraction, yaw normalisation and a
descriptor; ``DescriptorPCA`` projects descriptors to 25 dimensions before matching ("all of the
above descriptors are projected down to a 25-dimensional space via PCA", Sec. 5.2).

Defaults and their sources: NBLD's domain (r = 10 m, h = 20 m) is the semi-dense paper's (Fig. 6
caption); its subdivisions (8 sectors, 3 rings, 4 layers) are mapkit's choice, the NBLD paper's
values not being at hand. M2DP's p = 4, q = 16, l = 8, t = 16 (192 dimensions) are those of the
original paper and its reference code; its radius, 10 m, is mapkit's choice (the semi-dense
paper does not state it). Points are binned in float32: a point within ~1e-6 rad or ~1e-6 m of
a bin edge may fall on either side, as it may in any implementation.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Literal, Optional

import numpy as np
from pydantic import Field, model_validator
from scipy.spatial import cKDTree

from .config import MapkitConfig
from .errors import InputError
from .patches import M2DP_DOMAIN, NBLD_DOMAIN, PatchDomain, extract_patches, gather_local, keypoint_blocks, patch_blocks, xy_tree, yaw_normalise_patches

_NBLD_CHUNK_POINTS = 1 << 16  # patch points per block (NBLD works on ~10 arrays of this length)
_NBLD_CHUNK_PATCHES = 1 << 14  # ... and patches per block (bounds the bincount output)
_M2DP_CHUNK_POINTS = 1 << 12  # patch points per block; x 61 planes: float32 work arrays of ~1 MiB
_M2DP_CHUNK_PATCHES = 256  # ... and patches per block and per batched singular-vector solve


class NBLDConfig(MapkitConfig):
    """NBLD (Cieslewski et al. 2016) on the domain of the semi-dense paper."""

    domain: PatchDomain = Field(NBLD_DOMAIN, description="Finite vertical cylinder; r = 10 m, h = 20 m from the semi-dense paper (Fig. 6 caption).")
    n_azimuth: int = Field(8, ge=2, description="Azimuthal sectors n_a, from the patch x-axis counter-clockwise (mapkit's choice: 45 deg sectors).")
    n_radial: int = Field(3, ge=1, description="Rings n_r of equal width (mapkit's choice).")
    # with 8 x 3 x 4 = 96 cells a patch of 500-3000 points has ~5-30 points per cell on
    # average, enough for a density comparison to mean more than counting noise
    n_vertical: int = Field(4, ge=1, description="Layers n_z of equal height (mapkit's choice: 5 m layers).")

    @model_validator(mode="after")
    def _check(self) -> "NBLDConfig":
        if self.domain.kind != "cylinder":
            raise ValueError(f"NBLD needs a finite cylinder domain, got {self.domain.kind}")
        return self

    @property
    def dim(self) -> int:
        return 3 * self.n_radial * self.n_azimuth * self.n_vertical


class M2DPConfig(MapkitConfig):
    """M2DP (He et al. 2016); the counts are those of the original paper and code."""

    domain: PatchDomain = Field(M2DP_DOMAIN, description="Infinite vertical cylinder; r = 10 m (the semi-dense paper leaves r open).")
    n_plane_azimuths: int = Field(4, ge=1, description="p: plane-normal azimuths, linearly spaced over [-pi/2, pi/2] (M2DP default 4).")
    n_plane_elevations: int = Field(16, ge=1, description="q: plane-normal elevations, linearly spaced over [0, pi/2] (M2DP default 16).")
    n_radial: int = Field(8, ge=1, description="l: rings per plane, outer radii r * (i / l)^2 as in the original (M2DP default 8).")
    n_angular: int = Field(16, ge=1, description="t: sectors per plane over [-pi, pi) (M2DP default 16).")

    @model_validator(mode="after")
    def _check(self) -> "M2DPConfig":
        if self.domain.kind == "cube":
            raise ValueError("M2DP needs a cylinder domain (its polar grid has the cylinder's radius)")
        return self

    @property
    def n_planes(self) -> int:
        return self.n_plane_azimuths * self.n_plane_elevations

    @property
    def dim(self) -> int:
        return self.n_planes + self.n_radial * self.n_angular


class StructureDescriptorConfig(MapkitConfig):
    """Hand-crafted structure descriptors of Sec. 3.3.1 and their PCA (Sec. 5.2)."""

    keypoint_fraction: float = Field(0.05, gt=0, le=1, description="Fraction of map points drawn as keypoints by the caller of describe() (Sec. 3.2: a random five percent).")
    nbld: NBLDConfig = Field(default_factory=NBLDConfig, description="NBLD parameters.")
    m2dp: M2DPConfig = Field(default_factory=M2DPConfig, description="M2DP parameters.")
    pca_dim: int = Field(25, ge=1, description="Dimensions kept by PCA before matching (Sec. 5.2: 25).")


# --- NBLD -------------------------------------------------------------------------------------------

def nbld_cell_volumes(cfg: NBLDConfig) -> np.ndarray:
    """(n_radial,) volume (m^3) of one cell of each ring: annular sector times layer height."""
    edges = np.linspace(0.0, cfg.domain.radius, cfg.n_radial + 1)
    return math.pi * np.diff(edges**2) / cfg.n_azimuth * (cfg.domain.height / cfg.n_vertical)


def nbld_counts(points_normalised: np.ndarray, indptr: np.ndarray, cfg: Optional[NBLDConfig] = None) -> np.ndarray:
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
    R, H = float(cfg.domain.radius), float(cfg.domain.height)
    cells = nr * na * nz
    out = np.zeros((m, nr, na, nz), np.int64)
    # float32 / int32 throughout: numpy's float64 arctan2 is not vectorised, and the narrower
    # types halve the memory traffic of these ~20 passes
    for k0, k1 in patch_blocks(indptr, _NBLD_CHUNK_POINTS, min(_NBLD_CHUNK_PATCHES, (1 << 31) // cells)):  # int32 cell ids
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


def nbld_bits_from_counts(counts: np.ndarray, cfg: Optional[NBLDConfig] = None) -> np.ndarray:
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


def nbld_patches(points_normalised: np.ndarray, indptr: np.ndarray, cfg: Optional[NBLDConfig] = None, packed: bool = False) -> np.ndarray:
    """NBLD of many yaw-normalised patches: (M, 3 n_r n_a n_z) float32 0/1, or packed uint8.

    Bit order is that of :func:`nbld_bits_from_counts` flattened in C order (channel, ring,
    sector, layer). ``packed`` returns ``np.packbits`` bytes per row (Hamming matching); the float
    form is what PCA and L2 matching take.
    """
    cfg = cfg or NBLDConfig()
    bits = nbld_bits_from_counts(nbld_counts(points_normalised, indptr, cfg), cfg).reshape(len(indptr) - 1, -1)
    return np.packbits(bits, axis=1) if packed else bits.astype(np.float32)


# --- M2DP -------------------------------------------------------------------------------------------

def m2dp_planes(cfg: Optional[M2DPConfig] = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normals and in-plane axes (each (p q, 3)) of the M2DP planes, azimuth-major.

    Plane (i, j) has the normal (cos e_j cos a_i, cos e_j sin a_i, sin e_j) with azimuth a_i and
    elevation e_j (row ``i q + j`` of the signature matrix, the original's loop order). Its
    in-plane x-axis is the projection of the patch x-axis onto the plane, normalised (the
    original code leaves it unnormalised, which shrinks the plane's coordinates by
    sqrt(1 - n_x^2); with a fixed grid radius r the metric projection is the consistent choice);
    its y-axis is normal x x-axis. Where the patch x-axis is the normal itself (azimuth 0 and
    elevation 0, absent from the default p = 4) the patch y-axis is projected instead.
    """
    cfg = cfg or M2DPConfig()
    az = np.linspace(-math.pi / 2, math.pi / 2, cfg.n_plane_azimuths)
    el = np.linspace(0.0, math.pi / 2, cfg.n_plane_elevations)
    a, e = np.meshgrid(az, el, indexing="ij")
    a, e = a.ravel(), e.ravel()
    normal = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], axis=1)
    ax = np.array([1.0, 0.0, 0.0]) - normal[:, :1] * normal
    short = np.linalg.norm(ax, axis=1) < 1e-9
    ax[short] = np.array([0.0, 1.0, 0.0]) - normal[short, 1:2] * normal[short]
    ax /= np.linalg.norm(ax, axis=1, keepdims=True)
    ay = np.cross(normal, ax)
    return normal, ax, ay


def m2dp_signature_matrices(points_normalised: np.ndarray, indptr: np.ndarray, cfg: Optional[M2DPConfig] = None) -> np.ndarray:
    """(M, p q, l t) float32 point counts of each patch on the M2DP planes' polar grids.

    On each plane, the in-plane angle theta in [-pi, pi] falls into sector
    floor((theta + pi) t / 2 pi) (theta = pi into the last one), and the in-plane distance rho
    into ring i when r (i / l)^2 <= rho < r ((i + 1) / l)^2, the original's concentric circles of
    radii r (i / l)^2. Points with rho >= r lie outside the grid and are not counted (the grid
    ends at r, Sec. 3.3.1; the original takes r as the farthest point, so it has no such points).
    A point at the keypoint itself has no angle; it counts as theta = 0 (as atan2(0, 0) = 0).
    Column ``i t + j`` holds ring i, sector j, as in the original. The counts are not divided by
    the number of points as in the original code: the singular vectors do not depend on scale.
    """
    cfg = cfg or M2DPConfig()
    out = np.empty((len(indptr) - 1, cfg.n_planes, cfg.n_radial * cfg.n_angular), np.float32)
    for k0, k1, A in _m2dp_signature_blocks(points_normalised, indptr, cfg):
        out[k0:k1] = A
    return out


def _m2dp_signature_blocks(points_normalised: np.ndarray, indptr: np.ndarray, cfg: M2DPConfig):
    """Yields ``(k0, k1, A)`` with the signature matrices A (k1 - k0, p q, l t) of a block.

    Every (point, plane) pair of a block of patches is binned with a few float32 and int16
    passes, then counted with one ``np.bincount`` per patch. Nothing is clipped (``np.minimum``
    is among numpy's slowest element-wise loops): the rings go on past ring l - 1 as far as the
    block's farthest point reaches (its 3-D distance bounds its distance on every plane), those
    extra rings are counted and dropped (only for points ~140 m away, where the int16 bins would
    overflow, are the rings clipped); sector t only receives theta = pi exactly and is folded
    into sector t - 1. Planes that coincide (at elevation pi/2 every azimuth gives the
    horizontal plane) are binned once.
    """
    pts = _as_points(points_normalised)
    indptr = np.asarray(indptr, np.int64)
    P, L, T = cfg.n_planes, cfg.n_radial, cfg.n_angular
    R = float(cfg.domain.radius)
    _, ax, ay = m2dp_planes(cfg)
    _, first, plane_of = np.unique(np.round(np.hstack([ax, ay]), 12), axis=0, return_index=True, return_inverse=True)
    Pu = len(first)
    # in-plane axes scaled by l^2 / r: then x^2 + y^2 = rho^2 l^4 / r^2, whose fourth root is
    # l sqrt(rho / r), the ring (atan2 does not mind the common scale)
    wx = np.ascontiguousarray(ax[first].T * (L**2 / R), np.float32)
    wy = np.ascontiguousarray(ay[first].T * (L**2 / R), np.float32)
    cap = max(_M2DP_CHUNK_POINTS, int(np.diff(indptr).max(initial=0)))
    bx = np.empty((cap, Pu), np.float32)
    by = np.empty((cap, Pu), np.float32)
    bt = np.empty((cap, Pu), np.float32)
    bi = np.empty((cap, Pu), np.int16)
    bs = np.empty((cap, Pu), np.int16)
    sector_scale = np.float32(T / (2 * math.pi))
    dist2 = np.einsum("ij,ij->i", pts, pts)
    for k0, k1 in patch_blocks(indptr, _M2DP_CHUNK_POINTS, _M2DP_CHUNK_PATCHES):
        a, b = indptr[k0], indptr[k1]
        n = int(b - a)
        p = pts[a:b].astype(np.float32)
        far = math.sqrt(float(dist2[a:b].max(initial=0.0)))
        if not math.isfinite(far):
            raise InputError(None, "M2DP patch points must be finite", field="points_normalised")
        rings = max(L, int(L * math.sqrt(far / R)) + 1) + 1  # rings 0 .. the farthest, plus one
        clip = Pu * rings * (T + 1) >= 1 << 15  # points > ~140 m away: clip the rings instead
        if clip:
            rings = L + 1
        per_plane = rings * (T + 1)
        plane_off = (np.arange(Pu, dtype=np.int16) * per_plane)[None, :]
        x, y, th, ir, sec = bx[:n], by[:n], bt[:n], bi[:n], bs[:n]
        np.matmul(p, wx, out=x)
        np.matmul(p, wy, out=y)
        np.arctan2(y, x, out=th)
        th += np.float32(math.pi)
        th *= sector_scale
        np.copyto(sec, th, casting="unsafe")  # truncation = floor for the non-negative angles
        np.multiply(x, x, out=x)
        np.multiply(y, y, out=y)
        x += y
        np.sqrt(x, out=x)
        np.sqrt(x, out=x)
        if clip:
            np.minimum(x, np.float32(L), out=x)
        np.copyto(ir, x, casting="unsafe")
        ir *= T + 1
        ir += sec
        ir += plane_off
        # a point at the keypoint itself is (+-0, +-0) on every plane, and atan2 of signed
        # zeros is any of 0, pi, -0, -pi: it is put where theta = 0 puts it (the original's
        # atan2(0, 0) = 0), on the innermost ring
        at_keypoint = np.flatnonzero(dist2[a:b] == 0)
        if len(at_keypoint):
            ir[at_keypoint] = plane_off + T // 2
        A = np.empty((k1 - k0, Pu, L, T), np.float32)
        for k in range(k0, k1):
            rows = ir[indptr[k] - a : indptr[k + 1] - a]
            h = np.bincount(rows.ravel(), minlength=Pu * per_plane).reshape(Pu, rings, T + 1)[:, :L]
            h[:, :, T - 1] += h[:, :, T]
            A[k - k0] = h[:, :, :T]
        yield k0, k1, A[:, plane_of].reshape(k1 - k0, P, L * T)


def leading_singular_vectors(A: np.ndarray, tol: float = 1e-6, max_iter: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """First left and right singular vectors (M, m) and (M, n) of a stack of matrices (M, m, n).

    Power iteration u <- A A^T u in float32, batched over the stack (each step multiplies the
    error by (s2 / s1)^2; for M2DP's count matrices s2 / s1 is typically ~0.1, so a handful of
    steps reach float32 precision), started from A's row sums, which for a non-negative matrix
    are already close to the Perron vector. Matrices not converged to ``tol`` within
    ``max_iter`` steps (nearly equal first two singular values) are finished with an exact
    float64 SVD. Signs are fixed so that each right singular vector sums to >= 0 (for a
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
            va = np.matmul(ua[:, None, :], Aa)[:, 0, :]
            ua = np.matmul(Aa, va[:, :, None])[:, :, 0]
            ua /= np.linalg.norm(ua, axis=1, keepdims=True)
        steps += 4
        u[active] = ua
        active = active[np.abs(ua - prev).max(axis=1) > tol]
    if len(active):
        U = np.linalg.svd(A[active].astype(np.float64))[0]
        u[active] = U[:, :, 0]
    v = np.matmul(u[:, None, :], A)[:, 0, :]
    s = np.linalg.norm(v, axis=1, keepdims=True)
    v = np.divide(v, s, out=np.zeros_like(v), where=s > 0)
    u[zero] = 0.0
    sign = np.where(v.sum(axis=1) < 0, np.float32(-1.0), np.float32(1.0))[:, None]
    return u * sign, v * sign


def m2dp_patches(points_normalised: np.ndarray, indptr: np.ndarray, cfg: Optional[M2DPConfig] = None) -> np.ndarray:
    """M2DP of many yaw-normalised patches: (M, p q + l t) float32, [u1, v1] as in the original."""
    cfg = cfg or M2DPConfig()
    out = np.empty((len(indptr) - 1, cfg.dim), np.float32)
    pending: list[np.ndarray] = []
    start = 0

    def flush(stop: int) -> None:
        u, v = leading_singular_vectors(np.concatenate(pending))
        out[start:stop, : cfg.n_planes] = u
        out[start:stop, cfg.n_planes :] = v
        pending.clear()

    # the singular vectors of a few hundred patches at a time: one batched iteration for all
    for k0, k1, A in _m2dp_signature_blocks(points_normalised, indptr, cfg):
        pending.append(A)
        if k1 - start >= _M2DP_CHUNK_PATCHES:
            flush(k1)
            start = k1
    if pending:
        flush(len(out))
    return out


# --- the whole chain ----------------------------------------------------------------------------------

def describe(
    kind: Literal["nbld", "m2dp"],
    points: np.ndarray,
    keypoints: np.ndarray,
    observer_dirs: np.ndarray,
    cfg: Optional[StructureDescriptorConfig] = None,
    *,
    tree: Optional[cKDTree] = None,
) -> np.ndarray:
    """Descriptors (M, D) float32 of the patches about ``keypoints`` (M, 3) in the map ``points``.

    Extracts each patch on the descriptor's domain (``mapkit.patches.extract_patches``),
    normalises its yaw towards ``observer_dirs`` (M, 2 or 3; the horizontal direction from each
    keypoint towards its first observer, see ``first_observer_positions``) and describes it.
    ``tree`` is ``mapkit.patches.xy_tree(points)``, built here if omitted. Keypoints are
    processed in blocks of ~0.5 M patch points, so memory stays bounded for any number of them
    and any map density.
    """
    cfg = cfg or StructureDescriptorConfig()
    if kind == "nbld":
        sub: MapkitConfig = cfg.nbld
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
        local = gather_local(points, keypoints[k0:k1], indptr, indices)
        _, normalised = yaw_normalise_patches(local, indptr, observer_dirs[k0:k1, :2])
        out[k0:k1] = nbld_patches(normalised, indptr, sub) if kind == "nbld" else m2dp_patches(normalised, indptr, sub)
    return out


# --- PCA --------------------------------------------------------------------------------------------

class DescriptorPCA:
    """Mean-centred projection onto the leading principal axes of a descriptor set (Sec. 3.4)."""

    def __init__(self, mean: np.ndarray, components: np.ndarray, explained_variance: np.ndarray):
        self.mean = np.asarray(mean, np.float64)
        self.components = np.asarray(components, np.float64)  # (dim, D), orthonormal rows
        self.explained_variance = np.asarray(explained_variance, np.float64)  # (dim,)
        if self.components.ndim != 2 or self.components.shape[1] != len(self.mean) or len(self.explained_variance) != len(self.components):
            raise InputError(None, f"inconsistent PCA arrays: mean {self.mean.shape}, components {self.components.shape}, variance {self.explained_variance.shape}")

    @property
    def dim(self) -> int:
        return int(len(self.components))

    @classmethod
    def fit(cls, X: np.ndarray, dim: int = 25) -> "DescriptorPCA":
        """Principal axes of descriptors ``X`` (n, D); each axis signed so that its largest
        coefficient is positive (a deterministic basis for a given X)."""
        X = np.asarray(X, np.float64)
        if X.ndim != 2 or len(X) < 2:
            raise InputError(None, f"PCA needs at least 2 descriptors as an (n, D) array, got shape {X.shape}", field="X")
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
    def load(cls, path: str | Path) -> "DescriptorPCA":
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
