"""What the fourth ICP level costs ``mapkit align``: all sessions aligned from scratch with the
default four levels (1.0, 0.5, 0.25, 0.1 m) against the first three alone (1.0, 0.5, 0.25 m), in turns.

    python3 bench/bench_align_levels.py WORKSPACE [--repeat 2]   # a workspace built by `mapkit build`

Each run aligns every built session of WORKSPACE in a temporary workspace whose sessions link to
WORKSPACE's (empty registration cache), so both configurations register every pair. Printed: the
median wall time of each, their ratio (four levels over three), the registration seconds summed
over workers, and the pairs accepted.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mapkit.core.runio import read_timings
from mapkit.multisession.align import align_workspace

#: the first three levels alone (the baseline): voxel sizes and correspondence distances, m
THREE_LEVELS = {"voxel_sizes_m": [1.0, 0.5, 0.25], "max_correspondence_m": [4.0, 1.5, 0.6]}


def _align_from_scratch(src: Path, names: list[str], overrides: dict) -> tuple[float, dict]:
    tmp = Path(tempfile.mkdtemp(prefix="bench-align-levels-"))
    try:
        shutil.copy(src / "origin.json", tmp / "origin.json")
        (tmp / "sessions").mkdir()
        for n in names:
            os.symlink((src / "sessions" / n).resolve(), tmp / "sessions" / n)
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            out = align_workspace(tmp, overrides=overrides, progress=False)
        seconds = time.perf_counter() - t0
        return seconds, {**json.loads((out / "metrics.json").read_text()), "timings": read_timings(out)}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workspace", type=Path)
    ap.add_argument("--repeat", type=int, default=1, help="runs of each configuration, in turns")
    a = ap.parse_args()
    names = sorted(p.name for p in (a.workspace / "sessions").iterdir() if (p / "map" / ".done").is_file())
    runs: dict[str, list[tuple[float, dict]]] = {"three levels": [], "four levels (default)": []}
    for _ in range(a.repeat):
        runs["three levels"].append(_align_from_scratch(a.workspace, names, {"icp": THREE_LEVELS}))
        runs["four levels (default)"].append(_align_from_scratch(a.workspace, names, {}))
    med = {k: float(np.median([t for t, _ in v])) for k, v in runs.items()}
    for k, v in runs.items():
        m = v[-1][1]
        print(
            f"{k}: median {med[k]:.1f} s of {len(v)} ({', '.join(f'{t:.1f}' for t, _ in v)}); registering "
            f"{m['timings']['seconds_registering']:.1f} s summed over workers for {m['registration']['pairs']} pairs; "
            f"{m['pairs']['accepted']} accepted"
        )
    print(f"four levels / three: x{med['four levels (default)'] / med['three levels']:.2f}")


if __name__ == "__main__":
    main()
