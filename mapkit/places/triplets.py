"""``mapkit triplets``: training triplets of voxelised 3D patches (semi-dense paper, section 4.1).

From an aligned workspace (``mapkit align``): a random keypoint of one session gives a
georeferenced place; every session that mapped that place contributes its local cloud, aligned to
the anchor session's with ICP (a member whose RMSE after ICP exceeds lambda_ICP is rejected); the
patches are cut from the aligned clouds, yaw-normalised (section 3.2) and voxelised (occupancy and
density comparison, 32^3). N members give N-choose-2 positive pairs; each gets a negative: a patch
farther than ``negative_min_distance_m`` from the anchor, from the same split.

The maps cut are the aligned semi-dense maps, or with ``map_source: lidar`` the aligned LiDAR maps
(``align/sessions/<name>/lidar_map``: the voxel centroids as points, the voxels of submaps left out of
the merged map left out here too; a point's first observer is the trajectory pose, one every 2 m,
that first passed within 15 m of it while it was seen: :mod:`mapkit.places.lidar_observations`).
The default output folder is then ``WORKSPACE/triplets-lidar``.

Train and test places come from disjoint UTM tiles, with a buffer strip: no keypoint (anchor or
negative) lies within ``buffer_m`` of a tile of the other split, so no test place has a training
patch nearby. Output: shards of the patches' grids (bits packed; HDF5 by default, see
:func:`write_shard_hdf5`, or compressed NumPy; :func:`read_shard` and :class:`TripletDataset`
read both), a per-patch table, the triplets, a manifest with seed, config hash, shard format and
the shards' sizes and checksums, and a picture of a few triplets. An export that would make no
triplet raises :class:`NoTripletsError` (saying why) and writes nothing. The same patches in
PointNetVLAD's training layout are a later stage (:mod:`mapkit.places.pointnetvlad`, which imports this
module and not the reverse).

Where the time goes (20k triplets of a synthetic town): ICP, then cutting, normalising and
voxelising ~16k patches of ~5k points. Each session is downsampled and its normals estimated once
(not per registration); a cell's places are made together (:class:`ChunkSets`: one fetch of each
session's points about the cell, one batch through yaw normalisation and voxelisation).
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field, ValidationInfo, field_validator, model_validator
from scipy.spatial import cKDTree

from mapkit.core.bundle import building
from mapkit.core.config import MapkitConfig, dump_config, load_config
from mapkit.core.errors import InputError
from mapkit.core.geodesy import LocalFrame
from mapkit.core.runio import (
    atomic_path,
    atomic_write_text,
    config_hash,
    is_done,
    mark_done,
    marker_hash,
    progress_bar,
    sha256_file,
    stage_digest,
    stage_hash,
    verify_file,
    write_json,
    write_timings,
)
from mapkit.core.workspace import MapKind, Workspace
from mapkit.core.writers import writes_workspace
from mapkit.io.plots import triplet_examples
from mapkit.mapping.icp import IcpClouds, icp_coarse_to_fine
from mapkit.mapping.semidense import SemiDenseMap
from mapkit.multisession.align import check_levels
from mapkit.multisession.registration import IcpConfig, Registration, about_centre, evaluate_alignment
from mapkit.multisession.tiles import load_tiles
from mapkit.places.lidar_observations import LIDAR_MAP_FILES, load_lidar_observations
from mapkit.places.patches import (
    CNN_DOMAIN,
    PatchDomain,
    first_observer_frames,
    unpack_bits,
    voxelise_patches,
    yaw_normalise_patches,
)
from mapkit.places.pointnetvlad_config import PointNetVladConfig

log = logging.getLogger(__name__)

#: the version of this stage's algorithm, bumped whenever its output for the same inputs changes (it reruns)
STAGE_VERSION = 1

TRIPLETS_FORMAT_VERSION = 2  # 2: shards in HDF5 (or npz, as the manifest's shard_format says); 1: npz shards only
READABLE_FORMAT_VERSIONS = (1, 2)
SHARD_SUFFIX = {"hdf5": ".h5", "npz": ".npz"}
SHARD_FORMATS = tuple(SHARD_SUFFIX)
SHARD_CHUNK_PATCHES = 16  # patches per HDF5 chunk: 64 KB of packed 32^3 occupancy, 192 KB of density comparison
SPLITS = ("train", "test")
GridForm = Literal["occupancy", "density_comparison"]  # how a patch's grid is stored (TripletDataset.grids)


class NoTripletsError(InputError):
    """A triplet (or PointNetVLAD) export that would produce nothing: says why and what to change."""


class TripletConfig(MapkitConfig):
    domain: PatchDomain = Field(
        CNN_DOMAIN, description="Patch domain: the CNN's 20x20x20 m cube (semi-dense paper, Fig. 6 caption)."
    )
    grid: int = Field(32, ge=4, description="Voxels per axis (semi-dense paper, section 3.3.2: 32x32x32).")
    keypoint_fraction: float = Field(
        0.05, gt=0, le=1, description="Keypoints: a random 5% of map points (semi-dense paper, section 3.2)."
    )
    n_triplets: int = Field(20_000, ge=1, description="Triplets to export (the paper's triplet set has 20,000).")
    seen_radius_m: float = Field(
        0.5, gt=0, description="A session saw a place when one of its map points lies this close to it."
    )
    min_patch_points: int = Field(200, ge=1, description="A session's patch needs at least this many points.")
    icp_voxel_sizes_m: list[float] = Field(
        [0.3],
        description="ICP levels aligning the members' local clouds (m); one fine level, since "
        "mapkit align has already brought the sessions within a few decimetres.",
    )
    icp_max_correspondence_m: list[float] = Field([0.6], description="Correspondence distance per ICP level (m).")
    icp_cell_m: float = Field(
        10.0,
        gt=0,
        description="Places are drawn cell by cell (cells of this size, m) with one anchor session per "
        "cell, and one ICP per session and cell serves all of the cell's places. The paper aligns per place; "
        "within 10 m the transform is the same and the export is ten times faster.",
    )
    places_per_cell: int = Field(20, ge=1, description="Places drawn from a cell before moving to the next.")
    lambda_icp_m: float = Field(
        0.40,
        gt=0,
        description="lambda_ICP: a member whose point-to-plane RMSE after ICP exceeds this is rejected "
        "(semi-dense paper, section 4.1; no value given there: mapkit align's default).",
    )
    min_fitness: float = Field(0.3, ge=0, le=1, description="A member whose ICP fitness is below this is rejected.")
    max_members: int = Field(8, ge=2, description="At most this many sessions per place.")
    negative_min_distance_m: float = Field(
        100.0,
        gt=0,
        description='Negatives lie farther than this from the anchor (semi-dense paper, section 4.1: "far away", no '
        "value given; mapkit choice: 100 m, five patch widths).",
    )
    negative_pool: int = Field(2000, ge=10, description="Negative patches drawn per split and shared by its triplets.")
    tile_size_m: float = Field(
        200.0,
        gt=0,
        description="Side of the UTM tiles assigned to train or test (a few blocks of a town; "
        "the buffer strips take less of a larger tile).",
    )
    test_fraction: float = Field(0.25, gt=0, lt=1, description="Fraction of tiles held out for testing.")
    buffer_m: float = Field(
        30.0,
        ge=0,
        description="No keypoint within this distance of a tile of the other split (> a patch's reach, 14 m).",
    )
    shard_patches: int = Field(4096, ge=16, description="Patches per shard file.")
    shard_format: Literal["hdf5", "npz"] = Field(
        "hdf5",
        description="Shard files: HDF5 (patches-NNNNN.h5: datasets occupancy and "
        "density_comparison, chunked by 16 whole grids, gzip level 1, metadata in attributes) "
        "or compressed NumPy (patches-NNNNN.npz, read by np.load alone).",
    )
    icp_relative_change: float = Field(
        1e-4,
        gt=0,
        description="ICP stops when its fitness and RMSE change by less than this "
        "fraction between iterations. open3d's default is 1e-6; measured on a synthetic town's cells, "
        "1e-4 saves a third of the ICP time and moves no registration by more than 0.16 m at 16 m "
        "from the cell centre (99% by less than 0.10 m) nor changes any acceptance decision.",
    )
    pointnetvlad: PointNetVladConfig = Field(
        PointNetVladConfig(),
        description="Also export the dataset in PointNetVLAD's "
        "training layout (mapkit.places.pointnetvlad), from the same patches, positions and split; "
        "a stage of its own after the dataset (not part of its config hash).",
    )
    seed: int = Field(0, description="Seed of every random choice: the same seed and inputs give the same dataset.")
    sessions: list[str] | None = Field(
        None, description="Sessions to use; all merged sessions of the alignment if unset."
    )
    map_source: MapKind = Field(
        "semidense",
        description="Maps the patches are cut from: semidense (align/sessions/<name>/map), or lidar (the aligned LiDAR "
        "maps' voxel centroids; default folder WORKSPACE/triplets-lidar).",
    )

    @field_validator("icp_voxel_sizes_m", "icp_max_correspondence_m")
    @classmethod
    def _icp_level(cls, values: list[float], info: ValidationInfo) -> list[float]:
        """ICP levels, checked before anything is loaded (open3d fails on a voxel <= 0 deep inside the registration)."""
        assert info.field_name is not None  # pydantic names the field of a field validator
        check_levels(values, info.field_name)
        return values

    @model_validator(mode="after")
    def _icp_levels(self) -> TripletConfig:
        if len(self.icp_voxel_sizes_m) != len(self.icp_max_correspondence_m):
            raise ValueError(
                f"{len(self.icp_voxel_sizes_m)} icp_voxel_sizes_m but {len(self.icp_max_correspondence_m)} "
                "icp_max_correspondence_m (one per level)"
            )
        return self


# --- the inputs -------------------------------------------------------------------------------------


class GridIndex:
    """Points bucketed in square cells of the horizontal plane: every point within ``r`` of a
    position is among the points of the cells the disc touches, gathered by slicing (no Python
    list per query, unlike a kd-tree ball query)."""

    def __init__(self, xy: np.ndarray, cell_m: float):
        self.cell = cell_m
        ij = np.floor(xy / cell_m).astype(np.int64)
        self.key = ij[:, 0] * 1_000_003 + ij[:, 1]
        self.order = np.argsort(self.key, kind="stable")
        self.sorted_key = self.key[self.order]

    def candidates(self, centre_xy: np.ndarray, r: float) -> np.ndarray:
        lo = np.floor((centre_xy - r) / self.cell).astype(np.int64)
        hi = np.floor((centre_xy + r) / self.cell).astype(np.int64)
        parts = []
        for i in range(lo[0], hi[0] + 1):
            a = np.searchsorted(self.sorted_key, i * 1_000_003 + lo[1], side="left")
            b = np.searchsorted(self.sorted_key, i * 1_000_003 + hi[1], side="right")
            parts.append(self.order[a:b])
        return np.concatenate(parts) if parts else np.zeros(0, np.int64)

    def candidates_many(self, centres_xy: np.ndarray, r: float) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`candidates` of many centres at once, as CSR ``(indptr, indices)`` (same order)."""
        centres_xy = np.asarray(centres_xy, np.float64).reshape(-1, 2)
        lo = np.floor((centres_xy - r) / self.cell).astype(np.int64)
        hi = np.floor((centres_xy + r) / self.cell).astype(np.int64)
        rows = hi[:, 0] - lo[:, 0] + 1  # cell rows per centre, each one run of sorted keys
        owner = np.repeat(np.arange(len(centres_xy)), rows)
        i = lo[owner, 0] + np.arange(len(owner)) - np.repeat(np.cumsum(rows) - rows, rows)
        a = np.searchsorted(self.sorted_key, i * 1_000_003 + lo[owner, 1], side="left")
        b = np.searchsorted(self.sorted_key, i * 1_000_003 + hi[owner, 1], side="right")
        n = b - a
        total = int(n.sum())
        indices = self.order[np.repeat(a - (np.cumsum(n) - n), n) + np.arange(total)]
        indptr = np.zeros(len(centres_xy) + 1, np.int64)
        np.cumsum(np.bincount(owner, weights=n, minlength=len(centres_xy)).astype(np.int64), out=indptr[1:])
        return indptr, indices

    def disc(self, points: np.ndarray, centre: np.ndarray, r: float) -> np.ndarray:
        """Indices of ``points`` (the points this grid was built over) within horizontal distance
        ``r`` of ``centre``, in grid order."""
        idx = self.candidates(centre[:2], r)
        d = points[idx, :2] - centre[:2]
        return idx[np.einsum("ij,ij->i", d, d) <= r * r]


