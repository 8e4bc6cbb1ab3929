"""``mapkit index structure``: the deployable place-recognition index of semi-dense structure.

Sec. 3.2-3.4 of the semi-dense place-recognition paper. For every database session: a random
5 % of the map points are keypoints; their patches are cut, yaw-normalised towards each
keypoint's first observer and described (NBLD or M2DP, ``mapkit.places.descriptors3d``; or the CNN of
Sec. 3.3.2 run from its ONNX export, ``mapkit.places.cnn``, with ``cnn_model``); PCA learned on
the database descriptors keeps 25 dimensions (Sec. 5.2); an exact L2 index (faiss
``IndexFlatL2``) holds them, and every entry refers to EVERY frame that observed its keypoint.
A query frame describes the keypoints it observed in the query session's map, matches each to
its nearest database descriptor (L2, no threshold) and each match casts one vote for every
database frame that observed the matched keypoint. The frame d with the most votes v(d) is the
match, accepted when v(d) > lambda_v (Sec. 3.4).

The maps indexed are the semi-dense maps, or with ``map_source: lidar`` the LiDAR maps: their voxel
centroids are the points, poses of the session's trajectory every 2 m the frames, and a frame observed
the voxels near it seen while it passed (:mod:`mapkit.places.lidar_observations`).

Places are frames: ``(session, frame id)`` of the semi-dense maps. A map's observation lists
hold its keyframes (posed) and the non-key neighbour frames that confirmed a point (not posed in
the map). A non-key frame between two keyframes gets its pose by interpolating the keyframes'
poses over time (translation linearly, rotation by slerp) at its stamp; the map records keyframe
stamps only, so without the session's frame stamps (``session_frames``) a frame's stamp is
interpolated over its frame id (frame ids count the camera frames: a constant rate between two
keyframes). A frame outside the keyframe range keeps its votes but has no pose and is never
returned as the match.

Bundle layout (``WORKSPACE/indexes/structure-<kind>`` by default, ``structure-<kind>-lidar`` of the LiDAR maps)::

    manifest.json   format_version, kind, build hash, resolved config, source workspace, the
                    sessions (map source and checksum, keypoints, frames), counts, the CNN
                    model (kind cnn: folder, ONNX sha256, form, domain), and the sha256 and size
                    of every other file
    config.yaml     the resolved StructureIndexConfig
    pca.npz         DescriptorPCA (raw descriptors -> pca_dim)
    index.faiss     faiss IndexFlatL2 over the PCA'd database descriptors; row i = entry i
    entries.npz     per entry: session (index into manifest "session_names"), point index in
                    its session's map, keypoint position (local ENU, m); and the references as
                    CSR ``ref_indptr`` (N+1,), ``ref_frame`` (R,) rows of the frame table
    frames.npz      the frame table: session, frame_id, stamp_ns, world_from_cam (F, 4, 4),
                    pose_source (0 none, 1 keyframe, 2 interpolated between keyframes)
    metrics.json    patches per session, entries, the variance fraction the PCA keeps
    timings.json    wall-clock figures: per session the seconds describing and patches per second
                    (or cached), the PCA and index seconds, the total

The bundle is written into ``.<name>.partial-<pid>-<rand>`` beside the output and renamed into
place last; re-running with the same config and the same maps (by checksum) returns at once.
"""

from __future__ import annotations

import os
import time
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, TypeGuard

import numpy as np
from pydantic import Field

from mapkit import __version__
from mapkit.core.bundle import MANIFEST, building, is_finished, read_manifest, write_manifest
from mapkit.core.config import dump_config, load_config
from mapkit.core.errors import ConfigError, InputError
from mapkit.core.executor import SERIAL, get_executor
from mapkit.core.geometry import interpolate_poses
from mapkit.core.runio import (
    atomic_write_text,
    config_hash,
    progress_bar,
    sha256_file,
    verify_file,
    write_json,
    write_timings,
)
from mapkit.core.workspace import MapKind, MapSource, Workspace
from mapkit.core.writers import writes_workspace
from mapkit.mapping.semidense import SemiDenseMap
from mapkit.places.descriptors3d import DescriptorPCA, StructureDescriptorConfig, describe
from mapkit.places.lidar_observations import (
    LIDAR_FRAME_SPACING_M,
    LIDAR_MAP_FILES,
    LIDAR_OBSERVE_RADIUS_M,
    lidar_map_checksum,
    load_lidar_observations,
)
from mapkit.places.patches import first_observer_positions, select_keypoints, xy_tree

FORMAT_VERSION = 1
INDEX_FILE = "index.faiss"
PCA_FILE = "pca.npz"
ENTRIES_FILE = "entries.npz"
FRAMES_FILE = "frames.npz"

POSE_NONE, POSE_KEYFRAME, POSE_INTERPOLATED = 0, 1, 2

_DESCRIBE_CHUNK = 2048  # keypoints per describe() call (progress granularity)

#: settings that change neither descriptors nor index: a new value does not rebuild
_QUERY_TIME_FIELDS = {"lambda_v", "top_frames"}

Kind = Literal["nbld", "m2dp", "cnn"]


# --------------------------------------------------------------------------- configuration


