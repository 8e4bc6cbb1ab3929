"""Local 3D patches of a semi-dense map: keypoints, extraction, yaw normalisation, voxel grids.

Sec. 3.2 of the semi-dense place-recognition paper: a random 5 % of the map points are
keypoints; around each one a patch Gamma holds every map point of the descriptor's domain Omega
and nothing more; the patch is rotated about gravity (+z) so that its x-axis is the horizontal
part of the covariance eigenvector with the smallest eigenvalue, signed towards the keypoint's
first observer. The same patches feed the hand-crafted descriptors (``mapkit.places.descriptors3d``)
and the voxel grids of the CNN triplets (Sec. 3.3.2, 4.1).

Pure geometry on arrays (numpy, scipy's cKDTree). Frames and units: ``points`` and keypoints are
in one gravity-aligned metric frame (+z up, metres), e.g. ``points_world`` of a
:class:`mapkit.mapping.semidense.SemiDenseMap`; "local" points are relative to their keypoint;
"normalised" points are local points rotated by -yaw about +z.

Many patches at once are a CSR pair ``(indptr, indices)``: the map points of patch ``k`` are
``indices[indptr[k]:indptr[k + 1]]``; per-point arrays in patch order (``points_local`` and the
like) share that ``indptr``.

Shape of a patch: every domain's patch is a vertical cylinder about the keypoint. The finite
cylinder (NBLD) and the infinite one (M2DP) are their own domains; the CNN's cube is defined in
the *normalised* frame, so before normalisation its patch is the cylinder that holds the cube
under any yaw (radius ``half_size * sqrt(2)``, height ``2 * half_size``); ``voxelise`` keeps
the cube. All are found with one query of a 2-D tree over the points' (x, y), followed by a
vectorised filter in z: for a street map, whose height extent is close to the patch height,
the disc is a far tighter candidate set than the domain's bounding sphere (which reaches
``sqrt(2)`` times as far horizontally): on the synthetic street of the benchmark the disc holds
1.2 candidates per kept point and the sphere 1.6, on the KITTI clip's semi-dense map 1.00 and
1.7. And a single 2-D tree then serves every domain.
"""

from __future__ import annotations

import math
from itertools import chain
from typing import Literal

import numpy as np
from pydantic import Field, model_validator
from scipy.spatial import cKDTree

from mapkit.core.config import MapkitConfig
from mapkit.core.errors import InputError

#: Below this, the horizontal part of the smallest-eigenvalue eigenvector is too short to define
#: a direction (the patch is dominated by one near-horizontal plane, typically the road); the
#: eigenvector of the middle eigenvalue is used instead. sin(5.7 deg) = 0.1. The paper has no
#: degenerate case; the value is this module's choice.
MIN_HORIZONTAL_NORM = 0.1

_VOXEL_CHUNK_PATCHES = 16  # patches per block of voxel grids (int64 counts: 256 KiB per 32^3 patch)
_BLOCK_POINTS = 1 << 18  # patch points per block where a block's temporaries are ~10 arrays of this length


