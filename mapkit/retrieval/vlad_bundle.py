"""The VLAD bundle's format, shared by building (:mod:`mapkit.retrieval.vlad_build`) and loading
(:mod:`mapkit.retrieval.vlad_index`): its file names, its config, the workspace's session image
tables it is built from, and its database table (``database.csv``). See
:mod:`mapkit.retrieval.index_vlad` for the bundle layout.
"""

from __future__ import annotations

import csv
import io
import json
import os
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field

from mapkit.core.config import MapkitConfig
from mapkit.core.errors import InputError
from mapkit.core.geodesy import LocalFrame
from mapkit.core.geometry import matrix_to_quat_wxyz
from mapkit.core.runio import atomic_write_text
from mapkit.core.workspace import Workspace
from mapkit.mapping.imagedb import images_world_from_cam, read_images_csv
from mapkit.retrieval.vlad import VladConfig

FORMAT_VERSION = 1
DATABASE_CSV = "database.csv"
INDEX_FILE = "index.faiss"
VECTORS_FILE = "vectors.npy"
ENCODER_DIR = "encoder"

DATABASE_COLUMNS = [
    "entry_id",
    "session",
    "image_id",
    "stamp_ns",
    "camera",
    "image",
    "x_m",
    "y_m",
    "z_m",
    "qw",
    "qx",
    "qy",
    "qz",
    "easting_m",
    "northing_m",
    "up_m",
    "lat_deg",
    "lon_deg",
    "alt_m",
    "utm_epsg",
]

#: settings that change neither the vectors nor the index: a new value rewrites the config, no rebuild
_QUERY_TIME_FIELDS = {"workers", "top_k", "mean_shift_bandwidth_m"}


# --------------------------------------------------------------------------- configuration


class IvfConfig(MapkitConfig):
    """Inverted-file index for large databases (faiss IndexIVFFlat, or IndexIVFPQ with ``pq_m``)."""

    nlist: int | None = Field(
        None,
        ge=1,
        description="Inverted lists (coarse centroids). None = 4 sqrt(N) (faiss's guideline); always capped at N / 39 "
        "so that k-means has the 39 training points per list faiss asks for.",
    )
    nprobe: int = Field(
        16,
        ge=1,
        description="Lists visited per query. With 1024 lists over 100k 4096-D vectors on one core: 14 ms per query "
        "and recall@20 0.999 of the exact top-20, against 107 ms exact (bench/bench_vlad_query.py, road-clustered "
        "synthetic vectors).",
    )
    pq_m: int | None = Field(
        None,
        ge=1,
        description="None = IVF-Flat (exact distances inside the visited lists). m = IVF-PQ with m sub-quantizers (m "
        "bytes per vector at 8 bits; must divide the dimension): for city scale, at a recall cost measured by the "
        "benchmark.",
    )
    pq_bits: int = Field(8, ge=1, le=16, description="Bits per PQ sub-quantizer code.")
    max_training_vectors: int = Field(
        200_000,
        ge=1,
        description="The coarse quantizer (and PQ) train on a uniform sample of at most this many database vectors.",
    )


class VladIndexConfig(MapkitConfig):
    """The VLAD retrieval index; defaults are MCVL's (Sec. III-B, IV-A) where the paper gives one."""

    vlad: VladConfig = Field(
        default_factory=VladConfig, description="The observation encoder (see mapkit.retrieval.vlad)."
    )
    train_sessions: list[str] | None = Field(
        None,
        description="Sessions whose images train the vocabulary and PCA. None = the database sessions (the PCA then "
        "learns on the database itself, which is why vlad.whitening is regularised by default). Sessions beyond the "
        "database give the PCA images the database does not hold. Never the query sessions.",
    )
    training_frames: bool = Field(
        False,
        description="The vocabulary and PCA learn also from the frames the training sessions' image databases skipped "
        "and kept for this (mapkit build's imagedb.training_frames): images that are not database images. Off by "
        "default: frames of the same drives add dimensions to the PCA, not new appearance, and gave no retrieval gain "
        "on the synthetic town. Drives of other days named in train_sessions are the other way.",
    )
    database_sessions: list[str] | None = Field(
        None, description="Sessions whose images are indexed. None = every session in the workspace."
    )
    prefer_aligned_poses: bool = Field(
        True,
        description="Take camera poses from WORKSPACE/align (multi-session refinement) for sessions it finished, else "
        "from the session's GPS-aligned imagedb.",
    )
    index: Literal["flat", "ivf"] = Field(
        "flat", description="'flat': exact search (faiss IndexFlatL2); 'ivf': approximate, for city scale."
    )
    ivf: IvfConfig = Field(default_factory=IvfConfig, description="IVF settings (used when index = 'ivf').")
    top_k: int = Field(20, ge=1, description="Images retrieved per query, R (MCVL Sec. IV-A: 20).")
    mean_shift_bandwidth_m: float = Field(
        5.0,
        gt=0,
        description="Radius of the flat mean-shift kernel over retrieved translations (m; the authors' code: 5).",
    )
    max_training_images: int = Field(
        5000,
        ge=2,
        description="PCA trains on a uniform sample of at most this many training images (not in the paper; the 4096-D "
        "PCA of Sec. IV-A needs more than 4096; fewer cap the dimension at n - 1).",
    )
    max_vocabulary_images: int = Field(
        250,
        ge=1,
        description="The k-means descriptor sample (vlad.kmeans_max_descriptors) is drawn evenly from at most this "
        "many of the training images (not in the paper; ~800 descriptors per image at the defaults).",
    )
    workers: int = Field(1, ge=1, description="Processes encoding images (1 = in this process).")
    seed: int = Field(0, description="Seed of the image subsamples.")


