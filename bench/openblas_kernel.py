"""The OpenBLAS kernel mapkit names on import against the kernels the libraries pick alone: the VLAD vocabulary's
k-means and the word assignment of descriptors, timed, with the bits each gives.

Baseline: numpy, faiss and OpenCV imported before mapkit, so each bundled OpenBLAS picks its own kernel (on a CPU
newer than faiss's and OpenCV's copies, their generic one). mapkit: mapkit imported first (mapkit.core.blas). Each
runs in its own interpreter, ``--repeat`` times, alternating, on the same descriptors: RootSIFT-like rows from a
fixed seed, the vocabulary's size and iterations of ``configs/index_vlad`` (128 words, 25 iterations). Printed:
the kernel of each library, the median seconds and their ratio, and whether the centroids and the assignments are
the same bits in every run of a mode and across the two modes.

    python3 bench/openblas_kernel.py [--repeat 3] [--descriptors 200000] [--assign 1000000]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.common import report  # noqa: E402  (after the checkout is on the path)

CHILD = """
import hashlib, json, sys, time
if sys.argv[1] == "mapkit":
    import mapkit  # names the kernel before the libraries load
import numpy as np, faiss, cv2  # noqa: F401  (faiss and OpenCV load their own OpenBLAS)
from mapkit.core.blas import openblas_kernels
from mapkit.retrieval.vlad import VladAccumulator, kmeans

n, m = int(sys.argv[2]), int(sys.argv[3])
rng = np.random.default_rng(0)
x = np.abs(rng.standard_normal((max(n, m), 128), dtype=np.float32))
x = np.sqrt(x / x.sum(axis=1, keepdims=True))
t0 = time.perf_counter()
centroids = kmeans(x[:n], 128, iterations=25, seed=0)
t1 = time.perf_counter()
words = VladAccumulator(centroids).assign(x[:m])
t2 = time.perf_counter()
print(json.dumps({
    "kernels": openblas_kernels(),
    "kmeans_s": t1 - t0,
    "assign_s": t2 - t1,
    "centroids": hashlib.sha256(centroids.tobytes()).hexdigest()[:12],
    "words": hashlib.sha256(np.ascontiguousarray(words).tobytes()).hexdigest()[:12],
}))
"""


def run(mode: str, n: int, m: int) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_CORETYPE"}
    out = subprocess.run(
        [sys.executable, "-c", CHILD, mode, str(n), str(m)], env=env, capture_output=True, text=True, check=True
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--descriptors", type=int, default=200_000, help="k-means samples (the vocabulary's cap)")
    ap.add_argument("--assign", type=int, default=1_000_000, help="descriptors assigned to words")
    a = ap.parse_args(argv)
    labels = {"baseline": "libraries alone", "mapkit": "mapkit"}
    runs: dict[str, list[dict]] = {mode: [] for mode in labels}
    for _ in range(a.repeat):
        for mode in runs:
            runs[mode].append(run(mode, a.descriptors, a.assign))
    rows = []
    for mode, rs in runs.items():
        rows.append(
            {
                "kernels": ", ".join(f"{k} {v}" for k, v in sorted(rs[0]["kernels"].items())),
                "mode": labels[mode],
                "kmeans_s": statistics.median(r["kmeans_s"] for r in rs),
                "assign_s": statistics.median(r["assign_s"] for r in rs),
                "same_bits_every_run": len({(r["centroids"], r["words"]) for r in rs}) == 1,
                "centroids": rs[0]["centroids"],
            }
        )
    base, mine = rows
    ratio = (mine["kmeans_s"] + mine["assign_s"]) / (base["kmeans_s"] + base["assign_s"])
    same = base["centroids"] == mine["centroids"]
    report(
        "openblas_kernel",
        rows,
        ratio_note=f"mapkit / libraries alone: {ratio:.2f}x the time; the same centroids in both modes: {same}",
        headline={
            "mapkit": f"{mine['kmeans_s'] + mine['assign_s']:.2f} s",
            "baseline": f"{base['kmeans_s'] + base['assign_s']:.2f} s",
            "ratio": f"{ratio:.2f}x",
        },
    )


if __name__ == "__main__":
    main()
