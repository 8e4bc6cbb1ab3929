"""Adding one session to an aligned workspace against aligning all of them from scratch.

    python3 bench/bench_align_incremental.py WORKSPACE    # a workspace built by `mapkit build` (demo preset)

With N built sessions in WORKSPACE: (a) all N aligned from scratch (empty registration cache);
(b) the first N-1 aligned, then the N-th added, which registers only its own submap pairs (the
cache) and solves only its submaps (the others stay frozen, their frame entering the graph as
priors). The ratio (b)'s second run / (a) is printed, with the graph's own seconds (iSAM2) apart.
Each case runs in a temporary workspace whose sessions link to WORKSPACE's.
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

from mapkit.multisession.align import align_workspace  # noqa: E402


def _workspace(src: Path, names: list[str]) -> Path:
    tmp = Path(tempfile.mkdtemp(prefix="bench-align-inc-"))
    shutil.copy(src / "origin.json", tmp / "origin.json")
    (tmp / "sessions").mkdir()
    for n in names:
        os.symlink((src / "sessions" / n).resolve(), tmp / "sessions" / n)
    return tmp


def _align(ws: Path) -> tuple[float, dict]:
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out = align_workspace(ws, progress=False)
    return time.perf_counter() - t0, json.loads((out / "metrics.json").read_text())


def run(workspace: Path) -> dict:
    names = sorted(p.name for p in (workspace / "sessions").iterdir() if (p / "map" / ".done").is_file())
    if len(names) < 3:
        raise SystemExit(f"{workspace}: {len(names)} built sessions; this benchmark needs at least 3")
    scratch = _workspace(workspace, names)
    inc = _workspace(workspace, names[:-1])
    try:
        t_all, m_all = _align(scratch)
        t_first, _ = _align(inc)
        os.symlink((workspace / "sessions" / names[-1]).resolve(), inc / "sessions" / names[-1])
        t_add, m_add = _align(inc)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
        shutil.rmtree(inc, ignore_errors=True)
    r = {"sessions": len(names), "added": names[-1], "scratch_s": t_all, "first_n_minus_1_s": t_first, "add_one_s": t_add,
         "ratio": t_add / t_all, "pairs_scratch": m_all["registration"]["pairs"], "pairs_registered_adding": m_add["registration"]["registered_this_run"],
         "graph_scratch_s": m_all["graph"]["seconds"], "graph_add_s": m_add["graph"]["seconds"],
         "sessions_solved_adding": m_add["graph"]["sessions_solved"]}
    print(f"all {len(names)} sessions from scratch: {t_all:.1f} s ({r['pairs_scratch']} submap pairs registered, graph {r['graph_scratch_s']:.2f} s)")
    print(f"adding {names[-1]} to the other {len(names) - 1}: {t_add:.1f} s ({r['pairs_registered_adding']} pairs registered, "
          f"{r['sessions_solved_adding']} session solved, graph {r['graph_add_s']:.2f} s)")
    print(f"add one / from scratch: x{r['ratio']:.2f} (target < 0.33)")
    return r


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workspace", type=Path)
    ap.add_argument("--json", type=Path, help="also write the figures here")
    a = ap.parse_args()
    r = run(a.workspace)
    if a.json:
        a.json.write_text(json.dumps(r, indent=2))


if __name__ == "__main__":
    main()