class SessionPoints:
    """One aligned session: its merged map points, their first observers, and spatial indexes."""

    def __init__(
        self,
        name: str,
        points: np.ndarray,
        observer_pos: np.ndarray,
        observer_frame: np.ndarray,
        keyframe_ids: np.ndarray | None = None,
        keyframe_stamps_ns: np.ndarray | None = None,
    ):
        self.name = name
        self.points = points
        self.observer_pos = observer_pos
        self.observer_frame = observer_frame
        self.keyframe_ids = (
            keyframe_ids  # with keyframe_stamps_ns: the time of each observer frame (PointNetVLAD's file names)
        )
        self.keyframe_stamps_ns = keyframe_stamps_ns
        self.grid = GridIndex(points[:, :2], 5.0)
        self.tree3 = cKDTree(points)
        self._icp_levels: dict[tuple, tuple[np.ndarray, np.ndarray | None, GridIndex]] = {}

    def frame_stamps_ns(self, frames: np.ndarray) -> np.ndarray:
        """Time stamps (ns) of keyframes ``frames`` (ids, as ``observer_frame`` holds them)."""
        if self.keyframe_ids is None or self.keyframe_stamps_ns is None:
            raise InputError(None, f"session {self.name}: no keyframe time stamps loaded")
        frames = np.asarray(frames, np.int64)
        order = np.argsort(self.keyframe_ids, kind="stable")
        pos = np.minimum(np.searchsorted(self.keyframe_ids[order], frames), max(len(order) - 1, 0))
        if len(frames) and (len(order) == 0 or np.any(self.keyframe_ids[order][pos] != frames)):
            raise InputError(
                None,
                f"session {self.name}: frames {sorted(set(frames.tolist()) - set(self.keyframe_ids.tolist()))[:5]} "
                "are not keyframes of its map",
            )
        return np.asarray(self.keyframe_stamps_ns, np.int64)[order][pos]

    def around_indices(self, centre: np.ndarray, r: float) -> np.ndarray:
        """Indices of the points within horizontal distance ``r`` of ``centre``, in grid order."""
        return self.grid.disc(self.points, centre, r)

    def around(self, centre: np.ndarray, r: float) -> np.ndarray:
        """Points within horizontal distance ``r`` of ``centre``."""
        return self.points[self.around_indices(centre, r)]

    def icp_level(
        self, voxel: float, normal_radius: float | None = None, normal_max_nn: int = 30
    ) -> tuple[np.ndarray, np.ndarray | None, GridIndex]:
        """The whole session voxel-downsampled for ICP, its normals (when ``normal_radius`` is
        given) and a grid over it, built once: every cell's registration then crops it instead
        of downsampling and estimating normals again (the normals of a crop's border points
        also see their full neighbourhood)."""
        key = (voxel, normal_radius, normal_max_nn)
        if key not in self._icp_levels:
            import open3d as o3d

            origin = self.points.mean(axis=0)
            pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(self.points - origin)).voxel_down_sample(voxel)
            normals = None
            if normal_radius is not None:
                pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=normal_radius, max_nn=normal_max_nn))
                normals = np.asarray(pc.normals).copy()
            pts = np.asarray(pc.points) + origin
            self._icp_levels[key] = (pts, normals, GridIndex(pts[:, :2], 5.0))
        return self._icp_levels[key]


def load_aligned_sessions(
    workspace: str | Path | Workspace, names: list[str] | None = None, source: MapKind = "semidense"
) -> tuple[list[SessionPoints], LocalFrame]:
    """The merged points of every session (or of ``names``) of a finished ``mapkit align``, and the workspace frame;
    with ``source`` lidar, the merged voxels of the aligned LiDAR maps, their first observers the frames of
    :func:`~mapkit.places.lidar_observations.lidar_observations` (trajectory poses, ids = pose indices)."""

    ws = Workspace(workspace)
    if not ws.align_done.is_file():
        raise InputError(ws.align_dir, "no finished multi-session alignment here (run mapkit align first)")
    frame = ws.require_frame()
    if source == "lidar":
        return _load_aligned_lidar_sessions(ws, names), frame
    for p in sorted(
        ws.tiles_dir.rglob("*")
    ):  # each checked against what align recorded: no truncated cloud is cut into patches
        if p.is_file():
            verify_file(p, "mapkit align")
    _, sid, idx, tile_names = load_tiles(ws.tiles_dir)
    out = []
    for k, name in enumerate(tile_names):
        if names is not None and name not in names:
            continue
        keep = np.sort(idx[sid == k])
        if len(keep) == 0:
            continue
        for f in ("points.ply", "observations.npz"):
            verify_file(ws.aligned(name).map / f, "mapkit align")
        smap = SemiDenseMap.load(ws.aligned(name).map)
        first = first_observer_frames(keep, smap.obs_indptr, smap.obs_frame_ids, smap.keyframe_ids)
        order = np.argsort(smap.keyframe_ids, kind="stable")
        pos = smap.keyframe_world_from_cam[order[np.searchsorted(smap.keyframe_ids[order], first)], :3, 3]
        out.append(SessionPoints(name, smap.points_world[keep], pos, first, smap.keyframe_ids, smap.keyframe_stamps_ns))
    if names is not None:
        missing = sorted(set(names) - {s.name for s in out})
        if missing:
            raise InputError(ws.tiles_dir / "tiles.json", f"sessions {missing} have no merged points", field="sessions")
    if len(out) < 2:
        raise InputError(ws.align_dir, f"{len(out)} session(s) with merged points; triplets need two or more")
    return out, frame


