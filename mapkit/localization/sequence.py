"""A drive's 6-DoF poses joined by its odometry: a pose graph over the query sequence (gtsam).

Each query is a ``Pose3`` variable (``world_from_camera``). An accepted 6-DoF registration is a prior on its
query, under a Cauchy kernel so that a registration far from what its neighbours and the odometry say loses its
pull instead of bending the track; the odometry between consecutive queries is a between factor whose noise grows
with the distance driven. A query without a registration is placed by the odometry from its neighbours; the first
query of a stretch the odometry does not link to anything earlier starts from the fallback pose (the filter's),
under a weak prior that only fixes the gauge until a registration arrives.

Two ways to read the graph:

* ``causal`` (the default): each query's pose is the estimate right after it was added (iSAM2), from it and the
  queries before it, as a vehicle localizing online has it;
* ``batch``: every pose from the whole drive (Levenberg-Marquardt over the full graph), as an offline
  re-localization of a recorded drive would use it.

A single image's registration is off wherever its matched points constrain the camera poorly (most of them far
away, or on one facade); along a drive those stretches are short, and odometry to the well-constrained views on
either side carries their accuracy across.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import numpy as np

Smoothing = Literal["causal", "batch", "off"]

#: the Cauchy kernel's scale (in sigmas): 95 % efficiency on Gaussian residuals (Holland and Welsch, 1977)
CAUCHY_K = 2.3849
#: the weak prior that fixes a stretch's first pose to the fallback until a registration arrives (m, deg)
GAUGE_SIGMA = (10.0, 10.0)


def smooth_sequence(
    registered: Sequence[np.ndarray | None],
    odometry: Sequence[np.ndarray | None],
    fallback: Sequence[np.ndarray | None],
    *,
    mode: Literal["causal", "batch"] = "causal",
    prior_sigma_m: float,
    prior_sigma_deg: float,
    odometry_sigma_m: float,
    odometry_sigma_fraction: float,
    odometry_sigma_deg: float,
) -> list[np.ndarray | None]:
    """Each query's ``world_from_camera`` from the pose graph of the sequence (see the module), None for a query
    nothing places (no registration, no fallback and no odometry to a placed neighbour).

    ``registered[t]``: query t's accepted 6-DoF pose (None where it has none); ``odometry[t]``: camera t-1 from
    camera t (``cam_prev_from_cam``, None for the first query and across gaps); ``fallback[t]``: the pose a stretch
    starts from. Prior noise: ``prior_sigma_m`` per axis of the position, ``prior_sigma_deg`` per rotation axis;
    odometry noise per step: ``odometry_sigma_m + odometry_sigma_fraction * step length`` per axis and
    ``odometry_sigma_deg`` per rotation axis."""
    import gtsam

    n = len(registered)
    if len(odometry) != n or len(fallback) != n:
        raise ValueError(f"{n} registered poses, {len(odometry)} odometry steps, {len(fallback)} fallback poses")
    if mode not in ("causal", "batch"):
        raise ValueError(f"smoothing mode {mode!r}: choose causal or batch")

    def sigmas(m: float, deg: float) -> np.ndarray:
        return np.r_[np.full(3, np.radians(deg)), np.full(3, m)]  # gtsam's Pose3 tangent: rotation, then translation

    prior_noise = gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Cauchy.Create(CAUCHY_K),
        gtsam.noiseModel.Diagonal.Sigmas(sigmas(prior_sigma_m, prior_sigma_deg)),
    )
    gauge_noise = gtsam.noiseModel.Diagonal.Sigmas(sigmas(*GAUGE_SIGMA))

    out: list[np.ndarray | None] = [None] * n
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    isam = gtsam.ISAM2() if mode == "causal" else None
    last: np.ndarray | None = None  # the previous query's pose as placed so far (None: it is not in the graph)
    anchored = False  # whether a registration holds the stretch the previous query is on
    for t in range(n):
        # the odometry's prediction of this query from the previous one, where both are linked
        predicted = None if t == 0 or odometry[t] is None or last is None else last @ np.asarray(odometry[t], float)
        pose = registered[t]
        anchored = anchored and predicted is not None
        # on a stretch that a registration holds, the odometry's prediction is the starting point: started at a
        # wrong registration, the optimizer would stay there (its prior's residual is zero, and the kernel then
        # trusts it); on a stretch only the weak fallback holds, the first registration is, else the kernel would
        # take it for an outlier of the fallback's metres-off place
        if predicted is not None and (anchored or pose is None):
            guess = predicted
        elif pose is not None:
            guess = np.asarray(pose, np.float64)
        elif fallback[t] is not None:
            guess = np.asarray(fallback[t], np.float64)
        else:
            last = None
            continue
        anchored = anchored or pose is not None
        values.insert(t, gtsam.Pose3(guess))
        if pose is not None:
            graph.add(gtsam.PriorFactorPose3(t, gtsam.Pose3(np.asarray(pose, np.float64)), prior_noise))
        if predicted is not None:
            step = np.asarray(odometry[t], np.float64)
            length = float(np.linalg.norm(step[:3, 3]))
            noise = gtsam.noiseModel.Diagonal.Sigmas(
                sigmas(odometry_sigma_m + odometry_sigma_fraction * length, odometry_sigma_deg)
            )
            graph.add(gtsam.BetweenFactorPose3(t - 1, t, gtsam.Pose3(step), noise))
        else:  # a stretch's first query: its guess fixes the gauge, weakly
            graph.add(gtsam.PriorFactorPose3(t, gtsam.Pose3(guess), gauge_noise))
        if isam is not None:
            isam.update(graph, values)
            graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
            last = isam.calculateEstimatePose3(t).matrix()
            out[t] = last
        else:
            last = guess
    if isam is None and values.size():
        params = gtsam.LevenbergMarquardtParams()
        result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
        for t in range(n):
            if result.exists(t):
                out[t] = result.atPose3(t).matrix()
    return out