class PatchDomain(MapkitConfig):
    """The domain Omega of a structure descriptor around its keypoint (Sec. 3.2).

    ``cylinder``: vertical cylinder of ``radius`` and total ``height`` centred on the keypoint.
    ``cylinder_inf``: vertical cylinder of ``radius``, unbounded in z.
    ``cube``: axis-aligned cube of ``half_size`` in the yaw-normalised frame.
    """

    kind: Literal["cylinder", "cylinder_inf", "cube"] = Field(..., description="Shape of the domain.")
    radius: float | None = Field(None, gt=0, description="Cylinder radius (m); cylinder and cylinder_inf.")
    height: float | None = Field(None, gt=0, description="Cylinder height (m), centred on the keypoint; cylinder only.")
    half_size: float | None = Field(None, gt=0, description="Half the cube's edge (m); cube only.")

    @model_validator(mode="after")
    def _check(self) -> PatchDomain:
        need = {"cylinder": {"radius", "height"}, "cylinder_inf": {"radius"}, "cube": {"half_size"}}[self.kind]
        given = {k for k in ("radius", "height", "half_size") if getattr(self, k) is not None}
        if given != need:
            raise ValueError(f"a {self.kind} domain takes {sorted(need)}, got {sorted(given)}")
        return self

    # the validator above guarantees the dimensions of each kind: the asserts below state it for the type checker

    @property
    def patch_radius(self) -> float:
        """Horizontal radius of the patch Gamma (m)."""
        if self.kind == "cube":
            assert self.half_size is not None
            return float(self.half_size * math.sqrt(2.0))
        assert self.radius is not None
        return float(self.radius)

    @property
    def patch_half_height(self) -> float:
        """Half the vertical extent of the patch Gamma (m); inf for cylinder_inf."""
        if self.kind == "cylinder":
            assert self.height is not None
            return float(self.height) / 2.0
        if self.kind == "cube":
            assert self.half_size is not None
            return float(self.half_size)
        return math.inf

    @property
    def bounding_radius(self) -> float:
        """Radius of the smallest sphere about the keypoint holding the patch (inf if unbounded)."""
        return math.hypot(self.patch_radius, self.patch_half_height)

    @property
    def box_half_extents(self) -> np.ndarray:
        """Half extents (x, y, z) of the domain's bounding box in the normalised frame (m)."""
        if self.kind == "cube":
            assert self.half_size is not None
            return np.full(3, float(self.half_size))
        if self.kind == "cylinder":
            assert self.radius is not None and self.height is not None
            return np.array([self.radius, self.radius, self.height / 2.0], np.float64)
        raise InputError(None, "an unbounded cylinder has no bounding box (no voxel grid)", field="domain.kind")


#: NBLD as evaluated in the semi-dense paper: "NBLD uses a radius of 10m and a height of 20m"
#: (caption of Fig. 6).
NBLD_DOMAIN = PatchDomain(kind="cylinder", radius=10.0, height=20.0)
#: M2DP: Sec. 3.3.1 of the semi-dense paper sets an infinite cylinder of radius r but does not give
#: r; 10 m here, the horizontal extent of its NBLD and CNN domains. It always bounds the patch;
#: whether it is also the radius of M2DP's polar grids is ``M2DPConfig.radius``: the original M2DP
#: (He et al. IROS 2016, ``M2DP.m``) describes a whole scan and takes the grid radius from its
#: farthest point (``radius="farthest"``), so that no point falls outside the grid.
M2DP_DOMAIN = PatchDomain(kind="cylinder_inf", radius=10.0)
#: CNN voxel grids: "input patches of size 20x20x20m3" (caption of Fig. 6).
CNN_DOMAIN = PatchDomain(kind="cube", half_size=10.0)


# --- keypoints and extraction ---------------------------------------------------------------------


def select_keypoints(n_points: int, fraction: float = 0.05, rng: np.random.Generator | None = None) -> np.ndarray:
    """Indices of a random ``fraction`` of ``n_points`` map points, ascending (Sec. 3.2: 5 %).

    At least one keypoint is drawn from a non-empty map.
    """
    if not 0.0 < fraction <= 1.0:
        raise InputError(None, f"keypoint fraction must be in (0, 1], got {fraction}", field="fraction")
    if n_points <= 0:
        return np.zeros(0, np.int64)
    rng = np.random.default_rng() if rng is None else rng
    k = max(1, int(round(fraction * n_points)))
    return np.sort(rng.choice(n_points, size=k, replace=False)).astype(np.int64)


def xy_tree(points: np.ndarray) -> cKDTree:
    """The 2-D tree over (x, y) that ``extract_patches`` queries; build it once per map."""
    return cKDTree(np.asarray(points, np.float64)[:, :2])


