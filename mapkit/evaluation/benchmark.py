"""``mapkit eval benchmark``: a 6-DoF localizer's poses scored against a benchmark folder's ground truth
(``mapkit export benchmark``), as the visual localization benchmark scores its entries.

Per query, the position error is the distance between the estimated and the true camera centre (m)
and the orientation error the angle of ``R_est R_gt^T`` (deg). A query is localized within a
threshold pair when both errors are at most it: (0.25 m, 2 deg), (0.5 m, 5 deg) and (5 m, 10 deg),
the benchmark's three bands (Sattler et al. 2018, the Aachen Day-Night and RobotCar Seasons
tables). A query missing from the poses file is a failure at every threshold and is counted;
medians are over every query with a missing one's error infinite, so they are None when more than
half are missing. Scores are given overall and per condition (``conditions.json``).
"""

from __future__ import annotations

import json
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path, PurePosixPath

import numpy as np

from mapkit.core.errors import InputError
from mapkit.core.geometry import invert_pose, rotation_angle_rad
from mapkit.core.runio import atomic_write_text, write_json
from mapkit.core.writers import writes_workspace
from mapkit.io.benchmark import CONDITIONS, GROUND_TRUTH
from mapkit.io.trajectory import read_benchmark_poses

#: (position m, orientation deg) bands of the visual localization benchmark
THRESHOLDS: tuple[tuple[float, float], ...] = ((0.25, 2.0), (0.5, 5.0), (5.0, 10.0))


def band_key(t_m: float, r_deg: float) -> str:
    return f"{t_m:g}m_{r_deg:g}deg"


@dataclass
class BenchmarkScores:
    """The scores of one set of queries: ``recall[band_key]`` is the share localized within the band."""

    queries: int
    localized: int
    missing: int
    recall: dict[str, float]
    median_translation_m: float | None
    median_rotation_deg: float | None


@dataclass
class BenchmarkEvaluation:
    """Overall and per-condition scores, each query's errors (None when missing), and names of the poses file
    that are no query of the ground truth (ignored)."""

    overall: BenchmarkScores
    conditions: dict[str, BenchmarkScores]
    errors: dict[str, tuple[float, float] | None]
    unknown_names: list[str] = field(default_factory=list)
    thresholds: tuple[tuple[float, float], ...] = THRESHOLDS


