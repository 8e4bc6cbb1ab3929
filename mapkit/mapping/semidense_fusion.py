"""Fusion of keyframe depths into one map: outlier rejection, then greedy non-maximum suppression, streamed.

Step 5 of the semi-dense mapper (:mod:`mapkit.mapping.semidense`):

- **Multi-view geometric consistency** (:func:`consistent_views`, :class:`_ViewWindow`; as COLMAP's
  depth-map fusion and DSO's point activation): a keyframe's depths are reprojected into the
  keyframes up to ``consistency_window_keyframes`` before and after it, and a depth enters the map
  only where enough of them hold their own depth within a relative tolerance there. A wrong match
  (a streak along the viewing ray behind a tree or a pole) lands where no other keyframe saw
  anything at that depth. :func:`visibility_views` tells a contradicting view's two cases apart:
  the depth hides behind what the view sees (occlusion) or floats in front of it (free space).
- **Photometric consistency** (:func:`photometric_ncc`, :func:`photometric_filter`; DSO activates a
  point only where its photometric residual is low in the frames that see it, COLMAP scores depths
  by patch NCC): the patch around each depth, lifted at that depth, is compared by NCC with its
  image in the same keyframes, skipping those whose depths show it hidden.
- **Free space** (:func:`free_space_filter`, :func:`hidden_in_source`; the carving of TSDF fusion
  and Merrell et al.'s stability-based fusion, ICCV 2007), over a wider window and against the
  depths that passed the two tests above: a depth goes when a keyframe sees through it (it floats
  in front of a surface that keyframe holds) or saw a surface that would hide it in its own image.
  A depth merely hidden from another keyframe is kept.
- **Fusion**: points of nearby keyframes closer than ``fusion_radius_m`` are fused by greedy
  non-maximum suppression on the depth sigma; the surviving (best-measured) point inherits the
  observations of those it absorbed, so every map point lists every frame that observed it (the
  references that the place-recognition paper's voting needs, its Sec. 3.1). A point stays open
  for fusion until ``fusion_window_keyframes`` keyframes pass without it absorbing a new
  observation, so memory follows the window, not the drive.
- **Statistical outlier pass** (:func:`statistical_inliers`, open3d's ``remove_statistical_outlier``)
  over the finished map: isolated points whose neighbours are unusually far.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterator, Sequence
from typing import Generic, TypeVar

import numpy as np
from scipy.spatial import cKDTree

from mapkit.core.geometry import invert_pose, transform_points
from mapkit.mapping.semidense_epipolar import _remap

T = TypeVar("T")


class SparseDepth:
    """A keyframe's sparse depth image kept as its pixels: the same lookups as a dense (H, W) array
    (NaN where there is no depth) at a few kilobytes instead of H x W floats; for long windows."""

    def __init__(self, pixels_uv: np.ndarray, depth: np.ndarray, shape: tuple[int, int]):
        self.shape = (int(shape[0]), int(shape[1]))
        lin = pixels_uv[:, 1].astype(np.int64) * self.shape[1] + pixels_uv[:, 0].astype(np.int64)
        order = np.argsort(lin, kind="stable")
        self.lin, self.depth = lin[order], np.asarray(depth, np.float32)[order]

    def take(self, lin: np.ndarray) -> np.ndarray:
        """Depths (float32, NaN where none) at linear pixel indices ``row * W + column`` of any shape."""
        if len(self.lin) == 0:
            return np.full(lin.shape, np.nan, np.float32)
        pos = np.minimum(np.searchsorted(self.lin, lin), len(self.lin) - 1)
        return np.where(self.lin[pos] == lin, self.depth[pos], np.float32(np.nan))


def _take(depth, lin: np.ndarray) -> np.ndarray:
    """Values of a dense (H, W) depth image or a :class:`SparseDepth` at linear pixel indices."""
    return depth.take(lin) if isinstance(depth, SparseDepth) else np.take(depth.ravel(), lin)


def _project(
    world_from_cam: np.ndarray, K: np.ndarray, points_world: np.ndarray, shape: tuple[int, int], margin: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(index, x, y, z) of the points in front of a camera whose projection lies inside its (H, W)
    image grown by ``margin`` px; z is the depth in that camera."""
    h, w = shape
    E = invert_pose(world_from_cam)[:3]
    P = K @ E  # (3, 4); column by column: matrix products with 3 columns are slow in BLAS
    X, Y, Z = points_world[:, 0], points_world[:, 1], points_world[:, 2]
    hx, hy, hz = (P[i, 0] * X + P[i, 1] * Y + P[i, 2] * Z + P[i, 3] for i in range(3))
    z = E[2, 0] * X + E[2, 1] * Y + E[2, 2] * Z + E[2, 3]
    idx = np.nonzero(z > 1e-3)[0]
    x, y, z = hx[idx] / hz[idx], hy[idx] / hz[idx], z[idx]
    inside = (x > -0.5 - margin) & (x < w - 0.5 + margin) & (y > -0.5 - margin) & (y < h - 0.5 + margin)
    return idx[inside], x[inside], y[inside], z[inside]


