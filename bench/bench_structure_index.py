"""Speed of the structure voting index (mapkit.places.index_structure), with its baselines in the same run.

1. ``describe()``: patches described per second for NBLD and M2DP through the whole chain
   (patch extraction, yaw normalisation towards the first observer, descriptor), on real patches
   of the demo workspace (keypoints drawn as the index draws them from the densest aligned map of
   ``--workspace``, default runs/main/workspace, the main job's) or, without it, on the synthetic street of
   bench_descriptors3d. CPU time of this process and wall time, best of ``--repeat``.
2. Query time per frame of the voting index on a database of ``--db-size`` (default 1,000,000)
   descriptors: PCA'd 25-D descriptors drawn from a Gaussian with the variance spectrum of a real
   index's PCA (the demo's NBLD index when found, else a decaying spectrum), each entry referring
   to 1-7 consecutive frames (mean 4, as in the demo maps) of ``--db-size / 20`` frames. A query
   frame holds ``--keypoints`` descriptors (default 100, the demo's median per query keyframe),
   each a database descriptor plus Gaussian noise of ``--query-noise`` times the spectrum's
   spread (0.7: at the demo's database size this puts the nearest neighbour at 0.23 of the mean
   squared distance between database descriptors, as measured for test-snowy's NBLD queries
   against train-sunny; a kd-tree is the faster the closer the queries lie). Timed through the
   library (``StructureIndex.nearest`` = faiss IndexFlatL2 k=1, ``StructureIndex.votes`` = CSR
   gather + np.bincount, and the batched ``vote_frames`` over many frames), against in the same
   run:
   - nearest neighbours with scipy's cKDTree (exact), build time printed separately;
   - voting with a Python loop over the matched entries' references (a dict counter).
   The two nearest-neighbour searches are checked to agree, and the two votings to be equal.

Everything runs on one thread (BLAS, OpenMP and faiss pinned): the machine's 2 cores are shared.

Run from the repository root::

    python3 bench/bench_structure_index.py
    python3 bench/bench_structure_index.py --db-size 200000 --repeat 1      # quicker
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections import Counter
from functools import partial
from pathlib import Path

for _var in (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS",
    "NUMEXPR_NUM_THREADS",
):
    os.environ[_var] = "1"

import numpy as np  # noqa: E402 (after the thread count is pinned)

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.common import best_wall_and_cpu, report  # noqa: E402 (after sys.path points at this checkout)
from mapkit.places import descriptors3d as d3  # noqa: E402 (after sys.path points at this checkout)
from mapkit.places import patches as pa  # noqa: E402 (after sys.path points at this checkout)
from mapkit.places.index_structure import (  # noqa: E402 (after sys.path points at this checkout)
    POSE_KEYFRAME,
    QueryKeypoints,
    SessionKeypoints,
    StructureIndex,
    StructureIndexConfig,
    session_keypoints,
)

# --- 1. describe() ------------------------------------------------------------------------------------


def demo_keypoints(workspace: Path, n: int, seed: int):
    """(label, points, keypoints, observer_dirs) from the densest aligned map of the workspace."""
    from mapkit.mapping.semidense import SemiDenseMap
    from mapkit.places.index_structure import session_map_dir, session_names

    best = None
    for name in session_names(workspace):
        d, _ = session_map_dir(workspace, name)
        size = (d / "points.ply").stat().st_size
        if best is None or size > best[0]:
            best = (size, name, d)
    _, name, d = best
    smap = SemiDenseMap.load(d)
    kps = session_keypoints(smap, name, 0.05, 0)
    pick = np.sort(np.random.default_rng(seed).choice(len(kps), min(n, len(kps)), replace=False))
    return (
        f"demo {name} ({len(smap.points_world)} points)",
        smap.points_world,
        kps.positions[pick],
        (kps.observer_positions - kps.positions)[pick],
    )


def synthetic_keypoints(n: int, seed: int):
    from bench.bench_descriptors3d import OBSERVER_BEHIND_M, street_map

    rng = np.random.default_rng(seed)
    points = street_map(rng)
    kp = points[np.sort(rng.choice(len(points), n, replace=False))]
    observers = np.c_[kp[:, 0] - OBSERVER_BEHIND_M, np.zeros(n), np.full(n, 1.5)]
    return f"synthetic street ({len(points)} points)", points, kp, observers - kp


def bench_describe(args) -> list[dict]:
    ws = Path(args.workspace)
    found = (ws / "align" / "sessions").is_dir()
    rows = []
    for kind, n in (("nbld", args.patches_nbld), ("m2dp", args.patches_m2dp)):
        label, points, kp, dirs = demo_keypoints(ws, n, 1) if found else synthetic_keypoints(n, 1)
        tree = pa.xy_tree(points)
        cfg = d3.StructureDescriptorConfig()
        sub = cfg.nbld if kind == "nbld" else cfg.m2dp
        ptr, _ = pa.extract_patches(points, kp, sub.domain, tree)
        wall, cpu = best_wall_and_cpu(partial(d3.describe, kind, points, kp, dirs, cfg, tree=tree), args.repeat)
        rows.append(
            {
                "descriptor": kind.upper(),
                "data": label,
                "patches": len(kp),
                "points_per_patch_median": float(np.median(np.diff(ptr))),
                "patches_per_s_cpu": len(kp) / cpu,
                "patches_per_s_wall": len(kp) / wall,
            }
        )
    return rows


# --- 2. query time on a large database ------------------------------------------------------------------


def variance_spectrum(workspace: Path, dim: int) -> tuple[np.ndarray, str]:
    for p in sorted((workspace / "places-scratch").glob("**/nbld-*/pca.npz")) if workspace.is_dir() else []:
        pca = d3.DescriptorPCA.load(p)
        if pca.dim == dim:
            return pca.explained_variance, f"PCA spectrum of {p.parent}"
    return 4.0 * 0.85 ** np.arange(dim), "decaying spectrum 4 * 0.85^i"


def synthetic_index(n: int, dim: int, spectrum: np.ndarray, rng: np.random.Generator) -> StructureIndex:
    """A loaded-index object over ``n`` synthetic descriptors (identity PCA) and their frame CSR."""
    import faiss

    X = rng.standard_normal((n, dim), dtype=np.float32) * np.sqrt(spectrum).astype(np.float32)
    index = faiss.IndexFlatL2(dim)
    index.add(X)
    n_frames = max(n // 20, 2)
    counts = rng.integers(1, 8, n)  # 1-7 observers, mean 4
    first = np.sort(rng.integers(0, n_frames - 7, n))  # entries in driving order
    ptr = np.r_[0, np.cumsum(counts)].astype(np.int64)
    ref = np.repeat(first - ptr[:-1], counts) + np.arange(ptr[-1])
    entries = {
        "session": np.zeros(n, np.int32),
        "point_index": np.arange(n),
        "position": np.zeros((n, 3)),
        "ref_indptr": ptr,
        "ref_frame": ref,
    }
    T = np.repeat(np.eye(4)[None], n_frames, axis=0)
    frames = {
        "session": np.zeros(n_frames, np.int32),
        "frame_id": np.arange(n_frames),
        "stamp_ns": np.arange(n_frames),
        "world_from_cam": T,
        "pose_source": np.full(n_frames, POSE_KEYFRAME, np.int8),
    }
    pca = d3.DescriptorPCA(np.zeros(dim), np.eye(dim), spectrum)
    manifest = {"session_names": ["synthetic"], "format_version": 1}
    idx = StructureIndex(Path("synthetic"), manifest, StructureIndexConfig(), pca, index, entries, frames)
    idx.X = X  # for the baseline
    return idx


def loop_votes(entry_ids: np.ndarray, ptr: np.ndarray, ref: np.ndarray, n_frames: int) -> np.ndarray:
    c: Counter = Counter()
    for e in entry_ids.tolist():
        for f in ref[ptr[e] : ptr[e + 1]].tolist():
            c[f] += 1
    v = np.zeros(n_frames, np.int64)
    for f, k in c.items():
        v[f] = k
    return v


def bench_query(args) -> list[dict]:
    import faiss
    from scipy.spatial import cKDTree

    faiss.omp_set_num_threads(1)
    rng = np.random.default_rng(7)
    dim = 25
    spectrum, spectrum_src = variance_spectrum(Path(args.workspace), dim)
    t0 = time.perf_counter()
    idx = synthetic_index(args.db_size, dim, spectrum, rng)
    t_faiss_build = time.perf_counter() - t0
    n_frames_q = args.frames
    K = args.keypoints
    src = rng.integers(0, len(idx), (n_frames_q, K))
    Q = idx.X[src] + (args.query_noise * rng.standard_normal((n_frames_q, K, dim)) * np.sqrt(spectrum)).astype(
        np.float32
    )
    ptr, ref = idx.entries["ref_indptr"], idx.entries["ref_frame"]

    def faiss_frame(q):
        e, _ = idx.nearest(q)
        return idx.votes(e)

    n_timed = min(args.timed_frames, n_frames_q)
    wall_f, cpu_f = best_wall_and_cpu(lambda: [faiss_frame(Q[i]) for i in range(n_timed)], args.repeat)
    # match alone and vote alone
    ents = [idx.nearest(Q[i])[0] for i in range(n_timed)]
    wall_vote, cpu_vote = best_wall_and_cpu(lambda: [idx.votes(e) for e in ents], args.repeat)
    wall_loop, cpu_loop = best_wall_and_cpu(lambda: [loop_votes(e, ptr, ref, idx.n_frames) for e in ents], 1)
    same_votes = all(np.array_equal(idx.votes(e), loop_votes(e, ptr, ref, idx.n_frames)) for e in ents[:5])

    # batched: all frames of a session at once (one faiss call, vote_many)
    kp = SessionKeypoints(
        "q",
        np.arange(n_frames_q * K),
        np.zeros((n_frames_q * K, 3)),
        np.zeros((n_frames_q * K, 3)),
        np.arange(n_frames_q * K + 1, dtype=np.int64),
        np.repeat(np.arange(n_frames_q), K).astype(np.int64),
    )

    def batch():
        e, d = idx.nearest(Q.reshape(-1, dim))
        return idx.vote_frames(QueryKeypoints(kp, Q.reshape(-1, dim), e, d), np.arange(n_frames_q))

    wall_b, cpu_b = best_wall_and_cpu(batch, args.repeat)
    res_b = batch()
    single = [int(np.argmax(faiss_frame(Q[i]))) for i in range(min(3, n_frames_q))]
    same_batch = single == res_b.best_frame[: len(single)].tolist()

    t0 = time.perf_counter()
    tree = cKDTree(idx.X)
    t_tree_build = time.perf_counter() - t0
    n_tree = min(args.tree_frames, n_timed)
    wall_t, cpu_t = best_wall_and_cpu(lambda: [tree.query(Q[i], k=1) for i in range(n_tree)], 1)
    agree = float(np.mean([np.mean(tree.query(Q[i], k=1)[1] == ents[i]) for i in range(n_tree)]))

    rows = [
        {
            "method": "faiss IndexFlatL2 + bincount votes (library, per frame)",
            "db_descriptors": len(idx),
            "keypoints_per_frame": K,
            "ms_per_frame_cpu": 1e3 * cpu_f / n_timed,
            "ms_per_frame_wall": 1e3 * wall_f / n_timed,
            "build_s": t_faiss_build,
        },
        {
            "method": "library, batched over the session (vote_frames)",
            "db_descriptors": len(idx),
            "keypoints_per_frame": K,
            "ms_per_frame_cpu": 1e3 * cpu_b / n_frames_q,
            "ms_per_frame_wall": 1e3 * wall_b / n_frames_q,
            "build_s": t_faiss_build,
        },
        {
            "method": "baseline: scipy cKDTree (exact) per frame",
            "db_descriptors": len(idx),
            "keypoints_per_frame": K,
            "ms_per_frame_cpu": 1e3 * cpu_t / n_tree,
            "ms_per_frame_wall": 1e3 * wall_t / n_tree,
            "build_s": t_tree_build,
        },
        {
            "method": "voting alone: CSR gather + np.bincount",
            "db_descriptors": len(idx),
            "keypoints_per_frame": K,
            "ms_per_frame_cpu": 1e3 * cpu_vote / n_timed,
            "ms_per_frame_wall": 1e3 * wall_vote / n_timed,
            "build_s": 0.0,
        },
        {
            "method": "baseline: voting with a Python loop",
            "db_descriptors": len(idx),
            "keypoints_per_frame": K,
            "ms_per_frame_cpu": 1e3 * cpu_loop / n_timed,
            "ms_per_frame_wall": 1e3 * wall_loop / n_timed,
            "build_s": 0.0,
        },
    ]
    checks = {
        "spectrum": spectrum_src,
        "query_noise": args.query_noise,
        "frames": idx.n_frames,
        "references": int(len(ref)),
        "cKDTree_agrees_with_faiss": agree,
        "loop_votes_equal": same_votes,
        "batched_equals_single": same_batch,
        "ratio_cKDTree_over_faiss_per_frame_cpu": (cpu_t / n_tree) / (cpu_f / n_timed),
        "ratio_loop_over_bincount_voting_cpu": cpu_loop / max(cpu_vote, 1e-12),
        "ratio_single_over_batched_per_frame_cpu": (cpu_f / n_timed) / (cpu_b / n_frames_q),
    }
    return rows, checks


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--workspace",
        default="runs/main/workspace",
        help="Aligned workspace for real patches (synthetic street if absent).",
    )
    ap.add_argument("--patches-nbld", type=int, default=1000)
    ap.add_argument("--patches-m2dp", type=int, default=200)
    ap.add_argument("--db-size", type=int, default=1_000_000)
    ap.add_argument("--keypoints", type=int, default=100, help="Query keypoints per frame (demo median: ~100).")
    ap.add_argument(
        "--query-noise", type=float, default=0.7, help="Query = database descriptor + this x spread of noise."
    )
    ap.add_argument("--frames", type=int, default=100, help="Query frames of the batched run.")
    ap.add_argument("--timed-frames", type=int, default=20, help="Frames timed one by one.")
    ap.add_argument("--tree-frames", type=int, default=3, help="Frames timed with cKDTree (slow in 25-D).")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)

    rows_d = bench_describe(args)
    report("describe(): patches per second (whole chain, one thread)", rows_d)
    rows_q, checks = bench_query(args)
    report(
        f"query time per frame, {args.db_size} database descriptors (one thread)",
        rows_q,
        "ratios: " + ", ".join(f"{k} = {v:.3g}" for k, v in checks.items() if k.startswith("ratio")),
    )
    print("checks: " + ", ".join(f"{k} = {v}" for k, v in checks.items() if not k.startswith("ratio")))
    print(
        "BENCH_JSON " + json.dumps({"bench": "structure_index", "describe": rows_d, "query": rows_q, "checks": checks})
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