def _load_aligned_lidar_sessions(ws: Workspace, names: list[str] | None = None) -> list[SessionPoints]:
    """The merged voxels of every aligned LiDAR map (or of ``names``: each must have one)."""
    aligned = ws.aligned_sessions()
    if names is not None:
        for n in names:
            ws.session_map(n, source="lidar")  # one error naming a session without a LiDAR map
    wanted = aligned if names is None else [n for n in names if n in aligned]
    out = []
    for name in wanted:
        folder = ws.aligned(name).lidar_map
        if not (folder / "voxels.npz").is_file():
            continue
        for f in (*LIDAR_MAP_FILES, "voxel_submaps.npz"):
            verify_file(folder / f, "mapkit align")
        view = load_lidar_observations(folder, ws.map_trajectory(name, "align"))
        with np.load(folder / "voxel_submaps.npz") as z:
            keep = np.flatnonzero(z["merged"])
        if len(keep) == 0:
            continue
        first = first_observer_frames(keep, view.obs_indptr, view.obs_frame_ids, view.keyframe_ids)
        pos = view.keyframe_world_from_cam[np.searchsorted(view.keyframe_ids, first), :3, 3]
        out.append(SessionPoints(name, view.points_world[keep], pos, first, view.keyframe_ids, view.keyframe_stamps_ns))
    if names is not None:
        missing = sorted(set(names) - {s.name for s in out})
        if missing:
            raise InputError(ws.align_dir, f"sessions {missing} have no merged LiDAR voxels", field="sessions")
    if len(out) < 2:
        raise InputError(
            ws.align_dir,
            f"{len(out)} session(s) with an aligned LiDAR map ({[s.name for s in out]} of the aligned {aligned}); "
            "LiDAR triplets need two or more",
            field="map_source",
        )
    return out


# --- the spatial split ------------------------------------------------------------------------------


def tile_split(utm_xy: np.ndarray, tile_m: float, test_fraction: float, seed: int) -> dict[tuple[int, int], str]:
    """Every tile touched by ``utm_xy`` labelled train or test, at random but reproducibly: tiles
    are taken in random order into the test split until it holds ``test_fraction`` of the points
    (so the test split gets its share of the mapped places, not of empty tiles); at least one
    tile stays in each split when there are two or more."""
    key_rows, counts = np.unique(np.floor(utm_xy / tile_m).astype(np.int64), axis=0, return_counts=True)
    keys = [(int(k[0]), int(k[1])) for k in key_rows]
    rng = np.random.default_rng(seed)
    labels = {k: "train" for k in keys}
    if len(keys) < 2:
        return labels
    total, taken = counts.sum(), 0
    for i in rng.permutation(len(keys)):
        if taken >= test_fraction * total or sum(v == "test" for v in labels.values()) == len(keys) - 1:
            break
        if taken and taken + counts[i] > 1.5 * test_fraction * total:
            continue  # a tile that would overshoot by far: try a smaller one
        labels[keys[i]] = "test"
        taken += counts[i]
    return labels


def tiles_to_manifest(tiles: dict[tuple[int, int], str], tile_m: float) -> list[dict]:
    """The tiles as a dataset's manifest lists them: each tile's south-west UTM corner and its split."""
    return [{"utm_min": [k[0] * tile_m, k[1] * tile_m], "split": v} for k, v in sorted(tiles.items())]


def tiles_from_manifest(entries: list[dict], tile_m: float) -> dict[tuple[int, int], str]:
    """The inverse of :func:`tiles_to_manifest`; ``ValueError`` naming the first entry that is not
    a ``tile_m`` tile labelled train or test."""
    tiles = {}
    for e in entries:
        corner = np.asarray(e["utm_min"], np.float64)
        key = np.round(corner / tile_m).astype(np.int64)
        if np.any(np.abs(key * tile_m - corner) > 1e-6 * max(tile_m, 1.0)) or e.get("split") not in ("train", "test"):
            raise ValueError(f"tile {e} is not a {tile_m:g} m tile labelled train or test")
        tiles[(int(key[0]), int(key[1]))] = e["split"]
    return tiles


def split_of(utm_xy: np.ndarray, tiles: dict[tuple[int, int], str], tile_m: float, buffer_m: float) -> np.ndarray:
    """Per point: "train", "test", or "" when within ``buffer_m`` of a tile of the other split."""
    ij = np.floor(utm_xy / tile_m).astype(np.int64)
    uniq, inv = np.unique(ij.reshape(-1, 2), axis=0, return_inverse=True)
    inv = inv.ravel()
    code = {"train": 1, "test": 2}

    def label(di: int, dj: int, missing: int) -> np.ndarray:
        """Per point, the code of a neighbouring tile (looked up per tile)."""
        return np.array([code.get(tiles.get((int(a) + di, int(b) + dj), ""), missing) for a, b in uniq], np.int8)[inv]

    own = label(0, 0, 1)  # a tile without a label is a training tile
    u = utm_xy - ij * tile_m  # position inside the tile, [0, tile_m)
    dmin = np.full(len(utm_xy), np.inf)
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            if di == dj == 0:
                continue
            other = label(di, dj, 0)
            differs = (other != 0) & (other != own)
            dx = np.where(di < 0, u[:, 0], np.where(di > 0, tile_m - u[:, 0], 0.0))
            dy = np.where(dj < 0, u[:, 1], np.where(dj > 0, tile_m - u[:, 1], 0.0))
            d = np.hypot(dx, dy)
            dmin = np.where(differs, np.minimum(dmin, d), dmin)
    return np.where(dmin < buffer_m, "", np.where(own == 2, "test", "train")).astype(object)


# --- patches ------------------------------------------------------------------------------------------


