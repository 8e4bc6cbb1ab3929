"""Fusion of keyframe depths into one map: greedy non-maximum suppression of 3-D points, streamed.

Step 5 of the semi-dense mapper (:mod:`mapkit.mapping.semidense`): points of nearby keyframes
closer than ``fusion_radius_m`` are fused by greedy non-maximum suppression on the depth sigma;
the surviving (best-measured) point inherits the observations of those it absorbed, so every map
point lists every frame that observed it (the references that the place-recognition paper's
voting needs, its Sec. 3.1). A point stays open for fusion until ``fusion_window_keyframes``
keyframes pass without it absorbing a new observation, so memory follows the window, not the drive.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


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
