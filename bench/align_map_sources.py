"""Align on LiDAR maps, on semi-dense maps, and on semi-dense maps with LiDAR where they are too sparse, on one
workspace and its town's truth.

The workspace needs both maps for every session (the README's main job builds them: `runs/main/workspace`).
For each map source the sessions are copied into a fresh workspace beside the record, aligned there with
`mapkit align --map-source SOURCE` and scored with `mapkit eval align`: the misalignment of the same true
surface between each pair of sessions after alignment, the registered pairs, and the time align took. The copies
are removed afterwards. It writes the record that docs/guide/align.md's table is made from:

    python3 bench/align_map_sources.py runs/main/workspace --truth runs/main/town --out runs/align-sources.json
    python3 docs/figures.py collect align-sources runs/align-sources.json && python3 docs/figures.py render
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's mapkit, whatever is installed

from mapkit.core.workspace import Workspace  # noqa: E402 (after sys.path points at this checkout)
from mapkit.evaluation.evaluate import evaluate_align  # noqa: E402 (after sys.path points at this checkout)
from mapkit.multisession.align import align_workspace  # noqa: E402 (after sys.path points at this checkout)

SOURCES = ("semidense", "semidense+lidar", "lidar")
#: what a session needs for align: its stage folders and records (not the workspace's later products)
KEEP = ("origin.json", "sessions")


def copy_sessions(ws: Path, to: Path) -> Path:
    """The workspace's origin and sessions (trajectories, maps, image databases) into ``to``; the refined sessions
    of an earlier align are left out, so that each source aligns from the build's maps."""
    to.mkdir(parents=True)
    for name in KEEP:
        src = ws / name
        if src.is_dir():
            shutil.copytree(src, to / name)
        elif src.is_file():
            shutil.copy2(src, to / name)
    return to


def one_source(ws: Path, truth: Path, source: str, scratch: Path) -> dict:
    copy = copy_sessions(ws, scratch / f"ws-{source}")
    try:
        t0 = time.perf_counter()
        align_workspace(copy, overrides={"map_source": source}, progress=False)
        seconds = time.perf_counter() - t0
        ev = evaluate_align(copy, truth)
        metrics = json.loads((copy / "align" / "metrics.json").read_text())
    finally:
        shutil.rmtree(copy, ignore_errors=True)
    return {
        "align_s": seconds,
        "after_median_m": ev["after_median_m"],
        "before_median_m": ev["before_median_m"],
        "pairs": {k: v["after_median_m"] for k, v in ev["pairs"].items()},
        "accepted_pairs": ev["accepted_pairs"],
        "accepted_pair_true_error_max_m": ev["accepted_pair_true_error_max_m"],
        "registered_on": metrics.get("map_source"),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workspace", type=Path, help="a built workspace whose sessions have both maps")
    ap.add_argument("--truth", type=Path, required=True, help="the synthetic town the workspace was built from")
    ap.add_argument("--out", type=Path, required=True, help="the record to write (JSON)")
    ap.add_argument(
        "--sources", nargs="+", choices=SOURCES, default=list(SOURCES), help="the map sources to align on (all)"
    )
    args = ap.parse_args(argv)
    ws = Workspace(args.workspace)
    missing = [n for n in ws.session_names() if not (ws.session(n).lidar_map / "voxels.npz").is_file()]
    if missing:
        print(f"error: sessions without a LiDAR map: {missing} (build with lidar_map: true)", file=sys.stderr)
        return 2
    results = {}
    with tempfile.TemporaryDirectory(prefix="align-sources-", dir=args.out.parent) as scratch:
        for source in args.sources:
            print(f"[align-sources] {source} ...", file=sys.stderr, flush=True)
            results[source] = one_source(ws.root, args.truth, source, Path(scratch))
            r = results[source]
            print(
                f"[align-sources] {source}: misalignment median {r['after_median_m']:.3f} m, worst pair "
                f"{max(r['pairs'].values()):.3f} m, {r['accepted_pairs']} pairs accepted, {r['align_s']:.0f} s",
                file=sys.stderr,
            )
    record = {
        "command": "python3 bench/align_map_sources.py WS --truth TOWN --out FILE",
        "sessions": ws.session_names(),
        "sources": results,
    }
    args.out.write_text(json.dumps(record, indent=1) + "\n")
    print(f"record written to {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
