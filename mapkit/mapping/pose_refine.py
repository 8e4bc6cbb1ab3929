"""Camera rotations refined against the images, on the given camera positions.

The poses a mapper is handed come from GPS/INS, LiDAR odometry or a factor graph: their positions are
good to centimetres between neighbouring frames, but a camera rotation off by a few tenths of a degree
(an INS heading settling, a mount flexing, an extrinsic calibrated on another day) moves every epipolar
line by pixels, and the depths a keyframe finds along such lines disagree with every other keyframe's
(issue 26: frames 0-14 of the KITTI odometry clip, 2 px off their epipolar lines, rotations off by up to
0.8 deg). DSO removes such errors by its photometric bundle adjustment; with the positions trusted, the
rotations alone are a small, well-posed problem:

- SIFT features per frame (OpenCV), matched with the frames up to ``max_gap`` after it (Lowe's ratio test),
  matches farther than ``gate_px`` from the given epipolar lines left out (repeated facades);
- per frame a small rotation ``x`` (rotation vector, camera frame: ``R = R_given @ exp(x)``) minimising the
  matches' distances (px) to the epipolar lines their partners predict, Huber-robust, with a weak prior at
  the given rotation (``prior_px`` pixels per 1/f rad of correction): on a straight drive a common roll about
  the line of camera centres leaves every epipolar line in place, and the prior holds it;
- streaming, in a sliding window: a frame's rotation is solved with the ``lag`` frames before and after it
  (those handed on held near their final rotations by ``anchor_px``), and handed on once the ``lag``-th frame
  after it has arrived.

:func:`refine_rotations` solves a whole set of frames at once (a diagnostic, ``bench/semidense_kitti_clip.py``);
:class:`RotationRefiner` is the streaming form that :func:`mapkit.mapping.semidense.build_semidense_map` runs
when ``SemiDenseConfig.refine_rotations`` is on.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Iterable, Iterator, Optional, Sequence

import numpy as np

from mapkit.core.geometry import skew

#: (i, j, pixels in frame i (n, 2), their matches in frame j (n, 2))
Matches = Sequence[tuple[int, int, np.ndarray, np.ndarray]]


def epipolar_distances_px(K: np.ndarray, poses: np.ndarray, i: int, j: int, xi: np.ndarray, xj: np.ndarray) -> np.ndarray:
    """(n,) distances (px) of the pixels ``xj`` of frame j from the epipolar lines of their matches ``xi`` in
    frame i under ``poses`` (world_from_cam, indexable by frame id)."""
    Ki = np.linalg.inv(K)
    rel = np.linalg.inv(poses[j]) @ poses[i]  # cam_j from cam_i
    F = Ki.T @ skew(rel[:3, 3]) @ rel[:3, :3] @ Ki
    lines = np.column_stack([xi, np.ones(len(xi))]) @ F.T
    return np.abs((np.column_stack([xj, np.ones(len(xj))]) * lines).sum(1)) / np.maximum(np.hypot(lines[:, 0], lines[:, 1]), 1e-12)


def _rotvecs_to_matrices(x: np.ndarray) -> np.ndarray:
    """(n, 3, 3) rotation matrices of the rotation vectors ``x`` (n, 3) (Rodrigues, vectorised)."""
    theta = np.linalg.norm(x, axis=1)
    small = theta < 1e-12
    k = np.where(small[:, None], 0.0, x / np.where(small, 1.0, theta)[:, None])
    Kx = np.zeros((len(x), 3, 3))
    Kx[:, 0, 1], Kx[:, 0, 2], Kx[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    Kx[:, 1, 0], Kx[:, 2, 0], Kx[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    s, c = np.sin(theta)[:, None, None], np.cos(theta)[:, None, None]
    return np.eye(3) + s * Kx + (1 - c) * (Kx @ Kx)


def _solve(f_px: float, R0: dict[int, np.ndarray], C: dict[int, np.ndarray], free: list[int],
           pairs: list[tuple[int, int, np.ndarray, np.ndarray]], huber_px: float, prior_px: float | np.ndarray,
           prior_at: Optional[np.ndarray] = None, x0: Optional[np.ndarray] = None) -> np.ndarray:
    """Rotation corrections (len(free), 3) of the ``free`` frames (``R = R0 @ exp(x)``), each held by a prior at
    ``prior_at`` (default: no correction) of ``prior_px`` px per 1/f rad (a number, or one per frame).
    ``pairs`` hold normalised homogeneous coordinates (n, 3) of the matches in frame i and frame j."""
    from scipy.optimize import least_squares

    if not free:
        return np.zeros((0, 3))
    pairs = [p for p in pairs if p[0] in R0 and p[1] in R0]
    centre = np.zeros((len(free), 3)) if prior_at is None else np.asarray(prior_at, float).reshape(-1, 3)
    scale = np.broadcast_to(np.asarray(prior_px, float), (len(free),))[:, None]

    col = {f: k for k, f in enumerate(free)}
    rows = np.cumsum([0] + [len(p[2]) for p in pairs])
    touching = {f: [q for q, (i, j, _, _) in enumerate(pairs) if f in (i, j)] for f in free}

    def rotations(x: np.ndarray) -> dict[int, np.ndarray]:
        Rs = _rotvecs_to_matrices(x.reshape(-1, 3))
        return {f: R0[f] @ Rs[k] for k, f in enumerate(free)}

    def pair_residuals(q: int, Ri: np.ndarray, Rj: np.ndarray) -> np.ndarray:
        i, j, a, b = pairs[q]
        E = skew(Rj.T @ (C[i] - C[j])) @ (Rj.T @ Ri)
        lines = a @ E.T
        return f_px * (b * lines).sum(1) / np.maximum(np.hypot(lines[:, 0], lines[:, 1]), 1e-12)

    def residuals(x: np.ndarray) -> np.ndarray:
        R = rotations(x)
        out = [pair_residuals(q, R[i], R[j]) for q, (i, j, _, _) in enumerate(pairs)]
        out.append((f_px * (x.reshape(-1, 3) - centre) / scale).ravel())  # prior_px px of epipolar distance per 1/f rad
        return np.concatenate(out)

    def jacobian(x: np.ndarray) -> np.ndarray:
        """Forward differences, each column re-evaluating only the pairs of its own frame (a pair's residuals
        depend on its two frames' corrections alone): a window of n frames costs 6 pair evaluations per column
        instead of all of them."""
        R = rotations(x)
        base = [pair_residuals(q, R[i], R[j]) for q, (i, j, _, _) in enumerate(pairs)]
        J = np.zeros((rows[-1] + 3 * len(free), 3 * len(free)))
        h = 1e-7  # rad
        for f in free:
            k = col[f]
            for ax in range(3):
                xk = x[3 * k: 3 * k + 3].copy()
                xk[ax] += h
                Rf = R0[f] @ _rotvecs_to_matrices(xk[None])[0]
                for q in touching[f]:
                    i, j = pairs[q][0], pairs[q][1]
                    J[rows[q]:rows[q + 1], 3 * k + ax] = (pair_residuals(q, Rf if i == f else R[i], Rf if j == f else R[j]) - base[q]) / h
        J[rows[-1]:, :] = np.diag(np.repeat(f_px / scale[:, 0], 3))
        return J

    x0 = np.zeros(3 * len(free)) if x0 is None else np.asarray(x0, float).ravel()
    # a dense Jacobian: a window holds a few frames (scipy's sparse trust-region solver, lsmr, needed hundreds of
    # iterations here where the exact one takes under ten)
    sol = least_squares(residuals, x0, jac=jacobian, loss="huber", f_scale=huber_px)
    return sol.x.reshape(-1, 3)


def _normalised(K: np.ndarray, uv: np.ndarray) -> np.ndarray:
    return np.column_stack([uv, np.ones(len(uv))]) @ np.linalg.inv(K).T


def refine_rotations(K: np.ndarray, poses: np.ndarray, matches: Matches, huber_px: float = 1.0, prior_px: float = 1.0) -> np.ndarray:
    """``poses`` (N, 4, 4 world_from_cam) with the rotations of the matched frames re-estimated from ``matches``,
    positions held: every frame at once (a bundle adjustment of rotations only)."""
    ids = sorted({f for i, j, _, _ in matches for f in (i, j)})
    R0 = {f: poses[f, :3, :3] for f in ids}
    C = {f: poses[f, :3, 3] for f in ids}
    pairs = [(i, j, _normalised(K, a), _normalised(K, b)) for i, j, a, b in matches if len(a)]
    x = _solve(float(K[0, 0]), R0, C, ids, pairs, huber_px, prior_px)
    out = np.array(poses, np.float64, copy=True)
    Rs = _rotvecs_to_matrices(x)
    for k, f in enumerate(ids):
        out[f, :3, :3] = R0[f] @ Rs[k]
    return out


@dataclass
class _Frame:
    frame_id: int
    stamp_ns: int
    gray: np.ndarray
    given: np.ndarray  # 4x4 world_from_cam as handed in
    uv: np.ndarray  # (n, 2) keypoints
    desc: Optional[np.ndarray]  # (n, 128) float32 SIFT descriptors
    x: np.ndarray = field(default_factory=lambda: np.zeros(3))  # rotation correction so far


@dataclass
class RotationRefiner:
    """Streaming rotation refinement (see the module's docstring): wraps a stream of
    ``(frame_id, stamp_ns, gray, world_from_cam)`` into the same stream with refined rotations, ``lag`` frames late.

    ``report`` after the stream ends: frames refined, the correction per frame (deg) and the median epipolar
    distance (px) of the matches under the given and the refined rotations.
    """

    K: np.ndarray
    max_gap: int = 3
    lag: int = 6
    huber_px: float = 1.0
    prior_px: float = 1.0
    anchor_px: float = 0.1
    gate_px: float = 10.0
    features: int = 3000
    lowe_ratio: float = 0.7
    min_matches: int = 30
    min_baseline_m: float = 0.1
    corrections_deg: dict = field(default_factory=dict)
    _before: list = field(default_factory=list)
    _after: list = field(default_factory=list)

    def __post_init__(self) -> None:
        if self.lag < self.max_gap:
            raise ValueError(f"lag ({self.lag}) must be at least max_gap ({self.max_gap}): a frame's matches must all be in the window")
        self.K = np.asarray(self.K, np.float64)

    def _features(self, gray: np.ndarray) -> tuple[np.ndarray, Optional[np.ndarray]]:
        import cv2

        if not hasattr(self, "_sift"):
            self._sift = cv2.SIFT_create(nfeatures=self.features)
            self._matcher = cv2.BFMatcher(cv2.NORM_L2)
        g = gray if gray.dtype == np.uint8 else np.clip(gray, 0, 255).astype(np.uint8)
        kp, desc = self._sift.detectAndCompute(g, None)
        return np.array([k.pt for k in kp], np.float64).reshape(-1, 2), desc

    def _match(self, a: _Frame, b: _Frame) -> Optional[tuple[np.ndarray, np.ndarray]]:
        if a.desc is None or b.desc is None or len(a.desc) < 2 or len(b.desc) < 2:
            return None
        if np.linalg.norm(a.given[:3, 3] - b.given[:3, 3]) < self.min_baseline_m:
            return None  # no parallax: the epipolar geometry is undefined
        good = [m for m, n in self._matcher.knnMatch(a.desc, b.desc, k=2) if m.distance < self.lowe_ratio * n.distance]
        ua, ub = a.uv[[m.queryIdx for m in good]].reshape(-1, 2), b.uv[[m.trainIdx for m in good]].reshape(-1, 2)
        if len(ua):  # matches far from the given epipolar lines are wrong (repeated facades), not signs of a rotation error
            near = epipolar_distances_px(self.K, {0: a.given, 1: b.given}, 0, 1, ua, ub) <= self.gate_px
            ua, ub = ua[near], ub[near]
        if len(ua) < self.min_matches:
            return None
        return _normalised(self.K, ua), _normalised(self.K, ub)

    def stream(self, frames: Iterable[tuple[int, int, np.ndarray, np.ndarray]]) -> Iterator[tuple[int, int, np.ndarray, np.ndarray]]:
        f_px = float(self.K[0, 0])
        # the window: up to ``lag`` frames already handed on (features dropped), then those still waiting; a frame is
        # handed on once ``lag`` frames after it have arrived, solved with every frame of the window free: those
        # still waiting held at their given rotations (prior_px), those handed on at their final ones (anchor_px);
        # no frame is fixed outright (fixed anchors passed their error on, and the weakly seen rotation about the
        # drive wandered 1.4 deg over the KITTI clip)
        window: deque[_Frame] = deque()
        done = 0  # frames at the window's front already handed on
        pairs: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
        final: dict[int, np.ndarray] = {}

        def pose(fr: _Frame, x: np.ndarray) -> np.ndarray:
            T = np.array(fr.given, np.float64, copy=True)
            T[:3, :3] = fr.given[:3, :3] @ _rotvecs_to_matrices(x[None])[0]
            return T

        def hand_on() -> tuple[int, int, np.ndarray, np.ndarray]:
            nonlocal done
            ids = [f.frame_id for f in window]
            # frames handed on are held at their final rotations (anchor_px), the others at their given ones (prior_px)
            at = np.array([final.get(f.frame_id, np.zeros(3)) for f in window])
            px = np.array([self.anchor_px if f.frame_id in final else self.prior_px for f in window])
            x = _solve(f_px, {f.frame_id: f.given[:3, :3] for f in window}, {f.frame_id: f.given[:3, 3] for f in window}, ids,
                       [(i, j, a, b) for (i, j), (a, b) in pairs.items()], self.huber_px, px, at, np.concatenate([f.x for f in window]))
            for f, xi in zip(window, x):
                f.x = xi  # warm start of the next window
            fr = window[done]
            final[fr.frame_id] = x[done].copy()
            self.corrections_deg[fr.frame_id] = float(np.degrees(np.linalg.norm(x[done])))
            by_id = {f.frame_id: f for f in window}
            for (i, j), (a, b) in pairs.items():  # a pair is scored once both its frames are handed on
                if fr.frame_id in (i, j) and i in final and j in final:
                    self._score(by_id[i], by_id[j], final[i], final[j], a, b, pose)
            gray = fr.gray
            fr.gray, fr.desc = None, None  # type: ignore[assignment]
            done += 1
            while done > self.lag:  # no frame still waiting is matched with the oldest any more
                old = window.popleft().frame_id
                done -= 1
                final.pop(old, None)
                for key in [key for key in pairs if old in key]:
                    del pairs[key]
            return fr.frame_id, fr.stamp_ns, gray, pose(fr, final[fr.frame_id])

        for frame_id, stamp_ns, gray, world_from_cam in frames:
            uv, desc = self._features(np.asarray(gray))
            fr = _Frame(int(frame_id), int(stamp_ns), gray, np.asarray(world_from_cam, np.float64), uv, desc)
            for prev in list(window)[max(done, len(window) - self.max_gap):]:
                m = self._match(prev, fr)
                if m is not None:
                    pairs[(prev.frame_id, fr.frame_id)] = m
            fr.x = window[-1].x.copy() if window else np.zeros(3)  # warm start: the neighbour's correction
            window.append(fr)
            if len(window) - done > self.lag:
                yield hand_on()
        while len(window) > done:
            yield hand_on()

    def _score(self, fi: _Frame, fj: _Frame, xi: np.ndarray, xj: np.ndarray, na: np.ndarray, nb: np.ndarray, pose) -> None:
        """Median epipolar distances (px) of the pair (i, j) under the given and the refined rotations."""
        i, j = fi.frame_id, fj.frame_id
        uv_i, uv_j = (na @ self.K.T)[:, :2], (nb @ self.K.T)[:, :2]
        self._before.append(float(np.median(epipolar_distances_px(self.K, {i: fi.given, j: fj.given}, i, j, uv_i, uv_j))))
        self._after.append(float(np.median(epipolar_distances_px(self.K, {i: pose(fi, xi), j: pose(fj, xj)}, i, j, uv_i, uv_j))))

    def report(self) -> dict:
        c = np.array(list(self.corrections_deg.values()))
        return {
            "frames": int(len(c)),
            "correction_deg_median": float(np.median(c)) if len(c) else None,
            "correction_deg_max": float(c.max()) if len(c) else None,
            "pairs_matched": int(len(self._before)),
            "epipolar_px_median_given": float(np.median(self._before)) if self._before else None,
            "epipolar_px_median_refined": float(np.median(self._after)) if self._after else None,
        }

