"""Adding one session to an aligned workspace against aligning all of them from scratch.

    python3 bench/bench_align_incremental.py WORKSPACE    # a workspace built by `mapkit build` (demo preset)

With N built sessions in WORKSPACE: (a) all N aligned from scratch (empty registration cache);
(b) the first N-1 aligned, then the N-th added, which registers only its own submap pairs (the
cache) and solves only its submaps (the others stay frozen, their frame entering the graph as
priors, their files kept). The ratio (b)'s second run / (a) is printed, with the graph's own seconds
(iSAM2) apart and the share of all pairs that the added session brings (the floor of the ratio when
registration is all the time). ``--repeat N`` runs (a) and (b) N times in turns (each (b) from the same
aligned N-1) and takes the ratio of the medians; ``--added NAME`` picks the session added (default:
the last by name). Each case runs in a temporary workspace whose sessions link to WORKSPACE's.
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
    return time.perf_counter() - t0, {**json.loads((out / "metrics.json").read_text()), "timings": read_timings(out)}


def run(workspace: Path, repeat: int = 1, added: str | None = None) -> dict:
    names = sorted(p.name for p in (workspace / "sessions").iterdir() if (p / "map" / ".done").is_file())
    if len(names) < 3:
        raise SystemExit(f"{workspace}: {len(names)} built sessions; this benchmark needs at least 3")
    if added is not None:
        if added not in names:
            raise SystemExit(f"--added {added}: not a built session of {workspace} ({', '.join(names)})")
        names = [n for n in names if n != added] + [added]
    scratch = _workspace(workspace, names)
    inc = _workspace(workspace, names[:-1])
    t_all, t_add, m_all, m_add = [], [], {}, {}
    try:
        t_first, _ = _align(inc)
        snapshot = inc.parent / (inc.name + "-aligned")
        shutil.copytree(inc / "align", snapshot, symlinks=True)
        os.symlink((workspace / "sessions" / names[-1]).resolve(), inc / "sessions" / names[-1])
        for _ in range(repeat):  # scratch and add in turns, so that a busy spell of the machine hits both
            shutil.rmtree(scratch / "align", ignore_errors=True)
            t, m_all = _align(scratch)
            t_all.append(t)
            shutil.rmtree(inc / "align")
            shutil.copytree(snapshot, inc / "align", symlinks=True)
            t, m_add = _align(inc)
            t_add.append(t)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
        shutil.rmtree(inc, ignore_errors=True)
        shutil.rmtree(inc.parent / (inc.name + "-aligned"), ignore_errors=True)
    med_all, med_add = float(np.median(t_all)), float(np.median(t_add))
    reg = m_add["registration"]
    r = {
        "sessions": len(names),
        "added": names[-1],
        "repeat": repeat,
        "scratch_s": t_all,
        "first_n_minus_1_s": t_first,
        "add_one_s": t_add,
        "ratio": med_add / med_all,
        "ratios": [a / b for a, b in zip(t_add, t_all, strict=True)],
        "pairs_scratch": m_all["registration"]["pairs"],
        "pairs_registered_adding": reg["registered_this_run"],
        "pair_share": reg["registered_this_run"] / m_all["registration"]["pairs"],
        "graph_scratch_s": m_all["timings"]["graph_seconds"],
        "graph_add_s": m_add["timings"]["graph_seconds"],
        "sessions_solved_adding": m_add["graph"]["sessions_solved"],
        "sessions_kept_adding": sum(bool(v.get("outputs_kept")) for v in m_add["sessions"].values()),
    }
    print(
        f"all {len(names)} sessions from scratch: median {med_all:.1f} s of {len(t_all)} "
        f"({r['pairs_scratch']} submap pairs registered, graph {r['graph_scratch_s']:.2f} s)"
    )
    print(
        f"adding {names[-1]} to the other {len(names) - 1}: median {med_add:.1f} s of {len(t_add)} "
        f"({r['pairs_registered_adding']} pairs registered, {r['pair_share']:.0%} of all; "
        f"{r['sessions_solved_adding']} session solved, graph {r['graph_add_s']:.2f} s; "
        f"{r['sessions_kept_adding']} frozen sessions' files kept)"
    )
    print(
        f"add one / from scratch: x{r['ratio']:.2f} "
        f"(each run: {', '.join(f'x{x:.2f}' for x in r['ratios'])}; target < 0.33)"
    )
    return r


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workspace", type=Path)
    ap.add_argument("--json", type=Path, help="also write the figures here")
    ap.add_argument(
        "--repeat", type=int, default=1, help="scratch and add runs, in turns; the ratio is of their medians"
    )
    ap.add_argument("--added", help="the session to add (default: the last by name)")
    a = ap.parse_args()
    r = run(a.workspace, a.repeat, a.added)
    if a.json:
        a.json.write_text(json.dumps(r, indent=2))


if __name__ == "__main__":
    main()