# --------------------------------------------------------------------------- workspace sessions


@dataclass
class SessionImages:
    """One session's database images as the workspace gives them."""

    name: str
    pose_source: Literal["align", "imagedb"]
    csv_path: Path
    table: dict[str, np.ndarray]
    image_paths: list[Path]  # readable paths
    workspace_paths: list[str]  # relative to the workspace, as written to database.csv
    world_from_cam: np.ndarray  # (n, 4, 4) local ENU
    base_from_camera: np.ndarray | None = None  # (4, 4) the camera's mount, when the build recorded it
    training_csv: Path | None = (
        None  # the frames the database skipped, kept for encoder training (imagedb.training_frames)
    )

    def __len__(self) -> int:
        """Database images (training frames not counted)."""
        return len(self.image_paths)

    @cached_property
    def training_paths(self) -> list[Path]:
        """The training frames' readable paths, read from ``training_csv`` when first asked for (only an
        index that learns from them does)."""
        if self.training_csv is None:
            return []
        return [self.training_csv.parent / p for p in read_images_csv(self.training_csv)["image"]]

    def path(self, row: int) -> Path:
        """Row ``row`` of the database images followed by the training frames."""
        n = len(self.image_paths)
        return self.image_paths[row] if row < n else self.training_paths[row - n]


def workspace_sessions(workspace: str | Path) -> list[str]:
    """Names of the sessions of a workspace that have an image database, sorted."""
    return Workspace(workspace).sessions_with_images()


def read_session_images(workspace: str | Path | Workspace, name: str, prefer_aligned: bool = True) -> SessionImages:
    """A session's image table: the aligned one (``align/sessions/<name>/images.csv``) when the
    alignment finished and holds the session, else ``sessions/<name>/imagedb/images.csv``."""
    ws = Workspace(workspace)
    csv_path = ws.session_images_csv(name, prefer_aligned)
    source: Literal["align", "imagedb"] = "align" if csv_path == ws.aligned(name).images_csv else "imagedb"
    if not csv_path.is_file():
        raise InputError(csv_path, f"session {name!r} has no image database (run mapkit build)")
    table = read_images_csv(csv_path)
    paths = [csv_path.parent / p for p in table["image"]]
    rel = [os.path.relpath(p, ws.root) for p in paths]
    training_csv = ws.session(name).training_csv
    return SessionImages(
        name,
        source,
        csv_path,
        table,
        paths,
        rel,
        images_world_from_cam(table),
        read_camera_mount(ws, name),
        training_csv if training_csv.is_file() else None,
    )


def read_camera_mount(workspace: str | Path | Workspace, name: str) -> np.ndarray | None:
    """Session ``name``'s camera mount ``base_from_camera`` (4, 4) as ``mapkit build`` recorded it;
    None for image databases built before it was recorded."""
    path = Workspace(workspace).session(name).camera_mount
    if not path.is_file():
        return None
    try:
        T = np.asarray(json.loads(path.read_text())["base_from_camera"], np.float64)
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise InputError(path, f"not a camera mount ({exc})", field="base_from_camera") from None
    if T.shape != (4, 4):
        raise InputError(path, f"base_from_camera is {T.shape}, not 4x4", field="base_from_camera")
    return T


# --------------------------------------------------------------------------- the database table


def _write_index(folder: Path, index, vectors: np.ndarray | None) -> None:
    import faiss

    faiss.write_index(index, str(folder / INDEX_FILE))
    if vectors is not None:
        np.save(folder / VECTORS_FILE, np.ascontiguousarray(vectors, np.float32))


