"""Time of merging a LiDAR map's voxels into the coarser ones place recognition reads, against ``np.unique`` of the
voxel index rows.

Place recognition on the LiDAR maps (``mapkit eval places --map-source lidar``, the demo's places stage) merges each
drive's 0.25 m voxels to ``lidar_voxel_m`` (:func:`mapkit.places.lidar_observations.coarsen`). mapkit sorts one
packed int64 key per voxel; the baseline sorts the (i, j, k) rows with ``np.unique(axis=0)``. Both give the same
merged map, bit for bit (the table says so per session).

Run from the repository root::

    python3 bench/bench_coarsen.py runs/main/workspace --voxel 0.45
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.common import report  # noqa: E402 (after sys.path points at this checkout)

WORKSPACE_NEEDS = "align/sessions"  # bench/run_all.py skips a workspace without it

FIELDS = ("centroid", "count", "intensity", "first_ns", "last_ns")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workspace", type=Path)
    ap.add_argument("--voxel", type=float, default=0.45, help="the merged voxel (m; the demo's places stage: 0.45)")
    args = ap.parse_args(argv)
    from mapkit.core.workspace import Workspace
    from mapkit.mapping.lidar_map import load_voxel_stats
    from mapkit.places import lidar_observations as lo

    ws = Workspace(args.workspace)
    rows = []
    for name in ws.session_names():
        folder, _ = ws.session_map(name, True, "lidar")
        if not (folder / "voxels.npz").is_file():
            print(f"{name}: no LiDAR map, skipped", file=sys.stderr)
            continue
        stats = load_voxel_stats(folder)
        t = time.perf_counter()
        packed = lo.coarsen(stats, args.voxel)
        packed_s = time.perf_counter() - t
        real = lo.packable
        lo.packable = lambda keys: False  # type: ignore[assignment]
        try:
            t = time.perf_counter()
            rows_way = lo.coarsen(stats, args.voxel)
            rows_s = time.perf_counter() - t
        finally:
            lo.packable = real
        same = all(np.array_equal(getattr(packed, f), getattr(rows_way, f), equal_nan=True) for f in FIELDS)
        rows.append(
            {
                "session": name,
                "voxels": len(stats.count),
                "merged": len(packed.count),
                "mapkit s": round(packed_s, 3),
                "np.unique rows s": round(rows_s, 3),
                "speed-up": round(rows_s / packed_s, 2),
                "same map": same,
            }
        )
    if not rows:
        print(f"no LiDAR map in {args.workspace}", file=sys.stderr)
        return 2
    mine, base = sum(r["mapkit s"] for r in rows), sum(r["np.unique rows s"] for r in rows)
    report(
        f"LiDAR voxels merged to {args.voxel:g} m: packed keys against np.unique of the rows",
        rows,
        f"all sessions: {mine:.2f} s against {base:.2f} s, {base / mine:.2f}x",
        headline={
            "mapkit": f"{mine:.2f} s",
            "baseline": f"{base:.2f} s (np.unique axis=0)",
            "ratio": f"{base / mine:.2f}x",
        },
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
