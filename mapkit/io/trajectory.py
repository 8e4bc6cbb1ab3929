"""Trajectory files: TUM (``t x y z qx qy qz qw``) and KITTI (12 numbers, 3x4 row-major) poses.

A trajectory is ``(stamps_ns (N,) int64, world_from_body (N, 4, 4))``. Malformed rows raise an
``InputError`` naming the file and line.
"""

from __future__ import annotations

from decimal import ROUND_HALF_EVEN, Decimal, InvalidOperation
from pathlib import Path

import numpy as np

from mapkit.core.errors import InputError
from mapkit.core.geometry import make_pose, matrix_to_quat_wxyz, quat_wxyz_to_matrix
from mapkit.core.runio import atomic_write_text

_NS_PER_S = Decimal(1_000_000_000)


#: int64 nanoseconds span about 292 years either side of 1970
_MAX_SECONDS = Decimal(2**63 - 1) / _NS_PER_S


def seconds_to_ns(text: str) -> int:
    """Decimal seconds (``12.5``, ``1.036224e-01``) to integer nanoseconds, exactly (no float)."""
    try:
        value = Decimal(text.strip())
    except InvalidOperation:
        raise ValueError(f"{text!r} is not a number of seconds") from None
    if (
        not value.is_finite() or abs(value) >= _MAX_SECONDS
    ):  # a huge exponent would overflow the context or build a huge integer
        raise ValueError(f"{text.strip()[:40]!r} is not a finite number of seconds within +-{_MAX_SECONDS:.3g}")
    return int((value * _NS_PER_S).to_integral_value(rounding=ROUND_HALF_EVEN))


def _rows(path: Path, ncols: tuple[int, ...]) -> list[tuple[int, list[float]]]:
    if not path.is_file():
        raise InputError(path, "no such file")
    rows = []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.replace(",", " ").split()
        if len(parts) not in ncols:
            raise InputError(
                path,
                f"line {lineno} has {len(parts)} values, expected {' or '.join(map(str, ncols))}",
                field=f"line {lineno}",
            )
        try:
            vals = [float(p) for p in parts]
        except ValueError:
            raise InputError(
                path, f"line {lineno} has a value that is not a number: {s[:80]!r}", field=f"line {lineno}"
            ) from None
        if not np.all(np.isfinite(vals)):
            raise InputError(path, f"line {lineno} has a non-finite value", field=f"line {lineno}")
        rows.append((lineno, vals))
    if not rows:
        raise InputError(path, "holds no poses")
    return rows


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    path = Path(path)
    rows = _rows(path, (8,))
    arr = np.array([v for _, v in rows])
    lines = path.read_text().splitlines()
    stamps = np.array([seconds_to_ns(lines[i - 1].replace(",", " ").split()[0]) for i, _ in rows], dtype=np.int64)
    q_wxyz = arr[:, [7, 4, 5, 6]]
    norms = np.linalg.norm(q_wxyz, axis=1)
    bad = np.nonzero(np.abs(norms - 1.0) > 1e-3)[0]
    if len(bad):
        raise InputError(
            path,
            f"line {rows[bad[0]][0]} has a quaternion of norm {norms[bad[0]]:.4f}",
            field=f"line {rows[bad[0]][0]}",
        )
    if np.any(np.diff(stamps) <= 0):
        i = int(np.nonzero(np.diff(stamps) <= 0)[0][0]) + 1
        raise InputError(path, f"line {rows[i][0]}: timestamps do not increase", field=f"line {rows[i][0]}")
    return stamps, make_pose(quat_wxyz_to_matrix(q_wxyz / norms[:, None]), arr[:, 1:4])


def write_tum(path: str | Path, stamps_ns: np.ndarray, world_from_body: np.ndarray) -> Path:
    q = matrix_to_quat_wxyz(world_from_body[:, :3, :3])
    t = world_from_body[:, :3, 3]
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for s, ti, qi in zip(np.asarray(stamps_ns, np.int64), t, q, strict=True):
        lines.append(
            f"{s // 1_000_000_000}.{s % 1_000_000_000:09d} {ti[0]:.6f} {ti[1]:.6f} {ti[2]:.6f} {qi[1]:.9f} {qi[2]:.9f} "
            f"{qi[3]:.9f} {qi[0]:.9f}"
        )
    return atomic_write_text(path, "\n".join(lines) + "\n")


def read_kitti_poses(path: str | Path) -> np.ndarray:
    """(N, 4, 4) poses of a KITTI ``poses.txt``; stamps come from ``times.txt`` when there is one."""
    path = Path(path)
    rows = _rows(path, (12,))
    P = np.array([v for _, v in rows]).reshape(-1, 3, 4)
    T = np.zeros((len(P), 4, 4))
    T[:, :3, :] = P
    T[:, 3, 3] = 1.0
    return T


def write_kitti_poses(path: str | Path, world_from_body: np.ndarray) -> Path:
    lines = [" ".join(f"{x:.9e}" for x in T[:3, :].ravel()) for T in np.asarray(world_from_body)]
    return atomic_write_text(path, "\n".join(lines) + "\n")


def write_benchmark_poses(path: str | Path, names: list[str], cam_from_world: np.ndarray) -> Path:
    """The visual localization benchmark's submission format: one line ``name qw qx qy qz tx ty tz`` per
    query image, the pose ``cam_from_world`` (world to camera, as COLMAP's images.txt), quaternion scalar-first."""
    T = np.asarray(cam_from_world, np.float64).reshape(-1, 4, 4)
    if len(names) != len(T):
        raise ValueError(f"{len(names)} names for {len(T)} poses")
    q = matrix_to_quat_wxyz(T[:, :3, :3]) if len(T) else np.zeros((0, 4))
    lines = []
    for name, qi, ti in zip(names, q, T[:, :3, 3], strict=True):
        if not name or any(c.isspace() for c in name):
            raise ValueError(f"image name {name!r} is empty or holds white space: the format splits on it")
        lines.append(f"{name} {' '.join(f'{v:.12f}' for v in qi)} {' '.join(f'{v:.9f}' for v in ti)}")
    return atomic_write_text(path, "".join(f"{line}\n" for line in lines))


def read_benchmark_poses(path: str | Path) -> tuple[list[str], np.ndarray]:
    """(image names, cam_from_world (N, 4, 4)) of a benchmark pose file (``name qw qx qy qz tx ty tz``)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "no such file")
    names: list[str] = []
    poses = []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        parts = line.split()
        if not parts or parts[0].startswith("#"):
            continue
        where = f"line {lineno}"
        if len(parts) != 8:
            raise InputError(path, f"{where} has {len(parts)} fields, expected name qw qx qy qz tx ty tz", field=where)
        try:
            vals = np.array([float(p) for p in parts[1:]])
        except ValueError:
            raise InputError(path, f"{where} has a value that is not a number: {line[:80]!r}", field=where) from None
        norm = np.linalg.norm(vals[:4])
        if not np.all(np.isfinite(vals)) or abs(norm - 1.0) > 1e-3:
            raise InputError(path, f"{where} has a quaternion of norm {norm:.4f} or a non-finite value", field=where)
        names.append(parts[0])
        poses.append(make_pose(quat_wxyz_to_matrix(vals[:4] / norm), vals[4:]))
    return names, np.array(poses).reshape(-1, 4, 4)