def extract_patches(
    points: np.ndarray, keypoints: np.ndarray, domain: PatchDomain, tree: cKDTree | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Map points of each keypoint's patch Gamma, as CSR ``(indptr (M+1,), indices (nnz,))``.

    ``points`` (N, 3), ``keypoints`` (M, 3) positions in the same frame; ``tree`` from
    :func:`xy_tree` (built here if omitted). One batched ``query_ball_point`` of the disc of the
    patch radius, then a vectorised cut in z; the boundary is inclusive (distance <= radius,
    |dz| <= half height). Within a patch, indices are in the tree's order (deterministic, not
    sorted: sorting costs a third of the query and nothing downstream needs it).
    """
    points = _as_points(points, "points")
    keypoints = _as_points(keypoints, "keypoints")
    if tree is None:
        tree = xy_tree(points)
    elif tree.m != 2 or tree.n != len(points):
        raise InputError(
            None,
            f"tree must be xy_tree(points) (2-D over {len(points)} points), got {tree.m}-D over {tree.n}",
            field="tree",
        )
    m = len(keypoints)
    if m == 0:
        return np.zeros(1, np.int64), np.zeros(0, np.int64)
    lists = tree.query_ball_point(keypoints[:, :2], domain.patch_radius, return_sorted=False)
    counts = np.fromiter(map(len, lists), np.int64, count=m)
    indices = np.fromiter(chain.from_iterable(lists), np.int64, count=int(counts.sum()))
    half_h = domain.patch_half_height
    if math.isfinite(half_h):
        owner = np.repeat(np.arange(m), counts)
        keep = np.abs(points[indices, 2] - keypoints[owner, 2]) <= half_h
        indices = indices[keep]
        counts = np.bincount(owner[keep], minlength=m)
    indptr = np.zeros(m + 1, np.int64)
    np.cumsum(counts, out=indptr[1:])
    return indptr, indices


def keypoint_blocks(tree: cKDTree, keypoints: np.ndarray, domain: PatchDomain, max_points: int = 1 << 19):
    """Consecutive keypoint ranges ``(k0, k1)`` whose patches hold about ``max_points`` points.

    Sized from the number of points in each keypoint's disc (a count-only query, ~15x cheaper
    than the extraction), so that the per-block arrays stay in memory whatever the map's
    density; a keypoint with a bigger patch gets a block of its own.
    """
    keypoints = np.asarray(keypoints, np.float64)
    if not len(keypoints):
        return
    lengths = tree.query_ball_point(keypoints[:, :2], domain.patch_radius, return_length=True)
    ends = np.zeros(len(keypoints) + 1, np.int64)
    np.cumsum(lengths, out=ends[1:])
    yield from patch_blocks(ends, max_points)


def patch_blocks(indptr: np.ndarray, max_points: int, max_patches: int | None = None):
    """Consecutive patch ranges ``(k0, k1)`` of at most ``max_points`` points (one patch at
    least) and at most ``max_patches`` patches."""
    m = len(indptr) - 1
    cap = m if max_patches is None else max(1, max_patches)
    k0 = 0
    while k0 < m:
        k1 = int(np.searchsorted(indptr, indptr[k0] + max_points, side="right")) - 1
        k1 = min(max(k1, k0 + 1), m, k0 + cap)
        yield k0, k1
        k0 = k1


def gather_local(points: np.ndarray, keypoints: np.ndarray, indptr: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """(nnz, 3) patch points relative to their keypoint, in patch order."""
    points = np.asarray(points, np.float64)
    keypoints = np.asarray(keypoints, np.float64)
    local = points.take(indices, axis=0)
    local -= np.repeat(keypoints, np.diff(indptr), axis=0)
    return local


# --- yaw normalisation ----------------------------------------------------------------------------


def yaw_normalise(
    points_local_centered: np.ndarray, observer_dir_xy: np.ndarray, min_horizontal_norm: float = MIN_HORIZONTAL_NORM
) -> tuple[float, np.ndarray]:
    """Yaw of one patch and its points rotated into the normalised frame.

    ``points_local_centered`` (n, 3) relative to the keypoint; ``observer_dir_xy`` the horizontal
    direction from the keypoint towards its first observer. See :func:`yaw_normalise_patches`.
    """
    pts = _as_points(points_local_centered, "points_local_centered")
    yaw, out = yaw_normalise_patches(
        pts, np.array([0, len(pts)], np.int64), np.asarray(observer_dir_xy, np.float64)[None, :2], min_horizontal_norm
    )
    return float(yaw[0]), out


def yaw_normalise_patches(
    points_local: np.ndarray,
    indptr: np.ndarray,
    observer_dirs_xy: np.ndarray,
    min_horizontal_norm: float = MIN_HORIZONTAL_NORM,
) -> tuple[np.ndarray, np.ndarray]:
    """Yaw angles (M,) and normalised points (nnz, 3) of many patches (Sec. 3.2, after [4]).

    The x-axis of patch k is the horizontal projection of e0, the unit eigenvector of the
    smallest eigenvalue of the sample covariance of its points, signed so that it points towards
    the first observer (``observer_dirs_xy[k]``, (M, 2) or (M, 3), only x and y are used).
    ``yaw[k]`` is the angle of that axis from +x about +z; the normalised points are the local
    points rotated by ``-yaw[k]``, so that the axis becomes +x and z is unchanged.

    Degenerate cases: where the horizontal part of e0 is shorter than ``min_horizontal_norm``
    (e0 within ~6 degrees of vertical, a patch dominated by flat ground), the eigenvector of the
    middle eigenvalue is projected instead; the two are orthonormal, so at least one has a
    horizontal part of length >= 1/sqrt(2). An observer straight above the keypoint (zero
    horizontal direction) leaves the sign as the eigen-solver returned it. Empty patches get
    yaw 0. Covariances are accumulated per patch with ``np.add.reduceat`` and solved with one
    batched ``np.linalg.eigh``.
    """
    pts = _as_points(points_local, "points_local")
    indptr = np.asarray(indptr, np.int64)
    m = len(indptr) - 1
    obs = np.asarray(observer_dirs_xy, np.float64).reshape(m, -1)[:, :2]
    if indptr[-1] != len(pts):
        raise InputError(None, f"indptr ends at {indptr[-1]} but there are {len(pts)} patch points", field="indptr")
    yaw = np.zeros(m)
    out = np.empty_like(pts)
    for k0, k1 in patch_blocks(indptr, _BLOCK_POINTS):  # bounds the (9, n) moments below
        a, b = indptr[k0], indptr[k1]
        yaw[k0:k1] = _yaw_block(pts[a:b], indptr[k0 : k1 + 1] - a, obs[k0:k1], min_horizontal_norm, out[a:b])
    return yaw, out


def _yaw_block(
    pts: np.ndarray, indptr: np.ndarray, obs: np.ndarray, min_horizontal_norm: float, out: np.ndarray
) -> np.ndarray:
    """Yaws of the patches of one block; writes their normalised points into ``out``."""
    m = len(indptr) - 1
    counts = np.diff(indptr)
    nonempty = np.flatnonzero(counts > 0)
    # first and second moments per patch: the coordinates and their six products stacked as
    # rows of one (9, n) array, summed per patch by a single np.add.reduceat along the rows
    moments = np.empty((9, len(pts)))
    x, y, z = moments[:3]
    np.copyto(moments[:3], pts.T)
    for row, (i, j) in enumerate(((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)), start=3):
        np.multiply(moments[i], moments[j], out=moments[row])
    sums = np.zeros((m, 9))
    if len(nonempty):
        sums[nonempty] = np.add.reduceat(moments, indptr[:-1][nonempty], axis=1).T
    n = np.maximum(counts, 1)
    mean = sums[:, :3] / n[:, None]
    cov = np.empty((m, 3, 3))
    for col, (i, j) in enumerate(((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))):
        cov[:, i, j] = cov[:, j, i] = sums[:, 3 + col] / n - mean[:, i] * mean[:, j]
    _, vecs = np.linalg.eigh(cov)  # ascending eigenvalues; columns are eigenvectors
    axis = vecs[:, :2, 0]
    weak = np.hypot(axis[:, 0], axis[:, 1]) < min_horizontal_norm
    axis[weak] = vecs[weak, :2, 1]
    axis /= np.hypot(axis[:, 0], axis[:, 1])[:, None]
    flip = np.einsum("ij,ij->i", axis, obs) < 0
    axis[flip] *= -1.0
    yaw = np.where(counts > 0, np.arctan2(axis[:, 1], axis[:, 0]), 0.0)
    c = np.repeat(np.cos(yaw), counts)
    s = np.repeat(np.sin(yaw), counts)
    tmp = moments[3]  # the products are summed; their rows are free
    np.multiply(c, x, out=out[:, 0])
    out[:, 0] += np.multiply(s, y, out=tmp)
    np.multiply(c, y, out=out[:, 1])
    out[:, 1] -= np.multiply(s, x, out=tmp)
    out[:, 2] = z
    return yaw


def first_observer_frames(
    point_indices: np.ndarray, obs_indptr: np.ndarray, obs_frame_ids: np.ndarray, frame_ids: np.ndarray
) -> np.ndarray:
    """(K,) id of the first frame with a known position that observed each of ``point_indices``.

    ``obs_indptr``/``obs_frame_ids`` are the observation CSR of a
    :class:`~mapkit.mapping.semidense.SemiDenseMap`; ``frame_ids`` (F,) the frames whose positions are
    known (``keyframe_ids``). Frame ids grow with time, so the first observer is the smallest id
    among a point's observers whose position is known (a semi-dense point also lists the non-key
    neighbour frames that confirmed it, and those have no stored pose). A point with no such
    observer is an error.
    """
    pidx = np.asarray(point_indices, np.int64)
    obs_indptr = np.asarray(obs_indptr, np.int64)
    obs_frame_ids = np.asarray(obs_frame_ids, np.int64)
    sorted_ids = np.sort(np.asarray(frame_ids, np.int64))
    starts, stops = obs_indptr[pidx], obs_indptr[pidx + 1]
    counts = stops - starts
    # flat entries of the selected points' observation lists
    entry = np.repeat(starts - np.cumsum(counts) + counts, counts) + np.arange(int(counts.sum()))
    fid = obs_frame_ids[entry]
    pos = np.minimum(np.searchsorted(sorted_ids, fid), max(len(sorted_ids) - 1, 0))
    known = (sorted_ids[pos] == fid) if len(sorted_ids) else np.zeros(len(fid), bool)
    big = np.iinfo(np.int64).max
    key = np.where(known, fid, big)
    first = np.full(len(pidx), big)
    has = counts > 0
    if has.any():
        seg = np.zeros(len(pidx) + 1, np.int64)
        np.cumsum(counts, out=seg[1:])
        first[has] = np.minimum.reduceat(key, seg[:-1][has])
    if np.any(first == big):
        bad = int(pidx[np.argmax(first == big)])
        raise InputError(None, f"map point {bad} has no observing frame with a known position", field="obs_frame_ids")
    return first


def first_observer_positions(
    point_indices: np.ndarray,
    obs_indptr: np.ndarray,
    obs_frame_ids: np.ndarray,
    frame_ids: np.ndarray,
    frame_positions: np.ndarray,
) -> np.ndarray:
    """(K, 3) position of the first frame that observed each of ``point_indices`` (see
    :func:`first_observer_frames`); ``frame_positions`` (F, 3) go with ``frame_ids`` (F,)."""
    frame_ids = np.asarray(frame_ids, np.int64)
    frame_positions = np.asarray(frame_positions, np.float64).reshape(len(frame_ids), 3)
    first = first_observer_frames(point_indices, obs_indptr, obs_frame_ids, frame_ids)
    order = np.argsort(frame_ids, kind="stable")
    return frame_positions[order[np.searchsorted(frame_ids[order], first)]]


# --- voxel grids ----------------------------------------------------------------------------------


def _voxel_counts_block(pts: np.ndarray, indptr: np.ndarray, domain: PatchDomain, grid: int) -> np.ndarray:
    """Counts (k, g, g, g) int64 of the k patches ``indptr`` delimits (a view of one bincount).

    Axes are (x, y, z) of the normalised frame, cell ``i`` of an axis covering
    ``[-h + 2h i / grid, -h + 2h (i + 1) / grid)`` for half extent ``h``; points outside the box
    are left out, points exactly on its far face fall into the last cell.
    """
    k = len(indptr) - 1
    p = pts[indptr[0] : indptr[-1]]
    half = domain.box_half_extents
    inside = np.abs(p[:, 0]) <= half[0]
    inside &= np.abs(p[:, 1]) <= half[1]
    inside &= np.abs(p[:, 2]) <= half[2]
    ijk = ((p + half) * (grid / (2.0 * half))).astype(np.int64)
    np.minimum(ijk, grid - 1, out=ijk)
    flat = np.repeat(np.arange(k, dtype=np.int64) * grid**3, np.diff(indptr))
    flat += (ijk[:, 0] * grid + ijk[:, 1]) * grid + ijk[:, 2]
    return np.bincount(flat[inside], minlength=k * grid**3).reshape(k, grid, grid, grid)


def density_comparison(counts: np.ndarray) -> np.ndarray:
    """Binary density-comparison channels (..., 3, g, g, g) of voxel counts (..., g, g, g).

    Channel a (x, y, z) of a voxel is 1 when its count (= density, all voxels having one volume)
    is strictly higher than that of its neighbour one cell further along +a. The last cell of an
    axis has no neighbour inside the domain; it is compared with 0, i.e. it is 1 when the voxel
    holds any point (what lies beyond the domain is unknown, and this keeps the channel's
    meaning "density drops towards +a").
    """
    c = np.asarray(counts)
    out = np.empty(c.shape[:-3] + (3,) + c.shape[-3:], np.uint8)
    for a in range(3):
        ax = c.ndim - 3 + a
        first, rest, last = [slice(None)] * c.ndim, [slice(None)] * c.ndim, [slice(None)] * c.ndim
        first[ax], rest[ax], last[ax] = slice(None, -1), slice(1, None), slice(-1, None)
        channel = out[..., a, :, :, :]
        np.greater(c[tuple(first)], c[tuple(rest)], out=channel[tuple(first)])
        np.greater(c[tuple(last)], 0, out=channel[tuple(last)])
    return out


def voxelise(
    points_normalised: np.ndarray, domain: PatchDomain = CNN_DOMAIN, grid: int = 32
) -> tuple[np.ndarray, np.ndarray]:
    """Binary occupancy (g, g, g) and density-comparison grid (3, g, g, g), uint8, of one patch.

    Sec. 3.3.2: the points of the (normalised) domain in a regular grid (axes x, y, z of the
    normalised frame, each axis cut into ``grid`` equal cells over the box; points outside it left
    out); see :func:`density_comparison` for the channels.
    """
    pts = _as_points(points_normalised, "points_normalised")
    occ, dcg = voxelise_patches(pts, np.array([0, len(pts)], np.int64), domain, grid)
    return occ[0], dcg[0]


def voxelise_patches(
    points_normalised: np.ndarray,
    indptr: np.ndarray,
    domain: PatchDomain = CNN_DOMAIN,
    grid: int = 32,
    packed: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Occupancy (M, g, g, g) and density comparison (M, 3, g, g, g) grids of many patches, uint8.

    With ``packed`` both are returned through :func:`pack_bits` (last axis g -> ceil(g / 8)
    bytes), an eighth of the memory: 16 KiB instead of 128 KiB per 32^3 patch.
    """
    pts = _as_points(points_normalised, "points_normalised")
    indptr = np.asarray(indptr, np.int64)
    m = len(indptr) - 1
    last = (grid + 7) // 8 if packed else grid
    occ = np.empty((m, grid, grid, last), np.uint8)
    dcg = np.empty((m, 3, grid, grid, last), np.uint8)
    for k0 in range(0, m, _VOXEL_CHUNK_PATCHES):  # the counts of a block stay small
        k1 = min(k0 + _VOXEL_CHUNK_PATCHES, m)
        counts = _voxel_counts_block(pts, indptr[k0 : k1 + 1], domain, grid)
        o, d = (counts > 0).view(np.uint8), density_comparison(counts)
        occ[k0:k1], dcg[k0:k1] = (pack_bits(o), pack_bits(d)) if packed else (o, d)
    return occ, dcg


