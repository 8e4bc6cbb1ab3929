"""MCVL's motion model estimated from training drives, as the paper permits.

The filter's motion model (MCVL eqs. 1-2) is a world-frame random walk: per step the position
moves by v ~ N(mu_v, Sigma_v). The paper sets mu_v = (0.1, 0.1, 0.01) m and Sigma_v = diag(1, 1,
0.01) m^2 (Sec. IV-A) and notes that they "can be tuned or estimated from training data". This
module does the latter: the training drives' base trajectories are sampled at the query rate, and
mu_v and Sigma_v are the mean and the per-axis variance of the world-frame displacements between
consecutive samples. The paper's values stay the default; an estimate is a labelled alternative
(``pipelines/mcvl_benchmark.py`` reports both).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from mapkit.core.errors import InputError
from mapkit.core.geometry import interpolate_poses


@dataclass(frozen=True)
class MotionEstimate:
    """mu_v and Sigma_v (diagonal) of world-frame steps at ``rate_hz``, from ``steps`` displacements."""

    velocity_mean_m: tuple[float, float, float]
    velocity_cov_m2: tuple[float, float, float]
    rate_hz: float
    steps: int
    drives: int

    def overrides(self) -> dict:
        """``LocalizeConfig`` overrides that put this estimate into the filter."""
        return {"mcl": {"velocity_mean_m": list(self.velocity_mean_m), "velocity_cov_m2": list(self.velocity_cov_m2)}}

    def to_dict(self) -> dict:
        return {
            "velocity_mean_m": list(self.velocity_mean_m),
            "velocity_cov_m2": list(self.velocity_cov_m2),
            "rate_hz": self.rate_hz,
            "steps": self.steps,
            "drives": self.drives,
            "source": "training drives' base trajectories sampled at the query rate (MCVL Sec. III-A: estimated from "
            "training data)",
        }


def estimate_motion_model(
    trajectories: Iterable[tuple[np.ndarray, np.ndarray]], rate_hz: float, min_variance_m2: float = 1e-4
) -> MotionEstimate:
    """mu_v and Sigma_v of the paper's random walk from ``(stamps_ns, world_from_base)`` drives.

    Each drive is sampled every ``1 / rate_hz`` seconds over its span (poses interpolated), and
    every displacement between consecutive samples is one step. Variances are floored at
    ``min_variance_m2`` so that an axis the drives never moved along (height on a flat town) does
    not freeze the particles on it.
    """
    if rate_hz <= 0:
        raise ValueError(f"rate_hz must be positive, not {rate_hz}")
    dt_ns = int(round(1e9 / rate_hz))
    steps, drives = [], 0
    for stamps, poses in trajectories:
        stamps = np.asarray(stamps, np.int64)
        if len(stamps) < 2 or stamps[-1] - stamps[0] < dt_ns:
            continue
        at = np.arange(stamps[0], stamps[-1] + 1, dt_ns, dtype=np.int64)  # inside the span: nothing extrapolated
        sampled, _ = interpolate_poses(stamps, np.asarray(poses, np.float64), at)
        steps.append(np.diff(sampled[:, :3, 3], axis=0))
        drives += 1
    if not steps or sum(len(s) for s in steps) < 2:
        raise InputError(
            None,
            f"no training drive spans a step of {1 / rate_hz:.3g} s: cannot estimate the motion model",
            field="train_sessions",
        )
    d = np.concatenate(steps)
    mean = d.mean(axis=0)
    var = np.maximum(d.var(axis=0), min_variance_m2)
    return MotionEstimate(
        (float(mean[0]), float(mean[1]), float(mean[2])),
        (float(var[0]), float(var[1]), float(var[2])),
        float(rate_hz),
        int(len(d)),
        drives,
    )


__all__ = ["MotionEstimate", "estimate_motion_model"]