class StructureIndexConfig(StructureDescriptorConfig):
    """The voting index of Sec. 3.4. Inherits keypoint_fraction (0.05, Sec. 3.2), pca_dim (25,
    Sec. 5.2) and the NBLD / M2DP parameters from ``StructureDescriptorConfig``."""

    kind: Kind = Field(
        "nbld",
        description="Descriptor: nbld or m2dp (Sec. 3.3.1); cnn (Sec. 3.3.2) with cnn_model set, or a describer "
        "registered with register_describer.",
    )
    cnn_model: str | None = Field(
        None,
        description="kind cnn: a trained model folder (mapkit train); its model.onnx is run with onnxruntime (no torch "
        "needed).",
    )
    database_sessions: list[str] | None = Field(
        None, description="Sessions indexed. None = every session of the workspace with a map."
    )
    map_source: MapKind = Field(
        "semidense",
        description="Maps indexed: semidense (map/), or lidar (lidar_map/: voxel centroids as points, trajectory poses "
        "every 2 m as frames; mapkit.places.lidar_observations).",
    )
    lidar_voxel_m: float | None = Field(
        None,
        gt=0,
        description="With map_source lidar: merge the LiDAR map's voxels into voxels of this size first (m; unset: "
        "as built). A map of 0.25 m voxels holds ten times the points of a semi-dense map of the same drive: its "
        "patches take ten times as long to describe, and their density differs from the semi-dense patches'.",
    )
    prefer_aligned_maps: bool = Field(
        True,
        description="Index WORKSPACE/align/sessions/<name>/map where mapkit align finished, else the session's own "
        "map.",
    )
    seed: int = Field(0, description="Seed of the keypoint draw; each session's draw is seeded by (seed, crc32(name)).")
    lambda_v: float = Field(
        0.0,
        ge=0,
        description="Vote threshold lambda_v: a match is accepted when v(d) > lambda_v (Sec. 3.4). The paper sweeps it "
        "for its PR curves and gives no operating value; 0 accepts any voted frame. `mapkit eval places` reports the "
        "value of best F1.",
    )
    top_frames: int = Field(10, ge=1, description="Entries of the vote vector returned per query (best first).")


# --------------------------------------------------------------------------- describers


#: kind -> fn(points (N,3), keypoints (M,3), observer_dirs (M,3), cfg, tree) -> (M, D) float32.
#: nbld and m2dp are mapkit.places.descriptors3d.describe; the CNN registers itself here (hook).
_DESCRIBERS: dict[str, Callable] = {}


def register_describer(kind: str, fn: Callable) -> None:
    """Register the descriptor function of ``kind`` (the hook for the CNN of Sec. 3.3.2)."""
    _DESCRIBERS[kind] = fn


def _describer(kind: str, cfg: StructureIndexConfig) -> Callable | None:
    """The describer of a kind beyond nbld/m2dp: the ONNX model of ``cfg.cnn_model`` for cnn when
    set (mapkit.places.cnn, imported only then), else a registered one."""
    if kind == "cnn" and cfg.cnn_model is not None:
        from mapkit.places.cnn import describe_cnn

        return describe_cnn
    return _DESCRIBERS.get(kind)


def _is_handcrafted(kind: str) -> TypeGuard[Literal["nbld", "m2dp"]]:
    return kind in ("nbld", "m2dp")


def _describe(
    kind: str, points: np.ndarray, keypoints: np.ndarray, observer_dirs: np.ndarray, cfg: StructureIndexConfig, tree
) -> np.ndarray:
    if _is_handcrafted(kind):
        return describe(kind, points, keypoints, observer_dirs, cfg, tree=tree)
    fn = _describer(kind, cfg)
    if fn is None:
        raise ConfigError(
            f"structure descriptor {kind!r} is not available: no describer registered (register_describer)"
        )
    return np.asarray(fn(points, keypoints, observer_dirs, cfg, tree), np.float32)


class _DescribeShared:
    """What every chunk of a session's keypoints needs: the map and the config, shipped once per
    worker; the kd-tree is rebuilt where it is used (cheaper than pickling it)."""

    def __init__(self, kind: str, points: np.ndarray, cfg: StructureIndexConfig):
        self.kind, self.points, self.cfg = kind, points, cfg
        self._tree = None

    @property
    def tree(self):
        if self._tree is None:
            self._tree = xy_tree(self.points)
        return self._tree

    def __getstate__(self) -> dict:
        return {"kind": self.kind, "points": self.points, "cfg": self.cfg, "_tree": None}


def _describe_task(shared: _DescribeShared, chunk: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Raw descriptors of one chunk of keypoints (positions, observer directions)."""
    positions, dirs = chunk
    return _describe(shared.kind, shared.points, positions, dirs, shared.cfg, shared.tree)


def _descriptor_params(cfg: StructureIndexConfig, kind: str) -> dict:
    """What a session's raw descriptors depend on (besides the map)."""
    sub = {"nbld": cfg.nbld, "m2dp": cfg.m2dp}.get(kind)
    params = {
        "kind": kind,
        "keypoint_fraction": cfg.keypoint_fraction,
        "seed": cfg.seed,
        "descriptor": None if sub is None else sub.model_dump(mode="json"),
    }
    if kind == "cnn" and cfg.cnn_model is not None:
        # a retrained model invalidates cached descriptors
        params["cnn_onnx_sha256"] = _cnn_model_info(cfg.cnn_model)["onnx_sha256"]
    return params


def _cnn_model_info(cnn_model: str) -> dict:
    from mapkit.places.cnn import model_fingerprint

    return model_fingerprint(cnn_model)


# --------------------------------------------------------------------------- sessions: keypoints and frames


def _csr_rows(indptr: np.ndarray, indices: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The sub-CSR of ``rows`` (repeats allowed), vectorised."""
    rows = np.asarray(rows, np.int64)
    starts, counts = indptr[rows], indptr[rows + 1] - indptr[rows]
    out_ptr = np.zeros(len(rows) + 1, np.int64)
    np.cumsum(counts, out=out_ptr[1:])
    flat = np.repeat(starts - out_ptr[:-1], counts) + np.arange(int(out_ptr[-1]))
    return out_ptr, indices[flat]


@dataclass(frozen=True, eq=False)
class SessionKeypoints:
    """A session's keypoints (Sec. 3.2) with the CSR of the frames that observed each."""

    name: str
    point_index: np.ndarray  # (K,) int64, rows of the map's points
    positions: np.ndarray  # (K, 3) m, the map's frame
    observer_positions: np.ndarray  # (K, 3) m, first posed observer of each keypoint
    obs_indptr: np.ndarray  # (K+1,) int64
    obs_frame_ids: np.ndarray  # (nnz,) int64, sorted within each keypoint

    def __len__(self) -> int:
        return len(self.point_index)


def keypoint_rng(seed: int, name: str) -> np.random.Generator:
    """The keypoint draw of session ``name``: independent of which other sessions are indexed."""
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, zlib.crc32(name.encode())])