def voxel_grids(
    points: np.ndarray,
    keypoints: np.ndarray,
    observer_dirs_xy: np.ndarray,
    domain: PatchDomain = CNN_DOMAIN,
    grid: int = 32,
    tree: cKDTree | None = None,
    packed: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """CNN inputs of the patches about ``keypoints`` (M, 3): extract, normalise yaw, voxelise.

    Returns the occupancy grids (M, g, g, g), the density-comparison grids (M, 3, g, g, g)
    (packed along the last axis unless ``packed`` is False) and the yaw angles (M,). Keypoints
    go through in blocks of ~0.5 M patch points, so memory stays bounded for any number of them
    and any map density.
    """
    points = _as_points(points, "points")
    keypoints = _as_points(keypoints, "keypoints")
    obs = np.asarray(observer_dirs_xy, np.float64).reshape(len(keypoints), -1)[:, :2]
    tree = xy_tree(points) if tree is None else tree
    m = len(keypoints)
    last = (grid + 7) // 8 if packed else grid
    occ = np.empty((m, grid, grid, last), np.uint8)
    dcg = np.empty((m, 3, grid, grid, last), np.uint8)
    yaw = np.empty(m)
    for k0, k1 in keypoint_blocks(tree, keypoints, domain):
        indptr, indices = extract_patches(points, keypoints[k0:k1], domain, tree)
        yaw[k0:k1], normalised = yaw_normalise_patches(
            gather_local(points, keypoints[k0:k1], indptr, indices), indptr, obs[k0:k1]
        )
        occ[k0:k1], dcg[k0:k1] = voxelise_patches(normalised, indptr, domain, grid, packed)
    return occ, dcg, yaw


def pack_bits(bits: np.ndarray) -> np.ndarray:
    """Pack a 0/1 array along its last axis (big-endian bit order, ``np.packbits``)."""
    bits = np.ascontiguousarray(bits, np.uint8)
    n = bits.shape[-1]
    if n % 8 == 0:  # rows fill whole bytes: packing the flat array gives the same bytes, ~10x faster
        return np.packbits(bits.reshape(-1)).reshape(bits.shape[:-1] + (n // 8,))
    return np.packbits(bits, axis=-1)


def unpack_bits(packed: np.ndarray, n: int) -> np.ndarray:
    """Inverse of :func:`pack_bits` for a last axis of ``n`` bits; uint8 0/1."""
    packed = np.ascontiguousarray(packed, np.uint8)
    if n % 8 == 0 and packed.shape[-1] == n // 8:
        return np.unpackbits(packed.reshape(-1)).reshape(packed.shape[:-1] + (n,))
    return np.unpackbits(packed, axis=-1, count=n)


def _as_points(a: np.ndarray, name: str) -> np.ndarray:
    a = np.asarray(a, np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise InputError(None, f"{name} must have shape (n, 3), got {a.shape}", field=name)
    return a
