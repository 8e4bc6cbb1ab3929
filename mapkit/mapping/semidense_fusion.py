"""Fusion of keyframe depths into one map: outlier rejection, then greedy non-maximum suppression, streamed.

Step 5 of the semi-dense mapper (:mod:`mapkit.mapping.semidense`):

- **Multi-view geometric consistency** (:func:`consistent_views`, :class:`_ViewWindow`; as COLMAP's
  depth-map fusion and DSO's point activation): a keyframe's depths are reprojected into the
  keyframes up to ``consistency_window_keyframes`` before and after it, and a depth enters the map
  only where enough of them hold their own depth within a relative tolerance there. A wrong match
  (a streak along the viewing ray behind a tree or a pole) lands where no other keyframe saw
  anything at that depth.
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
from typing import Generic, Iterator, Sequence, TypeVar

import numpy as np
from scipy.spatial import cKDTree

from mapkit.core.geometry import invert_pose, transform_points

T = TypeVar("T")


def consistent_views(points_world: np.ndarray, views: Sequence[tuple[np.ndarray, np.ndarray]], K: np.ndarray,
                     rel_tol: float, pixel_radius: float) -> tuple[np.ndarray, np.ndarray]:
    """How many ``views`` agree on each point's depth, and how many contradict it: two (N,) int.

    A view is ``(world_from_cam, depth image (H, W) in m, NaN where it has no depth)``. It agrees
    with a point when some pixel within ``pixel_radius`` of the point's reprojection holds a depth
    ``z_own`` with ``|z - z_own| <= rel_tol * z_own``, ``z`` the point's depth in that view; it
    contradicts the point when such pixels hold depths but none agrees (the point lies in front of
    what that view saw, or hides behind it: Merrell et al.'s free-space violations and occlusions,
    ICCV 2007). A view without a depth there says nothing.
    """
    n = len(points_world)
    count = np.zeros(n, np.int64)
    conflict = np.zeros(n, np.int64)
    r = int(np.ceil(pixel_radius))
    offsets = [(dx, dy) for dy in range(-r, r + 1) for dx in range(-r, r + 1)]
    for world_from_cam, depth in views:
        h, w = depth.shape
        X = transform_points(invert_pose(world_from_cam), points_world)
        idx = np.nonzero(X[:, 2] > 1e-3)[0]
        uvw = X[idx] @ K.T
        x, y, z = uvw[:, 0] / uvw[:, 2], uvw[:, 1] / uvw[:, 2], X[idx, 2]
        inside = (x > -0.5 - r) & (x < w - 0.5 + r) & (y > -0.5 - r) & (y < h - 0.5 + r)
        idx, x, y, z = idx[inside], x[inside], y[inside], z[inside]
        xi, yi = np.rint(x).astype(np.int64), np.rint(y).astype(np.int64)
        agree = np.zeros(len(idx), bool)
        seen = np.zeros(len(idx), bool)
        for dx, dy in offsets:
            cx, cy = xi + dx, yi + dy
            ok = (cx >= 0) & (cx < w) & (cy >= 0) & (cy < h) & ((cx - x) ** 2 + (cy - y) ** 2 <= pixel_radius**2)
            z_own = np.full(len(idx), np.nan)
            z_own[ok] = depth[cy[ok], cx[ok]]
            seen |= np.isfinite(z_own)
            with np.errstate(invalid="ignore"):
                agree |= np.abs(z - z_own) <= rel_tol * z_own
        count[idx[agree]] += 1
        conflict[idx[seen & ~agree]] += 1
    return count, conflict


def multi_view_filter(points_world: np.ndarray, views: Sequence[tuple[np.ndarray, np.ndarray]], K: np.ndarray, *, min_views: int,
                      min_agree_over_conflict: float, rel_tol: float, pixel_radius: float) -> np.ndarray:
    """(N,) bool: the points at least ``min_views`` views agree with (:func:`consistent_views`), by
    at least ``min_agree_over_conflict`` times as many views as contradict them."""
    agree, conflict = consistent_views(points_world, views, K, rel_tol, pixel_radius)
    return (agree >= min_views) & (agree >= min_agree_over_conflict * conflict)


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
        return self.buf[k], [x for i, x in enumerate(self.buf) if i != k]


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
