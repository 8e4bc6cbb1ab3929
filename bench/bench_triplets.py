"""Benchmark of ``mapkit triplets``: triplets exported per second and peak memory.

Baselines, in the same run:
- the paper's procedure taken literally, one ICP per place (``icp_cell_m`` so small that every
  place has its own cell), with this checkout's code;
- with ``--reference FILE``, an earlier ``mapkit/places/triplets.py`` (a saved copy), on the same
  workspace: the before/after of a change.

Each export runs in a fresh process; besides the wall-clock rate (the goal's figure) it prints
the rate per CPU second (user + system of all threads), the steadier figure on a machine shared
with other work.

    python3 bench/bench_triplets.py WORKSPACE [--n 2000] [--reference OLD_TRIPLETS_PY]
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


def run_one(workspace: Path, n: int, overrides: dict, module_file: Path | None = None) -> dict:
    """Export ``n`` triplets in a fresh process; its metrics, CPU seconds and peak resident memory (VmHWM)."""
    if module_file is None:
        load = "from mapkit.places.triplets import export_triplets\n"
    else:  # an earlier copy of the module, imported as a sibling of mapkit's modules (its relative imports resolve)
        load = (
            "import importlib.util\n"
            f"spec = importlib.util.spec_from_file_location('mapkit._triplets_reference', {str(module_file)!r})\n"
            "mod = importlib.util.module_from_spec(spec); sys.modules[spec.name] = mod; spec.loader.exec_module(mod)\n"
            "export_triplets = mod.export_triplets\n"
        )
    with tempfile.TemporaryDirectory(prefix="bench-triplets-") as tmp:
        code = (
            "import sys, json, warnings, resource; "
            f"sys.path.insert(0, {str(ROOT)!r}); warnings.simplefilter('ignore')\n"
            + load
            + f"out = export_triplets({str(workspace)!r}, out={tmp + '/t'!r}, "
            f"overrides={dict(overrides, n_triplets=n)!r}, progress=False)\n"
            "print('METRICS', open(out / 'metrics.json').read().replace(chr(10), ' '))\n"
            "print('TIMINGS', open(out / 'timings.json').read().replace(chr(10), ' '))\n"
            "ru = resource.getrusage(resource.RUSAGE_SELF)\n"
            "print('CPU_S', ru.ru_utime + ru.ru_stime)\n"
        )
        wrapper = (
            code + "\nhwm = [l for l in open('/proc/self/status') if l.startswith('VmHWM:')][0].split()[1]\n"
            "print('PEAK_RSS_KB', hwm)\n"
        )
        proc = subprocess.run([sys.executable, "-c", wrapper], capture_output=True, text=True, check=True)
        metrics = peak = cpu = None
        timings: dict = {}  # wall-clock figures: the stage's run record, apart from its metrics
        for line in proc.stdout.splitlines():
            if line.startswith("METRICS"):
                metrics = json.loads(line[len("METRICS") :])
            if line.startswith("TIMINGS"):
                timings = json.loads(line[len("TIMINGS") :])
            if line.startswith("CPU_S"):
                cpu = float(line.split()[1])
            if line.startswith("PEAK_RSS_KB"):
                peak = int(line.split()[1]) / 1024.0
        made = sum(metrics["triplets"].values())
        return {**metrics, **timings, "cpu_s_process": cpu, "triplets_per_cpu_s": made / cpu, "peak_rss_mb": peak}


def _line(label: str, r: dict) -> str:
    return (
        f"{label:<34} {r['triplets_per_s']:7.1f} triplets/s  {r['triplets_per_cpu_s']:6.1f} per CPU s  "
        f"{r['icp_registrations']:5d} ICPs  peak {r['peak_rss_mb']:.0f} MB"
    )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workspace", type=Path)
    ap.add_argument("--n", type=int, default=2000, help="triplets per run (default 2000)")
    ap.add_argument(
        "--reference", type=Path, help="an earlier mapkit/places/triplets.py to compare with (before/after)"
    )
    args = ap.parse_args()
    rows = {}
    rows["per_place_icp"] = run_one(args.workspace, args.n, {"icp_cell_m": 0.001, "places_per_cell": 1})
    print(_line("per-place ICP (paper, literal):", rows["per_place_icp"]), flush=True)
    if args.reference is not None:
        rows["reference"] = run_one(args.workspace, args.n, {}, args.reference)
        print(_line(f"reference ({args.reference.name}):", rows["reference"]), flush=True)
    rows["mapkit"] = ours = run_one(args.workspace, args.n, {})
    print(_line("mapkit (ICP per 10 m cell):", ours), flush=True)
    ratios = {
        k: {
            "wall": ours["triplets_per_s"] / r["triplets_per_s"],
            "cpu": ours["triplets_per_cpu_s"] / r["triplets_per_cpu_s"],
        }
        for k, r in rows.items()
        if k != "mapkit"
    }
    for k, r in ratios.items():
        print(f"speed-up over {k}: x{r['wall']:.2f} wall, x{r['cpu']:.2f} per CPU second")
    print(f"goal 200 triplets/s (wall): {'met' if ours['triplets_per_s'] >= 200 else 'NOT met'}")
    print(json.dumps({"benchmark": "triplets", "n": args.n, **rows, "ratios": ratios}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
