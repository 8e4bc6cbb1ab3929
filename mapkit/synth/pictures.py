"""Pictures for people: a bird's-eye map of the town and routes, and a contact sheet of one place.

Both are drawn with matplotlib's Agg backend (no display needed) and written atomically.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mapkit.core.runio import atomic_path
from mapkit.synth.world import Mat, Town


def _figure(figsize):
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    return Figure(figsize=figsize, dpi=110)


def _save(fig, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        fig.savefig(f, format="png", bbox_inches="tight")
    return path


def _triangles_xy(town: Town, materials: tuple[Mat, ...], stride: int = 1) -> np.ndarray:
    g = town.geometry
    sel = np.flatnonzero(np.isin(g.material, materials))[::stride]
    return g.vertices[g.triangles[sel]][:, :, :2]


def draw_map(town: Town, routes: list[dict], path: Path) -> Path:
    """Buildings, roads, trees and lamps from above, every session's route, grid lines every 100 m."""
    from matplotlib.collections import PolyCollection

    fig = _figure((11, 10))
    ax = fig.add_subplot(1, 1, 1)
    ax.set_facecolor((0.86, 0.9, 0.82))
    for mats, colour in (
        ((Mat.SIDEWALK,), (0.78, 0.78, 0.76)),
        ((Mat.ROAD, Mat.JUNCTION), (0.35, 0.35, 0.37)),
        ((Mat.ROOF,), (0.62, 0.5, 0.45)),
    ):
        tri = _triangles_xy(town, mats)
        # matplotlib's stub asks for a sequence; an (N, 3, 2) array is what PolyCollection takes fastest
        ax.add_collection(PolyCollection(tri, facecolors=[colour], edgecolors="none", zorder=1))  # type: ignore[arg-type]
    g = town.geometry
    fol = g.material == Mat.FOLIAGE
    if fol.any():
        ids = g.object_id[fol]
        cen = g.vertices[g.triangles[fol]].mean(axis=1)
        n = ids.max() + 1
        cnt = np.bincount(ids, minlength=n)
        cx = np.bincount(ids, cen[:, 0], minlength=n)[cnt > 0] / cnt[cnt > 0]
        cy = np.bincount(ids, cen[:, 1], minlength=n)[cnt > 0] / cnt[cnt > 0]
        ax.scatter(cx, cy, s=6, c=[(0.2, 0.5, 0.2)], zorder=2, linewidths=0)
    if len(town.lamps_xyz):
        ax.scatter(town.lamps_xyz[:, 0], town.lamps_xyz[:, 1], s=4, c=[(0.95, 0.75, 0.1)], zorder=3, linewidths=0)
    deg = town.roads.degree()
    dead = np.flatnonzero(deg == 1)
    ax.scatter(
        town.roads.nodes_xy[dead, 0], town.roads.nodes_xy[dead, 1], s=25, marker="x", c="k", zorder=4, label="dead end"
    )
    import matplotlib.cm as cm

    cmap = cm.get_cmap("tab10") if hasattr(cm, "get_cmap") else __import__("matplotlib").colormaps["tab10"]
    for k, r in enumerate(routes):
        xy = r["xy"]
        style = "-" if r["role"] == "train" else "--"
        ax.plot(
            xy[:, 0],
            xy[:, 1],
            style,
            lw=2.0,
            color=cmap(k % 10),
            zorder=5,
            label=f"{r['name']} ({r['role']}): {r['condition']} {r['time']}",
        )
        ax.plot(xy[0, 0], xy[0, 1], "o", color=cmap(k % 10), ms=5, zorder=6)
    a = town.anchor
    ax.plot(
        a["xy"][0], a["xy"][1], "*", ms=18, color="magenta", markeredgecolor="k", zorder=7, label="contact-sheet place"
    )
    ext = max(town.extent_m)
    ax.set_xlim(-town.extent_m[0], town.extent_m[0])
    ax.set_ylim(-town.extent_m[1], town.extent_m[1])
    ax.set_aspect("equal")
    ticks = np.arange(-np.ceil(ext / 100) * 100, ext + 1, 100)
    ax.set_xticks(ticks)
    ax.set_yticks(ticks)
    ax.grid(True, lw=0.4, color="white", alpha=0.8)
    ax.tick_params(labelsize=7)
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    f = town.frame
    ax.set_title(
        f"mapkit synthetic town (seed {town.config.seed}): origin {f.lat0_deg:.5f}, {f.lon0_deg:.5f}, "
        f"UTM EPSG:{f.utm_epsg}; grid 100 m",
        fontsize=10,
    )
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7, frameon=False)
    return _save(fig, path)


def draw_contact_sheet(frames: list[tuple[str, np.ndarray]], path: Path, title: str) -> Path:
    """Images (RGB uint8) with captions in a grid of up to four columns."""
    n = max(1, len(frames))
    cols = min(4, n)
    rows = int(np.ceil(n / cols))
    h, w = frames[0][1].shape[:2] if frames else (480, 640)
    fig = _figure((3.6 * cols, 3.6 * rows * h / w + 0.5))
    for k, (caption, img) in enumerate(frames):
        ax = fig.add_subplot(rows, cols, k + 1)
        ax.imshow(img)
        ax.set_title(caption, fontsize=8)
        ax.axis("off")
    fig.suptitle(title, fontsize=10)
    return _save(fig, path)