def read_vectors(folder: Path, index=None) -> np.ndarray:
    """(N, D) float32 database vectors of the bundle at ``folder``: vectors.npy (IVF bundles), else
    reconstructed exactly from its flat index (``index``, read from the bundle if not given)."""
    p = folder / VECTORS_FILE
    if p.is_file():
        return np.load(p)
    if index is None:
        import faiss

        index = faiss.read_index(str(folder / INDEX_FILE))
    return index.reconstruct_n(0, index.ntotal)


def _database_table(
    names: list[str], sessions: dict[str, SessionImages], frame: LocalFrame | None, first_id: int = 0
) -> dict[str, Any]:
    cols: dict[str, list] = {c: [] for c in DATABASE_COLUMNS}
    T_all = []
    for n in names:
        s = sessions[n]
        cols["session"] += [n] * len(s)
        cols["image_id"] += list(s.table["image_id"])
        cols["stamp_ns"] += list(s.table["stamp_ns"])
        cols["camera"] += list(s.table["camera"])
        cols["image"] += s.workspace_paths
        T_all.append(s.world_from_cam)
    T = np.concatenate(T_all) if T_all else np.zeros((0, 4, 4))
    n_all = len(T)
    xyz = T[:, :3, 3]
    q = matrix_to_quat_wxyz(T[:, :3, :3]) if n_all else np.zeros((0, 4))
    if frame is not None and n_all:
        lat, lon, alt = frame.enu_to_geodetic(xyz)
        utm = frame.enu_to_utm(xyz)
        epsg = int(frame.utm_epsg)
    else:
        lat = lon = alt = np.full(n_all, np.nan)
        utm = np.full((n_all, 3), np.nan)
        epsg = 0
    out: dict[str, Any] = {
        "entry_id": np.arange(first_id, first_id + n_all, dtype=np.int64),
        "session": np.asarray(cols["session"], dtype=object),
        "image_id": np.asarray(cols["image_id"], np.int64),
        "stamp_ns": np.asarray(cols["stamp_ns"], np.int64),
        "camera": np.asarray(cols["camera"], dtype=object),
        "image": np.asarray(cols["image"], dtype=object),
        "x_m": xyz[:, 0],
        "y_m": xyz[:, 1],
        "z_m": xyz[:, 2],
        "qw": q[:, 0],
        "qx": q[:, 1],
        "qy": q[:, 2],
        "qz": q[:, 3],
        "easting_m": utm[:, 0],
        "northing_m": utm[:, 1],
        "up_m": utm[:, 2],
        "lat_deg": np.asarray(lat, np.float64),
        "lon_deg": np.asarray(lon, np.float64),
        "alt_m": np.asarray(alt, np.float64),
        "utm_epsg": np.full(n_all, epsg, np.int64),
    }
    return out


_FORMATS = {
    "x_m": ".4f",
    "y_m": ".4f",
    "z_m": ".4f",
    "qw": ".9f",
    "qx": ".9f",
    "qy": ".9f",
    "qz": ".9f",
    "easting_m": ".4f",
    "northing_m": ".4f",
    "up_m": ".4f",
    "lat_deg": ".9f",
    "lon_deg": ".9f",
    "alt_m": ".4f",
}


def _write_database_csv(path: Path, table: dict[str, Any]) -> None:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(DATABASE_COLUMNS)
    for i in range(len(table["entry_id"])):
        w.writerow([format(table[c][i], _FORMATS[c]) if c in _FORMATS else table[c][i] for c in DATABASE_COLUMNS])
    atomic_write_text(path, buf.getvalue())


def read_database_csv(path: str | Path) -> dict[str, np.ndarray]:
    """The bundle's database table as columns (numbers as arrays, names and paths as object arrays)."""
    path = Path(path)
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        missing = [c for c in DATABASE_COLUMNS if c not in (reader.fieldnames or [])]
        if missing:
            raise InputError(path, f"header lacks {missing}", field="header")
        rows = list(reader)
    out: dict[str, np.ndarray] = {}
    for c in DATABASE_COLUMNS:
        vals = [r[c] for r in rows]
        if c in ("session", "camera", "image"):
            out[c] = np.asarray(vals, dtype=object)
        elif c in ("entry_id", "image_id", "stamp_ns", "utm_epsg"):
            out[c] = np.asarray([int(v) for v in vals], np.int64)
        else:
            out[c] = np.asarray([float(v) for v in vals], np.float64)
    return out


def _concat_tables(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    return {c: np.concatenate([np.asarray(a[c]), np.asarray(b[c])]) for c in DATABASE_COLUMNS}


def _same_frame(a: LocalFrame, b: LocalFrame) -> bool:
    return (
        abs(a.lat0_deg - b.lat0_deg) < 1e-9
        and abs(a.lon0_deg - b.lon0_deg) < 1e-9
        and abs(a.alt0_m - b.alt0_m) < 1e-4
        and int(a.utm_epsg) == int(b.utm_epsg)
    )
