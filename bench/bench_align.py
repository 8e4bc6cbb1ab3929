"""Benchmark of ``mapkit align``: submap pairs registered per second, total time, and how the time
grows with the number of sessions.

The baseline is the quadratic growth a naive all-sessions-against-all design would show: the
time of aligning k sessions is compared with the first subset's, against both the growth of the
number of overlapping submap pairs (what mapkit's work should follow) and k^2.

    python3 bench/bench_align.py WORKSPACE        # a workspace built by `mapkit build` (demo preset)

Each subset is aligned from scratch in a temporary workspace whose sessions link to WORKSPACE's.
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

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mapkit.core.runio import read_timings
from mapkit.multisession.align import align_workspace


def run(workspace: Path, counts: list[int]) -> dict:
    names = sorted(p.name for p in (workspace / "sessions").iterdir() if (p / "map" / ".done").is_file())
    rows = []
    for k in counts:
        if k > len(names):
            break
        tmp = Path(tempfile.mkdtemp(prefix="bench-align-"))
        try:
            shutil.copy(workspace / "origin.json", tmp / "origin.json")
            (tmp / "sessions").mkdir()
            for n in names[:k]:
                os.symlink((workspace / "sessions" / n).resolve(), tmp / "sessions" / n)
            t0 = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                out = align_workspace(tmp, progress=False)
            total = time.perf_counter() - t0
            m = json.loads((out / "metrics.json").read_text())
            reg = {**m["registration"], **read_timings(out)}
            rows.append(
                {
                    "sessions": k,
                    "pairs": reg["pairs"],
                    "accepted": m["pairs"]["accepted"],
                    "total_s": total,
                    "registration_s": reg["seconds_registering"],
                    "pairs_per_s": reg["pairs_per_s"],
                }
            )
            print(
                f"{k} sessions: {reg['pairs']:4d} submap pairs ({m['pairs']['accepted']} accepted), "
                f"{reg['pairs_per_s']:.1f} pairs/s, align total {total:.1f} s",
                flush=True,
            )
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    base = rows[0]
    for r in rows[1:]:
        r["time_ratio"] = r["total_s"] / base["total_s"]
        r["pairs_ratio"] = r["pairs"] / max(1, base["pairs"])
        r["quadratic_ratio"] = (r["sessions"] / base["sessions"]) ** 2
        print(
            f"{base['sessions']} -> {r['sessions']} sessions: time x{r['time_ratio']:.2f}, overlapping pairs "
            f"x{r['pairs_ratio']:.2f}, "
            f"sessions^2 x{r['quadratic_ratio']:.1f}"
        )
    return {"benchmark": "align", "workspace": str(workspace), "rows": rows}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workspace", type=Path)
    ap.add_argument("--sessions", default="2,4,8", help="subset sizes (default 2,4,8)")
    args = ap.parse_args()
    res = run(args.workspace, [int(x) for x in args.sessions.split(",")])
    print(json.dumps(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
