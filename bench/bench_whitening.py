"""Retrieval quality of the VLAD encoder's whitening variants, with the PCA learned on the database.

A PCA learned on n database images keeps n - 1 directions, and full whitening
(MCVL's [33]) then maps those n images to the corners of a regular simplex: every pair of database
vectors is the same distance apart, and a query's coordinates along the last, noise-dominated
directions are scaled up the most. This benchmark measures, on a workspace's sessions and in one
run, every whitening variant against the paper's full whitening (the baseline):

* ``none``: plain PCA (``whiten: false``);
* ``full``: eigenvalues^(-1/2), the paper's;
* ``power a``: eigenvalues^(-a/2) (power-law whitening);
* ``shrink b``: (eigenvalue + b x mean kept eigenvalue)^(-1/2) (eigenvalue shrinkage).

Each session in turn is the query set and the others the database (leave one session out). The
vocabulary and the PCA learn on the database sessions' images, as ``mapkit index vlad`` does with
its defaults (train sessions = database sessions), at ``pca_dim`` 4096 (capped at n - 1). Scored:

* query recall@1/5/20: a query is a hit at k when one of its k first database images lies within
  ``--radius`` m of it (positions: the sessions' image tables, GPS-aligned);
* database self-search: every database image against the others (itself left out): recall@1 within
  the radius, the fraction whose two nearest others are tied (squared distances within 1e-4), and
  the relative spread (std / mean) of all pairwise squared distances (0 = all equidistant).

Raw VLADs are computed once per split and cached in ``--cache``; the variants only refit the PCA.

Run from the repository root, on a built workspace (the tiny town takes a few minutes to synthesize
and build, the encoding here ~4 min on one core)::

    python3 bench/bench_whitening.py WS [--cache DIR] [--radius 25]
"""

from __future__ import annotations

import argparse
import os
import sys
import warnings
from pathlib import Path

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"  # before numpy and faiss: one core

import numpy as np  # noqa: E402 (after the thread count is pinned)

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.common import report  # noqa: E402 (after sys.path points at this checkout)
from mapkit.core.workspace import Workspace  # noqa: E402 (after sys.path points at this checkout)
from mapkit.evaluation.retrieval import recall_at_k  # noqa: E402 (after sys.path points at this checkout)
from mapkit.retrieval.vlad import PcaWhitening, VladConfig, VladEncoder  # noqa: E402 (after sys.path points at this checkout)
from mapkit.retrieval.vlad_bundle import read_session_images  # noqa: E402 (after sys.path points at this checkout)
from mapkit.retrieval.vlad_encoding import read_image  # noqa: E402 (after sys.path points at this checkout)

KS = (1, 5, 20)
VARIANTS = [
    ("none", False, 0.0, 0.0),
    ("full", True, 1.0, 0.0),
    ("power 0.25", True, 0.25, 0.0),
    ("power 0.5", True, 0.5, 0.0),
    ("power 0.75", True, 0.75, 0.0),
    ("shrink 0.1", True, 1.0, 0.1),
    ("shrink 1", True, 1.0, 1.0),
    ("shrink 10", True, 1.0, 10.0),
]