def session_keypoints(smap, name: str, fraction: float = 0.05, seed: int = 0) -> SessionKeypoints:
    """A random ``fraction`` of the map's points (seeded by ``seed`` and ``name``) as keypoints."""
    idx = select_keypoints(len(smap.points_world), fraction, keypoint_rng(seed, name))
    obs_pos = first_observer_positions(
        idx, smap.obs_indptr, smap.obs_frame_ids, smap.keyframe_ids, smap.keyframe_world_from_cam[:, :3, 3]
    )
    ptr, fids = _csr_rows(np.asarray(smap.obs_indptr, np.int64), np.asarray(smap.obs_frame_ids, np.int64), idx)
    return SessionKeypoints(name, idx, np.asarray(smap.points_world, np.float64)[idx], obs_pos, ptr, fids)


def session_frames(smap, frame_stamps: tuple[np.ndarray, np.ndarray] | None = None) -> dict[str, np.ndarray]:
    """The frame table of a map: every frame id in its observation lists or its keyframes, sorted.

    Keyframes keep their pose and stamp. A frame between two keyframes is posed by interpolating
    them over time (translation linearly, rotation by slerp) at its own stamp, taken from
    ``frame_stamps`` = ``(frame ids, stamps_ns)`` of the session's camera frames where they list
    it (by default the map's own table of the frames it was built from). A frame not listed (maps
    saved before that table existed record only keyframe stamps) gets its stamp and
    pose interpolated over the frame id between its keyframes (a constant camera rate between
    them; where frames are evenly spaced in time both ways agree). Frames outside the keyframe
    range get no pose (NaN, stamp -1, pose_source 0).
    """

    if frame_stamps is None and getattr(smap, "frame_stamps_ns", None) is not None:
        frame_stamps = (smap.frame_ids, smap.frame_stamps_ns)
    kf_ids = np.asarray(smap.keyframe_ids, np.int64)
    order = np.argsort(kf_ids, kind="stable")
    kf_ids = kf_ids[order]
    kf_T = np.asarray(smap.keyframe_world_from_cam, np.float64)[order]
    kf_stamps = np.asarray(smap.keyframe_stamps_ns, np.int64)[order]
    ids = np.union1d(kf_ids, np.asarray(smap.obs_frame_ids, np.int64))
    n = len(ids)
    T = np.full((n, 4, 4), np.nan)
    stamps = np.full(n, -1, np.int64)
    source = np.zeros(n, np.int8)
    is_kf = np.isin(ids, kf_ids)
    pos = np.searchsorted(kf_ids, ids[is_kf])
    T[is_kf], stamps[is_kf], source[is_kf] = kf_T[pos], kf_stamps[pos], POSE_KEYFRAME
    other = np.flatnonzero(~is_kf)
    if len(other) == 0 or len(kf_ids) < 2:
        return {"frame_id": ids, "stamp_ns": stamps, "world_from_cam": T, "pose_source": source}
    own_stamp = np.full(len(other), -1, np.int64)
    timed = np.zeros(len(other), bool)
    if frame_stamps is not None:
        f_ids, f_stamps = (np.asarray(a, np.int64) for a in frame_stamps)
        f_order = np.argsort(f_ids, kind="stable")
        at = np.minimum(np.searchsorted(f_ids[f_order], ids[other]), max(len(f_ids) - 1, 0))
        listed = (f_ids[f_order][at] == ids[other]) if len(f_ids) else np.zeros(len(other), bool)
        own_stamp[listed], timed = f_stamps[f_order][at[listed]], listed
    if timed.any():  # over time, at the frame's own stamp
        poses, ok = interpolate_poses(kf_stamps, kf_T, own_stamp[timed])
        inside = other[timed][ok]
        T[inside], stamps[inside], source[inside] = poses, own_stamp[timed][ok], POSE_INTERPOLATED
    if not timed.all():  # over the frame id: interpolate_poses takes any increasing integers
        poses, ok = interpolate_poses(kf_ids, kf_T, ids[other[~timed]])
        inside = other[~timed][ok]
        T[inside] = poses
        stamps[inside] = np.round(np.interp(ids[inside], kf_ids, kf_stamps.astype(np.float64))).astype(np.int64)
        source[inside] = POSE_INTERPOLATED
    return {"frame_id": ids, "stamp_ns": stamps, "world_from_cam": T, "pose_source": source}


def session_names(workspace: str | Path, source: MapKind = "semidense") -> list[str]:
    """Sessions of a workspace with a ``source`` map (semi-dense by default; aligned or not), sorted."""
    return Workspace(workspace).sessions_with_maps(source)


def session_map_dir(
    workspace: str | Path, name: str, prefer_aligned: bool = True, source: MapKind = "semidense"
) -> tuple[Path, str]:
    """(map folder, source) of a session: ``align`` (WORKSPACE/align/sessions/<name>/map, one
    common frame for all sessions) when mapkit align finished it, else ``build``."""
    return Workspace(workspace).session_map(name, prefer_aligned, source)


def map_checksum(folder: Path) -> str:
    """sha256 over a map folder's points.ply and observations.npz."""
    return config_hash({n: sha256_file(folder / n) for n in ("points.ply", "observations.npz")})


def map_files(source: MapKind) -> tuple[str, ...]:
    """The files of a ``source`` map folder that its stage recorded (checked before use)."""
    return ("points.ply", "observations.npz") if source == "semidense" else LIDAR_MAP_FILES


