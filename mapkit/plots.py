"""PNG pictures for people: trajectories over GPS fixes, map top views. matplotlib, Agg backend."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from .runio import atomic_path


def _figure(size=(8, 8)):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=size, dpi=110)
    return plt, fig, ax


def _frame_equal(ax, xy: np.ndarray, min_ratio: float = 0.4, pad: float = 0.05) -> None:
    """Equal axes around ``xy``, the short side padded to at least ``min_ratio`` of the long one,
    so a straight drive is not drawn as a hairline strip."""
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    span = np.maximum(hi - lo, 1e-3)
    long = span.max() * (1 + 2 * pad)
    half = np.maximum(span * (1 + 2 * pad), min_ratio * long) / 2
    c = (lo + hi) / 2
    ax.set_xlim(c[0] - half[0], c[0] + half[0])
    ax.set_ylim(c[1] - half[1], c[1] + half[1])
    ax.set_aspect("equal", adjustable="box")


def _save(plt, fig, path: Path) -> Path:
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", bbox_inches="tight")
    plt.close(fig)
    return path


def trajectory_over_gps(
    path: Path,
    traj_enu: np.ndarray,
    gps_enu: np.ndarray,
    inliers: np.ndarray,
    title: str,
    truth_enu: Optional[np.ndarray] = None,
) -> Path:
    plt, fig, ax = _figure()
    if truth_enu is not None:
        ax.plot(truth_enu[:, 0], truth_enu[:, 1], color="0.6", lw=3, label="ground truth")
    ax.plot(traj_enu[:, 0], traj_enu[:, 1], "b-", lw=1.2, label="trajectory (aligned)")
    ax.scatter(gps_enu[inliers, 0], gps_enu[inliers, 1], s=6, c="g", label=f"GPS used ({int(inliers.sum())})")
    if (~inliers).any():
        ax.scatter(gps_enu[~inliers, 0], gps_enu[~inliers, 1], s=18, c="r", marker="x", label=f"GPS rejected ({int((~inliers).sum())})")
    _frame_equal(ax, np.vstack([traj_enu[:, :2], gps_enu[:, :2]]))
    ax.set_xlabel("east [m]")
    ax.set_ylabel("north [m]")
    ax.set_title(title)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.2), ncol=4, fontsize=8, frameon=False)
    ax.grid(True, alpha=0.3)
    return _save(plt, fig, path)


def map_top_view(path: Path, points: np.ndarray, traj_enu: Optional[np.ndarray], title: str, max_points: int = 300_000) -> Path:
    plt, fig, ax = _figure((9, 9))
    if len(points) > max_points:
        points = points[np.random.default_rng(0).choice(len(points), max_points, replace=False)]
    if len(points):
        z = points[:, 2]
        lo, hi = np.percentile(z, [2, 98]) if len(z) > 10 else (z.min(), z.max() + 1e-6)
        sc = ax.scatter(points[:, 0], points[:, 1], s=0.2, c=np.clip(z, lo, hi), cmap="viridis", linewidths=0)
        fig.colorbar(sc, ax=ax, shrink=0.6, label="height [m]")
    if traj_enu is not None and len(traj_enu):
        ax.plot(traj_enu[:, 0], traj_enu[:, 1], "r-", lw=0.8, label="trajectory")
        ax.legend(loc="best", fontsize=8)
    extent = [a for a in (points[:, :2] if len(points) else None, None if traj_enu is None else traj_enu[:, :2]) if a is not None and len(a)]
    if extent:
        _frame_equal(ax, np.vstack(extent))
    ax.set_xlabel("east [m]")
    ax.set_ylabel("north [m]")
    ax.set_title(title)
    return _save(plt, fig, path)
