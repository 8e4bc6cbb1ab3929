"""What recognising a changed log costs: mapkit's sampled log fingerprint against hashing the whole file.

A done-marker records the identity of the log a stage read, and a re-run compares it
before trusting the stage. This benchmark writes a log-sized file of random bytes (``--gib``,
default 1 GiB, in a temporary folder), then times, in one run, the best of ``--repeat``:

* baseline: the SHA-256 of the whole file (``mapkit.core.fingerprint.sha256_file``);
* ``log_fingerprint(watch=False)``: size plus the SHA-256 of the first and last MiB, as every
  stage checks it;
* ``log_fingerprint()`` on a file modified just now: the same, plus the growth watch a fresh log
  gets before a build reads it.

It checks that the fingerprint changes when one byte of the tail changes and when the file grows,
and prints each time and its ratio to the baseline. It never fails.

    python bench/bench_fingerprint.py [--gib 1] [--repeat 3]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import report  # noqa: E402 (after sys.path points at this checkout)
from mapkit.core.fingerprint import log_fingerprint, sha256_file


def best_of(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gib", type=float, default=1.0, help="size of the test log (GiB)")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="mapkit-bench-fp-") as tmp:
        log = Path(tmp) / "drive.mcap"
        block = os.urandom(1 << 24)
        with open(log, "wb") as f:
            for _ in range(max(1, int(args.gib * 64))):
                f.write(block)
        os.utime(log, (time.time() - 60, time.time() - 60))  # settled: no growth watch
        size = log.stat().st_size
        full = best_of(lambda: sha256_file(log), args.repeat)
        sampled = best_of(lambda: log_fingerprint(log, watch=False), args.repeat)
        before = log_fingerprint(log, watch=False)
        with open(log, "r+b") as f:  # one byte of the tail changed
            f.seek(size - 100)
            f.write(bytes([f.read(1)[0] ^ 0xFF]))
        tail_noticed = log_fingerprint(log, watch=False) != before
        with open(log, "ab") as f:  # the file grew
            f.write(b"\0" * 4096)
        grown_noticed = log_fingerprint(log, watch=False) != before
        os.utime(log)  # modified just now: the build watches it for growth first
        watched = best_of(lambda: log_fingerprint(log), args.repeat)
    print(f"log of {size / 2**30:.2f} GiB, best of {args.repeat}")
    print(f"{'method':<44} {'seconds':>9} {'ratio to full hash':>19}")
    for name, t in (
        ("SHA-256 of the whole file (baseline)", full),
        ("log_fingerprint, settled log", sampled),
        ("log_fingerprint, fresh log (growth watch)", watched),
    ):
        print(f"{name:<44} {t:>9.4f} {t / full:>19.4f}")
    print(f"a changed tail byte noticed: {tail_noticed}; growth noticed: {grown_noticed}")
    report(
        "fingerprint",
        [{"method": "whole-file SHA-256", "seconds": full}, {"method": "log_fingerprint", "seconds": sampled}],
        headline={
            "mapkit": f"log_fingerprint {sampled * 1000:.1f} ms ({size / 2**30:.2f} GiB log)",
            "baseline": f"SHA-256 of the whole file {full:.2f} s",
            "ratio": f"{full / sampled:,.0f} (speed-up)",
        },
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