def load_session_map(
    ws: Workspace, name: str, folder: Path, where: MapSource, source: MapKind, lidar_voxel_m: float | None = None
):
    """Session ``name``'s map in ``folder`` (from ``where``: ``align`` or ``build``): a :class:`SemiDenseMap`, or for
    ``lidar`` its LiDAR map with the frames that observed each voxel
    (:func:`~mapkit.places.lidar_observations.load_lidar_observations`, voxels merged to ``lidar_voxel_m`` when
    given), which the structure stages read as they read a semi-dense map."""
    if source == "lidar":
        trajectory = ws.map_trajectory(name, where)
        key = lidar_map_checksum(folder, trajectory, lidar_voxel_m)  # what is read, by content
        if key not in _LIDAR_LOADED:
            while len(_LIDAR_LOADED) >= _LIDAR_LOADED_MAX:
                _LIDAR_LOADED.pop(next(iter(_LIDAR_LOADED)))
            _LIDAR_LOADED[key] = load_lidar_observations(folder, trajectory, lidar_voxel_m)
        return _LIDAR_LOADED[key]
    return SemiDenseMap.load(folder)


#: LiDAR maps with their observing frames, as :func:`load_session_map` last read them, by the checksum of what it
#: read: an evaluation of several pairs and methods reads each session's map once (each read merges a drive's
#: 1.9 M voxels again). The maps are shared, not copied: their readers do not change them.
_LIDAR_LOADED: dict[str, object] = {}
_LIDAR_LOADED_MAX = 6


def session_map_checksum(
    ws: Workspace, name: str, folder: Path, where: MapSource, source: MapKind, lidar_voxel_m: float | None = None
) -> str:
    """The checksum of what :func:`load_session_map` reads with the same arguments."""
    if source == "lidar":
        return lidar_map_checksum(folder, ws.map_trajectory(name, where), lidar_voxel_m)
    return map_checksum(folder)


def session_descriptors(
    smap,
    name: str,
    kind: str,
    cfg: StructureIndexConfig,
    cache_dir: str | Path | None = None,
    map_sha: str | None = None,
    progress: bool = False,
) -> tuple[SessionKeypoints, np.ndarray, float]:
    """A session's keypoints and their raw descriptors (K, D) float32, and the seconds spent describing.

    With ``cache_dir`` (and ``map_sha``, the map's checksum) the descriptors are kept in
    ``<cache_dir>/<kind>-<name>-<hash>.npy`` and read back on the next call with the same map and
    descriptor parameters (the keypoints are drawn again: that is cheap and deterministic).
    """
    kps = session_keypoints(smap, name, cfg.keypoint_fraction, cfg.seed)
    path = None
    if cache_dir is not None and map_sha is not None:
        key = config_hash({"map": map_sha, **_descriptor_params(cfg, kind), "keypoints": len(kps)})
        path = Path(cache_dir) / f"{kind}-{name}-{key}.npy"
        if path.is_file():
            raw = np.load(path)
            if raw.shape[0] == len(kps):
                return kps, raw, 0.0
    t0 = time.perf_counter()
    shared = _DescribeShared(kind, np.asarray(smap.points_world, np.float64), cfg)
    dirs = kps.observer_positions - kps.positions
    chunks = [
        (kps.positions[k0 : k0 + _DESCRIBE_CHUNK], dirs[k0 : k0 + _DESCRIBE_CHUNK])
        for k0 in range(0, max(len(kps), 1), _DESCRIBE_CHUNK)
    ]
    # a describer registered at run time exists in this process only: it cannot run in workers
    executor = get_executor() if kind in ("nbld", "m2dp") or (kind == "cnn" and cfg.cnn_model is not None) else SERIAL
    parts = []
    bar = progress_bar(len(kps), progress, f"{kind} {name}", "patch")
    for part in executor.map(
        _describe_task,
        chunks,
        shared=shared,
        desc=f"describe {kind} {name}",
        label=lambda c: f"{len(c[0])} keypoints from {c[0][:1].round(1).tolist()}",
    ):
        parts.append(part)
        bar.update(len(part))
    bar.close()
    raw = np.concatenate(parts)
    seconds = time.perf_counter() - t0
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.partial.npy")
        np.save(tmp, raw)
        os.replace(tmp, path)
    return kps, raw, seconds


# --------------------------------------------------------------------------- building


