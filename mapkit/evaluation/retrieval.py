"""How well a VLAD bundle retrieves the place of query images: recall@k within a radius, and the error
of MCVL's retrieval measurement z_t.

Two protocols:

* ``evaluate_retrieval``: query sessions of a workspace (never in the bundle's database nor in its
  training set) against the bundle. A query is a hit at k when any of its top-k database images
  lies within ``radius_m`` (25 m, the usual place-recognition threshold) of the query's true
  camera position: the synthetic town's ground truth when ``truth`` is given, else the query
  session's own (aligned) camera poses. Database positions are the bundle's, i.e. what a
  localizer would use. Also the measurement of Sec. III-B (mean shift over the top R = 20
  translations): its translation error ||c_est - c_gt|| and rotation error
  arccos((trace(R_gt^T R_est) - 1) / 2), the figures of MCVL Sec. IV.
* ``self_retrieval_kitti``: one real clip with no second visit: every frame's nearest neighbour
  among the other frames, excluding itself and its ``exclude`` neighbours on each side; the
  distribution of the frame-index gap (small gaps: the encoder tells nearby places from far ones).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from mapkit.core.errors import InputError
from mapkit.core.geodesy import LocalFrame
from mapkit.core.runio import atomic_path, atomic_write_text, write_json, write_timings
from mapkit.core.threads import single_thread_blas
from mapkit.core.workspace import Workspace
from mapkit.core.writers import writes_workspace
from mapkit.evaluation.truth import town_sessions, truth_camera_poses_at
from mapkit.retrieval.index_vlad import (
    VladIndex,
    _faiss_threads,
    _same_frame,
    encode_images,
    read_image,
    read_session_images,
)
from mapkit.retrieval.vlad import VladConfig, VladEncoder

DEFAULT_KS = (1, 5, 20)


# --------------------------------------------------------------------------- pure computations


def recall_at_k(
    query_positions: np.ndarray,
    database_positions: np.ndarray,
    retrieved_ids: np.ndarray,
    ks: Sequence[int] = DEFAULT_KS,
    radius_m: float = 25.0,
) -> dict:
    """Recall@k of ranked retrievals: a query is a hit at k when one of its first k retrieved
    database positions is within ``radius_m`` of its own position (3-D Euclidean).

    ``retrieved_ids`` (n, K) index ``database_positions`` (N, 3); ids < 0 (padding) never hit.
    Returns ``recall`` {k: fraction}, ``curve`` (K,) recall at 1..K, ``first_hit_rank`` (n,) 1-based
    (0 = no hit within K), ``reachable`` (fraction of queries with any database position within
    the radius: the best recall possible), and ``within`` (n, K) booleans.
    """
    q = np.asarray(query_positions, np.float64).reshape(-1, 3)
    db = np.asarray(database_positions, np.float64).reshape(-1, 3)
    ids = np.asarray(retrieved_ids, np.int64).reshape(len(q), -1)
    valid = ids >= 0
    d = np.linalg.norm(db[np.where(valid, ids, 0)] - q[:, None, :], axis=2)
    within = valid & (d <= radius_m)
    hit_by = np.logical_or.accumulate(within, axis=1)
    n = max(len(q), 1)
    curve = hit_by.sum(axis=0) / n
    first = np.where(within.any(axis=1), within.argmax(axis=1) + 1, 0)
    if len(db) and len(q):
        from scipy.spatial import cKDTree

        nearest, _ = cKDTree(db).query(q)
        reachable = float(np.mean(nearest <= radius_m))
    else:
        reachable = 0.0
    K = ids.shape[1]
    return {
        "recall": {int(k): float(curve[min(k, K) - 1]) if K else 0.0 for k in ks},
        "curve": curve,
        "first_hit_rank": first,
        "reachable": reachable,
        "within": within,
    }


def rotation_error_deg(R_gt: np.ndarray, R_est: np.ndarray) -> np.ndarray:
    """Angle of R_gt^T R_est in degrees: arccos((trace(R_gt^T R_est) - 1) / 2) (MCVL Sec. IV prints
    "2 cos|a| = trace(R_gt^-1 R_est)", the "1 +" lost)."""
    R_gt, R_est = np.asarray(R_gt, np.float64), np.asarray(R_est, np.float64)
    tr = np.einsum("...ji,...ji->...", R_gt, R_est)
    return np.degrees(np.arccos(np.clip((tr - 1.0) / 2.0, -1.0, 1.0)))


def self_retrieval(vectors: np.ndarray, exclude: int = 2, positions: np.ndarray | None = None) -> dict:
    """Every vector's nearest neighbour (L2) among the others, skipping itself and its ``exclude``
    neighbours on each side in sequence order; the gap distribution of the matches.

    With ``positions`` (n, 3) also the distance (m) between each frame and its match.
    """
    v = np.asarray(vectors, np.float64)
    n = len(v)
    if n <= 2 * exclude + 1:
        raise InputError(None, f"{n} frames: nothing left to retrieve once +-{exclude} neighbours are excluded")
    sq = np.sum(v * v, axis=1)
    d2 = sq[:, None] + sq[None, :] - 2.0 * v @ v.T
    idx = np.arange(n)
    d2[np.abs(idx[:, None] - idx[None, :]) <= exclude] = np.inf
    nearest = d2.argmin(axis=1)
    gaps = np.abs(nearest - idx)
    values, counts = np.unique(gaps, return_counts=True)
    out = {
        "frames": n,
        "exclude": exclude,
        "nearest": nearest.tolist(),
        "gaps": gaps.tolist(),
        "median_gap": float(np.median(gaps)),
        "fraction_gap_within_5": float(np.mean(gaps <= 5)),
        "fraction_gap_within_10": float(np.mean(gaps <= 10)),
        "histogram": {int(a): int(b) for a, b in zip(values, counts, strict=True)},
    }
    if positions is not None:
        p = np.asarray(positions, np.float64)
        dist = np.linalg.norm(p[nearest] - p, axis=1)
        out["distances_m"] = dist.tolist()
        out["median_distance_m"] = float(np.median(dist))
    return out


def _clip_frames(clip: Path) -> list[Path]:
    for sub in ("image_0", "image_2", "image_l"):
        files = sorted((clip / sub).glob("*.png"))
        if files:
            return files
    raise InputError(clip, "no frames (expected PNGs in image_0/, image_2/ or image_l/)")


def self_retrieval_kitti(frames, encoder=None, exclude: int = 2, config=None, vocabulary_stride: int = 5) -> dict:
    """The self-retrieval protocol on a KITTI odometry clip (folder) or a sequence of images.

    Without ``encoder`` one is trained on the clip's own frames with ``config`` (a VladConfig):
    the vocabulary on every ``vocabulary_stride``-th frame, the PCA on all of them. There is no
    other data of that place, so the figure says whether the descriptor separates nearby from
    distant frames, not how it generalises; and whitening learned on the very frames it ranks
    equalises their distances (n centred vectors whitened in n - 1 dimensions are equidistant),
    so use ``whiten=False`` or few dimensions here. A clip folder's ``poses.txt`` adds the metric
    distance of every match.
    """

    positions = None
    source = None
    if isinstance(frames, (str, Path)):
        clip = Path(frames)
        files = _clip_frames(clip)
        source = str(files[0].parent)
        images = [read_image(f) for f in files]
        poses = clip / "poses.txt"
        if poses.is_file():
            rows = np.loadtxt(poses, ndmin=2)
            if len(rows) >= len(images) and rows.shape[1] == 12:
                positions = rows[: len(images)].reshape(-1, 3, 4)[:, :, 3]
    else:
        images = list(frames)
    t0 = time.perf_counter()
    with single_thread_blas(), _faiss_threads(1):
        if encoder is None:
            encoder = VladEncoder(config or VladConfig())
            encoder.fit_vocabulary(images[::vocabulary_stride])
            raw = np.stack([encoder.encode_raw(im) for im in images])
            encoder.fit_pca(raw)
            vectors = encoder.pca.transform(raw)
        else:
            vectors = np.stack([encoder.encode(im) for im in images])
    seconds = time.perf_counter() - t0
    res = self_retrieval(vectors, exclude, positions)
    res.update({"source": source, "seconds": seconds, "dim": int(vectors.shape[1])})
    return res


# --------------------------------------------------------------------------- the workspace protocol


def _stats(trans_err: np.ndarray, rot_err: np.ndarray) -> dict:
    if len(trans_err) == 0:
        return {}
    return {
        "median_translation_m": float(np.median(trans_err)),
        "mean_translation_m": float(np.mean(trans_err)),
        "p90_translation_m": float(np.percentile(trans_err, 90)),
        "median_rotation_deg": float(np.median(rot_err)),
        "mean_rotation_deg": float(np.mean(rot_err)),
        "fraction_within_5m": float(np.mean(trans_err <= 5.0)),
        "fraction_within_25m": float(np.mean(trans_err <= 25.0)),
    }


@writes_workspace("workspace")
def evaluate_retrieval(
    workspace: str | Path | Workspace,
    bundle: str | Path,
    query_sessions: Sequence[str],
    truth: str | Path | None = None,
    radius_m: float = 25.0,
    ks: Sequence[int] = DEFAULT_KS,
    out: str | Path | None = None,
    workers: int | None = None,
    progress: bool = True,
) -> dict:
    """Recall@k and the measurement's error for query sessions; writes ``eval_retrieval.json``,
    ``.md``, ``.png`` and ``eval_retrieval_queries.csv`` into ``out`` (default: the bundle's folder).

    The query sessions must be in neither the bundle's database nor its training set.
    """
    ws, bundle = Workspace(workspace), Path(bundle)
    truth = None if truth is None else Path(truth)
    out = bundle if out is None else Path(out)
    idx = VladIndex.load(bundle)
    ks = sorted({int(k) for k in ks})
    used = set(idx.database_sessions) | set(idx.train_sessions)
    clash = [n for n in query_sessions if n in used]
    if clash:
        raise InputError(
            bundle / "manifest.json",
            f"query session(s) {clash} are in the bundle's database or training set: they cannot measure retrieval",
            field="sessions",
        )
    if not query_sessions:
        raise InputError(ws.root, "no query session given", field="query_sessions")
    ws_frame = ws.frame()
    if idx.frame is not None and ws_frame is not None and not _same_frame(idx.frame, ws_frame):
        raise InputError(ws.origin, "the workspace's local frame differs from the bundle's", field="frame")
    town = town_sessions(truth)
    db_pos = idx.world_from_cam[:, :3, 3]
    workers = idx.cfg.workers if workers is None else workers

    results: dict = {
        "bundle": str(bundle),
        "workspace": str(ws.root),
        "truth": None if truth is None else str(truth),
        "radius_m": radius_m,
        "ks": ks,
        "top_k": idx.cfg.top_k,
        "mean_shift_bandwidth_m": idx.cfg.mean_shift_bandwidth_m,
        "database_sessions": idx.database_sessions,
        "database_images": len(idx),
        "dim": idx.dim,
        "sessions": {},
    }
    rows: list[list] = []
    per_session: dict[str, dict] = {}
    for name in query_sessions:
        results["sessions"][name], per_session[name] = _query_session(
            ws, idx, name, truth, ws_frame, town.get(name, {}), ks, radius_m, workers, progress, rows
        )
    # per condition and overall, pooled over queries
    by_cond: dict[str, list[str]] = {}
    for n, r in results["sessions"].items():
        by_cond.setdefault(r["condition"] or "unknown", []).append(n)
    results["conditions"] = {c: _pooled(per_session, ns, ks) for c, ns in by_cond.items()}
    results["all"] = _pooled(per_session, list(results["sessions"]), ks)

    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "eval_retrieval.json", results)
    write_timings(out, sessions={n: a["timings"] for n, a in per_session.items()})
    atomic_write_text(out / "eval_retrieval.md", format_retrieval(results))
    _write_queries_csv(out / "eval_retrieval_queries.csv", rows)
    plot_retrieval(out / "eval_retrieval.png", per_session, results, db_pos)
    return results


def _query_session(
    ws: Workspace,
    idx: VladIndex,
    name: str,
    truth: Path | None,
    ws_frame: LocalFrame | None,
    info: dict,
    ks: list[int],
    radius_m: float,
    workers: int,
    progress: bool,
    rows: list[list],
) -> tuple[dict, dict]:
    """One query session against the bundle: (its entry of ``eval_retrieval.json``, its arrays for
    pooling and :func:`plot_retrieval`); appends its rows of the queries CSV to ``rows``."""
    K = max(max(ks), idx.cfg.top_k)
    db_pos = idx.world_from_cam[:, :3, 3]
    s = read_session_images(ws.root, name, idx.cfg.prefer_aligned_poses)
    if truth is not None:
        true_T, ok = truth_camera_poses_at(truth, name, ws_frame, s.table["stamp_ns"])
        truth_source = "synthetic town"
    else:
        true_T, ok = s.world_from_cam, np.ones(len(s), bool)
        truth_source = f"session poses ({s.pose_source})"
    keep = np.flatnonzero(ok)
    if len(keep) == 0:
        raise InputError(s.csv_path, f"no query image of {name!r} has a true pose")
    t0 = time.perf_counter()
    vectors = encode_images(idx.encoder, [s.image_paths[i] for i in keep], workers, progress, f"query {name}")
    encode_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    dist, ids = idx.search(vectors, K)
    search_s = time.perf_counter() - t0
    q_pos = true_T[:, :3, 3]
    rec = recall_at_k(q_pos, db_pos, ids, ks, radius_m)
    t_list: list[float] = []
    r_list: list[float] = []
    z_list: list[np.ndarray] = []
    for i in range(len(keep)):
        z = idx.measurement_from_hits(idx.hits(ids[i, : idx.cfg.top_k], dist[i, : idx.cfg.top_k]))
        t_list.append(float(np.linalg.norm(z.translation - q_pos[i])))
        r_list.append(float(rotation_error_deg(true_T[i, :3, :3], z.rotation)))
        z_list.append(z.translation)
    t_err, r_err, z_pos = np.asarray(t_list), np.asarray(r_list), np.asarray(z_list).reshape(-1, 3)
    r = {
        "condition": info.get("condition"),
        "weather": info.get("weather"),
        "role": info.get("role"),
        "queries": int(len(keep)),
        "images_without_truth": int(len(s) - len(keep)),
        "pose_source": s.pose_source,
        "truth_source": truth_source,
        "reachable": rec["reachable"],
        "recall": rec["recall"],
        "recall_curve": [float(x) for x in rec["curve"]],
        "measurement": _stats(t_err, r_err),
    }
    arrays = {
        "timings": {"encode_s_per_image": encode_s / len(keep), "search_ms_per_query": 1e3 * search_s / len(keep)},
        "q": q_pos,
        "top1": db_pos[ids[:, 0]],
        "hit1": rec["first_hit_rank"] == 1,
        "z": z_pos,
        "curve": rec["curve"],
        "t_err": t_err,
        "r_err": r_err,
        "first": rec["first_hit_rank"],
    }
    for i, j in enumerate(keep):
        rows.append(
            [
                name,
                int(s.table["image_id"][j]),
                int(s.table["stamp_ns"][j]),
                *q_pos[i],
                int(ids[i, 0]),
                *db_pos[ids[i, 0]],
                float(np.linalg.norm(db_pos[ids[i, 0]] - q_pos[i])),
                int(rec["first_hit_rank"][i]),
                *z_pos[i],
                t_err[i],
                r_err[i],
            ]
        )
    return r, arrays


def _pooled(per_session: dict[str, dict], names: list[str], ks: list[int]) -> dict:
    """Recall and measurement figures of several query sessions, pooled over their queries."""
    first = np.concatenate([per_session[n]["first"] for n in names])
    t = np.concatenate([per_session[n]["t_err"] for n in names])
    rr = np.concatenate([per_session[n]["r_err"] for n in names])
    return {
        "sessions": names,
        "queries": int(len(first)),
        "recall": {int(k): float(np.mean((first >= 1) & (first <= k))) for k in ks},
        "measurement": _stats(t, rr),
    }


def _write_queries_csv(path: Path, rows: list[list]) -> None:
    head = [
        "session",
        "image_id",
        "stamp_ns",
        "true_x_m",
        "true_y_m",
        "true_z_m",
        "top1_entry",
        "top1_x_m",
        "top1_y_m",
        "top1_z_m",
        "top1_distance_m",
        "first_hit_rank",
        "z_x_m",
        "z_y_m",
        "z_z_m",
        "z_translation_error_m",
        "z_rotation_error_deg",
    ]
    lines = [",".join(head)]
    for r in rows:
        lines.append(",".join(f"{v:.3f}" if isinstance(v, float) else str(v) for v in r))
    atomic_write_text(path, "\n".join(lines) + "\n")


def format_retrieval(results: dict) -> str:
    ks = results["ks"]
    f = lambda v, p=2: "" if v is None else f"{v:.{p}f}"  # noqa: E731 (a one-line helper local to this function)
    lines = [
        f"# Retrieval: {results['database_images']} database images ({', '.join(results['database_sessions'])}), "
        f"{results['dim']}-D",
        "",
        f"Hit: one of the top k within {results['radius_m']:g} m of the query's true position. Measurement: mean shift "
        f"(bandwidth {results['mean_shift_bandwidth_m']:g} m) over the top {results['top_k']}.",
        "",
        "| session | condition | queries | reachable | "
        + " | ".join(f"recall@{k}" for k in ks)
        + " | z median m | z median deg | z within 5 m |",
        "|---|---|---|---|" + "---|" * len(ks) + "---|---|---|",
    ]
    for n, r in results["sessions"].items():
        m = r["measurement"]
        lines.append(
            f"| {n} | {r['condition'] or ''} | {r['queries']} | {f(r['reachable'])} | "
            + " | ".join(f(r["recall"][k] if k in r["recall"] else r["recall"][str(k)]) for k in ks)
            + f" | {f(m.get('median_translation_m'), 1)} | {f(m.get('median_rotation_deg'), 1)} | "
            f"{f(m.get('fraction_within_5m'))} |"
        )
    a = results["all"]
    lines.append(
        f"| **all** | | {a['queries']} | | "
        + " | ".join(f(a["recall"][k]) for k in ks)
        + f" | {f(a['measurement'].get('median_translation_m'), 1)} | "
        f"{f(a['measurement'].get('median_rotation_deg'), 1)} | {f(a['measurement'].get('fraction_within_5m'))} |"
    )
    return "\n".join(lines) + "\n"


def plot_retrieval(path: Path, per_session: dict, results: dict, db_pos: np.ndarray) -> Path:
    """Recall@k curves per query session, and a map: database positions, queries (hit or miss at
    top-1), a line from each top-1 miss to what it retrieved."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(15, 7), dpi=100)
    for n, d in per_session.items():
        cond = results["sessions"][n]["condition"]
        k = np.arange(1, len(d["curve"]) + 1)
        ax1.plot(k, d["curve"], marker=".", label=f"{n}" + (f" ({cond})" if cond else ""))
    ax1.set_xlabel("k (retrieved images)")
    ax1.set_ylabel(f"recall@k within {results['radius_m']:g} m")
    ax1.set_ylim(0, 1.02)
    ax1.grid(alpha=0.3)
    ax1.legend(loc="lower right")
    ax2.scatter(db_pos[:, 0], db_pos[:, 1], s=4, c="0.7", label="database")
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for c, (n, d) in zip(colors * 10, per_session.items(), strict=False):
        q, t, hit = d["q"], d["top1"], d["hit1"]
        ax2.scatter(q[hit, 0], q[hit, 1], s=8, color=c, label=f"{n}: top-1 within radius")
        ax2.scatter(q[~hit, 0], q[~hit, 1], s=22, color=c, marker="x", label=f"{n}: top-1 miss")
        for a, b in zip(q[~hit], t[~hit], strict=True):
            ax2.plot([a[0], b[0]], [a[1], b[1]], color=c, lw=0.5, alpha=0.6)
    ax2.set_aspect("equal", adjustable="datalim")
    ax2.set_xlabel("east [m]")
    ax2.set_ylabel("north [m]")
    ax2.legend(loc="best", fontsize=7)
    ax2.set_title("queries (true positions); lines: top-1 misses to what they retrieved")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", bbox_inches="tight")
    plt.close(fig)
    return path


__all__ = [
    "recall_at_k",
    "rotation_error_deg",
    "self_retrieval",
    "self_retrieval_kitti",
    "evaluate_retrieval",
    "format_retrieval",
    "plot_retrieval",
]
