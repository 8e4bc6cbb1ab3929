"""A loaded VLAD bundle (:class:`VladIndex`): encode query images, retrieve the top R = 20
database images (MCVL Sec. IV-A) with their poses, and measure ``z_t`` (Sec. III-B: mean shift over
the retrieved translations, :func:`mapkit.retrieval.measurement.mean_shift_measurement`); and grow
the bundle by a session (:meth:`VladIndex.add_session`). The bundle is built by
:mod:`mapkit.retrieval.vlad_build`; its layout is described in :mod:`mapkit.retrieval.index_vlad`.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mapkit.core.bundle import MANIFEST, building, copy_file, read_manifest, write_manifest
from mapkit.core.errors import InputError
from mapkit.core.executor import Executor
from mapkit.core.geodesy import LocalFrame
from mapkit.core.runio import TIMINGS, atomic_path, read_timings, sha256_file, write_json, write_timings
from mapkit.core.workspace import Workspace
from mapkit.mapping.imagedb import images_world_from_cam
from mapkit.retrieval.measurement import Measurement, mean_shift_measurement
from mapkit.retrieval.vlad import VladEncoder
from mapkit.retrieval.vlad_bundle import (
    DATABASE_CSV,
    ENCODER_DIR,
    FORMAT_VERSION,
    INDEX_FILE,
    VECTORS_FILE,
    VladIndexConfig,
    _concat_tables,
    _database_table,
    _same_frame,
    _write_database_csv,
    _write_index,
    read_database_csv,
    read_session_images,
    read_vectors,
)
from mapkit.retrieval.vlad_encoding import _file_key, encode_images, read_image


@dataclass(frozen=True, eq=False)
class Hits:
    """The database images retrieved for one query, best first.

    ``distances`` are squared L2 between unit vectors (0 to 4); ``world_from_cam`` (k, 4, 4) are
    camera poses in the bundle's local ENU frame; ``utm_enh`` (k, 3) easting, northing (m) and
    ellipsoidal height; ``lat_lon_alt`` (k, 3) WGS84 degrees and metres.
    """

    ids: np.ndarray
    distances: np.ndarray
    world_from_cam: np.ndarray
    utm_enh: np.ndarray
    lat_lon_alt: np.ndarray
    sessions: list[str]
    images: list[str]
    image_ids: np.ndarray
    stamps_ns: np.ndarray

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def translations(self) -> np.ndarray:
        """(k, 3) camera positions in the local ENU frame (m)."""
        return self.world_from_cam[:, :3, 3]


class VladIndex:
    """A loaded VLAD bundle: encode images, retrieve the top-k database images, measure the pose."""

    def __init__(
        self,
        path: Path,
        manifest: dict,
        cfg: VladIndexConfig,
        encoder: VladEncoder,
        index,
        database: dict[str, np.ndarray],
    ):
        self.path = Path(path)
        self.manifest = manifest
        self.cfg = cfg
        self.encoder = encoder
        self.index = index
        self.database = database
        self.world_from_cam = images_world_from_cam(database)
        self.frame = LocalFrame.from_dict(manifest["frame"]) if manifest.get("frame") else None

    @property
    def base_from_camera(self) -> np.ndarray | None:
        """The database camera's mount (4, 4) when every database session recorded the same one; else None."""
        mounts = [np.asarray(m, np.float64) for m in (self.manifest.get("camera_mounts") or {}).values()]
        if not mounts or len(mounts) < len(self.manifest.get("database_sessions", [])):
            return None
        if any(not np.allclose(m, mounts[0], atol=1e-6) for m in mounts[1:]):
            return None
        return mounts[0]

    # ---- loading

    @classmethod
    def load(cls, path: str | Path, verify: bool = True) -> VladIndex:
        """Read a bundle; checks its format version and (``verify``) every file's sha256."""
        import faiss

        path = Path(path)
        mpath = path / MANIFEST
        manifest = read_manifest(
            path,
            "VLAD index",
            FORMAT_VERSION,
            (DATABASE_CSV, INDEX_FILE, f"{ENCODER_DIR}/{VladEncoder.MODEL_FILE}"),
            verify,
        )
        try:
            cfg = VladIndexConfig.model_validate(manifest["config"])
        except Exception as exc:  # noqa: BLE001 - pydantic's error, reported against the manifest
            raise InputError(mpath, f"invalid config ({exc})", field="config") from None
        encoder = VladEncoder.load(path / ENCODER_DIR)
        index = faiss.read_index(str(path / INDEX_FILE))
        if hasattr(index, "nprobe") and manifest.get("index", {}).get("nprobe"):
            index.nprobe = int(manifest["index"]["nprobe"])
        database = read_database_csv(path / DATABASE_CSV)
        n = len(database["entry_id"])
        if index.ntotal != n or not np.array_equal(database["entry_id"], np.arange(n)):
            raise InputError(
                path / DATABASE_CSV,
                f"{n} rows (ids 0..n-1 expected) for an index of {index.ntotal} vectors",
                field="entry_id",
            )
        if encoder.pca is None or index.d != encoder.pca.dim:
            raise InputError(path / INDEX_FILE, f"index dimension {index.d} differs from the encoder's", field="dim")
        return cls(path, manifest, cfg, encoder, index, database)

    # ---- facts

    def __len__(self) -> int:
        return int(self.index.ntotal)

    @property
    def dim(self) -> int:
        return int(self.index.d)

    @property
    def database_sessions(self) -> list[str]:
        return [n for n, s in self.manifest["sessions"].items() if s.get("database")]

    @property
    def train_sessions(self) -> list[str]:
        return [n for n, s in self.manifest["sessions"].items() if s.get("training")]

    # ---- queries

    def encode(self, image: np.ndarray | str | Path) -> np.ndarray:
        """(D,) float32 unit vector of an image (array or file)."""
        if isinstance(image, (str, Path)):
            image = read_image(image)
        return self.encoder.encode(np.asarray(image))

    def _as_vector(self, image_or_vector) -> np.ndarray:
        if isinstance(image_or_vector, (str, Path)):
            return self.encode(image_or_vector)
        a = np.asarray(image_or_vector)
        if a.ndim == 1 and a.dtype.kind == "f":
            if len(a) != self.dim:
                raise InputError(None, f"query vector has {len(a)} dimensions, the index {self.dim}", field="dim")
            return a.astype(np.float32)
        return self.encode(a)

    def search(self, vectors: np.ndarray, k: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Batch search: (distances (n, k) squared L2, ids (n, k)); ids -1 pad when k > len(self)."""
        q = np.ascontiguousarray(np.atleast_2d(vectors), np.float32)
        if q.shape[1] != self.dim:
            raise InputError(None, f"query vectors have {q.shape[1]} dimensions, the index {self.dim}", field="dim")
        return self.index.search(q, int(k or self.cfg.top_k))

    def hits(self, ids: np.ndarray, distances: np.ndarray) -> Hits:
        """The database rows of retrieved ``ids`` (padding ids < 0 dropped)."""
        keep = np.asarray(ids) >= 0
        ids, distances = np.asarray(ids)[keep].astype(np.int64), np.asarray(distances)[keep]
        db = self.database
        return Hits(
            ids=ids,
            distances=distances,
            world_from_cam=self.world_from_cam[ids],
            utm_enh=np.stack([db["easting_m"][ids], db["northing_m"][ids], db["up_m"][ids]], axis=1),
            lat_lon_alt=np.stack([db["lat_deg"][ids], db["lon_deg"][ids], db["alt_m"][ids]], axis=1),
            sessions=[str(s) for s in db["session"][ids]],
            images=[str(s) for s in db["image"][ids]],
            image_ids=db["image_id"][ids],
            stamps_ns=db["stamp_ns"][ids],
        )

    def encode_files(
        self,
        paths: Sequence[str | Path],
        progress: bool = False,
        desc: str = "encode",
        cache_dir: str | Path | None = None,
        workers: int | None = None,
    ) -> np.ndarray:
        """(n, D) encodings of image files, on the run's executor (see :func:`encode_images`).

        With ``cache_dir``, encodings are kept in ``encodings-<build hash>.npz`` there, keyed by
        each file's resolved path, size and content hash, and only the files not found are encoded: two
        evaluations of the same images (localization and place recognition) encode them once.
        ``workers`` (default: the bundle's setting) applies when no run-wide executor is set.
        """
        workers = self.cfg.workers if workers is None else workers
        if cache_dir is None:
            return encode_images(self.encoder, paths, workers, progress, desc)
        cache = Path(cache_dir) / f"encodings-{self.manifest.get('build_hash', 'x')}.npz"
        keys = [_file_key(p) for p in paths]
        have: dict[str, np.ndarray] = {}
        if cache.is_file():
            try:
                with np.load(cache, allow_pickle=False) as z:
                    if z["vectors"].shape[1:] == (self.dim,):
                        have = dict(zip(z["keys"].tolist(), z["vectors"], strict=True))
            except (OSError, KeyError, ValueError):
                have = {}  # unreadable: encode again, the file is replaced below
        todo = sorted({k: i for i, k in enumerate(keys) if k not in have}.values())
        if todo:
            vec = encode_images(self.encoder, [paths[i] for i in todo], workers, progress, desc)
            have.update({keys[i]: v for i, v in zip(todo, vec, strict=True)})
            with atomic_path(cache) as tmp, open(tmp, "wb") as f:
                np.savez(f, keys=np.array(list(have)), vectors=np.stack(list(have.values())).astype(np.float32))
        out = np.zeros((len(paths), self.dim), np.float32)
        for i, k in enumerate(keys):
            out[i] = have[k]
        return out

    def query(self, image_or_vector, k: int | None = None) -> Hits:
        """The top ``k`` (default ``top_k`` = 20) database images of an image, image file or encoded vector."""
        dist, ids = self.search(self._as_vector(image_or_vector)[None], k)
        return self.hits(ids[0], dist[0])

    def measurement(self, image_or_vector, k: int | None = None) -> Measurement:
        """MCVL's measurement z_t (Sec. III-B): mean shift over the top-k translations, the largest
        cluster's mean translation and rotation (camera pose, local ENU)."""
        return self.measurement_from_hits(self.query(image_or_vector, k))

    def measurement_from_hits(self, hits: Hits) -> Measurement:
        if len(hits) == 0:
            raise InputError(self.path, "the index is empty: no measurement")
        return mean_shift_measurement(
            hits.translations, hits.world_from_cam[:, :3, :3], bandwidth=self.cfg.mean_shift_bandwidth_m
        )

    def vectors(self) -> np.ndarray:
        """(N, D) float32 database vectors: from vectors.npy, or reconstructed exactly from a flat index."""
        return read_vectors(self.path, self.index)

    # ---- growing

    def add_session(
        self, workspace: str | Path, name: str, progress: bool = False, executor: Executor | None = None
    ) -> VladIndex:
        """Append a session's images (encoded with this bundle's vocabulary and PCA, not relearned).

        The grown bundle is written beside this one and renamed into place; ``self`` then holds it.
        """
        ws = Workspace(workspace)
        mpath = self.path / MANIFEST
        if name in self.manifest["sessions"] and self.manifest["sessions"][name].get("database"):
            raise InputError(mpath, f"session {name!r} is already in the index", field="sessions")
        frame = ws.frame()
        mine = self.manifest.get("frame")
        if (frame is None) != (mine is None) or (
            frame is not None and mine is not None and not _same_frame(frame, LocalFrame.from_dict(mine))
        ):
            raise InputError(
                ws.origin,
                "the workspace's local frame differs from the bundle's: its poses would not match",
                field="frame",
            )
        s = read_session_images(ws, name, self.cfg.prefer_aligned_poses)
        t0 = time.perf_counter()
        new = encode_images(
            self.encoder, [str(p) for p in s.image_paths], self.cfg.workers, progress, f"add {name}", executor
        )
        encode_s = time.perf_counter() - t0
        table = _database_table([name], {name: s}, frame, first_id=len(self))
        database = _concat_tables(self.database, table)

        import faiss

        index = faiss.clone_index(self.index)
        index.add(new)
        with building(self.path) as tmp:
            rewritten = {MANIFEST, INDEX_FILE, VECTORS_FILE, DATABASE_CSV, "metrics.json", TIMINGS}
            for p in self.path.rglob("*"):
                rel = p.relative_to(self.path)
                if p.is_file() and rel.as_posix() not in rewritten:
                    copy_file(p, tmp / rel)
            vectors = (
                np.concatenate([np.load(self.path / VECTORS_FILE), new])
                if (self.path / VECTORS_FILE).is_file()
                else None
            )
            _write_index(tmp, index, vectors)
            _write_database_csv(tmp / DATABASE_CSV, database)
            metrics = (
                json.loads((self.path / "metrics.json").read_text()) if (self.path / "metrics.json").is_file() else {}
            )
            metrics.setdefault("added_sessions", {})[name] = {"images": len(s)}
            write_json(tmp / "metrics.json", metrics)
            timings = read_timings(self.path)
            timings.setdefault("added_sessions", {})[name] = {
                "encode_s": encode_s,
                "images_encoded_per_s": len(s) / encode_s if encode_s > 0 else None,
            }
            write_timings(tmp, **timings)
            manifest = json.loads(json.dumps(self.manifest))
            manifest["sessions"][name] = {
                "images": len(s),
                "training_images": 0,
                "database": True,
                "training": False,
                "pose_source": s.pose_source,
                "images_csv": os.path.relpath(s.csv_path, ws.root),
                "images_csv_sha256": sha256_file(s.csv_path),
                "source_workspace": str(ws.root.resolve()),
            }
            manifest["database_sessions"] = list(manifest["database_sessions"]) + [name]
            manifest["added_sessions"] = list(manifest.get("added_sessions", [])) + [
                {"session": name, "images": len(s)}
            ]
            manifest["entries"] = int(index.ntotal)
            manifest["index"]["ntotal"] = int(index.ntotal)
            write_manifest(tmp, manifest)
        self.manifest, self.index, self.database = manifest, index, database
        self.world_from_cam = images_world_from_cam(database)
        return self


__all__ = ["FORMAT_VERSION", "Hits", "VladIndex"]