@writes_workspace("workspace")
def build_structure_index(
    workspace: str | Path,
    kind: str | None = None,
    out: str | Path | None = None,
    sessions: Sequence[str] | None = None,
    config: StructureIndexConfig | str | Path | None = None,
    overrides: dict | None = None,
    cache_dir: str | Path | None = None,
    progress: bool = False,
    map_source: MapKind | None = None,
) -> Path:
    """Build the structure index bundle of ``workspace``; returns its folder.

    ``kind``, ``sessions`` and ``map_source`` override the config's ``kind``, ``database_sessions`` and
    ``map_source``. Default output: ``WORKSPACE/indexes/structure-<kind>`` (``structure-<kind>-lidar`` of the
    LiDAR maps). ``cache_dir`` keeps each session's raw
    descriptors for reuse (e.g. by ``mapkit eval places``). Skips when the bundle at ``out`` was
    built from the same config and the same maps.
    """
    ws = Workspace(workspace)
    ov = dict(overrides or {})
    if kind is not None:
        ov["kind"] = kind
    if sessions is not None:
        ov["database_sessions"] = list(sessions)
    if map_source is not None:
        ov["map_source"] = map_source
    cfg = load_config(StructureIndexConfig, config, ov)
    out = Path(out) if out is not None else ws.structure_index(cfg.kind, cfg.map_source)
    names = _database_sessions(ws, cfg)
    cnn_info = _cnn_model_info(cfg.cnn_model) if cfg.kind == "cnn" and cfg.cnn_model is not None else None
    dirs = {n: ws.session_map(n, cfg.prefer_aligned_maps, cfg.map_source) for n in names}
    for n, (d, source) in dirs.items():  # a map changed since its stage wrote it is refused, naming the stage to re-run
        for f in map_files(cfg.map_source):
            verify_file(d / f, "mapkit align" if source == "align" else f"mapkit build (session {n})")
    shas = {n: session_map_checksum(ws, n, d, w, cfg.map_source, cfg.lidar_voxel_m) for n, (d, w) in dirs.items()}
    build_hash = _build_hash(cfg, names, dirs, shas, cnn_info)
    if is_finished(out, build_hash, FORMAT_VERSION):
        return out
    if out.exists() and not (out / MANIFEST).is_file() and any(out.iterdir()):
        raise InputError(out, "exists and is not a structure index bundle (no manifest.json): refusing to replace it")

    t_start = time.perf_counter()
    described = _describe_sessions(ws, cfg, names, dirs, shas, cache_dir, progress)
    raw_all = np.concatenate(described.raws) if described.raws else np.zeros((0, 0), np.float32)
    if len(raw_all) < 2:
        raise InputError(
            ws.root,
            f"{len(raw_all)} keypoint(s) in sessions {names}: an index needs at least 2; add sessions with "
            "fuller maps or raise keypoint_fraction",
            field="database_sessions",
        )

    t0 = time.perf_counter()
    pca = DescriptorPCA.fit(raw_all, min(cfg.pca_dim, raw_all.shape[1]))
    vectors = pca.transform(raw_all)
    index = _flat_index(vectors)
    t_index = time.perf_counter() - t0

    entries, frames = _entries_and_frames(described.keypoints, described.frames)
    metrics = {
        "map_source": cfg.map_source,
        "sessions": {n: {"patches": t["patches"]} for n, t in described.timings.items()},
        "entries": int(len(vectors)),
        "pca_explained_variance_fraction": float(
            pca.explained_variance.sum() / max(np.var(raw_all, axis=0, ddof=1).sum(), 1e-12)
        ),
    }
    timings = {
        "sessions": described.timings,
        "pca_s_and_index_s": t_index,
        "seconds_total": time.perf_counter() - t_start,
    }
    manifest = {
        "format_version": FORMAT_VERSION,
        "kind": "mapkit structure index",
        "mapkit_version": __version__,
        "build_hash": build_hash,
        "config": cfg.model_dump(mode="json"),
        "descriptor": cfg.kind,
        **({"cnn_model": cnn_info} if cnn_info else {}),
        **(
            {"lidar_frames": {"spacing_m": LIDAR_FRAME_SPACING_M, "observe_radius_m": LIDAR_OBSERVE_RADIUS_M}}
            if cfg.map_source == "lidar"
            else {}
        ),
        "source_workspace": str(ws.root.resolve()),
        "session_names": names,
        "sessions": described.info,
        "counts": {
            "entries": int(len(vectors)),
            "frames": int(len(frames["frame_id"])),
            "references": int(len(entries["ref_frame"])),
            "raw_dim": int(raw_all.shape[1]),
            "dim": int(pca.dim),
        },
        "index": {"faiss": "IndexFlatL2", "metric": "squared L2", "dim": int(pca.dim), "ntotal": int(index.ntotal)},
    }
    with building(out) as tmp:
        import faiss

        faiss.write_index(index, str(tmp / INDEX_FILE))
        pca.save(tmp / PCA_FILE)
        _savez(tmp / ENTRIES_FILE, entries)
        _savez(tmp / FRAMES_FILE, frames)
        atomic_write_text(tmp / "config.yaml", dump_config(cfg))
        write_json(tmp / "metrics.json", metrics)
        write_timings(tmp, **timings)
        write_manifest(tmp, manifest)  # last: it checksums every other file
    return out


def _database_sessions(ws: Workspace, cfg: StructureIndexConfig) -> list[str]:
    """The sessions to index (the config's, else every one with a map), checked, and the descriptor available."""
    available = ws.sessions_with_maps(cfg.map_source)
    what = "semi-dense map" if cfg.map_source == "semidense" else "LiDAR map"
    names = list(cfg.database_sessions) if cfg.database_sessions is not None else available
    if not names:
        raise InputError(ws.root, f"no session with a {what} to index", field="database_sessions")
    if len(set(names)) != len(names):
        raise ConfigError(f"database_sessions lists a session twice: {names}")
    missing = [n for n in names if n not in available]
    if missing:
        raise InputError(
            ws.root,
            f"no {what} for session(s) {missing} (map_source {cfg.map_source}); the workspace has one for {available}",
            field="database_sessions",
        )
    if cfg.kind not in ("nbld", "m2dp") and _describer(cfg.kind, cfg) is None:
        raise ConfigError(
            f"structure descriptor {cfg.kind!r} is not available: "
            + ("set cnn_model to a trained model folder (mapkit train) or " if cfg.kind == "cnn" else "")
            + "register a describer (register_describer)"
        )
    return names


def _build_hash(
    cfg: StructureIndexConfig,
    names: list[str],
    dirs: dict[str, tuple[Path, MapSource]],
    shas: dict[str, str],
    cnn_info: dict | None,
) -> str:
    """What the bundle depends on: the config (not its query-time settings), the maps (source and checksum), the CNN
    model."""
    # cnn_model only enters the hash of a cnn index: nbld / m2dp bundles of earlier versions stay valid
    # and map_source only that of a LiDAR index: semi-dense bundles made before the option stay valid
    hashed = cfg.model_dump(
        mode="json",
        exclude=_QUERY_TIME_FIELDS
        | (set() if cfg.kind == "cnn" else {"cnn_model"})
        | (set() if cfg.map_source == "lidar" else {"map_source"}),
    )
    return config_hash(
        {
            "format_version": FORMAT_VERSION,
            "config": hashed,
            "sessions": names,
            "maps": {n: [dirs[n][1], shas[n]] for n in names},
            **({"cnn_onnx_sha256": cnn_info["onnx_sha256"]} if cnn_info else {}),
        }
    )