def pose_errors(gt_cam_from_world: np.ndarray, est_cam_from_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(camera centre distance m, rotation angle deg) between stacks of ``cam_from_world`` poses."""
    gt = np.asarray(gt_cam_from_world, np.float64).reshape(-1, 4, 4)
    est = np.asarray(est_cam_from_world, np.float64).reshape(-1, 4, 4)
    c_gt = np.array([invert_pose(T)[:3, 3] for T in gt]).reshape(-1, 3)
    c_est = np.array([invert_pose(T)[:3, 3] for T in est]).reshape(-1, 3)
    R = est[:, :3, :3] @ np.swapaxes(gt[:, :3, :3], 1, 2)
    ang = np.degrees(rotation_angle_rad(R)) if len(R) else np.zeros(0)
    return np.linalg.norm(c_est - c_gt, axis=1), ang


def errors_or_missing(gt_cam_from_world: np.ndarray, est_cam_from_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per query (camera centre distance m, rotation angle deg) between stacks of ``cam_from_world`` poses; a
    query whose estimate is not finite (NaN: there is none) gets inf for both, which fails every band."""
    gt = np.asarray(gt_cam_from_world, np.float64).reshape(-1, 4, 4)
    est = np.asarray(est_cam_from_world, np.float64).reshape(-1, 4, 4)
    if len(gt) != len(est):
        raise ValueError(f"{len(est)} estimates for {len(gt)} true poses")
    have = np.all(np.isfinite(est), axis=(1, 2))
    t, r = np.full(len(gt), np.inf), np.full(len(gt), np.inf)
    if have.any():
        t[have], r[have] = pose_errors(gt[have], est[have])
    return t, r


def band_scores(
    t: np.ndarray, r: np.ndarray, thresholds: tuple[tuple[float, float], ...] = THRESHOLDS
) -> BenchmarkScores:
    """The scores of per-query errors (position m ``t``, orientation deg ``r``), a missing query's inf: the share
    within each threshold pair and the medians (None when more than half are missing)."""
    n = len(t)
    missing = int(np.sum(~np.isfinite(t)))
    recall = {band_key(a, b): float(np.mean((t <= a) & (r <= b))) if n else 0.0 for a, b in thresholds}

    def median(v: np.ndarray) -> float | None:
        m = float(np.median(v)) if n else np.inf
        return round(m, 6) if np.isfinite(m) else None

    return BenchmarkScores(n, n - missing, missing, recall, median(t), median(r))


def _conditions_of(conditions: str | Path | dict | None, names: list[str]) -> dict[str, str]:
    """Each query's condition label ('unknown' where none is given)."""
    if conditions is None:
        return {}
    if not isinstance(conditions, dict):
        path = Path(conditions)
        if not path.is_file():
            raise InputError(path, "no such conditions file")
        try:
            conditions = json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise InputError(path, f"not JSON ({exc})") from None
    assert isinstance(conditions, dict)
    out = {}
    for n in names:
        c = conditions.get(n)
        label = c.get("condition") if isinstance(c, dict) else c
        out[n] = str(label) if label else "unknown"
    return out


def evaluate_benchmark(
    gt_file: str | Path,
    poses_file: str | Path,
    conditions: str | Path | dict | None = None,
    thresholds: tuple[tuple[float, float], ...] = THRESHOLDS,
) -> BenchmarkEvaluation:
    """Score the poses of ``poses_file`` (benchmark format, ``cam_from_world``) against ``gt_file``: overall and,
    with ``conditions`` (conditions.json or a dict name -> label or -> {"condition": label}), per condition. A pose
    named by its file name alone (as hloc's ``localize_sfm`` writes them) scores the query of that file name where
    no other query shares it."""
    gt_names, gt = read_benchmark_poses(gt_file)
    est_names, est = read_benchmark_poses(poses_file)
    if len(set(gt_names)) != len(gt_names):
        raise InputError(gt_file, "a query is listed twice")
    known = set(gt_names)
    file_names = Counter(PurePosixPath(n).name for n in gt_names)
    by_file_name = {PurePosixPath(n).name: n for n in gt_names if file_names[PurePosixPath(n).name] == 1}
    est_names = [n if n in known else by_file_name.get(n, n) for n in est_names]
    if len(set(est_names)) != len(est_names):
        dup = next(n for n in est_names if est_names.count(n) > 1)
        raise InputError(poses_file, f"query {dup} has two poses", field=dup)
    by_name = dict(zip(est_names, est, strict=True))
    have = np.array([n in by_name for n in gt_names], bool)
    t, r = errors_or_missing(gt, np.array([by_name.get(n, np.full((4, 4), np.nan)) for n in gt_names]))
    errors = {
        n: (round(float(a), 6), round(float(b), 6)) if h else None
        for n, a, b, h in zip(gt_names, t, r, have, strict=True)
    }
    labels = _conditions_of(conditions, gt_names)
    per: dict[str, BenchmarkScores] = {}
    for label in sorted(set(labels.values())):
        sel = np.array([labels[n] == label for n in gt_names])
        per[label] = band_scores(t[sel], r[sel], thresholds)
    unknown = sorted(set(est_names) - set(gt_names))
    return BenchmarkEvaluation(band_scores(t, r, thresholds), per, errors, unknown, thresholds)


def format_benchmark(ev: BenchmarkEvaluation) -> str:
    """A markdown table: per condition and overall, the share within each band and the median errors."""
    bands = [band_key(a, b) for a, b in ev.thresholds]
    head = " | ".join(f"{a:g} m, {b:g} deg" for a, b in ev.thresholds)
    lines = [
        f"| condition | queries | missing | {head} | median m | median deg |",
        "|---|---|---|" + "---|" * len(bands) + "---|---|",
    ]
    rows = [*ev.conditions.items(), ("overall", ev.overall)]
    for label, s in rows:
        shares = " | ".join(f"{100 * s.recall[k]:.1f} %" for k in bands)
        med_t = "" if s.median_translation_m is None else f"{s.median_translation_m:.3f}"
        med_r = "" if s.median_rotation_deg is None else f"{s.median_rotation_deg:.3f}"
        lines.append(f"| {label} | {s.queries} | {s.missing} | {shares} | {med_t} | {med_r} |")
    if ev.unknown_names:
        lines.append(f"\n{len(ev.unknown_names)} poses name no query of the ground truth (ignored).")
    return "\n".join(lines) + "\n"


@writes_workspace("poses_file", within=True)
def score_benchmark(folder: str | Path, poses_file: str | Path) -> BenchmarkEvaluation:
    """Score ``poses_file`` against the benchmark folder ``folder`` (its queries_gt.txt and conditions.json);
    writes ``eval_benchmark.json`` and ``.md`` next to the poses file."""
    folder, poses_file = Path(folder), Path(poses_file)
    if not (folder / GROUND_TRUTH).is_file():
        raise InputError(folder, f"no {GROUND_TRUTH} here: not a benchmark folder (run mapkit export benchmark)")
    if not poses_file.is_file():
        raise InputError(poses_file, "no such poses file")
    cond = folder / CONDITIONS
    ev = evaluate_benchmark(folder / GROUND_TRUTH, poses_file, cond if cond.is_file() else None)
    out = poses_file.parent
    write_json(
        out / "eval_benchmark.json",
        {"benchmark": str(folder), "poses": str(poses_file), **asdict(ev)},
    )
    atomic_write_text(out / "eval_benchmark.md", format_benchmark(ev))
    return ev
