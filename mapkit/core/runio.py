"""Run-folder plumbing: atomic writes, finished-stage markers, resolved configs and metrics.

A stage writes into its output folder and, last of all, a ``.done`` marker holding the hash of
the configuration that made it. A folder without the marker (an interrupted run) is never taken
for a finished one; a marker with another hash means the config changed and the stage reruns.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator, Optional, Sequence

import numpy as np

if TYPE_CHECKING:
    from mapkit.core.geodesy import LocalFrame

DONE_MARKER = ".done"
_UMASK = os.umask(0)
os.umask(_UMASK)


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it replaces ``path`` in one rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".partial", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    os.chmod(tmp_path, 0o666 & ~_UMASK)  # mkstemp makes 0600; outputs get the usual permissions
    try:
        yield tmp_path
        os.replace(tmp_path, path)
    except BaseException:
        tmp_path.unlink(missing_ok=True)
        raise


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
    return Path(path)


def atomic_write_ply(path: str | Path, points: np.ndarray, colors: Optional[np.ndarray] = None,
                     frame: Optional["LocalFrame"] = None, crs_epsg: Optional[int] = None, comments: Sequence[str] = ()) -> Path:
    """A binary little-endian PLY point cloud (float64 x, y, z; optional RGB in [0, 1], stored as
    uchar), written atomically: the file only appears, under its name, complete.

    The header states the frame of the coordinates (:func:`mapkit.core.geodesy.ply_crs_comments`):
    ``frame`` is the workspace's :class:`~mapkit.core.geodesy.LocalFrame` (or None: unspecified) and
    ``crs_epsg`` the EPSG code the points are in, or None for the local ENU frame of ``frame``.
    ``comments`` are extra header comment lines. Coordinates are float64 without an offset, so
    UTM or ECEF coordinates keep sub-micrometre precision and every PLY reader (open3d, PDAL,
    CloudCompare, which offers its own global shift on import) gets them as they are.
    """
    from mapkit.core.geodesy import ply_crs_comments

    path = Path(path)
    pts = np.asarray(points, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        pts = pts.reshape(-1, 3)
    n = len(pts)
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    if colors is not None:
        col = np.asarray(colors, np.float64)
        if col.shape != (n, 3):
            raise ValueError(f"{path}: colors of shape {col.shape} for {n} points")
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    rec = np.empty(n, np.dtype(fields))
    rec["x"], rec["y"], rec["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    if colors is not None:
        c8 = np.clip(np.rint(col * 255.0), 0, 255).astype(np.uint8)
        rec["red"], rec["green"], rec["blue"] = c8[:, 0], c8[:, 1], c8[:, 2]
    lines = ["ply", "format binary_little_endian 1.0", "comment generator mapkit"]
    for c in [*ply_crs_comments(frame, crs_epsg), *comments]:
        if "\n" in c or "\r" in c:
            raise ValueError(f"{path}: a PLY header comment cannot span lines: {c!r}")
        lines.append(f"comment {c}")
    lines.append(f"element vertex {n}")
    lines += [f"property {'double' if t == '<f8' else 'uchar'} {name}" for name, t in fields]
    lines.append("end_header")
    header = ("\n".join(lines) + "\n").encode("ascii")
    body = rec.tobytes()
    expected = len(header) + n * rec.dtype.itemsize
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(header)
            f.write(body)
            f.flush()
            os.fsync(f.fileno())
            size = os.fstat(f.fileno()).st_size
        if size != expected:
            raise OSError(f"{path}: wrote {size} bytes, expected {expected} ({n} points); not renamed into place")
    return path


def atomic_write_text(path: str | Path, text: str) -> Path:
    return atomic_write_bytes(path, text.encode())


def _json_default(o: Any):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, Path):
        return str(o)
    if hasattr(o, "model_dump"):
        return o.model_dump(mode="json")
    raise TypeError(f"{type(o).__name__} is not JSON serialisable")


def to_json(obj: Any) -> str:
    return json.dumps(obj, indent=2, sort_keys=False, default=_json_default) + "\n"


def write_json(path: str | Path, obj: Any) -> Path:
    return atomic_write_text(path, to_json(obj))


def config_hash(obj: Any) -> str:
    """Stable short hash of a configuration (any JSON-serialisable object or pydantic model)."""
    text = json.dumps(json.loads(to_json(obj)), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def is_done(folder: str | Path, cfg_hash: str | None = None) -> bool:
    marker = Path(folder) / DONE_MARKER
    if not marker.is_file():
        return False
    return cfg_hash is None or json.loads(marker.read_text()).get("config_hash") == cfg_hash


def mark_done(folder: str | Path, cfg_hash: str, **info: Any) -> None:
    write_json(Path(folder) / DONE_MARKER, {"config_hash": cfg_hash, **info})


def reset_stage(folder: str | Path) -> Path:
    """Empty a stage folder whose previous run did not finish (or must be redone)."""
    folder = Path(folder)
    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    return folder


def sha256_file(path: str | Path, block: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(block):
            h.update(chunk)
    return h.hexdigest()


def progress_bar(total: Optional[int], enabled: Optional[bool], desc: str, unit: str, leave: bool = True):
    """The one progress bar of mapkit: tqdm on stderr for long work (``update``/``close``).

    ``enabled``: shown or silent; None shows it when stderr is a terminal (so logs and CI output
    stay free of redraws)."""
    import sys

    from tqdm import tqdm

    if enabled is None:
        enabled = sys.stderr.isatty()
    return tqdm(total=total, desc=desc, unit=unit, leave=leave, disable=not enabled, file=sys.stderr)
