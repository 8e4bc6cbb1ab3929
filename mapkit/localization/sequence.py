"""A drive's 6-DoF poses joined by its odometry: a pose graph over the query sequence (gtsam).

A stretch is a run of queries the odometry links (``odometry[t]`` known from each to the next). Within a stretch
every accepted 6-DoF registration, moved by the odometry, says where every other query is; two registrations agree
where one moved to the other lies within (``agree_m``, ``agree_deg``) of it, widened by three standard deviations
of the odometry between them. The registrations that agree with the most others are the stretch's consensus
(RANSAC over the registrations: a pair at a look-alike place hundreds of metres away, or a run of them where the
drive starts, is outvoted once the right ones outnumber it).

The consensus registrations are priors on their queries, under a Cauchy kernel, each with the configured noise
(the model's own error) plus the registration's covariance where it has one (how well its points fix the
camera: most of them far away fix it poorly along the view); the odometry steps are between
factors whose noise grows with the distance driven; Levenberg-Marquardt solves the stretch's graph, started from
the best-supported registration moved by the odometry. A query without a registration is placed by the odometry.
Until two registrations of a stretch agree, each query keeps its own registration, or the fallback pose (the
filter's) where it has none.

Two ways to read it:

* ``causal`` (the default): each query's pose from it and the queries before it, as a vehicle localizing online
  has it;
* ``batch``: every pose of a stretch from the whole stretch, as an offline re-localization of a recorded drive.

A single image's registration is off wherever its matched points constrain the camera poorly (most of them far
away, or on one facade); along a drive those stretches are short, and odometry to the well-constrained views on
either side carries their accuracy across.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from mapkit.core.geometry import invert_pose, pose_difference

#: the Cauchy kernel's scale (in sigmas): 95 % efficiency on Gaussian residuals (Holland and Welsch, 1977)
CAUCHY_K = 2.3849


@dataclass(frozen=True)
class SequenceNoise:
    """A registration's prior std per position axis (m) and rotation axis (deg); an odometry step's std per axis:
    ``odometry_m + odometry_fraction * step length`` (m) and ``odometry_deg``; two registrations agree within
    ``agree_m`` and ``agree_deg`` plus three stds of the odometry between them; a query's pose is solved from the
    queries within ``window_m`` of driving of it."""

    prior_m: float
    prior_deg: float
    odometry_m: float
    odometry_fraction: float
    odometry_deg: float
    agree_m: float = 0.5
    agree_deg: float = 5.0
    window_m: float = 200.0


def smooth_sequence(
    registered: Sequence[np.ndarray | None],
    odometry: Sequence[np.ndarray | None],
    fallback: Sequence[np.ndarray | None],
    noise: SequenceNoise,
    mode: Literal["causal", "batch"] = "causal",
    covariances: Sequence[np.ndarray | None] | None = None,
) -> list[np.ndarray | None]:
    """Each query's ``world_from_camera`` (see the module); where its stretch has no two agreeing registrations
    (yet), its registration or else its fallback (None where it has neither).

    ``registered[t]``: query t's accepted 6-DoF pose (None where it has none); ``odometry[t]``: camera t-1 from
    camera t (``cam_prev_from_cam``, None for the first query and across gaps); ``fallback[t]``: the pose kept where
    the graph gives none; ``covariances[t]``: the registration's covariance (6, 6) in gtsam's Pose3 convention
    (rotation, translation; ``mapkit.localization.sixdof.world_from_cam_covariance``), added to the prior's noise
    (None: the configured noise alone)."""
    n = len(registered)
    if len(odometry) != n or len(fallback) != n:
        raise ValueError(f"{n} registered poses, {len(odometry)} odometry steps, {len(fallback)} fallback poses")
    if covariances is not None and len(covariances) != n:
        raise ValueError(f"{n} registered poses, {len(covariances)} covariances")
    if mode not in ("causal", "batch"):
        raise ValueError(f"smoothing mode {mode!r}: choose causal or batch")
    out: list[np.ndarray | None] = []
    for reg, kept in zip(registered, fallback, strict=True):
        pose = reg if reg is not None else kept
        out.append(None if pose is None else np.asarray(pose, np.float64))
    starts = [t for t in range(n) if t == 0 or odometry[t] is None] + [n]
    for a, b in zip(starts[:-1], starts[1:], strict=True):
        _Stretch(registered, odometry, a, b, noise, covariances).solve(out, mode)
    return out


def _sigmas(m: float, deg: float) -> np.ndarray:
    """Stds in gtsam's Pose3 tangent order: rotation (from degrees), translation."""
    return np.r_[np.full(3, np.radians(deg)), np.full(3, m)]


def _prior_noise(noise: SequenceNoise, covariance: np.ndarray | None):
    """A registration's prior noise: the configured stds plus its own covariance (if any), under the Cauchy kernel.
    Made once per registration: every window that holds it shares it."""
    import gtsam

    cov = np.diag(_sigmas(noise.prior_m, noise.prior_deg) ** 2)
    if covariance is not None:
        cov = cov + np.asarray(covariance, np.float64)
    return gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Cauchy.Create(CAUCHY_K), gtsam.noiseModel.Gaussian.Covariance(cov)
    )