def _depth_evidence(
    depth, x: np.ndarray, y: np.ndarray, z: np.ndarray, rel_tol: float, pixel_radius: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What a view's depth image (dense (H, W) or :class:`SparseDepth`) says about points projected at
    ``x, y`` with depth ``z``: three (n,)
    bool, ``seen`` (some depth within ``pixel_radius``), ``agree`` (one of them within ``rel_tol``
    of its own value) and ``behind`` (one of them nearer than ``z / (1 + rel_tol)``: the view sees a
    surface in front of the point there)."""
    h, w = depth.shape
    r = int(np.ceil(pixel_radius))
    # the pixel offsets that can lie strictly within the radius of a point in the centre pixel's rounding cell
    d = np.arange(-r, r + 1)
    dx, dy = (a.ravel() for a in np.meshgrid(d, d))
    near = np.maximum(np.abs(dx) - 0.5, 0) ** 2 + np.maximum(np.abs(dy) - 0.5, 0) ** 2 < pixel_radius**2
    dx, dy = dx[near], dy[near]
    xf, yf = x.astype(np.float32)[:, None], y.astype(np.float32)[:, None]
    cx = np.rint(xf).astype(np.int32) + dx.astype(np.int32)[None]  # (n, O)
    cy = np.rint(yf).astype(np.int32) + dy.astype(np.int32)[None]
    ok = (cx >= 0) & (cx < w) & (cy >= 0) & (cy < h) & ((cx - xf) ** 2 + (cy - yf) ** 2 <= np.float32(pixel_radius**2))
    lin = np.clip(cy, 0, h - 1) * w + np.clip(cx, 0, w - 1)
    z_own = np.where(ok, _take(depth, lin), np.float32(np.nan))
    zc = z.astype(np.float32)[:, None]
    with np.errstate(invalid="ignore"):
        seen = np.isfinite(z_own).any(axis=1)
        agree = (np.abs(zc - z_own) <= np.float32(rel_tol) * z_own).any(axis=1)
        behind = (zc > np.float32(1.0 + rel_tol) * z_own).any(axis=1)
    # numpy's stub types any(axis=...) as "bool or array"; over axis 1 of a 2-D array it is an array
    return seen, agree, behind  # type: ignore[return-value]


def visibility_views(
    points_world: np.ndarray,
    views: Sequence[tuple[np.ndarray, np.ndarray | SparseDepth]],
    K: np.ndarray,
    rel_tol: float,
    pixel_radius: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per point, how many ``views`` agree with its depth, see it hidden behind a nearer surface, and
    see through it: three (N,) int.

    A view is ``(world_from_cam, depth image (H, W) in m, NaN where it has no depth)`` (or a
    :class:`SparseDepth`). It agrees
    with a point when some pixel within ``pixel_radius`` of the point's reprojection holds a depth
    ``z_own`` with ``|z - z_own| <= rel_tol * z_own``, ``z`` the point's depth in that view. When
    such pixels hold depths but none agrees, the view either holds one nearer than the point
    (``occluded``: the point hides behind what the view sees, which says nothing against it), or
    only farther ones (``free_space``: the point floats in front of the surface the view sees
    through it, so the view's rays pass where the point claims to be; Merrell et al.'s free-space
    violation, ICCV 2007). A view without a depth there says nothing.
    """
    n = len(points_world)
    agree_n, occluded_n, free_n = (np.zeros(n, np.int64) for _ in range(3))
    r = int(np.ceil(pixel_radius))
    for world_from_cam, depth in views:
        idx, x, y, z = _project(world_from_cam, K, points_world, depth.shape, r)
        seen, agree, behind = _depth_evidence(depth, x, y, z, rel_tol, pixel_radius)
        agree_n[idx[agree]] += 1
        occluded_n[idx[seen & ~agree & behind]] += 1
        free_n[idx[seen & ~agree & ~behind]] += 1
    return agree_n, occluded_n, free_n


def consistent_views(
    points_world: np.ndarray,
    views: Sequence[tuple[np.ndarray, np.ndarray]],
    K: np.ndarray,
    rel_tol: float,
    pixel_radius: float,
) -> tuple[np.ndarray, np.ndarray]:
    """How many ``views`` agree on each point's depth, and how many contradict it: two (N,) int.

    As :func:`visibility_views`; a view contradicts a point when it holds depths near the point's
    reprojection and none agrees, whether the point hides behind them or floats in front of them
    (Merrell et al.'s occlusions and free-space violations, ICCV 2007).
    """
    agree, occluded, free = visibility_views(points_world, views, K, rel_tol, pixel_radius)
    return agree, occluded + free


def hidden_in_source(
    source_world_from_cam: np.ndarray,
    pixels_uv: np.ndarray,
    depth: np.ndarray,
    surfaces_world: Sequence[np.ndarray],
    K: np.ndarray,
    shape: tuple[int, int],
    rel_tol: float,
) -> np.ndarray:
    """(N,) int: for each of a keyframe's depths (``pixels_uv`` (N, 2) int, ``depth`` (N,) m), how many
    of the other keyframes' surfaces (``surfaces_world``, one (M_k, 3) array of world points per
    keyframe) put a point on the same pixel of this keyframe nearer than ``depth / (1 + rel_tol)``.

    Such a depth would be hidden in the very image it was measured in: the keyframe's ray to it
    passes through a surface that another keyframe saw (a wrong match behind a pole or a trunk
    lands there). The other keyframes' points are splatted on their nearest pixel only, so that a
    foreground edge next to a background depth does not hide it.
    """
    h, w = shape
    n = len(depth)
    count = np.zeros(n, np.int64)
    if n == 0:
        return count
    lin = pixels_uv[:, 1].astype(np.int64) * w + pixels_uv[:, 0].astype(np.int64)
    pixels, at = np.unique(lin, return_inverse=True)  # the keyframe's pixels, sorted; ``at``: each depth's among them
    for pts in surfaces_world:
        if len(pts) == 0:
            continue
        _, x, y, z = _project(source_world_from_cam, K, pts, shape, 0.0)
        q = np.rint(y).astype(np.int64).clip(0, h - 1) * w + np.rint(x).astype(np.int64).clip(0, w - 1)
        pos = np.minimum(np.searchsorted(pixels, q), len(pixels) - 1)
        hit = pixels[pos] == q
        nearest = np.full(len(pixels), np.inf)
        np.minimum.at(nearest, pos[hit], z[hit])
        count += nearest[at] * (1.0 + rel_tol) < depth
    return count


def photometric_ncc(
    source_world_from_cam: np.ndarray,
    source_image: np.ndarray,
    pixels_uv: np.ndarray,
    depth: np.ndarray,
    views: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray | None]],
    K: np.ndarray,
    *,
    patch_radius: int,
    rel_tol: float,
    pixel_radius: float,
) -> np.ndarray:
    """(N, V) NCC of each keyframe depth's patch with its image in each view; NaN where not compared.

    The depths are a keyframe's (``pixels_uv`` (N, 2) int in ``source_image``, ``depth`` (N,) m); a
    view is ``(world_from_cam, grey image (H, W), depth image (H, W) in m or None)``. The
    ``(2 patch_radius + 1)^2`` pixels around each depth are lifted at its depth (a fronto-parallel
    patch, as the epipolar search assumes), projected into the view and sampled bilinearly; the
    normalised cross-correlation of the two patches is blind to exposure changes. A view is not
    compared where the patch leaves its image, or where its depth image shows a surface nearer
    than the point around the point's reprojection (the point is hidden there, so its patch is not
    expected to match: :func:`visibility_views`).
    """
    n = len(depth)
    out = np.full((n, len(views)), np.nan)
    if n == 0:
        return out
    Kinv = np.linalg.inv(K)
    r = int(patch_radius)
    du, dv = (a.ravel() for a in np.meshgrid(np.arange(-r, r + 1), np.arange(-r, r + 1)))
    src = np.asarray(source_image, np.float32)
    h, w = src.shape
    pu = np.clip(pixels_uv[:, 0:1] + du[None], 0, w - 1)
    pv = np.clip(pixels_uv[:, 1:2] + dv[None], 0, h - 1)
    a = src[pv, pu]  # (N, T)
    a -= a.mean(axis=1, keepdims=True)
    a_norm = np.sqrt((a * a).sum(axis=1))
    pu, pv = pu.astype(np.float32), pv.astype(np.float32)
    zc = depth.astype(np.float32)[:, None]
    centre_world = transform_points(
        source_world_from_cam, (np.column_stack([pixels_uv, np.ones(n)]) @ Kinv.T) * depth[:, None]
    )
    for k, (world_from_cam, image, view_depth) in enumerate(views):
        # a tap lifted at the centre's depth z, in the view: z K R K^-1 [u v 1] + K t
        # (columnwise: no BLAS on thin arrays)
        view_from_src = invert_pose(world_from_cam) @ source_world_from_cam
        A = (K @ view_from_src[:3, :3] @ Kinv).astype(np.float32)
        bt = (K @ view_from_src[:3, 3]).astype(np.float32)
        hx, hy, hz = (zc * (A[i, 0] * pu + A[i, 1] * pv + A[i, 2]) + bt[i] for i in range(3))
        front = hz > 1e-3
        with np.errstate(divide="ignore", invalid="ignore"):
            x = np.where(front, hx / hz, -1e4)
            y = np.where(front, hy / hz, -1e4)
        b = _remap(np.asarray(image, np.float32), x, y)  # NaN outside the image
        valid = np.isfinite(b).all(axis=1) & (a_norm > 1e-3)
        if view_depth is not None:
            idx, cx, cy, cz = _project(world_from_cam, K, centre_world, view_depth.shape, int(np.ceil(pixel_radius)))
            seen, agree, behind = _depth_evidence(view_depth, cx, cy, cz, rel_tol, pixel_radius)
            valid[idx[seen & ~agree & behind]] = False
        b = np.where(valid[:, None], b, np.float32(0))
        b -= b.mean(axis=1, keepdims=True)
        b_norm = np.sqrt((b * b).sum(axis=1))
        valid &= b_norm > 1e-3
        with np.errstate(divide="ignore", invalid="ignore"):
            ncc = (a * b).sum(axis=1) / (a_norm * b_norm)
        out[valid, k] = ncc[valid]
    return out