@dataclass
class _Described:
    """Per database session (in order): raw descriptors, keypoints, frame table; and the manifest's and metrics'
    facts by name."""

    raws: list[np.ndarray]
    keypoints: list[SessionKeypoints]
    frames: list[dict[str, np.ndarray]]
    info: dict[str, dict]
    timings: dict[str, dict]


def _describe_sessions(
    ws: Workspace,
    cfg: StructureIndexConfig,
    names: list[str],
    dirs: dict[str, tuple[Path, MapSource]],
    shas: dict[str, str],
    cache_dir: str | Path | None,
    progress: bool,
) -> _Described:
    """Each session's keypoints described (or read from ``cache_dir``) and its frame table."""

    out = _Described([], [], [], {}, {})
    for n in names:
        smap = load_session_map(ws, n, dirs[n][0], dirs[n][1], cfg.map_source, cfg.lidar_voxel_m)
        if len(smap.points_world) == 0:  # no keypoint to describe: fail before any bundle is written
            raise InputError(
                dirs[n][0],
                f"session {n!r} has an empty semi-dense map (0 points, 0 keypoints to describe): "
                "leave it out of database_sessions, or rebuild it with a longer or textured drive",
                field="database_sessions",
            )
        kps, raw, secs = session_descriptors(smap, n, cfg.kind, cfg, cache_dir, shas[n], progress)
        frames = session_frames(smap)
        out.raws.append(raw)
        out.keypoints.append(kps)
        out.frames.append(frames)
        out.timings[n] = {
            "patches": len(kps),
            "describe_s": secs,
            "patches_per_s": len(kps) / secs if secs > 0 else None,
            "cached": secs == 0.0,
        }
        out.info[n] = {
            "map": os.path.relpath(dirs[n][0], ws.root),
            "map_source": dirs[n][1],
            "map_kind": cfg.map_source,
            "map_checksum": shas[n],
            "map_points": int(len(smap.points_world)),
            "keypoints": int(len(kps)),
            "frames": int(len(frames["frame_id"])),
            "keyframes": int(np.sum(frames["pose_source"] == POSE_KEYFRAME)),
            "frames_interpolated": int(np.sum(frames["pose_source"] == POSE_INTERPOLATED)),
            "frames_without_pose": int(np.sum(frames["pose_source"] == POSE_NONE)),
        }
    return out


def _entries_and_frames(
    kp_list: list[SessionKeypoints], frame_tables: list[dict[str, np.ndarray]]
) -> tuple[dict, dict]:
    """The bundle's entry table (keypoints, with their observers as rows of the frame table) and
    the frame table: every session's, concatenated in order."""
    sess_of_entry = np.concatenate([np.full(len(k), i, np.int32) for i, k in enumerate(kp_list)])
    frame_offsets = np.cumsum([0] + [len(f["frame_id"]) for f in frame_tables])
    ptrs, refs = [np.zeros(1, np.int64)], []
    for i, (k, f) in enumerate(zip(kp_list, frame_tables, strict=True)):
        refs.append(np.searchsorted(f["frame_id"], k.obs_frame_ids) + frame_offsets[i])
        ptrs.append(k.obs_indptr[1:] + ptrs[-1][-1])
    entries = {
        "session": sess_of_entry,
        "point_index": np.concatenate([k.point_index for k in kp_list]),
        "position": np.concatenate([k.positions for k in kp_list]),
        "ref_indptr": np.concatenate(ptrs),
        "ref_frame": np.concatenate(refs).astype(np.int64),
    }
    frames = {
        "session": np.concatenate([np.full(len(f["frame_id"]), i, np.int32) for i, f in enumerate(frame_tables)]),
        **{
            c: np.concatenate([f[c] for f in frame_tables])
            for c in ("frame_id", "stamp_ns", "world_from_cam", "pose_source")
        },
    }
    return entries, frames


def _flat_index(vectors: np.ndarray):
    import faiss

    index = faiss.IndexFlatL2(int(vectors.shape[1]))
    index.add(np.ascontiguousarray(vectors, np.float32))
    return index


def _savez(path: Path, arrays: dict) -> None:
    with open(path, "wb") as f:
        np.savez(f, **arrays)


# --------------------------------------------------------------------------- voting


def vote_counts(entry_ids: np.ndarray, ref_indptr: np.ndarray, ref_frame: np.ndarray, n_frames: int) -> np.ndarray:
    """(n_frames,) votes v(d): each matched entry (repeats count again) votes once for every frame
    that observed its keypoint (Sec. 3.4). One gather over the CSR and one ``np.bincount``."""
    _, frames = _csr_rows(np.asarray(ref_indptr, np.int64), np.asarray(ref_frame, np.int64), entry_ids)
    return np.bincount(frames, minlength=n_frames)


