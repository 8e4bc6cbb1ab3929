"""Draw the documentation's picture: every session's semi-dense map and GPS-aligned trajectory of a
built workspace, seen from above in the workspace's local ENU frame.

The picture in the docs was made from the tiny synthetic town:

    mapkit synth --preset tiny --out /tmp/g/town
    mapkit build /tmp/g/town/sessions/*/ --out /tmp/g/ws
    python docs/img/make_top_view.py /tmp/g/ws docs/img/tiny-town-top-view.png
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import open3d as o3d

from mapkit.core.workspace import Workspace
from mapkit.io.trajectory import read_tum


def draw(workspace: Path, out: Path, max_points: int = 60_000, seed: int = 0) -> Path:
    ws = Workspace(workspace)
    rng = np.random.default_rng(seed)
    fig, ax = plt.subplots(figsize=(4.8, 6.4), dpi=110)
    colours = plt.get_cmap("tab10").colors
    names = ws.session_names()
    for i, name in enumerate(names):
        s = ws.session(name)
        colour = colours[i % len(colours)]
        ply = s.map / "points.ply"
        if ply.is_file():
            xyz = np.asarray(o3d.io.read_point_cloud(str(ply)).points)
            keep = rng.choice(len(xyz), size=min(len(xyz), max_points // len(names)), replace=False)
            ax.scatter(xyz[keep, 0], xyz[keep, 1], s=0.6, color=colour, alpha=0.35, linewidths=0, rasterized=True)
        tum = s.georef_trajectory / "poses_tum.txt"
        if tum.is_file():
            _, world_from_body = read_tum(tum)
            ax.plot(world_from_body[:, 0, 3], world_from_body[:, 1, 3], color=colour, lw=2.0, label=f"{name}")
    ax.set_aspect("equal")
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_title("semi-dense maps and GPS-aligned trajectories", fontsize=10)
    ax.legend(loc="best", fontsize=8, markerscale=4)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    plt.close(fig)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("workspace", type=Path)
    parser.add_argument("out", type=Path)
    args = parser.parse_args()
    path = draw(args.workspace, args.out)
    print(f"{path}: {path.stat().st_size / 1024:.0f} KB")


if __name__ == "__main__":
    main()
