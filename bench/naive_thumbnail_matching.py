"""Appearance change that defeats the naive: nearest neighbour on tiny grayscale thumbnails.

For pairs of sessions under different conditions (database = a training session, query = a test
session that drives partly the same roads), every image becomes a 32x24 grayscale thumbnail; a
query is matched to the database image with the smallest L2 distance between raw pixels. A query
counts if some database image was taken within 25 m of it (the place is in the database at all);
it is found if its match was taken within 25 m. Also printed: the same with zero-mean, unit-norm
thumbnails (a slightly less naive baseline), and chance (a random database image).

    python bench/naive_thumbnail_matching.py --dir DIR [--pair DB:QUERY ...]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import report
from mapkit.core.types import StreamKind
from mapkit.io.mcap_log import McapLog
from mapkit.synth import camera_poses, load_world

THUMB = (32, 24)
RADIUS_M = 25.0


def thumbnails(out: Path, session: str, size=THUMB) -> tuple[np.ndarray, np.ndarray]:
    """(thumbnails (N, w*h) float32 in 0..255, camera positions (N, 2) in the world frame)."""
    world = load_world(out)
    log = McapLog(out / world.session(session)["file"])
    stamps, thumbs = [], []
    for frame in log.records(StreamKind.IMAGE):
        gray = frame.gray()
        thumbs.append(cv2.resize(gray, size, interpolation=cv2.INTER_AREA).astype(np.float32).ravel())
        stamps.append(frame.stamp_ns)
    log.close()
    cs, wfc = camera_poses(out, session)
    pos = dict(zip(cs.tolist(), wfc[:, :2, 3], strict=True))
    return np.array(thumbs), np.array([pos[s] for s in stamps])


def match(
    db: tuple[np.ndarray, np.ndarray],
    q: tuple[np.ndarray, np.ndarray],
    normalise: bool = False,
    rng: np.random.Generator | None = None,
) -> dict:
    Xd, Pd = db
    Xq, Pq = q
    if normalise:
        Xd = (Xd - Xd.mean(1, keepdims=True)) / (
            np.linalg.norm(Xd - Xd.mean(1, keepdims=True), axis=1, keepdims=True) + 1e-6
        )
        Xq = (Xq - Xq.mean(1, keepdims=True)) / (
            np.linalg.norm(Xq - Xq.mean(1, keepdims=True), axis=1, keepdims=True) + 1e-6
        )
    d2 = (Xq**2).sum(1)[:, None] - 2 * Xq @ Xd.T + (Xd**2).sum(1)[None]
    nn = np.argmin(d2, axis=1)
    geo = np.linalg.norm(Pq[:, None, :] - Pd[None, :, :], axis=2)
    valid = geo.min(axis=1) <= RADIUS_M
    found = geo[np.arange(len(nn)), nn] <= RADIUS_M
    out = {"queries": int(valid.sum()), "found": int((found & valid).sum())}
    if rng is not None:
        chance = (geo <= RADIUS_M).mean(axis=1)[valid]
        out["chance"] = float(chance.mean()) if len(chance) else float("nan")
    return out


def default_pairs(world) -> list[tuple[str, str]]:
    """Each test session against the training session it follows (else every training session)."""
    train = [s["name"] for s in world.sessions if s["role"] == "train"]
    pairs = []
    for s in world.sessions:
        if s["role"] != "test":
            continue
        dbs = [s["follows"]] if s.get("follows") else train
        pairs += [(db, s["name"]) for db in dbs]
    return pairs


def evaluate(out: Path, pairs: list[tuple[str, str]] | None = None) -> tuple[list[dict], float]:
    world = load_world(out)
    pairs = pairs or default_pairs(world)
    cache: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    rows = []
    total_q = total_f = 0
    for db, q in pairs:
        for name in (db, q):
            if name not in cache:
                cache[name] = thumbnails(out, name)
        raw = match(cache[db], cache[q], rng=np.random.default_rng(0))
        norm = match(cache[db], cache[q], normalise=True)
        total_q += raw["queries"]
        total_f += raw["found"]
        rows.append(
            {
                "database": f"{db} ({world.session(db)['condition']})",
                "query": f"{q} ({world.session(q)['condition']})",
                "queries": raw["queries"],
                "found_raw": raw["found"],
                "recall_raw": round(raw["found"] / max(raw["queries"], 1), 3),
                "recall_normalised": round(norm["found"] / max(norm["queries"], 1), 3),
                "chance": round(raw["chance"], 3),
            }
        )
    return rows, total_f / max(total_q, 1)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dir", type=Path, required=True, help="a synthesized town (e.g. mapkit synth --preset demo)")
    ap.add_argument(
        "--pair", action="append", help="DATABASE:QUERY session names (default: each test vs its training session)"
    )
    args = ap.parse_args(argv)
    pairs = [tuple(p.split(":", 1)) for p in args.pair] if args.pair else None
    rows, overall = evaluate(args.dir, pairs)
    report(
        f"Naive nearest neighbour on {THUMB[0]}x{THUMB[1]} grayscale thumbnails across conditions (found within "
        f"{RADIUS_M:.0f} m)",
        rows,
        f"overall: {overall:.3f} of the queries found (raw pixels); the goal is under 0.5",
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