def multi_view_filter(
    points_world: np.ndarray,
    views: Sequence[tuple[np.ndarray, np.ndarray]],
    K: np.ndarray,
    *,
    min_views: int,
    min_agree_over_conflict: float,
    rel_tol: float,
    pixel_radius: float,
) -> np.ndarray:
    """(N,) bool: the points at least ``min_views`` views agree with (:func:`consistent_views`), by
    at least ``min_agree_over_conflict`` times as many views as contradict them."""
    agree, conflict = consistent_views(points_world, views, K, rel_tol, pixel_radius)
    return (agree >= min_views) & (agree >= min_agree_over_conflict * conflict)


def photometric_filter(
    source_world_from_cam: np.ndarray,
    source_image: np.ndarray,
    pixels_uv: np.ndarray,
    depth: np.ndarray,
    views: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray | None]],
    K: np.ndarray,
    *,
    min_views: int,
    ncc_min: float,
    min_agree_over_conflict: float,
    patch_radius: int,
    rel_tol: float,
    pixel_radius: float,
) -> np.ndarray:
    """(N,) bool: the keyframe depths whose patch at least ``min_views`` views show with NCC >= ``ncc_min``
    (:func:`photometric_ncc`; views that do not see a depth, or see it hidden, are not asked), by at
    least ``min_agree_over_conflict`` times as many views as show something else there."""
    ncc = photometric_ncc(
        source_world_from_cam,
        source_image,
        pixels_uv,
        depth,
        views,
        K,
        patch_radius=patch_radius,
        rel_tol=rel_tol,
        pixel_radius=pixel_radius,
    )
    compared = np.isfinite(ncc)
    with np.errstate(invalid="ignore"):
        agree = (ncc >= ncc_min).sum(axis=1)
    conflict = compared.sum(axis=1) - agree
    return (agree >= min_views) & (agree >= min_agree_over_conflict * conflict)