def vote_many(
    query_rows: np.ndarray, entry_ids: np.ndarray, ref_indptr: np.ndarray, ref_frame: np.ndarray, n_frames: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Votes of many query frames at once, as sparse triples ``(row, frame, votes)``.

    ``query_rows[j]`` is the query frame that matched entry ``entry_ids[j]`` (one pair per
    observed keypoint). The triples are sorted by row, then votes descending, then frame.
    """
    query_rows = np.asarray(query_rows, np.int64)
    ptr, frames = _csr_rows(np.asarray(ref_indptr, np.int64), np.asarray(ref_frame, np.int64), entry_ids)
    rows = np.repeat(query_rows, np.diff(ptr))
    keys, votes = np.unique(rows * np.int64(n_frames) + frames, return_counts=True)
    r, f = keys // n_frames, keys % n_frames
    order = np.lexsort((f, -votes, r))
    return r[order], f[order], votes[order]


@dataclass(frozen=True, eq=False)
class QueryKeypoints:
    """A query session's keypoints, described and matched against the index once for all its frames."""

    keypoints: SessionKeypoints
    descriptors: np.ndarray  # (K, dim) float32, PCA'd
    matched_entry: np.ndarray  # (K,) int64, nearest database entry (L2)
    match_sq_distance: np.ndarray  # (K,) float32


@dataclass(frozen=True, eq=False)
class FrameMatches:
    """The match of each query frame: the most voted database frame d and v(d); -1 / 0 when
    nothing voted. ``top_frames`` / ``top_votes`` (n, k): the vote vector's best entries (-1 / 0
    pad). Frame rows index the index's frame table (``StructureIndex.frames``)."""

    query_frame_ids: np.ndarray  # (n,)
    n_keypoints: np.ndarray  # (n,) query keypoints the frame observed
    best_frame: np.ndarray  # (n,) int64
    best_votes: np.ndarray  # (n,) int64, v(d)
    top_frames: np.ndarray  # (n, k)
    top_votes: np.ndarray  # (n, k)

    def __len__(self) -> int:
        return len(self.query_frame_ids)

    def accepted(self, lambda_v: float) -> np.ndarray:
        """Which matches pass v(d) > lambda_v."""
        return (self.best_frame >= 0) & (self.best_votes > lambda_v)


@dataclass(frozen=True, eq=False)
class PlaceMatch:
    """The match of one query frame (see ``FrameMatches``); ``session``/``frame_id``/pose None when none."""

    frame: int
    votes: int
    accepted: bool
    session: str | None
    frame_id: int | None
    world_from_cam: np.ndarray | None
    top_frames: np.ndarray
    top_votes: np.ndarray
    n_keypoints: int


class StructureIndex:
    """A loaded structure index: describe query keypoints, match, vote for database frames."""

    def __init__(
        self,
        path: Path,
        manifest: dict,
        cfg: StructureIndexConfig,
        pca: DescriptorPCA,
        index,
        entries: dict,
        frames: dict,
    ):
        self.path = Path(path)
        self.manifest = manifest
        self.cfg = cfg
        self.pca = pca
        self.index = index
        self.entries = entries
        self.frames = frames
        self.session_names: list[str] = list(manifest["session_names"])
        self._votable = frames["pose_source"] > POSE_NONE

    # ---- loading

    @classmethod
    def load(cls, path: str | Path, verify: bool = True) -> StructureIndex:
        """Read a bundle; checks its format version and (``verify``) every file's sha256."""
        import faiss

        path = Path(path)
        mpath = path / MANIFEST
        manifest = read_manifest(
            path, "structure index", FORMAT_VERSION, (INDEX_FILE, PCA_FILE, ENTRIES_FILE, FRAMES_FILE), verify
        )
        try:
            cfg = StructureIndexConfig.model_validate(manifest["config"])
        except Exception as exc:  # noqa: BLE001 - pydantic's error, reported against the manifest
            raise InputError(mpath, f"invalid config ({exc})", field="config") from None
        pca = DescriptorPCA.load(path / PCA_FILE)
        index = faiss.read_index(str(path / INDEX_FILE))
        with np.load(path / ENTRIES_FILE) as z:
            entries = {k: z[k] for k in z.files}
        with np.load(path / FRAMES_FILE) as z:
            frames = {k: z[k] for k in z.files}
        n, F = len(entries["point_index"]), len(frames["frame_id"])
        if (
            index.ntotal != n
            or len(entries["ref_indptr"]) != n + 1
            or entries["ref_indptr"][-1] != len(entries["ref_frame"])
        ):
            raise InputError(
                path / ENTRIES_FILE,
                f"{n} entries for an index of {index.ntotal} vectors, or a broken reference CSR",
                field="ref_indptr",
            )
        if len(entries["ref_frame"]) and (entries["ref_frame"].min() < 0 or entries["ref_frame"].max() >= F):
            raise InputError(
                path / ENTRIES_FILE, f"frame references outside the frame table of {F} rows", field="ref_frame"
            )
        if index.d != pca.dim:
            raise InputError(
                path / INDEX_FILE, f"index dimension {index.d} differs from the PCA's {pca.dim}", field="dim"
            )
        if cfg.kind == "cnn" and cfg.cnn_model is not None and "cnn_model" in manifest:
            # queries run the model at cnn_model: it must be the one indexed
            now = _cnn_model_info(cfg.cnn_model)["onnx_sha256"]
            if now != manifest["cnn_model"]["onnx_sha256"]:
                raise InputError(
                    Path(cfg.cnn_model) / "model.onnx",
                    "differs from the model this index was built with",
                    field="cnn_model",
                )
        return cls(path, manifest, cfg, pca, index, entries, frames)

    # ---- facts

    def __len__(self) -> int:
        return int(self.index.ntotal)

    @property
    def kind(self) -> str:
        return self.cfg.kind

    @property
    def n_frames(self) -> int:
        return int(len(self.frames["frame_id"]))

    def frame_rows(self, session: str) -> np.ndarray:
        """Rows of the frame table that belong to ``session``."""
        return np.flatnonzero(self.frames["session"] == self.session_names.index(session))

    def frame_positions(self) -> np.ndarray:
        """(F, 3) frame positions (NaN where the frame has no pose)."""
        return self.frames["world_from_cam"][:, :3, 3]

    # ---- queries

    def describe(
        self, points_world: np.ndarray, keypoint_positions: np.ndarray, observer_positions: np.ndarray, tree=None
    ) -> np.ndarray:
        """(K, dim) PCA'd descriptors of keypoints in a cloud (the index's descriptor and config)."""
        pts = np.asarray(points_world, np.float64)
        kp = np.asarray(keypoint_positions, np.float64).reshape(-1, 3)
        dirs = np.asarray(observer_positions, np.float64).reshape(-1, 3) - kp
        raw = _describe(self.kind, pts, kp, dirs, self.cfg, xy_tree(pts) if tree is None else tree)
        return self.pca.transform(raw)

    def nearest(self, descriptors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(entry ids (K,), squared L2 (K,)) of the nearest database descriptor of each of ``descriptors`` (K, dim)."""
        q = np.ascontiguousarray(np.asarray(descriptors, np.float32).reshape(-1, self.pca.dim))
        if len(q) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.float32)
        d, ids = self.index.search(q, 1)
        return ids[:, 0].astype(np.int64), d[:, 0]

    def votes(self, entry_ids: np.ndarray) -> np.ndarray:
        """(F,) vote vector of matched entries (Sec. 3.4)."""
        return vote_counts(entry_ids, self.entries["ref_indptr"], self.entries["ref_frame"], self.n_frames)

    def query_frame(
        self,
        points_world: np.ndarray,
        keypoint_positions: np.ndarray,
        observer_positions: np.ndarray,
        tree=None,
        lambda_v: float | None = None,
    ) -> PlaceMatch:
        """The match of one query frame from the keypoints it observed (positions (K, 3) in the
        cloud ``points_world``, with their first observers' positions)."""
        entry, _ = self.nearest(self.describe(points_world, keypoint_positions, observer_positions, tree))
        return self._place_match(self.votes(entry), len(entry), lambda_v)

    def _place_match(self, v: np.ndarray, n_keypoints: int, lambda_v: float | None) -> PlaceMatch:
        lam = self.cfg.lambda_v if lambda_v is None else lambda_v
        v = np.where(self._votable, v, 0)
        k = min(self.cfg.top_frames, len(v))
        # best first; ties go to the lower frame row (stable sort of -votes)
        top = np.argsort(-v, kind="stable")[:k]
        top = top[v[top] > 0]
        tv = v[top]
        if len(top) == 0:
            return PlaceMatch(-1, 0, False, None, None, None, top, tv, n_keypoints)
        b = int(top[0])
        return PlaceMatch(
            b,
            int(tv[0]),
            bool(tv[0] > lam),
            self.session_names[int(self.frames["session"][b])],
            int(self.frames["frame_id"][b]),
            self.frames["world_from_cam"][b],
            top,
            tv,
            n_keypoints,
        )

    def prepare_query(
        self, query_map, name: str = "query", raw_descriptors: np.ndarray | None = None
    ) -> QueryKeypoints:
        """Draw the query session's keypoints (the index's fraction, seeded by the index's seed and
        ``name``), describe them in the query map (or take ``raw_descriptors`` of exactly those
        keypoints, e.g. from ``session_descriptors``) and match each to its nearest database entry."""
        kps = session_keypoints(query_map, name, self.cfg.keypoint_fraction, self.cfg.seed)
        if raw_descriptors is None:
            pts = np.asarray(query_map.points_world, np.float64)
            raw_descriptors = _describe(
                self.kind, pts, kps.positions, kps.observer_positions - kps.positions, self.cfg, xy_tree(pts)
            )
        if len(raw_descriptors) != len(kps):
            raise InputError(
                None, f"{len(raw_descriptors)} descriptors for {len(kps)} query keypoints", field="raw_descriptors"
            )
        desc = self.pca.transform(raw_descriptors) if len(kps) else np.zeros((0, self.pca.dim), np.float32)
        entry, dist = self.nearest(desc)
        return QueryKeypoints(kps, desc, entry, dist)

    def vote_frames(self, query: QueryKeypoints, frame_ids: Sequence[int]) -> FrameMatches:
        """Votes of query frames ``frame_ids`` (ids of the query map): each uses the query
        keypoints its frame observed. Vectorised over all frames (``vote_many``)."""
        fids = np.asarray(frame_ids, np.int64)
        n, k = len(fids), self.cfg.top_frames
        kps = query.keypoints
        # (query row, keypoint) pairs: keypoint observed by a requested frame
        order = np.argsort(fids, kind="stable")
        sorted_ids = fids[order]
        kp_of_obs = np.repeat(np.arange(len(kps)), np.diff(kps.obs_indptr))
        pos = np.minimum(np.searchsorted(sorted_ids, kps.obs_frame_ids), max(n - 1, 0))
        hit = (sorted_ids[pos] == kps.obs_frame_ids) if n else np.zeros(len(kp_of_obs), bool)
        rows, kp = order[pos[hit]], kp_of_obs[hit]
        n_kp = np.bincount(rows, minlength=n)
        r, f, v = vote_many(
            rows, query.matched_entry[kp], self.entries["ref_indptr"], self.entries["ref_frame"], self.n_frames
        )
        keep = self._votable[f]
        r, f, v = r[keep], f[keep], v[keep]
        # rank within each row (the triples are sorted by row, then votes descending)
        first = np.searchsorted(r, np.arange(n))
        rank = np.arange(len(r)) - first[r]
        top_f = np.full((n, k), -1, np.int64)
        top_v = np.zeros((n, k), np.int64)
        sel = rank < k
        top_f[r[sel], rank[sel]] = f[sel]
        top_v[r[sel], rank[sel]] = v[sel]
        return FrameMatches(fids, n_kp, top_f[:, 0].copy(), top_v[:, 0].copy(), top_f, top_v)

    def query_session_frames(self, query_map, frame_ids: Sequence[int], name: str = "query") -> FrameMatches:
        """Matches of frames ``frame_ids`` of a query session's map (``prepare_query`` + ``vote_frames``)."""
        return self.vote_frames(self.prepare_query(query_map, name), frame_ids)


__all__ = [
    "FORMAT_VERSION",
    "StructureIndexConfig",
    "StructureIndex",
    "SessionKeypoints",
    "QueryKeypoints",
    "FrameMatches",
    "PlaceMatch",
    "build_structure_index",
    "load_session_map",
    "session_keypoints",
    "session_frames",
    "session_descriptors",
    "session_map_checksum",
    "session_map_dir",
    "session_names",
    "vote_counts",
    "vote_many",
    "register_describer",
    "keypoint_rng",
]
