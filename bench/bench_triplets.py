"""Benchmark of ``mapkit triplets``: triplets exported per second and peak memory.

Baseline, in the same run: the paper's procedure taken literally, one ICP per place
(``icp_cell_m`` so small that every place has its own cell). mapkit's default draws places cell
by cell and shares one ICP per session and 10 m cell.

    python3 bench/bench_triplets.py WORKSPACE [--n 2000]     # an aligned workspace (mapkit align)
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

ROOT = Path(__file__).resolve().parents[1]


def run_one(workspace: Path, n: int, overrides: dict) -> dict:
    """Export ``n`` triplets in a fresh process; its metrics and peak resident memory (VmHWM)."""
    with tempfile.TemporaryDirectory(prefix="bench-triplets-") as tmp:
        code = (
            f"import sys, json, warnings; sys.path.insert(0, {str(ROOT)!r}); warnings.simplefilter('ignore')\n"
            "from mapkit.triplets import export_triplets\n"
            f"out = export_triplets({str(workspace)!r}, out={tmp + '/t'!r}, overrides={dict(overrides, n_triplets=n)!r}, progress=False)\n"
            "print('METRICS', open(out / 'metrics.json').read().replace(chr(10), ' '))\n"
        )
        wrapper = code + "\nhwm = [l for l in open('/proc/self/status') if l.startswith('VmHWM:')][0].split()[1]\nprint('PEAK_RSS_KB', hwm)\n"
        proc = subprocess.run([sys.executable, "-c", wrapper], capture_output=True, text=True, check=True)
        metrics = peak = None
        for line in proc.stdout.splitlines():
            if line.startswith("METRICS"):
                metrics = json.loads(line[len("METRICS"):])
            if line.startswith("PEAK_RSS_KB"):
                peak = int(line.split()[1]) / 1024.0
        return {**metrics, "peak_rss_mb": peak}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workspace", type=Path)
    ap.add_argument("--n", type=int, default=2000, help="triplets per run (default 2000)")
    args = ap.parse_args()
    base = run_one(args.workspace, args.n, {"icp_cell_m": 0.001, "places_per_cell": 1})
    print(f"per-place ICP (paper, literal): {base['triplets_per_s']:.1f} triplets/s, {base['icp_registrations']} ICPs, "
          f"peak {base['peak_rss_mb']:.0f} MB", flush=True)
    ours = run_one(args.workspace, args.n, {})
    print(f"mapkit (ICP per 10 m cell):     {ours['triplets_per_s']:.1f} triplets/s, {ours['icp_registrations']} ICPs, "
          f"peak {ours['peak_rss_mb']:.0f} MB", flush=True)
    ratio = ours["triplets_per_s"] / base["triplets_per_s"]
    print(f"speed-up x{ratio:.2f}; goal 200 triplets/s: {'met' if ours['triplets_per_s'] >= 200 else 'NOT met'}")
    print(json.dumps({"benchmark": "triplets", "n": args.n, "baseline": base, "mapkit": ours, "ratio": ratio}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