def free_space_filter(
    source_world_from_cam: np.ndarray,
    pixels_uv: np.ndarray,
    depth: np.ndarray,
    points_world: np.ndarray,
    views: Sequence[tuple[np.ndarray, np.ndarray | SparseDepth, np.ndarray]],
    K: np.ndarray,
    shape: tuple[int, int],
    *,
    rel_tol: float,
    pixel_radius: float,
    max_violations: int,
) -> np.ndarray:
    """(N,) bool: a keyframe's depths (``pixels_uv``, ``depth``, and as ``points_world``) that at most
    ``max_violations`` of the ``views`` contradict on visibility. A view is ``(world_from_cam, depth
    image (H, W) or :class:`SparseDepth`, its depths as world points (M, 3))``; it contradicts a depth when it sees
    through it (the depth floats in front of the surface the view holds there: :func:`visibility_views`'s
    free-space count) or holds a surface that hides it in its own keyframe (:func:`hidden_in_source`).
    A depth hidden behind what a view sees is not contradicted (occlusion)."""
    _, _, free = visibility_views(points_world, [(T, d) for T, d, _ in views], K, rel_tol, pixel_radius)
    hidden = hidden_in_source(source_world_from_cam, pixels_uv, depth, [X for _, _, X in views], K, shape, rel_tol)
    return free + hidden <= max_violations


