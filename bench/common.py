"""Benchmark plumbing: time a callable, measure peak memory in a fresh process, print ratios.

Every benchmark compares against its baseline in the same run and prints the ratio; none of them
is part of the test suite's pass/fail.
"""

from __future__ import annotations

import json
import resource
import subprocess
import sys
import time
from collections.abc import Callable


def best_of(fn: Callable[[], object], repeat: int = 3) -> float:
    """Best wall time of ``repeat`` calls, in seconds (the least disturbed by other load)."""
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def best_wall_and_cpu(fn: Callable[[], object], repeat: int = 3) -> tuple[float, float]:
    """Best wall time and best CPU time of ``repeat`` calls (s). The CPU time leaves out the time
    this process waited for its core: the steadier figure on a machine shared with other work."""
    wall = cpu = float("inf")
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall, cpu = min(wall, time.perf_counter() - t0), min(cpu, time.process_time() - c0)
    return wall, cpu


def peak_rss_mb_of(code: str) -> float:
    """Peak resident memory (MiB) of running ``code`` in a fresh Python process."""
    # VmHWM, not ru_maxrss: Linux carries the parent's ru_maxrss into a forked child
    wrapper = (
        code
        + "\nimport sys\n"
        + "hwm = [l for l in open('/proc/self/status') if l.startswith('VmHWM:')][0].split()[1]\n"
        + "print('PEAK_RSS_KB', hwm, file=sys.stderr)\n"
    )
    proc = subprocess.run([sys.executable, "-c", wrapper], capture_output=True, text=True, check=True)
    for line in proc.stderr.splitlines():
        if line.startswith("PEAK_RSS_KB"):
            return int(line.split()[1]) / 1024.0
    raise RuntimeError(f"no peak memory reported:\n{proc.stderr}")


def self_peak_rss_mb() -> float:
    """This process's own peak resident memory (MiB)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def report(name: str, rows: list[dict], ratio_note: str = "", headline: dict | None = None) -> None:
    """Print a Markdown table of rows (dicts with the same keys) and a JSON line for machines.

    The JSON line (prefix ``BENCH_JSON``) holds the table's name, rows and note, and the
    benchmark's ``headline`` when given: a dict with ``mapkit`` (its figure, with units),
    ``baseline`` (the baseline's figure, same run) and ``ratio``, as strings, which
    ``bench/run_all.py`` puts into its summary table as they are.
    """
    keys = list(rows[0])
    print(f"\n## {name}\n")
    print("| " + " | ".join(keys) + " |")
    print("|" + "---|" * len(keys))
    for r in rows:
        print("| " + " | ".join(_fmt(r[k]) for k in keys) + " |")
    if ratio_note:
        print(f"\n{ratio_note}")
    record = {"bench": name, "rows": rows, "note": ratio_note}
    if headline is not None:
        record["headline"] = {k: str(v) for k, v in headline.items()}
    print("BENCH_JSON " + json.dumps(record, default=_json_default), flush=True)


def _json_default(v):
    """numpy scalars as Python numbers; anything else json cannot take as its text."""
    try:
        return v.item()
    except (AttributeError, TypeError, ValueError):
        return str(v)


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)
