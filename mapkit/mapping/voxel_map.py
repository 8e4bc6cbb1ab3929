"""A streaming voxel map of LiDAR points with per-voxel statistics.

Points are added scan by scan. Each scan is summed per voxel at once (its points labelled by voxel key through
one sort, each sum one ``np.bincount``: linear in the points however few share a voxel); the scans' sums are
buffered up to ``chunk_points`` points, summed per voxel again the same way, and merged into the map's arrays,
appended in the order they are first seen; a sorted index of their keys (``np.searchsorted``) finds the voxels
already there, and only that index (16 bytes a voxel) is spliced when new ones arrive. Memory is therefore bounded
by the map (128 bytes a voxel, up to half as much again in spare capacity) plus one chunk, not by the length of the log.

Per voxel the map keeps sums, so that merging is exact and order-free: the point count, the sum of
the points and of their outer products (relative to the voxel's corner, which keeps the covariance
well conditioned far from the origin), the sum of intensities, and the first and last stamp that
saw the voxel. :meth:`VoxelMap.stats` turns them into the centroid, the mean intensity, and from
the covariance's eigenvalues ``l1 >= l2 >= l3`` the normal (the eigenvector of ``l3``, turned to
point up, +z) and the planarity ``(l2 - l3) / l1`` (Weinmann et al., ISPRS J. 2015): 1 for points
on a plane, 0 on a line or in a ball. Both are NaN for voxels of fewer than 3 points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

_BITS = 21  # per axis of a packed voxel key: +-2**20 voxels, +-105 km at 0.1 m
_HALF = 1 << (_BITS - 1)
_MASK = (1 << _BITS) - 1
# the six distinct products of a point's coordinates: xx, xy, xz, yy, yz, zz
_OUTER_I = np.array([0, 0, 0, 1, 1, 2])
_OUTER_J = np.array([0, 1, 2, 1, 2, 2])
_SUMS = 11  # summed per voxel: x, y, z, xx, xy, xz, yy, yz, zz, intensity, points with an intensity
STATS_BLOCK = 65_536  # voxels whose normal and planarity are computed at a time


@dataclass
class VoxelStats:
    """The statistics of every voxel of a map, sorted by voxel key."""

    voxel_size_m: float
    centroid: np.ndarray  # (V, 3) mean of the voxel's points
    count: np.ndarray  # (V,) points
    intensity: np.ndarray  # (V,) mean intensity of the points that had one; NaN where none had
    normal: np.ndarray  # (V, 3) unit normal, +z up; NaN below 3 points
    planarity: np.ndarray  # (V,) (l2 - l3) / l1 of the covariance's eigenvalues; NaN below 3 points
    first_ns: np.ndarray  # (V,) stamp of the first scan that saw the voxel
    last_ns: np.ndarray  # (V,) stamp of the last one

    def __len__(self) -> int:
        return int(len(self.count))


class VoxelMap:
    """Voxel statistics of the points added with :meth:`add`, merged every ``chunk_points`` points."""

    def __init__(self, voxel_size_m: float, chunk_points: int = 1_000_000):
        if not voxel_size_m > 0:
            raise ValueError(f"voxel size must be positive, got {voxel_size_m}")
        self.voxel_size_m = float(voxel_size_m)
        self.chunk_points = int(chunk_points)
        # per voxel, in the order the voxels were first seen (appended, never moved; capacity grows by half): its
        # point count, sums (one row per sum: x, y, z, the six outer products, intensity, points with one) and
        # first and last stamp; and the keys sorted with the row each is at, the index a merge searches
        self._n = 0
        self._count = np.zeros(0, np.int64)
        self._sums = np.zeros((_SUMS, 0))
        self._first = np.zeros(0, np.int64)
        self._last = np.zeros(0, np.int64)
        self._sorted_keys = np.zeros(0, np.int64)
        self._sorted_rows = np.zeros(0, np.int64)
        self.points_added = 0
        self._pending: list[tuple[np.ndarray, np.ndarray, np.ndarray, int]] = []  # per scan: keys, count, sums, stamp
        self._pending_points = 0
        self.merges = 0  # chunks merged so far

    def __len__(self) -> int:
        self.flush()
        return self._n

    def add(self, points: np.ndarray, intensity: np.ndarray | None, stamp_ns: int) -> None:
        """Add ``points`` (N, 3, map frame, metres) seen at ``stamp_ns`` with their ``intensity`` (N,) or None.
        They are summed per voxel at once (one scan's arrays stay small); the sums wait for the next merge."""
        pts = np.asarray(points, np.float64).reshape(-1, 3)
        if not len(pts):
            return
        keys, count, sums = self._reduce(pts, None if intensity is None else np.asarray(intensity, np.float64))
        self._pending.append((keys, count, sums, int(stamp_ns)))
        self._pending_points += len(pts)
        self.points_added += len(pts)
        if self._pending_points >= self.chunk_points:
            self.flush()

    def flush(self) -> None:
        """Merge the buffered per-scan sums into the map, summed per voxel first."""
        if not self._pending:
            return
        pending, self._pending, self._pending_points = self._pending, [], 0
        self.merges += 1
        keys = np.concatenate([p[0] for p in pending])
        count = np.concatenate([p[1] for p in pending])
        sums = np.concatenate([p[2] for p in pending], axis=1)
        stamps = np.repeat(np.array([p[3] for p in pending], np.int64), [len(p[0]) for p in pending])
        first = last = stamps
        if len(pending) > 1:  # one scan's keys are unique and sorted already
            unique, label, order, start = _group(keys)
            count = np.bincount(label, weights=count, minlength=len(unique)).astype(np.int64)
            summed = np.empty((_SUMS, len(unique)))
            for c in range(_SUMS):
                summed[c] = np.bincount(label, weights=sums[c], minlength=len(unique))
            sums = summed
            stamps = stamps[order]
            first, last = np.minimum.reduceat(stamps, start), np.maximum.reduceat(stamps, start)
            keys = unique
        self._merge(keys, count, sums, first, last)

    def _reduce(self, pts: np.ndarray, inten: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per-voxel sums of one scan's points: (keys sorted and unique, count, sums (11, V)), each sum one
        ``np.bincount`` over the points' voxel labels (linear in the points, whatever their number per voxel)."""
        ijk = np.floor(pts * (1.0 / self.voxel_size_m)).astype(np.int64)
        if np.abs(ijk).max() >= _HALF:
            raise ValueError(
                f"points up to {np.abs(pts).max():.0f} m from the map's origin: beyond the voxel keys' reach of "
                f"{_HALF * self.voxel_size_m:.0f} m at {self.voxel_size_m} m voxels"
            )
        keys, label, _, _ = _group(_pack(ijk))
        local = pts - ijk * self.voxel_size_m  # from the voxel's corner: well conditioned far from the origin
        n = len(keys)
        sums = np.empty((_SUMS, n))
        for c in range(3):
            sums[c] = np.bincount(label, weights=local[:, c], minlength=n)
        for c, (i, j) in enumerate(zip(_OUTER_I, _OUTER_J, strict=True)):
            sums[3 + c] = np.bincount(label, weights=local[:, i] * local[:, j], minlength=n)
        count = np.bincount(label, minlength=n)
        if inten is None:
            sums[9:11] = 0.0
        else:
            has = np.isfinite(inten)
            sums[9] = np.bincount(label, weights=np.where(has, inten, 0.0), minlength=n)
            sums[10] = count if has.all() else np.bincount(label, weights=has, minlength=n)
        return keys, count, sums

    def _merge(self, keys, count, sums, first, last) -> None:
        """Add a chunk's per-voxel sums (keys unique and sorted; sums (11, K)): voxels already mapped are summed in
        place, new ones appended, and only the sorted index of keys (16 bytes a voxel) takes them in order."""
        pos = np.searchsorted(self._sorted_keys, keys)
        found = np.zeros(len(keys), bool)
        inside = pos < self._n
        found[inside] = self._sorted_keys[pos[inside]] == keys[inside]
        at = self._sorted_rows[pos[found]]  # unique: the chunk's keys are
        self._count[at] += count[found]
        self._sums[:, at] += sums[:, found]
        self._first[at] = np.minimum(self._first[at], first[found])
        self._last[at] = np.maximum(self._last[at], last[found])
        new = np.flatnonzero(~found)
        if not len(new):  # a pass over mapped ground: nothing to add
            return
        rows = self._append(count[new], sums[:, new], first[new], last[new])
        new_at, old_at = _spliced_positions(len(self._sorted_keys), pos[new])
        self._sorted_keys = _splice(self._sorted_keys, keys[new], new_at, old_at)
        self._sorted_rows = _splice(self._sorted_rows, rows, new_at, old_at)

    def _append(self, count, sums, first, last) -> np.ndarray:
        """Append voxels at the end of the per-voxel arrays (their capacity grown by half when full); their rows."""
        n, k = self._n, len(count)
        if n + k > len(self._count):
            cap = max(len(self._count) * 3 // 2, n + k, 1024)
            self._count = _grown(self._count, cap, n)
            self._sums = _grown(self._sums, cap, n)
            self._first = _grown(self._first, cap, n)
            self._last = _grown(self._last, cap, n)
        self._count[n : n + k] = count
        self._sums[:, n : n + k] = sums
        self._first[n : n + k] = first
        self._last[n : n + k] = last
        self._n = n + k
        return np.arange(n, n + k, dtype=np.int64)

    def nbytes(self) -> int:
        """Bytes held by the map's arrays, their spare capacity included (the buffered sums aside)."""
        arrays = (self._count, self._sums, self._first, self._last, self._sorted_keys, self._sorted_rows)
        return int(sum(a.nbytes for a in arrays))

    def stats(self) -> VoxelStats:
        """Centroid, mean intensity, normal, planarity and first/last stamp of every voxel, sorted by voxel key
        (buffered points merged first)."""
        self.flush()
        rows = self._sorted_rows
        count = self._count[rows]
        n = count.astype(np.float64)
        centroid = np.empty((len(n), 3))
        normal = np.full((len(n), 3), np.nan)
        planarity = np.full(len(n), np.nan)
        intensity = np.full(len(n), np.nan)
        for lo in range(0, len(n), STATS_BLOCK):  # in blocks: the gathered sums and eigen temporaries stay bounded
            blk = slice(lo, lo + STATS_BLOCK)
            sums = self._sums[:, rows[blk]]  # (11, B)
            nb = n[blk]
            mean_local = (sums[0:3] / nb).T
            centroid[blk] = _unpack(self._sorted_keys[blk]) * self.voxel_size_m + mean_local
            with np.errstate(invalid="ignore", divide="ignore"):
                intensity[blk] = np.where(sums[10] > 0, sums[9] / sums[10], np.nan)
            enough = np.flatnonzero(count[blk] >= 3)
            if not len(enough):
                continue
            # the covariance's six distinct entries (xx, xy, xz, yy, yz, zz)
            m = mean_local[enough]
            cov = (sums[3:9, enough] / nb[enough]).T - m[:, _OUTER_I] * m[:, _OUTER_J]
            evals, smallest = symmetric3_eigen(cov)  # ascending: l3, l2, l1
            at = lo + enough
            normal[at] = smallest * np.where(smallest[:, 2] < 0, -1.0, 1.0)[:, None]
            with np.errstate(invalid="ignore", divide="ignore"):
                planarity[at] = np.where(evals[:, 2] > 0, (evals[:, 1] - evals[:, 0]) / evals[:, 2], np.nan)
        return VoxelStats(
            self.voxel_size_m,
            centroid,
            count,
            intensity,
            normal,
            planarity,
            self._first[rows],
            self._last[rows],
        )


def symmetric3_eigen(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues (ascending) and the eigenvector of the smallest one of many symmetric 3x3 matrices, given as
    their six distinct entries ``a`` (V, 6: xx, xy, xz, yy, yz, zz), in closed form: the eigenvalues from the
    characteristic cubic by the trigonometric method (Smith, Comm. ACM 1961), the eigenvector as the longest cross
    product of two rows of ``a - l3 I``. Array arithmetic only, without LAPACK's per-matrix cost in a batched
    ``np.linalg.eigh``. Where the smallest eigenvalue is not simple (a line's or a ball's covariance: no unique
    normal) the vector is one of its eigenvectors."""
    a = np.asarray(a, np.float64)
    a00, a01, a02, a11, a12, a22 = a.T
    q = (a00 + a11 + a22) / 3.0
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p = np.sqrt((b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * (a01 * a01 + a02 * a02 + a12 * a12)) / 6.0)
    det = b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02) + a02 * (a01 * a12 - b11 * a02)
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.where(p > 0, det / (2.0 * p**3), 0.0)
    phi = np.arccos(np.clip(r, -1.0, 1.0)) / 3.0
    l1 = q + 2.0 * p * np.cos(phi)
    l3 = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    evals = np.stack([l3, 3.0 * q - l1 - l3, l1], axis=1)
    m00, m11, m22 = a00 - l3, a11 - l3, a22 - l3
    # rows of a - l3 I: (m00, a01, a02), (a01, m11, a12), (a02, a12, m22); their three cross products
    crosses = np.stack(
        [
            np.stack([a01 * a12 - a02 * m11, a02 * a01 - m00 * a12, m00 * m11 - a01 * a01], axis=1),
            np.stack([a01 * m22 - a02 * a12, a02 * a02 - m00 * m22, m00 * a12 - a01 * a02], axis=1),
            np.stack([m11 * m22 - a12 * a12, a12 * a02 - a01 * m22, a01 * a12 - m11 * a02], axis=1),
        ]
    )  # (3, V, 3)
    norm2 = np.einsum("kvi,kvi->kv", crosses, crosses)
    best = np.argmax(norm2, axis=0)
    rows = np.arange(len(a))
    longest = np.sqrt(norm2[best, rows])
    with np.errstate(invalid="ignore", divide="ignore"):
        vec = crosses[best, rows] / longest[:, None]
    # the cross products of a rank-1 (or 0) ``a - l3 I`` vanish: l3 is not simple (a line's or a ball's covariance).
    # Then any unit vector orthogonal to its longest row (the line's direction) is an eigenvector of l3, and where
    # every row vanishes (a ball, or one point seen again and again) any vector is: take up, +z
    weak = np.flatnonzero(~(longest > 1e-9 * np.maximum(l1 - l3, 0.0) ** 2) | (p <= 0))
    if len(weak):
        rows3 = np.stack(
            [np.stack([m00, a01, a02], axis=1), np.stack([a01, m11, a12], axis=1), np.stack([a02, a12, m22], axis=1)]
        )[:, weak]  # (3, W, 3)
        row_norm = np.linalg.norm(rows3, axis=2)
        pick = np.argmax(row_norm, axis=0)
        w = np.arange(len(weak))
        direction = rows3[pick, w]
        axis = np.eye(3)[np.argmin(np.abs(direction), axis=1)]  # the axis least along the line
        ortho = np.cross(direction, axis)
        size = np.linalg.norm(ortho, axis=1)
        flat = size > 1e-12 * np.maximum(row_norm[pick, w], 1e-300)
        vec[weak] = np.where(flat[:, None], ortho / np.where(flat, size, 1.0)[:, None], [0.0, 0.0, 1.0])
    return evals, vec


def packable(ijk: np.ndarray) -> bool:
    """Whether every voxel index (i, j, k) fits the packed keys' range (+-2**20 per axis)."""
    return not len(ijk) or bool(np.all(ijk >= -_HALF) and np.all(ijk < _HALF))


def pack_voxel_keys(ijk: np.ndarray) -> np.ndarray:
    """One int64 key per voxel index (i, j, k) (:func:`packable`), ordered by i, then j, then k: sorting the keys
    sorts the rows as ``np.unique(ijk, axis=0)`` does, several times faster."""
    return _pack(np.asarray(ijk, np.int64))


def _pack(ijk: np.ndarray) -> np.ndarray:
    """One int64 key per voxel index (i, j, k), ordered by i, then j, then k."""
    u = ijk + _HALF
    return (u[:, 0] << (2 * _BITS)) | (u[:, 1] << _BITS) | u[:, 2]


def _unpack(keys: np.ndarray) -> np.ndarray:
    return np.stack([(keys >> (2 * _BITS)) & _MASK, (keys >> _BITS) & _MASK, keys & _MASK], axis=1) - _HALF


def _group(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The unique ``keys`` (sorted), each entry's label (its key's index among them), the sorting order and where
    each key's run begins in it: what ``np.unique(return_inverse=True)`` gives, with the order kept."""
    order = np.argsort(keys)
    ordered = keys[order]
    edge = np.empty(len(keys), bool)
    edge[:1] = True
    np.not_equal(ordered[1:], ordered[:-1], out=edge[1:])
    label = np.empty(len(keys), np.intp)
    label[order] = np.cumsum(edge) - 1
    start = np.flatnonzero(edge)
    return ordered[start], label, order, start


def _grown(a: np.ndarray, capacity: int, used: int) -> np.ndarray:
    """``a`` with room for ``capacity`` entries along its last axis, its first ``used`` kept."""
    out = np.empty((*a.shape[:-1], capacity), a.dtype)
    out[..., :used] = a[..., :used]
    return out


def _spliced_positions(n_old: int, where: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where the new and the old entries go when new ones are inserted before the old indices ``where``
    (non-decreasing, as ``np.searchsorted`` gives for sorted keys): one pass, no sort."""
    new_at = where + np.arange(len(where))
    is_new = np.zeros(n_old + len(where), bool)
    is_new[new_at] = True
    return new_at, np.flatnonzero(~is_new)


def _splice(old: np.ndarray, new: np.ndarray, new_at: np.ndarray, old_at: np.ndarray) -> np.ndarray:
    out = np.empty((len(old) + len(new), *old.shape[1:]), old.dtype)
    out[old_at] = old
    out[new_at] = new
    return out