class _ViewWindow(Generic[T]):
    """Delays a stream of keyframes by ``window`` so each can be checked against up to ``window``
    keyframes on either side; yields ``(item, others)`` in input order. ``window = 0``: no delay."""

    def __init__(self, window: int):
        self.window = window
        self.buf: deque[T] = deque()
        self.released = 0  # items at the front of buf already yielded (kept as others for later ones)

    def push(self, item: T) -> Iterator[tuple[T, list[T]]]:
        self.buf.append(item)
        while len(self.buf) - self.released > self.window:
            yield self._release()
        while self.released > self.window:
            self.buf.popleft()
            self.released -= 1

    def flush(self) -> Iterator[tuple[T, list[T]]]:
        while self.released < len(self.buf):
            yield self._release()

    def _release(self) -> tuple[T, list[T]]:
        k = self.released
        self.released += 1
        # while flushing, released items are no longer dropped from the front: keep to +-window
        return self.buf[k], [x for i, x in enumerate(self.buf) if i != k and abs(i - k) <= self.window]


def statistical_inliers(points: np.ndarray, neighbours: int, std_ratio: float) -> np.ndarray:
    """(N,) bool: points that open3d's ``remove_statistical_outlier`` keeps (mean distance to
    ``neighbours`` nearest points within ``std_ratio`` standard deviations of the cloud's mean)."""
    import open3d as o3d

    keep = np.zeros(len(points), bool)
    if len(points) <= neighbours:
        return ~keep
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    _, index = pcd.remove_statistical_outlier(nb_neighbors=neighbours, std_ratio=std_ratio)
    keep[np.asarray(index, np.int64)] = True
    return keep


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
            "xyz": np.zeros((0, 3)),
            "sigma": np.zeros(0, np.float32),
            "intensity": np.zeros(0, np.uint8),
            "source": np.zeros(0, np.int64),
            "touched": np.zeros(0, np.int64),
            "obs_pt": np.zeros(0, np.int64),
            "obs_fid": np.zeros(0, np.int64),
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
            "xyz": xyz_all[keep],
            "sigma": sigma_all[keep],
            "intensity": np.concatenate([o["intensity"], intensity])[keep],
            "source": np.concatenate([o["source"], np.full(len(xyz), source_id, np.int64)])[keep],
            "touched": touched[keep],
            "obs_pt": pairs[:, 0],
            "obs_fid": pairs[:, 1],
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
        # offsets has one entry more than parts (the total), which zip leaves out
        obs_pt = np.concatenate([p["obs_pt"] + off for p, off in zip(parts, offsets, strict=False)])
        obs_fid = np.concatenate([p["obs_fid"] for p in parts])
        o = np.lexsort((obs_fid, obs_pt))
        out["obs_fid"] = obs_fid[o]
        out["indptr"] = np.r_[0, np.cumsum(np.bincount(obs_pt, minlength=len(out["xyz"])))].astype(np.int64)
        return out