def place_chunks(
    kp_session, kp_index, kp_split, sessions, cfg: TripletConfig, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Every usable keypoint, in the order places are drawn, and per place the number of its chunk.

    Places are drawn in rounds over the cells (in random order), each round taking the next
    ``places_per_cell`` keypoints of each cell, one anchor session at a time (so a cell's ICPs
    serve many places); a chunk is the up to ``places_per_cell`` consecutive places of one cell
    that one round takes (their patches are made together)."""
    valid = np.flatnonzero(kp_split != "")
    if len(valid) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    pos = np.empty((len(valid), 2))
    for si, sp in enumerate(sessions):
        mine = kp_session[valid] == si
        pos[mine] = sp.points[kp_index[valid][mine], :2]
    _, cell_id = np.unique(np.floor(pos / cfg.icp_cell_m).astype(np.int64), axis=0, return_inverse=True)
    cell_id = cell_id.ravel()
    chunks_per_cell = []
    for c in rng.permutation(int(cell_id.max()) + 1):
        members = valid[cell_id == c]
        ordered = np.concatenate(
            [
                rng.permutation(members[kp_session[members] == a])
                for a in rng.permutation(np.unique(kp_session[members]))
            ]
        )
        chunks_per_cell.append(
            [ordered[k : k + cfg.places_per_cell] for k in range(0, len(ordered), cfg.places_per_cell)]
        )
    rounds = max(len(ch) for ch in chunks_per_cell)
    chunks = [ch[r] for r in range(rounds) for ch in chunks_per_cell if r < len(ch)]
    return np.concatenate(chunks), np.repeat(np.arange(len(chunks)), [len(c) for c in chunks])


def make_patches(clouds: list[np.ndarray], centres: np.ndarray, observers: np.ndarray, cfg: TripletConfig):
    """Occupancy and density-comparison grids (bits packed) and yaws of one patch per cloud.

    ``clouds[k]`` holds the points around ``centres[k]``; ``observers[k]`` is the first observer
    of the keypoint in that cloud's session (the sign of the yaw).
    """
    d = cfg.domain
    idx = []
    offs = np.cumsum([0] + [len(c) for c in clouds])
    for k, c in enumerate(clouds):
        rel = c - centres[k]
        keep = (np.hypot(rel[:, 0], rel[:, 1]) <= d.patch_radius) & (np.abs(rel[:, 2]) <= d.patch_half_height)
        idx.append(np.flatnonzero(keep) + offs[k])
    counts = np.array([len(i) for i in idx], np.int64)
    points = np.concatenate(clouds)[np.concatenate(idx)] if clouds else np.zeros((0, 3))
    return make_patches_csr(points, np.concatenate([[0], np.cumsum(counts)]), centres, observers, cfg)


def make_patches_csr(
    points: np.ndarray, indptr: np.ndarray, centres: np.ndarray, observers: np.ndarray, cfg: TripletConfig
):
    """:func:`make_patches` of patches already cut: the points of patch ``k`` (in the patch
    domain about ``centres[k]``) are ``points[indptr[k]:indptr[k + 1]]``."""
    indptr = np.asarray(indptr, np.int64)
    counts = np.diff(indptr)
    centres = np.asarray(centres, np.float64).reshape(-1, 3)
    local = points - np.repeat(centres, counts, axis=0)
    yaw, normalised = yaw_normalise_patches(
        local, indptr, np.asarray(observers, np.float64).reshape(-1, 3)[:, :2] - centres[:, :2]
    )
    occ, dcg = voxelise_patches(normalised, indptr, cfg.domain, cfg.grid, packed=True)
    return occ, dcg, yaw, counts


def register_cell(
    source: SessionPoints,
    target: SessionPoints,
    centre: np.ndarray,
    reach: float,
    icp: IcpConfig,
    relative_change: float,
) -> Registration:
    """Point-to-plane ICP of ``source``'s points within ``reach`` (horizontally) of ``centre`` onto
    ``target``'s: :func:`mapkit.mapping.icp.icp_coarse_to_fine`, the loop of
    :func:`~mapkit.multisession.registration.register_clouds` (same levels, normals, correspondence
    distances), on crops of the sessions' cached downsampled clouds (:meth:`SessionPoints.icp_level`);
    fitness and point-to-plane RMSE at ``icp.eval_distance_m`` of the fine level, scored as
    :func:`~mapkit.multisession.registration.evaluate_alignment` scores (no structure-only figures).
    ``relative_change``: ICP stops when fitness and RMSE change by less than this (open3d's criteria)."""

    def level(voxel: float) -> IcpClouds | None:
        sp, _, sg = source.icp_level(voxel)
        tp, tn, tg = target.icp_level(voxel, icp.normal_radius_factor * voxel, icp.normal_max_nn)
        si, ti = sg.disc(sp, centre, reach), tg.disc(tp, centre, reach)
        if len(si) < 10 or len(ti) < 10:
            return None
        assert tn is not None  # asked for with a normal radius
        return IcpClouds(sp[si] - centre, tp[ti] - centre, tn[ti])  # centre-relative: rotations pivot about the cell

    T, clouds = icp_coarse_to_fine(
        level, icp.voxel_sizes_m, icp.max_correspondence_m, icp.max_iterations, relative_change
    )
    if clouds is None:
        return Registration.failed()
    ev = evaluate_alignment(
        clouds.source, clouds.target, T, icp.voxel_sizes_m[-1], icp, clouds.target_normals, structure=False
    )
    if ev["fitness"] == 0.0:  # no correspondence: no fit
        return Registration.failed()
    return Registration(about_centre(T, centre), **ev)


@dataclass
class _CellClouds:
    """The points of each candidate member session about a cell: ``index[si]``, indices into
    session si's points, and ``local[si]`` (rows, n) bool, the mask of those within the crop
    radius of each place that session is a candidate for (place k in row ``row_of[si][k]``): the
    place's local cloud ``around(p, crop)`` in that session, of ``n_local[si]`` points per row."""

    index: dict[int, np.ndarray]
    local: dict[int, np.ndarray]
    row_of: dict[int, dict[int, int]]
    n_local: dict[int, np.ndarray]


class ChunkSets:
    """The correspondence sets of one chunk of places (one cell), made together.

    For place ``j`` of the chunk, :meth:`get` gives the members that passed the checks of
    section 4.1 (seen within ``seen_radius_m``, enough points, ICP fitness and RMSE) and their
    grids, or ``None`` with the number of members ICP rejected. Each session's points about the
    cell are fetched and moved by their ICP transform once, every place's patch is cut from them
    by one vectorised mask, and all patches go through yaw normalisation and voxelisation in one
    batch; the patches are those :func:`make_patches` cuts from each member's local cloud.
    """

    def __init__(
        self,
        places: np.ndarray,
        sessions: list[SessionPoints],
        kp_session: np.ndarray,
        kp_index: np.ndarray,
        cfg: TripletConfig,
        icp_of: Callable[..., Registration],
    ):
        crop = cfg.domain.patch_radius + 2.0
        P = np.array([sessions[kp_session[j]].points[kp_index[j]] for j in places]).reshape(-1, 3)
        anchors = kp_session[places]
        cell = np.floor(P[0, :2] / cfg.icp_cell_m)
        centre = np.array([*((cell + 0.5) * cfg.icp_cell_m), P[0, 2]])
        reach = crop + 0.71 * cfg.icp_cell_m  # every place of the cell lies within 0.71 cells of its centre
        nearest, cand = _member_candidates(P, anchors, kp_index[places], sessions, cfg)
        clouds = _cell_clouds(cand, P, sessions, centre, reach, crop)
        self.n_icp = 0
        self.result: dict[int, dict | None] = {}
        self.rejected: dict[int, int] = {}
        members: dict[int, list] = {}
        transforms: dict[tuple[int, int], np.ndarray] = {}
        for k, j in enumerate(places):
            a, rejected, mem = int(anchors[k]), 0, []
            for si in cand[k]:
                if clouds.n_local[si][clouds.row_of[si][k]] < cfg.min_patch_points:
                    continue
                if si == a:
                    T, rmse = np.eye(4), 0.0
                else:
                    r = icp_of(si, a, centre, reach, len(clouds.index[si]), len(clouds.index.get(a, ())))
                    if r.fitness < cfg.min_fitness or not r.rmse_m <= cfg.lambda_icp_m:
                        rejected += 1
                        continue
                    T, rmse = r.target_from_source, r.rmse_m
                transforms[(si, a)] = T
                mem.append((si, int(nearest[k, si]), T, rmse))
            self.rejected[int(j)] = rejected
            if len(mem) < 2 or mem[0][0] != a:
                self.result[int(j)] = None
            else:
                members[k] = mem
        slot_of: dict[tuple[int, int], int] = {}
        for k in sorted(members):
            for si, _, _, _ in members[k]:
                slot_of[(k, si)] = len(slot_of)
        if slot_of:
            self.occ, self.dcg, self.yaw, self.npts = _member_patches(
                P, anchors, members, transforms, slot_of, clouds, sessions, cfg
            )
        for k, mem in members.items():
            slots = np.array([slot_of[(k, m[0])] for m in mem])
            self.result[int(places[k])] = {
                "slots": slots,
                "session": np.array([m[0] for m in mem]),
                "frame": np.array([sessions[m[0]].observer_frame[m[1]] for m in mem]),
                "centre": np.repeat(P[k][None], len(mem), axis=0),
                "rmse": np.array([m[3] for m in mem]),
                "transform": np.array([m[2] for m in mem]),
            }

    def get(self, j: int):
        """(place's member data with its grids, or None; members rejected by ICP) of place ``j``."""
        res = self.result[int(j)]
        if res is not None:
            sl = res["slots"]
            res = {**res, "occ": self.occ[sl], "dcg": self.dcg[sl], "yaw": self.yaw[sl], "points": self.npts[sl]}
        return res, self.rejected[int(j)]


def _member_candidates(
    P: np.ndarray, anchors: np.ndarray, anchor_index: np.ndarray, sessions: list[SessionPoints], cfg: TripletConfig
) -> tuple[np.ndarray, list[list[int]]]:
    """Per place (keypoint ``P[k]`` of session ``anchors[k]``, its point ``anchor_index[k]``): the
    nearest point of each session within ``seen_radius_m`` (K, sessions; -1 where none, the
    keypoint itself for the anchor), and the candidate members: the anchor, then every session
    that has such a point, in session order, at most ``max_members``."""
    K = len(P)
    nearest = np.full((K, len(sessions)), -1, np.int64)
    for si, s in enumerate(sessions):
        dist, nn = s.tree3.query(P, distance_upper_bound=cfg.seen_radius_m)
        nearest[:, si] = np.where(np.isfinite(dist) & (anchors != si), nn, -1)
    nearest[np.arange(K), anchors] = anchor_index
    cand = [[int(a)] + [int(si) for si in np.flatnonzero(nearest[k] >= 0) if si != a] for k, a in enumerate(anchors)]
    return nearest, [c[: cfg.max_members] for c in cand]


def _cell_clouds(
    cand: list[list[int]], P: np.ndarray, sessions: list[SessionPoints], centre: np.ndarray, reach: float, crop: float
) -> _CellClouds:
    """Each candidate session's points within ``reach`` of the cell ``centre`` and, per place it
    is a candidate for, which of them lie within ``crop`` of the place (horizontally)."""
    cloud_idx, raw_in, row_of = {}, {}, {}
    for si in sorted({si for c in cand for si in c}):
        rows = [k for k in range(len(P)) if si in cand[k]]
        row_of[si] = {k: r for r, k in enumerate(rows)}
        cloud_idx[si] = sessions[si].around_indices(centre, reach)
        xy = sessions[si].points[cloud_idx[si], :2]
        dx, dy = xy[None, :, 0] - P[rows, None, 0], xy[None, :, 1] - P[rows, None, 1]
        raw_in[si] = dx * dx + dy * dy <= crop * crop  # (rows, n): the local cloud ``around(p, crop)`` of each place
    return _CellClouds(cloud_idx, raw_in, row_of, {si: m.sum(axis=1) for si, m in raw_in.items()})


def _member_patches(
    P: np.ndarray,
    anchors: np.ndarray,
    members: dict[int, list],
    transforms: dict[tuple[int, int], np.ndarray],
    slot_of: dict[tuple[int, int], int],
    clouds: _CellClouds,
    sessions: list[SessionPoints],
    cfg: TripletConfig,
):
    """The grids of every member's patch (:func:`make_patches_csr`), patch ``slot_of[(k, si)]``
    being member si of place k: per session and transform, its points about the cell are moved
    once and one mask over (places, points) cuts every place's patch."""
    d = cfg.domain
    parts_slot, parts_pts = [], []
    for (si, a), T in transforms.items():
        rows = [k for k in sorted(members) if anchors[k] == a and (k, si) in slot_of]
        if not rows:
            continue
        moved = sessions[si].points[clouds.index[si]] @ T[:3, :3].T + T[:3, 3]
        local = clouds.local[si][[clouds.row_of[si][k] for k in rows]]  # each place's local cloud, place by place
        r_i, p_i = np.nonzero(local)
        pts = moved[p_i]
        rel = pts - P[rows][r_i]
        keep = (np.hypot(rel[:, 0], rel[:, 1]) <= d.patch_radius) & (np.abs(rel[:, 2]) <= d.patch_half_height)
        parts_slot.append(np.array([slot_of[(k, si)] for k in rows], np.int64)[r_i[keep]])
        parts_pts.append(pts[keep])
    n_slots = len(slot_of)
    slot = np.concatenate(parts_slot)
    order = np.argsort(slot, kind="stable")
    indptr = np.concatenate([[0], np.cumsum(np.bincount(slot, minlength=n_slots))])
    centres = np.empty((n_slots, 3))
    obs = np.empty((n_slots, 3))
    for (k, si), sl in slot_of.items():
        _, pi, T, _ = next(m for m in members[k] if m[0] == si)
        centres[sl] = P[k]
        obs[sl] = T[:3, :3] @ sessions[si].observer_pos[pi] + T[:3, 3]
    return make_patches_csr(np.concatenate(parts_pts)[order], indptr, centres, obs, cfg)


def mapped_patches(
    sessions: list[SessionPoints], sess: np.ndarray, centres: np.ndarray, domain: PatchDomain
) -> tuple[np.ndarray, np.ndarray]:
    """Each keypoint's patch as its session mapped it (no ICP), as CSR ``(points, indptr)``: the
    points that :func:`make_patches` keeps of the keypoint's local cloud (the disc of the patch
    radius), in the same order. Batched per session."""
    sess = np.asarray(sess)
    centres = np.asarray(centres, np.float64).reshape(-1, 3)
    r = domain.patch_radius
    pts_of: list[np.ndarray | None] = [None] * len(centres)
    counts = np.zeros(len(centres), np.int64)
    blocks = [
        (si, k[b : b + 64])
        for si in np.unique(sess)
        for k in [np.flatnonzero(sess == si)]
        for b in range(0, len(k), 64)
    ]
    for si, k in blocks:  # 64 patches at a time bound the candidates' memory
        s = sessions[si]
        indptr, idx = s.grid.candidates_many(centres[k, :2], r)
        pts = s.points[idx]
        rel = pts - np.repeat(centres[k], np.diff(indptr), axis=0)
        keep = np.einsum("ij,ij->i", rel[:, :2], rel[:, :2]) <= r * r  # the local cloud, as SessionPoints.around
        keep &= np.hypot(rel[:, 0], rel[:, 1]) <= r  # and the patch, as make_patches
        keep &= np.abs(rel[:, 2]) <= domain.patch_half_height
        owner = np.repeat(np.arange(len(k)), np.diff(indptr))[keep]
        n = np.bincount(owner, minlength=len(k))
        kept = pts[keep]
        bounds = np.concatenate([[0], np.cumsum(n)])
        for m, kk in enumerate(k):
            pts_of[kk] = kept[bounds[m] : bounds[m + 1]]
            counts[kk] = n[m]
    indptr = np.concatenate([[0], np.cumsum(counts)])
    patches = [p for p in pts_of if p is not None]
    assert len(patches) == len(pts_of)  # every centre is in one session's blocks
    return (np.concatenate(patches) if len(centres) else np.zeros((0, 3))), indptr


class ShardWriter:
    """Patches go to ``patches-NNNNN.h5`` (or ``.npz``) files of ``size`` patches (bits packed,
    compressed); :attr:`shards` lists them as the manifest does (file, first id, patches, bytes,
    sha256)."""

    def __init__(self, folder: Path, size: int, fmt: str = "hdf5", grid: int | None = None):
        if fmt not in SHARD_FORMATS:
            raise ValueError(f"shard format {fmt!r}: expected one of {SHARD_FORMATS}")
        self.folder, self.size, self.format, self.grid = folder, size, fmt, grid
        self.buf_occ: list[np.ndarray] = []
        self.buf_dcg: list[np.ndarray] = []
        self.n = self.buffered = 0
        self.shards: list[dict] = []

    def add(self, occ: np.ndarray, dcg: np.ndarray) -> np.ndarray:
        ids = np.arange(self.n, self.n + len(occ))
        self.buf_occ.append(occ)
        self.buf_dcg.append(dcg)
        self.n += len(occ)
        self.buffered += len(occ)
        if self.buffered >= self.size:
            self.flush()
        return ids

    def flush(self) -> None:
        if not self.buf_occ:
            return
        occ, dcg = np.concatenate(self.buf_occ), np.concatenate(self.buf_dcg)
        first = self.n - len(occ)
        while len(occ):
            take = min(self.size, len(occ))
            name = f"patches-{len(self.shards):05d}{SHARD_SUFFIX[self.format]}"
            with atomic_path(self.folder / name) as tmp:
                if self.format == "hdf5":
                    write_shard_hdf5(
                        tmp, occ[:take], dcg[:take], first, self.grid if self.grid is not None else occ.shape[1]
                    )
                else:
                    _savez_fast(tmp, occupancy=occ[:take], density_comparison=dcg[:take], first_id=np.int64(first))
            path = self.folder / name
            self.shards.append(
                {
                    "file": name,
                    "first_id": int(first),
                    "patches": int(take),
                    "bytes": path.stat().st_size,
                    "sha256": sha256_file(path),
                }
            )
            occ, dcg, first = occ[take:], dcg[take:], first + take
        self.buf_occ, self.buf_dcg, self.buffered = [], [], 0


def write_shard_hdf5(path: Path, occ: np.ndarray, dcg: np.ndarray, first_id: int, grid: int) -> None:
    """One HDF5 shard: datasets ``occupancy`` (n, g, g, ceil(g/8)) and ``density_comparison``
    (n, 3, g, g, ceil(g/8)), uint8 with the bits of the last axis packed (``np.packbits``, big
    bit order), chunked by whole grids (16 patches a chunk, so reading one patch inflates at most
    64 KB / 192 KB) and deflated at level 1 (gzip: any HDF5 reader has it; the packed grids
    compress about as well as at level 9, several times faster). Attributes name the layout.

    The file is made in memory and written in one Python write: HDF5 that meets a full disk cannot
    close its file, and the half-closed handle crashed the interpreter at exit; this way a full disk is
    one ``OSError`` like any other write's."""
    import io

    import h5py

    n = len(occ)
    image = io.BytesIO()
    with h5py.File(image, "w", track_order=True) as f:
        f.attrs.update(
            {
                "format": "mapkit triplet patches",
                "format_version": TRIPLETS_FORMAT_VERSION,
                "first_id": int(first_id),
                "patches": int(n),
                "grid": int(grid),
                "packing": "bits of the last axis packed, np.packbits (big bit order)",
                "ids": "patch id = first_id + row",
            }
        )
        for name, a, what in (
            ("occupancy", occ, "(n, g, g, ceil(g/8)) occupancy grids"),
            ("density_comparison", dcg, "(n, 3, g, g, ceil(g/8)); channel a = density above the +a neighbour's"),
        ):
            a = np.ascontiguousarray(a, np.uint8)
            chunks = (max(1, min(SHARD_CHUNK_PATCHES, n)),) + a.shape[1:] if n else None
            ds = f.create_dataset(
                name, data=a, chunks=chunks, compression="gzip" if n else None, compression_opts=1 if n else None
            )
            ds.attrs.update({"layout": what, "grid": int(grid), "unpack": "np.unpackbits(x, axis=-1, count=grid)"})
    Path(path).write_bytes(image.getbuffer())


def read_shard(path: str | Path, fmt: str | None = None) -> dict[str, np.ndarray]:
    """The packed grids of one shard, HDF5 or npz (``fmt``, else by the file's suffix):
    ``{"occupancy", "density_comparison", "first_id"}``. Training code reading a dataset goes
    through :class:`TripletDataset` (or this) and so reads either format."""
    path = Path(path)
    fmt = fmt or ("npz" if path.suffix == ".npz" else "hdf5")
    try:
        if fmt == "hdf5":
            import h5py

            with h5py.File(path, "r") as f:
                return {
                    "occupancy": f["occupancy"][()],
                    "density_comparison": f["density_comparison"][()],
                    "first_id": np.int64(f.attrs["first_id"]),
                }
        with np.load(path, allow_pickle=False) as z:
            return {
                "occupancy": z["occupancy"],
                "density_comparison": z["density_comparison"],
                "first_id": np.int64(z["first_id"]),
            }
    except (OSError, KeyError, ValueError) as exc:
        raise InputError(path, f"unreadable {fmt} shard ({type(exc).__name__}: {exc})") from None


def _savez_fast(path: Path, **arrays: np.ndarray) -> None:
    """An ``.npz`` (readable by ``np.load``) deflated at level 1: the packed grids compress about
    as well as at the default level, five times faster."""
    import zipfile

    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
        for name, a in arrays.items():
            with zf.open(f"{name}.npy", "w", force_zip64=True) as f:
                np.lib.format.write_array(f, np.asanyarray(a), allow_pickle=False)


# --- the export ---------------------------------------------------------------------------------------


@writes_workspace("workspace")
def export_triplets(
    workspace: str | Path,
    out: str | Path | None = None,
    config: str | Path | None = None,
    overrides: dict | None = None,
    progress: bool = True,
) -> Path:
    """Export a triplet dataset from an aligned workspace; returns its folder (default
    ``WORKSPACE/triplets``). Re-running with the same config and inputs does nothing. An export
    that would make no triplet raises :class:`NoTripletsError` and leaves any earlier dataset in
    place. The config's ``pointnetvlad`` section is not acted on here: ``mapkit triplets`` runs
    :func:`mapkit.places.pointnetvlad.export_triplets_pointnetvlad`, which calls this and then the export."""
    ws = Workspace(workspace)
    cfg = load_config(TripletConfig, config, overrides)
    out = Path(out) if out is not None else ws.triplets_folder(cfg.map_source)
    # the PointNetVLAD layout is a stage of its own (mapkit.places.pointnetvlad): its settings do not change the
    # dataset; map_source enters only when not the default (datasets made before the option stay valid); the
    # alignment as its downstream stages know it (the older hash of a migrated marker)
    exclude = {"pointnetvlad"} | ({"map_source"} if cfg.map_source == "semidense" else set())
    identity = {"cfg": cfg.model_dump(mode="json", exclude=exclude), "align": marker_hash(ws.align_record())}
    h = stage_hash("triplets", STAGE_VERSION, identity)
    inputs = {"align": stage_digest(ws.align_dir)}  # a re-made alignment (other maps, same config) makes a new dataset
    if is_done(out, h, inputs=inputs, legacy_hash=config_hash(identity), version=STAGE_VERSION):
        return out
    t0 = time.perf_counter()
    sessions, frame = load_aligned_sessions(ws, cfg.sessions, cfg.map_source)
    final = out
    with building(final) as out:  # a partial folder, renamed into place last: an earlier dataset survives a failure
        atomic_write_text(out / "config.yaml", dump_config(cfg))
        rng = np.random.default_rng(
            cfg.seed
        )  # drawn from in this order: keypoints, negatives, places, each triplet's negative
        kp = _Keypoints.draw(sessions, frame, cfg, rng)
        shards = ShardWriter(out, cfg.shard_patches, cfg.shard_format, cfg.grid)
        table = _PatchTable()
        pools = _negative_pools(sessions, kp, cfg, rng, shards, table)
        if not any(len(ids) for ids, _ in pools.values()):  # no negatives: no place could give a triplet
            raise NoTripletsError(ws.align_dir, _no_triplets_reason(cfg, kp.split, pools, _Counts()))
        places = _Places(sessions, kp, pools, cfg, rng, shards, table)
        places.make_triplets(progress)
        if (
            places.counts.triplets == 0
        ):  # raised inside the partial folder: nothing is renamed into place or marked done
            raise NoTripletsError(ws.align_dir, _no_triplets_reason(cfg, kp.split, pools, places.counts))
        shards.flush()
        log.info(
            "%d triplets from %d places (%d tried, %d ICP registrations)",
            places.counts.triplets,
            places.counts.sets,
            places.counts.tried,
            places.counts.icp,
        )
        _write_dataset(out, ws, h, cfg, sessions, frame, kp.tiles, shards, table, places, t0)
        mark_done(out, h, version=STAGE_VERSION, inputs=inputs)
    return final


@dataclass
class _Keypoints:
    """The drawn keypoints (a random ``keypoint_fraction`` of every session's points) and their split."""

    tiles: dict[tuple[int, int], str]  # UTM tile -> split
    session: np.ndarray  # (K,) session of each keypoint
    index: np.ndarray  # (K,) its point in the session
    split: np.ndarray  # (K,) "train", "test" or "" (in a buffer strip)

    @classmethod
    def draw(
        cls, sessions: list[SessionPoints], frame: LocalFrame, cfg: TripletConfig, rng: np.random.Generator
    ) -> _Keypoints:
        all_utm = np.concatenate(
            [frame.enu_to_utm(s.points[:: max(1, len(s.points) // 20000)])[:, :2] for s in sessions]
        )
        tiles = tile_split(all_utm, cfg.tile_size_m, cfg.test_fraction, cfg.seed)
        kp_session, kp_index, kp_split = [], [], []
        for si, s in enumerate(sessions):
            k = np.sort(
                rng.choice(len(s.points), max(1, int(round(cfg.keypoint_fraction * len(s.points)))), replace=False)
            )
            kp_session.append(np.full(len(k), si))
            kp_index.append(k)
            kp_split.append(split_of(frame.enu_to_utm(s.points[k])[:, :2], tiles, cfg.tile_size_m, cfg.buffer_m))
        return cls(tiles, np.concatenate(kp_session), np.concatenate(kp_index), np.concatenate(kp_split))


class _PatchTable:
    """The per-patch table (patches.npz, patches.csv), filled as patches are made."""

    COLUMNS = (
        "patch_id",
        "set_id",
        "split",
        "role",
        "session",
        "frame",
        "enu",
        "yaw",
        "points",
        "icp_rmse_m",
        "transform",
    )

    def __init__(self) -> None:
        self.columns: dict[str, list] = {k: [] for k in self.COLUMNS}

    def record(self, ids, set_id, split, role, sess, frames, enu, yaw, npts, rmse, T) -> None:
        c = self.columns
        c["patch_id"].append(ids)
        c["set_id"].append(np.full(len(ids), set_id))
        c["split"].append(np.full(len(ids), split, dtype=object))
        c["role"].append(np.full(len(ids), role, dtype=object))
        c["session"].append(np.asarray(sess))
        c["frame"].append(np.asarray(frames))
        c["enu"].append(np.asarray(enu))
        c["yaw"].append(np.asarray(yaw))
        c["points"].append(np.asarray(npts))
        c["icp_rmse_m"].append(np.asarray(rmse))
        c["transform"].append(np.asarray(T))

    def arrays(self) -> dict[str, np.ndarray]:
        """Every column as one array, rows in patch id order."""
        tab = {k: np.concatenate(v) if v else np.zeros(0) for k, v in self.columns.items()}
        order = np.argsort(tab["patch_id"])
        return {k: v[order] for k, v in tab.items()}


def _negative_pools(
    sessions: list[SessionPoints],
    kp: _Keypoints,
    cfg: TripletConfig,
    rng: np.random.Generator,
    shards: ShardWriter,
    table: _PatchTable,
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per split, (patch ids, centres) of random keypoints' patches as mapped (no ICP needed), shared by its
    triplets."""
    pools = {}
    for split in SPLITS:
        cand = np.flatnonzero(kp.split == split)
        if len(cand) == 0:
            continue
        pick = rng.choice(cand, min(cfg.negative_pool, len(cand)), replace=False)
        centres = np.array([sessions[kp.session[j]].points[kp.index[j]] for j in pick])
        obs = np.array([sessions[kp.session[j]].observer_pos[kp.index[j]] for j in pick])
        sess = kp.session[pick]
        frames = np.array([sessions[kp.session[j]].observer_frame[kp.index[j]] for j in pick])
        occ, dcg, yaw, npts = make_patches_csr(*mapped_patches(sessions, sess, centres, cfg.domain), centres, obs, cfg)
        ok = npts >= cfg.min_patch_points
        ids = shards.add(occ[ok], dcg[ok])
        table.record(
            ids,
            -1,
            split,
            "negative",
            sess[ok],
            frames[ok],
            centres[ok],
            yaw[ok],
            npts[ok],
            np.zeros(ok.sum()),
            np.repeat(np.eye(4)[None], ok.sum(), axis=0),
        )
        pools[split] = (ids, centres[ok])
    return pools


@dataclass
class _Counts:
    """What the export did: places tried, correspondence sets kept, members ICP rejected, ICPs run,
    triplets made, and the places that gave no triplet, by reason."""

    tried: int = 0
    sets: int = 0
    rejected_members: int = 0
    icp: int = 0
    triplets: int = 0
    why: dict[str, int] = field(default_factory=lambda: {"no_set": 0, "small_patches": 0, "no_far_negative": 0})


class _Places:
    """The places in the order they are drawn (:func:`place_chunks`), their correspondence sets
    made a chunk (one cell's places of a round) at a time, and the triplets of each."""

    def __init__(
        self,
        sessions: list[SessionPoints],
        kp: _Keypoints,
        pools: dict,
        cfg: TripletConfig,
        rng: np.random.Generator,
        shards: ShardWriter,
        table: _PatchTable,
    ):
        self.sessions, self.kp, self.pools, self.cfg, self.rng, self.shards, self.table = (
            sessions,
            kp,
            pools,
            cfg,
            rng,
            shards,
            table,
        )
        self.icp = IcpConfig(
            voxel_sizes_m=cfg.icp_voxel_sizes_m,
            max_correspondence_m=cfg.icp_max_correspondence_m,
            max_iterations=20,
            lambda_icp_m=cfg.lambda_icp_m,
            min_fitness=cfg.min_fitness,
            min_structure_fitness=0.0,
        )
        self.order, self.chunk_of = place_chunks(kp.session, kp.index, kp.split, sessions, cfg, rng)
        self.used = np.zeros(len(self.order), bool)
        self.counts = _Counts()
        self.triplets: dict[str, list] = {s: [] for s in SPLITS}
        # each split gets its share (test_fraction of the triplets to test); what a split cannot fill
        # (too few places seen by two sessions) goes to the other in a second pass
        self.quota = {"test": int(round(cfg.test_fraction * cfg.n_triplets))}
        self.quota["train"] = cfg.n_triplets - self.quota["test"]
        self._icp_cache: dict[tuple, Registration] = {}
        self._chunk = -1
        self._sets: ChunkSets | None = None

    def make_triplets(self, progress: bool) -> None:
        """Places in order until ``n_triplets`` are made: first each split up to its quota, then any."""
        cfg, made = self.cfg, {"train": 0, "test": 0}
        bar = progress_bar(cfg.n_triplets, progress, "triplets", "triplet")
        try:
            for pass_no in (0, 1):
                for pos, j in enumerate(self.order):
                    if self.counts.triplets >= cfg.n_triplets:
                        break
                    if self.used[pos]:
                        continue
                    split = self.kp.split[j]
                    if split not in self.pools or (pass_no == 0 and made[split] >= self.quota[split]):
                        continue
                    self.used[pos] = True
                    n_new = self._one_place(pos, split)
                    made[split] += n_new
                    self.counts.triplets += n_new
                    if n_new:
                        bar.update(n_new)
                        bar.set_postfix_str(f"{self.counts.sets} places", refresh=False)
        finally:
            bar.close()

    def icp_of(self, si: int, a: int, centre: np.ndarray, reach: float, n_src: int, n_tgt: int) -> Registration:
        """One ICP per session, anchor session and cell, shared by all the cell's places."""
        cfg = self.cfg
        key = (si, a, *np.floor(centre[:2] / cfg.icp_cell_m).astype(int).tolist())
        if key not in self._icp_cache:
            ok = min(n_src, n_tgt) >= cfg.min_patch_points
            self._icp_cache[key] = (
                register_cell(self.sessions[si], self.sessions[a], centre, reach, self.icp, cfg.icp_relative_change)
                if ok
                else Registration.failed()
            )
            self.counts.icp += 1
        return self._icp_cache[key]

    def _sets_of(self, pos: int) -> ChunkSets:
        """The correspondence sets of the chunk of the place at ``order[pos]``: its places not made
        yet (all of them, unless a quota left some for the second pass), made together."""
        c = self.chunk_of[pos]
        if self._sets is None or self._chunk != c or int(self.order[pos]) not in self._sets.result:
            todo = np.union1d(np.flatnonzero((self.chunk_of == c) & ~self.used), [pos])
            self._chunk, self._sets = (
                c,
                ChunkSets(self.order[todo], self.sessions, self.kp.session, self.kp.index, self.cfg, self.icp_of),
            )
        return self._sets

    def _one_place(self, pos: int, split: str) -> int:
        """Patches and triplets of the place at ``order[pos]``; returns the triplets made."""
        cfg, n = self.cfg, self.counts
        n.tried += 1
        res, rejected = self._sets_of(pos).get(self.order[pos])
        n.rejected_members += rejected
        if res is None:
            n.why["no_set"] += 1
            return 0
        ok = res["points"] >= cfg.min_patch_points
        if ok.sum() < 2:
            n.why["small_patches"] += 1
            return 0
        pool_ids, pool_pos = self.pools[split]
        p = res["centre"][0]
        far = np.flatnonzero(np.linalg.norm(pool_pos[:, :2] - p[:2], axis=1) > cfg.negative_min_distance_m)
        if len(far) == 0:  # before recording the set's patches, which would otherwise share the next set's id
            n.why["no_far_negative"] += 1
            return 0
        ids = self.shards.add(res["occ"][ok], res["dcg"][ok])
        set_rmse = float(max(res["rmse"][ok]))
        self.table.record(
            ids,
            n.sets,
            split,
            "positive",
            res["session"][ok],
            res["frame"][ok],
            res["centre"][ok],
            res["yaw"][ok],
            res["points"][ok],
            np.full(ok.sum(), set_rmse),
            res["transform"][ok],
        )
        ii, jj = np.triu_indices(len(ids), 1)
        ii, jj = ii[: cfg.n_triplets - n.triplets], jj[: cfg.n_triplets - n.triplets]
        neg = pool_ids[self.rng.choice(far, len(ii))]
        self.triplets[split].append(np.stack([ids[ii], ids[jj], neg], axis=1))
        n.sets += 1
        return len(ii)


def _write_dataset(
    out: Path,
    ws: Workspace,
    h: str,
    cfg: TripletConfig,
    sessions: list[SessionPoints],
    frame: LocalFrame,
    tiles: dict,
    shards: ShardWriter,
    table: _PatchTable,
    places: _Places,
    t0: float,
) -> None:
    """The patch table, the triplets, the manifest, the metrics and the examples picture (all but the marker)."""
    tab = table.arrays()
    utm = frame.enu_to_utm(tab["enu"]) if len(tab["enu"]) else np.zeros((0, 3))
    names = [s.name for s in sessions]
    with atomic_path(out / "patches.npz") as tmp, open(tmp, "wb") as f:
        np.savez_compressed(
            f,
            patch_id=tab["patch_id"],
            set_id=tab["set_id"],
            split=tab["split"].astype(str),
            role=tab["role"].astype(str),
            session=tab["session"],
            frame=tab["frame"],
            enu=tab["enu"],
            utm=utm,
            yaw=tab["yaw"],
            points=tab["points"],
            icp_rmse_m=tab["icp_rmse_m"],
            transform=tab["transform"],
        )
    _write_patches_csv(out / "patches.csv", tab, utm, names, cfg)
    counts = {}
    for split in SPLITS:
        t = np.concatenate(places.triplets[split]) if places.triplets[split] else np.zeros((0, 3), np.int64)
        with atomic_path(out / f"triplets_{split}.npy") as tmp, open(tmp, "wb") as f:
            np.save(f, t.astype(np.int64))
        counts[split] = int(len(t))
    seconds = time.perf_counter() - t0
    manifest = {
        "format_version": TRIPLETS_FORMAT_VERSION,
        "workspace": str(ws.root),
        "map_source": cfg.map_source,
        "sessions": names,
        "seed": cfg.seed,
        "config_hash": h,
        "frame": frame.to_dict(),
        "domain": cfg.domain.model_dump(),
        "grid": cfg.grid,
        "grids": {
            "occupancy": "(n, g, g, ceil(g/8)) uint8, bits packed along the last axis (np.packbits)",
            "density_comparison": "(n, 3, g, g, ceil(g/8)) uint8, same packing; channel a = density above the +a "
            "neighbour's",
        },
        "tiles": tiles_to_manifest(tiles, cfg.tile_size_m),
        "shard_format": cfg.shard_format,
        "shards": shards.shards,
        "patches": int(shards.n),
        "triplets": counts,
        "files": {
            n: sha256_file(out / n) for n in ("patches.npz", "patches.csv", "triplets_train.npy", "triplets_test.npy")
        },
    }
    write_json(out / "manifest.json", manifest)
    n = places.counts
    metrics = {
        "map_source": cfg.map_source,
        "triplets": counts,
        "quota": places.quota,
        "patches": int(shards.n),
        "places": n.sets,
        "places_tried": n.tried,
        "members_rejected_by_icp": n.rejected_members,
        "icp_registrations": n.icp,
    }
    write_json(out / "metrics.json", metrics)
    write_timings(out, seconds=seconds, triplets_per_s=sum(counts.values()) / seconds if seconds > 0 else None)

    ds = TripletDataset(out)
    if counts["train"] or counts["test"]:
        triplet_examples(out / "examples.png", ds, n=4, seed=cfg.seed)


def _no_triplets_reason(cfg: TripletConfig, kp_split: np.ndarray, pools: dict, n: _Counts) -> str:
    """One line: why an export made no triplet, and which setting to change."""
    tried, why, rejected = n.tried, n.why, n.rejected_members
    head = f"no triplets made ({tried} places tried"
    if not np.any(kp_split != ""):
        return (
            f"{head}): every keypoint lies within buffer_m={cfg.buffer_m:g} of a tile of the other split; "
            f"lower buffer_m or raise tile_size_m ({cfg.tile_size_m:g})"
        )
    if not any(len(ids) for ids, _ in pools.values()):
        return (
            f"{head}): no negative patch holds min_patch_points={cfg.min_patch_points} points; lower min_patch_points "
            "or map more densely"
        )
    reasons = (
        f"{head}: {why['no_set']} seen by fewer than two sessions agreeing by ICP ({rejected} members rejected), "
        f"{why['small_patches']} with fewer than two patches of min_patch_points={cfg.min_patch_points} points, "
        f"{why['no_far_negative']} without a negative farther than "
        f"negative_min_distance_m={cfg.negative_min_distance_m:g})"
    )
    worst = max(why, key=why.__getitem__) if tried else "no_set"
    advice = {
        "no_set": "too few overlapping places between sessions: drive the same streets in two sessions, raise "
        f"seen_radius_m ({cfg.seen_radius_m:g}) or lambda_icp_m ({cfg.lambda_icp_m:g}), or lower min_fitness "
        f"({cfg.min_fitness:g})",
        "small_patches": f"lower min_patch_points ({cfg.min_patch_points}) or map more densely (the patch radius is "
        f"{cfg.domain.patch_radius:g} m)",
        "no_far_negative": f"lower negative_min_distance_m ({cfg.negative_min_distance_m:g}) below the extent of each "
        f"split's map, or raise tile_size_m ({cfg.tile_size_m:g})",
    }[worst]
    return f"{reasons}; {advice}"


def _write_patches_csv(path: Path, tab: dict, utm: np.ndarray, names: list[str], cfg: TripletConfig) -> None:
    import csv
    import io

    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(
        [
            "patch_id",
            "set_id",
            "split",
            "role",
            "session",
            "first_observer_frame",
            "easting_m",
            "northing_m",
            "up_m",
            "yaw_rad",
            "domain",
            "points",
            "icp_rmse_m",
        ]
    )
    dom = f"{cfg.domain.kind}:{cfg.domain.patch_radius:g}"
    for i in range(len(tab["patch_id"])):
        w.writerow(
            [
                int(tab["patch_id"][i]),
                int(tab["set_id"][i]),
                tab["split"][i],
                tab["role"][i],
                names[int(tab["session"][i])],
                int(tab["frame"][i]),
                f"{utm[i, 0]:.3f}",
                f"{utm[i, 1]:.3f}",
                f"{utm[i, 2]:.3f}",
                f"{tab['yaw'][i]:.6f}",
                dom,
                int(tab["points"][i]),
                f"{tab['icp_rmse_m'][i]:.4f}",
            ]
        )
    atomic_write_text(path, buf.getvalue())


# --- reading -------------------------------------------------------------------------------------------


class TripletDataset:
    """A triplet dataset folder: grids by patch id, triplets per split, batches for training."""

    def __init__(self, folder: str | Path, verify: bool = False):
        self.folder = Path(folder)
        mpath = self.folder / "manifest.json"
        if not mpath.is_file():
            raise InputError(mpath, "no such file (not a triplet dataset folder?)")
        self.manifest = json.loads(mpath.read_text())
        if self.manifest.get("format_version") not in READABLE_FORMAT_VERSIONS:
            raise InputError(
                mpath,
                f"format version {self.manifest.get('format_version')!r}; this mapkit reads "
                f"{', '.join(map(str, READABLE_FORMAT_VERSIONS))}",
                field="format_version",
            )
        # version 1 datasets have npz shards and no shard_format
        self.shard_format = self.manifest.get("shard_format", "npz")
        if self.shard_format not in SHARD_FORMATS:
            raise InputError(
                mpath,
                f"shard format {self.shard_format!r}; this mapkit reads {', '.join(SHARD_FORMATS)}",
                field="shard_format",
            )
        if verify:
            for s in self.manifest["shards"]:
                if sha256_file(self.folder / s["file"]) != s["sha256"]:
                    raise InputError(self.folder / s["file"], "checksum differs from the manifest's", field="sha256")
            for name, digest in self.manifest["files"].items():
                if sha256_file(self.folder / name) != digest:
                    raise InputError(self.folder / name, "checksum differs from the manifest's", field="sha256")
        self.grid = int(self.manifest["grid"])
        with np.load(self.folder / "patches.npz", allow_pickle=False) as z:
            self.table = {k: z[k] for k in z.files}
        self._cache: dict[int, dict] = {}

    def triplets(self, split: str = "train") -> np.ndarray:
        return np.load(self.folder / f"triplets_{split}.npy")

    def _shard(self, k: int) -> dict:
        if k not in self._cache:
            if len(self._cache) > 4:
                self._cache.clear()
            self._cache[k] = read_shard(self.folder / self.manifest["shards"][k]["file"], self.shard_format)
        return self._cache[k]

    def grids(self, ids: np.ndarray, form: GridForm = "occupancy") -> np.ndarray:
        """Unpacked uint8 grids of patch ``ids``: (n, g, g, g) or (n, 3, g, g, g)."""
        ids = np.asarray(ids, np.int64)
        firsts = np.array([s["first_id"] for s in self.manifest["shards"]])
        shard = np.searchsorted(firsts, ids, side="right") - 1
        out = None
        for k in np.unique(shard):
            sel = np.flatnonzero(shard == k)
            data = self._shard(int(k))[form][ids[sel] - firsts[k]]
            g = unpack_bits(data, self.grid)
            if out is None:
                out = np.empty((len(ids),) + g.shape[1:], np.uint8)
            out[sel] = g
        return (
            out
            if out is not None
            else np.zeros((0,) + ((3,) if form == "density_comparison" else ()) + (self.grid,) * 3, np.uint8)
        )

    def batches(
        self,
        batch_size: int = 32,
        split: str = "train",
        form: GridForm = "occupancy",
        shuffle: bool = True,
        seed: int = 0,
    ) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """(X1, X2, X3) batches of unpacked grids."""
        t = self.triplets(split)
        order = np.random.default_rng(seed).permutation(len(t)) if shuffle else np.arange(len(t))
        for b in range(0, len(t), batch_size):
            rows = t[order[b : b + batch_size]]
            yield self.grids(rows[:, 0], form), self.grids(rows[:, 1], form), self.grids(rows[:, 2], form)

    def torch_dataset(self, split: str = "train", form: str = "occupancy"):
        """A ``torch.utils.data.Dataset`` of float32 (X1, X2, X3) triplets (needs the learning extra)."""
        try:
            import torch
        except ImportError:
            raise InputError(
                None, "torch is not installed: pip install torch==2.13.0 (the CPU build), then the learning extra"
            ) from None
        ds = self

        class _Triplets(torch.utils.data.Dataset):
            def __init__(self):
                self.t = ds.triplets(split)

            def __len__(self):
                return len(self.t)

            def __getitem__(self, i):
                g = ds.grids(self.t[i], form).astype(np.float32)
                return tuple(torch.from_numpy(g[c][None] if form == "occupancy" else g[c]) for c in range(3))

        return _Triplets()
