"""The files of a 6-DoF localization benchmark folder (``mapkit export benchmark``), as the visual
localization benchmark and hloc's pipelines write them.

- ``queries_with_intrinsics.txt``: ``name MODEL width height params...`` a line, the COLMAP camera
  model of each query image (``PINHOLE fx fy cx cy``, ``OPENCV fx fy cx cy k1 k2 p1 p2``, ...).
- ``pairs-query-retrieval.txt``: ``query_name db_name`` a line, each query's retrieved database
  images best first, as hloc's ``pairs_from_retrieval`` writes them.
- ground truth and submissions: ``name qw qx qy qz tx ty tz`` (:func:`mapkit.io.trajectory.write_benchmark_poses`).

The writer and the reader of each file live here, so the export and the localizer that reads it
agree on one definition.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from mapkit.core.errors import InputError
from mapkit.core.runio import atomic_write_text
from mapkit.core.types import CameraInfo

#: file names inside a benchmark folder
SFM = "sfm"
DATABASE = "database.db"
MODEL_CONFIG = "reference_model.yaml"
IMAGES = "images"
QUERY_PREFIX = "query"
QUERIES = "queries_with_intrinsics.txt"
GROUND_TRUTH = "queries_gt.txt"
PAIRS = "pairs-query-retrieval.txt"
CONDITIONS = "conditions.json"

#: COLMAP puts the image's origin at the top-left pixel's corner (its SIFT keypoints and cameras: the first pixel's
#: centre is (0.5, 0.5)); mapkit's cameras (ROS CameraInfo, KITTI, OpenCV) put it at that pixel's centre. A principal
#: point crosses between them with this added (to COLMAP) or taken off (from COLMAP); so does a projected keypoint.
COLMAP_PIXEL_OFFSET = 0.5

#: COLMAP camera models this module reads, with their parameter count
_PARAMS = {"SIMPLE_PINHOLE": 3, "PINHOLE": 4, "SIMPLE_RADIAL": 4, "RADIAL": 5, "OPENCV": 8, "FULL_OPENCV": 12}


def colmap_camera_params(info: CameraInfo) -> tuple[str, list[float]]:
    """COLMAP's model name and parameters of ``info``: PINHOLE without distortion, OPENCV with plumb-bob's
    four coefficients, FULL_OPENCV with rational-polynomial's eight; the principal point in COLMAP's pixel
    convention (``COLMAP_PIXEL_OFFSET``). Every camera mapkit hands to COLMAP goes through here."""
    D = np.zeros(8)
    D[: min(len(info.D), 8)] = np.asarray(info.D, np.float64)[:8]
    pin = [info.fx, info.fy, info.cx + COLMAP_PIXEL_OFFSET, info.cy + COLMAP_PIXEL_OFFSET]
    if not np.any(D):
        return "PINHOLE", pin
    if not np.any(D[4:]):
        return "OPENCV", pin + [float(d) for d in D[:4]]
    return "FULL_OPENCV", pin + [float(d) for d in D]


def camera_info_from_colmap(name: str, model: str, width: int, height: int, params: Sequence[float]) -> CameraInfo:
    """mapkit's :class:`CameraInfo` of a COLMAP camera (pinhole models and OpenCV's distortion), the principal point
    moved back to mapkit's pixel convention (``COLMAP_PIXEL_OFFSET``)."""
    p = [float(v) for v in params]
    if model not in _PARAMS or len(p) != _PARAMS[model]:
        raise ValueError(f"camera model {model} with {len(p)} parameters: expected one of {sorted(_PARAMS)}")
    if model.startswith("SIMPLE") or model == "RADIAL":
        f, cx, cy = p[:3]
        fx = fy = f
        D = [p[3], 0.0, 0.0, 0.0] if model == "SIMPLE_RADIAL" else [p[3], p[4], 0.0, 0.0] if model == "RADIAL" else []
    else:
        fx, fy, cx, cy = p[:4]
        D = p[4:]
    cx, cy = cx - COLMAP_PIXEL_OFFSET, cy - COLMAP_PIXEL_OFFSET
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], np.float64)
    return CameraInfo(
        name, int(width), int(height), K, "plumb_bob" if len(D) <= 5 else "rational_polynomial", np.array(D)
    )


def _check_name(name: str) -> str:
    if not name or any(c.isspace() for c in name):
        raise ValueError(f"image name {name!r} is empty or holds white space: the format splits on it")
    return name


def write_queries_with_intrinsics(path: str | Path, rows: Sequence[tuple[str, str, int, int, Sequence[float]]]) -> Path:
    """``name MODEL width height params...`` per query, parameters with 12 significant digits."""
    lines = [
        f"{_check_name(n)} {m} {int(w)} {int(h)} {' '.join(f'{float(v):.12g}' for v in p)}\n" for n, m, w, h, p in rows
    ]
    return atomic_write_text(path, "".join(lines))


def read_queries_with_intrinsics(path: str | Path) -> dict[str, CameraInfo]:
    """Every query's camera, by image name, in the file's order."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "no such file: not a benchmark folder (run mapkit export benchmark)")
    out: dict[str, CameraInfo] = {}
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        parts = line.split()
        if not parts or parts[0].startswith("#"):
            continue
        where = f"line {lineno}"
        try:
            if len(parts) < 5:
                raise ValueError(f"{len(parts)} fields, expected name MODEL width height params...")
            params = [float(v) for v in parts[4:]]
            out[parts[0]] = camera_info_from_colmap(parts[0], parts[1], int(parts[2]), int(parts[3]), params)
        except ValueError as exc:
            raise InputError(path, f"{where}: {exc}", field=where) from None
    return out


def write_pairs(path: str | Path, pairs: Sequence[tuple[str, str]]) -> Path:
    """``query_name db_name`` per line."""
    return atomic_write_text(path, "".join(f"{_check_name(q)} {_check_name(d)}\n" for q, d in pairs))


def read_pairs(path: str | Path) -> dict[str, list[str]]:
    """Each query's database images in the file's order (best first)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "no such file: no retrieval pairs")
    out: dict[str, list[str]] = {}
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        parts = line.split()
        if not parts or parts[0].startswith("#"):
            continue
        if len(parts) != 2:
            raise InputError(
                path, f"line {lineno} has {len(parts)} fields, expected query_name db_name", field=f"line {lineno}"
            )
        out.setdefault(parts[0], []).append(parts[1])
    return out


def model_image_root(model: str | Path) -> Path:
    """The folder a reference model's image names are relative to: its metrics.json's ``image_root`` (relative to
    the model folder; ``mapkit model`` builds on the workspace root), else the model folder's parent."""
    folder = Path(model)
    metrics = folder / "metrics.json"
    try:
        rel = json.loads(metrics.read_text()).get("image_root", "..") if metrics.is_file() else ".."
    except (json.JSONDecodeError, AttributeError) as exc:
        raise InputError(metrics, f"not the metrics of a reference model ({exc})", field="image_root") from None
    return (folder.resolve() / rel).resolve()
