"""mapkit against the authors' own outputs: M2DP against ``M2DP.m``, dense SIFT against VLFeat's ``vl_phow``.

    python3 bench/reference_checks.py [--out runs/references.json]

Reads the reference outputs in ../shared/data/ (m2dp-reference/, vlfeat-phow-reference/; their README
says how they were made) and prints, and writes as JSON for ``docs/figures.py collect references``:

- M2DP: ``m2dp_reference`` on the real KITTI scan against the 192 numbers ``M2DP.m`` computed; 1 - cos
  of each half (u1 and v1, each up to the SVD's sign), the larger of the two;
- dense SIFT: mode ``phow`` on the KITTI frame against ``vl_phow``'s descriptors at the same frames
  (VLFeat's orientation order): median and 5th-percentile cosine over the frames neither zeroes, and the
  share of frames whose contrast-threshold zeroing agrees.

The tests assert the same agreements (tests/test_descriptors3d.py, tests/test_dsift.py); this prints the
figures the docs quote.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mapkit.places import descriptors3d as d3  # noqa: E402 (after sys.path points at this checkout)
from mapkit.retrieval.dsift import DsiftConfig, dense_sift  # noqa: E402 (after sys.path points at this checkout)

DATA = Path(__import__("os").environ.get("MAPKIT_SHARED_DATA", ROOT.parent / "shared" / "data"))


def m2dp_check(folder: Path) -> dict:
    pts = np.fromfile(folder / "kitti-000000.bin", np.float32).reshape(-1, 4)[:, :3].astype(np.float64)
    ref = np.loadtxt(folder / "kitti-000000.m2dp.txt").ravel()
    desc = d3.m2dp_reference(pts)
    halves = [
        abs(float(a @ b)) / (np.linalg.norm(a) * np.linalg.norm(b))
        for a, b in ((desc[:64], ref[:64]), (desc[64:], ref[64:]))
    ]
    return {"points": int(len(pts)), "one_minus_cos": max(0.0, 1.0 - min(halves))}


def dsift_check(path: Path) -> dict:
    with np.load(path) as z:
        ref = {k: z[k] for k in z.files}
    _, _, desc = dense_sift(ref["image"], DsiftConfig(mode="phow"))
    ours = np.empty_like(desc[ref["index"]])
    ours.reshape(-1, 16, 8)[:, :, [(-o) % 8 for o in range(8)]] = desc[ref["index"]].reshape(
        -1, 16, 8
    )  # VLFeat's bin order
    zero_ours, zero_ref = ~ours.any(axis=1), ~ref["descriptors"].any(axis=1)
    kept = ~zero_ours & ~zero_ref
    a, b = ours[kept], ref["descriptors"][kept]
    cos = (a * b).sum(1) / np.maximum(np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1), 1e-12)
    return {
        "frames_compared": int(kept.sum()),
        "median_cosine": float(np.median(cos)),
        "p05_cosine": float(np.percentile(cos, 5)),
        "zeroing_agrees": float((zero_ours == zero_ref).mean()),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, help="write the figures as JSON here")
    a = ap.parse_args(argv)
    m2dp_dir, phow = DATA / "m2dp-reference", DATA / "vlfeat-phow-reference" / "phow_kitti000000_640x480.npz"
    if not (m2dp_dir / "kitti-000000.bin").is_file() or not phow.is_file():
        raise SystemExit(f"reference outputs not found under {DATA} (expected ../shared/data beside the project)")
    result = {"command": "python3 bench/reference_checks.py", "m2dp": m2dp_check(m2dp_dir), "dsift": dsift_check(phow)}
    print(f"M2DP against M2DP.m: 1 - cos = {result['m2dp']['one_minus_cos']:.1e} ({result['m2dp']['points']} points)")
    d = result["dsift"]
    print(
        f"dense SIFT (phow) against vl_phow: median cosine {d['median_cosine']:.6f}, 5th percentile "
        f"{d['p05_cosine']:.6f} over "
        f"{d['frames_compared']} frames; zeroing agrees on {100 * d['zeroing_agrees']:.2f} %"
    )
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