def raw_vlads(ws: Workspace, db: list[str], sessions: list[str], cache: Path, cfg: VladConfig) -> dict[str, np.ndarray]:
    """Raw VLADs of every session's images, with a vocabulary learned on the ``db`` sessions' images."""
    path = cache / f"raw-{'+'.join(db)}.npz"
    if path.is_file():
        with np.load(path) as z:
            return {n: z[n] for n in sessions}
    images = {n: [str(p) for p in read_session_images(ws, n).image_paths] for n in sessions}
    train = [p for n in db for p in images[n]]
    step = max(1, len(train) // 250)  # at most ~250 vocabulary images, as the build's max_vocabulary_images
    enc = VladEncoder(cfg)
    enc.fit_vocabulary([read_image(p) for p in train[::step]])
    out = {n: np.stack([enc.encode_raw(read_image(p)) for p in images[n]]) for n in sessions}
    cache.mkdir(parents=True, exist_ok=True)
    np.savez(path, **out)
    return out


def positions(ws: Workspace, name: str) -> np.ndarray:
    return read_session_images(ws, name).world_from_cam[:, :3, 3]


def self_search(vectors: np.ndarray, pos: np.ndarray, radius: float) -> tuple[float, float, float]:
    """(recall@1 of each database image among the others, fraction tied, std / mean of pairwise squared distances)."""
    g = vectors.astype(np.float64) @ vectors.T.astype(np.float64)
    sq = np.diag(g)[:, None] + np.diag(g)[None, :] - 2 * g
    n = len(vectors)
    off = ~np.eye(n, dtype=bool)
    pair = sq[off]
    sq_self = np.where(off, sq, np.inf)
    order = np.argsort(sq_self, axis=1)
    first, second = sq_self[np.arange(n), order[:, 0]], sq_self[np.arange(n), order[:, 1]]
    hit = np.linalg.norm(pos[order[:, 0]] - pos, axis=1) <= radius
    return float(hit.mean()), float(np.mean(second - first < 1e-4)), float(pair.std() / pair.mean())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("workspace", type=Path)
    ap.add_argument("--cache", type=Path, default=None, help="folder of the raw VLADs (default: WS/.bench-whitening)")
    ap.add_argument("--radius", type=float, default=25.0, help="a retrieved image is right within this distance (m)")
    ap.add_argument("--pca-dim", type=int, default=4096)
    args = ap.parse_args()
    ws = Workspace(args.workspace)
    cache = args.cache or ws.root / ".bench-whitening"
    sessions = ws.sessions_with_images()
    if len(sessions) < 2:
        sys.exit(f"{ws.root}: at least 2 sessions with images are needed, found {sessions}")
    cfg = VladConfig()
    rows, pooled = [], {v[0]: {"hits": {k: 0 for k in KS}, "queries": 0} for v in VARIANTS}
    for query in sessions:
        db = [n for n in sessions if n != query]
        raw = raw_vlads(ws, db, sessions, cache, cfg)
        x_db = np.concatenate([raw[n] for n in db])
        db_pos = np.concatenate([positions(ws, n) for n in db])
        q_pos = positions(ws, query)
        for name, whiten, power, shrinkage in VARIANTS:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # the dimension cap at n - 1 is the point here
                pca = PcaWhitening.fit(x_db, args.pca_dim, whiten=whiten, power=power, shrinkage=shrinkage)
            v_db, v_q = pca.transform(x_db), pca.transform(raw[query])
            d2 = (v_q**2).sum(1)[:, None] + (v_db**2).sum(1)[None, :] - 2 * v_q @ v_db.T
            ids = np.argsort(d2, axis=1)[:, : max(KS)]
            rec = recall_at_k(q_pos, db_pos, ids, KS, args.radius)
            self_r1, ties, spread = self_search(v_db, db_pos, args.radius)
            rows.append(
                {
                    "query": query,
                    "database": "+".join(db),
                    "n_db": len(x_db),
                    "dim": pca.dim,
                    "whitening": name,
                    **{f"recall@{k}": rec["recall"][k] for k in KS},
                    "db self r@1": self_r1,
                    "db ties": ties,
                    "db dist std/mean": spread,
                }
            )
            p = pooled[name]
            p["queries"] += len(q_pos)
            for k in KS:
                p["hits"][k] += round(rec["recall"][k] * len(q_pos))
    report(f"Whitening variants, leave one session out ({args.radius:g} m)", rows)
    full = pooled["full"]
    summary = [
        {
            "whitening": name,
            "queries": p["queries"],
            **{f"recall@{k}": p["hits"][k] / p["queries"] for k in KS},
            **{f"r@{k} / full": (p["hits"][k] / full["hits"][k]) if full["hits"][k] else float("nan") for k in KS},
        }
        for name, p in pooled.items()
    ]
    best = max(summary, key=lambda r: (r["recall@1"], r["recall@5"], r["recall@20"]))
    report(
        f"Pooled over the {len(sessions)} splits (baseline: full whitening, the paper's)",
        summary,
        ratio_note=(
            f"best recall@1: {best['whitening']} ({best['recall@1']:.3f} against {summary[1]['recall@1']:.3f} full)"
        ),
        headline={
            "mapkit": f"recall@1 {best['recall@1']:.3f} ({best['whitening']})",
            "baseline": f"recall@1 {summary[1]['recall@1']:.3f} (full whitening)",
            "ratio": f"{best['recall@1'] / summary[1]['recall@1']:.2f}" if summary[1]["recall@1"] else "n/a",
        },
    )


if __name__ == "__main__":
    main()