class _Stretch:
    """Queries ``a`` to ``b - 1``, linked by the odometry."""

    def __init__(self, registered, odometry, a: int, b: int, noise: SequenceNoise, covariances=None):
        self.a, self.b, self.noise = a, b, noise
        self.steps = [np.asarray(odometry[t], np.float64) for t in range(a + 1, b)]
        rel, var_m = [np.eye(4)], [0.0]  # each query in the frame of the first; the odometry's variance to it
        driven = [0.0]  # metres driven from the first
        for step in self.steps:
            rel.append(rel[-1] @ step)
            var_m.append(var_m[-1] + self._step_sigma_m(step) ** 2)
            driven.append(driven[-1] + float(np.linalg.norm(step[:3, 3])))
        self.rel, self.var_m, self.driven = rel, np.array(var_m), np.array(driven)
        self.regs = [t for t in range(a, b) if registered[t] is not None]
        self.pose = {t: np.asarray(registered[t], np.float64) for t in self.regs}
        self.prior_noise = {t: _prior_noise(noise, None if covariances is None else covariances[t]) for t in self.regs}
        # the stretch's first query as each registration places it
        self.origin = {t: self.pose[t] @ invert_pose(rel[t - a]) for t in self.regs}
        self.agree = self._agreement()

    def _step_sigma_m(self, step: np.ndarray) -> float:
        return self.noise.odometry_m + self.noise.odometry_fraction * float(np.linalg.norm(step[:3, 3]))

    def _agreement(self) -> np.ndarray:
        """(R, R) bool: registration i moved by the odometry to registration j's query lies within the gate of it.
        Pairs farther apart than the window are never in one window together: left False, uncompared."""
        r, a, nz = self.regs, self.a, self.noise
        A = np.eye(len(r), dtype=bool)
        for i in range(len(r)):
            for j in range(i + 1, len(r)):
                if self.driven[r[j] - a] - self.driven[r[i] - a] > nz.window_m:
                    break
                dm, ddeg = pose_difference(self.origin[r[i]] @ self.rel[r[j] - a], self.pose[r[j]])
                sd_m = np.sqrt(abs(self.var_m[r[j] - a] - self.var_m[r[i] - a]))
                sd_deg = nz.odometry_deg * np.sqrt(r[j] - r[i])
                A[i, j] = A[j, i] = dm <= nz.agree_m + 3 * sd_m and ddeg <= nz.agree_deg + 3 * sd_deg
        return A

    def _consensus(self, first: int, last: int) -> list[int] | None:
        """The registrations of queries ``first`` to ``last`` that agree with the best-supported one among them (it
        first), or None when no two agree. Ties go to the later registration."""
        idx = [k for k, t in enumerate(self.regs) if first <= t <= last]
        if len(idx) < 2:
            return None
        agree = self.agree[np.ix_(idx, idx)]
        support = agree.sum(axis=1)
        best = int(np.flatnonzero(support == support.max())[-1])
        if support[best] < 2:
            return None
        return [self.regs[idx[best]]] + [self.regs[idx[k]] for k in np.flatnonzero(agree[best]) if k != best]

    def _window(self, t: int, before: float, after: float) -> tuple[int, int]:
        """The first and last query of the stretch within ``before`` metres of driving before t and ``after``
        after it."""
        d = self.driven - self.driven[t - self.a]
        inside = np.flatnonzero((d >= -before) & (d <= after))
        return self.a + int(inside[0]), self.a + int(inside[-1])

    def _graph_poses(self, inliers: list[int], first: int, last: int) -> dict[int, np.ndarray]:
        """The graph's poses of queries ``first`` to ``last`` with ``inliers`` (the best first) as priors."""
        import gtsam

        nz = self.noise
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        origin = self.origin[inliers[0]]
        for t in range(first, last + 1):
            values.insert(t, gtsam.Pose3(origin @ self.rel[t - self.a]))
            if t > first:
                step = self.steps[t - self.a - 1]
                noise = gtsam.noiseModel.Diagonal.Sigmas(_sigmas(self._step_sigma_m(step), nz.odometry_deg))
                graph.add(gtsam.BetweenFactorPose3(t - 1, t, gtsam.Pose3(step), noise))
        for t in inliers:
            if first <= t <= last:
                graph.add(gtsam.PriorFactorPose3(t, gtsam.Pose3(self.pose[t]), self.prior_noise[t]))
        result = gtsam.LevenbergMarquardtOptimizer(graph, values, gtsam.LevenbergMarquardtParams()).optimize()
        return {t: result.atPose3(t).matrix() for t in range(first, last + 1)}

    def solve(self, out: list[np.ndarray | None], mode: str) -> None:
        """Each query's pose from the graph of its window: the ``window_m`` before it (causal), or half of it on
        either side (batch). A window's consensus holds where the odometry's drift across it stays within the
        agreement band, which a window of a few hundred metres keeps (bench/odometry_noise.py), and the cost per
        query stays bounded on long drives."""
        w = self.noise.window_m
        before, after = (w, 0.0) if mode == "causal" else (w / 2, w / 2)
        for t in range(self.a, self.b):
            first, last = self._window(t, before, after)
            inliers = self._consensus(first, last)
            if inliers is not None:
                # from the first consensus registration (causal; before it, only the odometry would place), or
                # the whole window
                lo = min(inliers) if mode == "causal" else first
                out[t] = self._graph_poses(inliers, lo, last)[t]
