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
from typing import Any, Iterator, Optional

import numpy as np

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


def atomic_write_ply(path: str | Path, points: np.ndarray, colors: Optional[np.ndarray] = None) -> Path:
    """A binary PLY point cloud (float64 xyz, optional RGB in [0, 1]) written by open3d, atomically."""
    import open3d as o3d

    path = Path(path)
    pc = o3d.geometry.PointCloud()
    pc.points = o3d.utility.Vector3dVector(np.asarray(points, np.float64))
    if colors is not None:
        pc.colors = o3d.utility.Vector3dVector(np.asarray(colors, np.float64))
    with atomic_path(path) as tmp:
        # open3d picks the format from the file name, so write a *.ply beside the temporary
        tmp_ply = tmp.with_name(tmp.name + ".ply")
        try:
            if not o3d.io.write_point_cloud(str(tmp_ply), pc, write_ascii=False):
                raise OSError(f"open3d could not write {path}")
            os.replace(tmp_ply, tmp)
        finally:
            tmp_ply.unlink(missing_ok=True)
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


def progress_bar(total: Optional[int], enabled: bool, desc: str, unit: str, leave: bool = True):
    """A tqdm bar on stderr for long work (``update``/``close``); silent when not ``enabled``."""
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit=unit, leave=leave, disable=not enabled)
