"""``mapkit triplets``: training triplets of voxelised 3D patches (semi-dense paper, section 4.1).

From an aligned workspace (``mapkit align``): a random keypoint of one session gives a
georeferenced place; every session that mapped that place contributes its local cloud, aligned to
the anchor session's with ICP (a member whose RMSE after ICP exceeds lambda_ICP is rejected); the
patches are cut from the aligned clouds, yaw-normalised (section 3.2) and voxelised (occupancy and
density comparison, 32^3). N members give N-choose-2 positive pairs; each gets a negative: a patch
farther than ``negative_min_distance_m`` from the anchor, from the same split.

Train and test places come from disjoint UTM tiles, with a buffer strip: no keypoint (anchor or
negative) lies within ``buffer_m`` of a tile of the other split, so no test place has a training
patch nearby. Output: compressed NumPy shards (bits packed), a per-patch table, the triplets, a
manifest with seed, config hash and checksums, and a picture of a few triplets.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Iterator, Literal, Optional

import numpy as np
from pydantic import Field
from scipy.spatial import cKDTree

from .bundle import building
from .config import MapkitConfig, dump_config, load_config
from .errors import InputError
from .geodesy import LocalFrame
from .patches import (
    CNN_DOMAIN,
    PatchDomain,
    first_observer_frames,
    gather_local,
    unpack_bits,
    voxelise_patches,
    yaw_normalise_patches,
)
from .runio import atomic_path, atomic_write_text, config_hash, is_done, mark_done, sha256_file, write_json

TRIPLETS_FORMAT_VERSION = 1
SPLITS = ("train", "test")


class TripletConfig(MapkitConfig):
    domain: PatchDomain = Field(CNN_DOMAIN, description="Patch domain: the CNN's 20x20x20 m cube (semi-dense paper, Fig. 6 caption).")
    grid: int = Field(32, ge=4, description="Voxels per axis (semi-dense paper, section 3.3.2: 32x32x32).")
    keypoint_fraction: float = Field(0.05, gt=0, le=1, description="Keypoints: a random 5% of map points (semi-dense paper, section 3.2).")
    n_triplets: int = Field(20_000, ge=1, description="Triplets to export (the paper's triplet set has 20,000).")
    seen_radius_m: float = Field(0.5, gt=0, description="A session saw a place when one of its map points lies this close to it.")
    min_patch_points: int = Field(200, ge=1, description="A session's patch needs at least this many points.")
    icp_voxel_sizes_m: list[float] = Field([0.3], description="ICP levels aligning the members' local clouds (m); one fine level, since "
                                           "mapkit align has already brought the sessions within a few decimetres.")
    icp_max_correspondence_m: list[float] = Field([0.6], description="Correspondence distance per ICP level (m).")
    icp_cell_m: float = Field(10.0, gt=0, description="Places are drawn cell by cell (cells of this size, m) with one anchor session per "
                              "cell, and one ICP per session and cell serves all of the cell's places. The paper aligns per place; "
                              "within 10 m the transform is the same and the export is ten times faster.")
    places_per_cell: int = Field(20, ge=1, description="Places drawn from a cell before moving to the next.")
    lambda_icp_m: float = Field(0.40, gt=0, description="lambda_ICP: a member whose point-to-plane RMSE after ICP exceeds this is rejected "
                                "(semi-dense paper, section 4.1; no value given there: mapkit align's default).")
    min_fitness: float = Field(0.3, ge=0, le=1, description="A member whose ICP fitness is below this is rejected.")
    max_members: int = Field(8, ge=2, description="At most this many sessions per place.")
    negative_min_distance_m: float = Field(100.0, gt=0, description="Negatives lie farther than this from the anchor (the issue's example, 100 m).")
    negative_pool: int = Field(2000, ge=10, description="Negative patches drawn per split and shared by its triplets.")
    tile_size_m: float = Field(200.0, gt=0, description="Side of the UTM tiles assigned to train or test (a few blocks of a town; "
                               "the buffer strips take less of a larger tile).")
    test_fraction: float = Field(0.25, gt=0, lt=1, description="Fraction of tiles held out for testing.")
    buffer_m: float = Field(30.0, ge=0, description="No keypoint within this distance of a tile of the other split (> a patch's reach, 14 m).")
    shard_patches: int = Field(4096, ge=16, description="Patches per shard file.")
    seed: int = Field(0, description="Seed of every random choice: the same seed and inputs give the same dataset.")
    sessions: Optional[list[str]] = Field(None, description="Sessions to use; all merged sessions of the alignment if unset.")


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


class SessionPoints:
    """One aligned session: its merged map points, their first observers, and spatial indexes."""

    def __init__(self, name: str, points: np.ndarray, observer_pos: np.ndarray, observer_frame: np.ndarray):
        self.name = name
        self.points = points
        self.observer_pos = observer_pos
        self.observer_frame = observer_frame
        self.grid = GridIndex(points[:, :2], 5.0)
        self.tree3 = cKDTree(points)

    def around(self, centre: np.ndarray, r: float) -> np.ndarray:
        """Points within horizontal distance ``r`` of ``centre``."""
        idx = self.grid.candidates(centre[:2], r)
        p = self.points[idx]
        return p[np.sum((p[:, :2] - centre[:2]) ** 2, axis=1) <= r * r]


def load_aligned_sessions(workspace: Path, names: Optional[list[str]] = None) -> tuple[list[SessionPoints], LocalFrame]:
    from .align import load_tiles
    from .semidense import SemiDenseMap

    al = workspace / "align"
    if not (al / ".done").is_file():
        raise InputError(al, "no finished multi-session alignment here (run mapkit align first)")
    frame = LocalFrame.from_dict(json.loads((workspace / "origin.json").read_text()))
    _, sid, idx, tile_names = load_tiles(al / "tiles")
    out = []
    for k, name in enumerate(tile_names):
        if names is not None and name not in names:
            continue
        keep = np.sort(idx[sid == k])
        if len(keep) == 0:
            continue
        smap = SemiDenseMap.load(al / "sessions" / name / "map")
        first = first_observer_frames(keep, smap.obs_indptr, smap.obs_frame_ids, smap.keyframe_ids)
        order = np.argsort(smap.keyframe_ids, kind="stable")
        pos = smap.keyframe_world_from_cam[order[np.searchsorted(smap.keyframe_ids[order], first)], :3, 3]
        out.append(SessionPoints(name, smap.points_world[keep], pos, first))
    if names is not None:
        missing = sorted(set(names) - {s.name for s in out})
        if missing:
            raise InputError(al / "tiles" / "tiles.json", f"sessions {missing} have no merged points", field="sessions")
    if len(out) < 2:
        raise InputError(al, f"{len(out)} session(s) with merged points; triplets need two or more")
    return out, frame


# --- the spatial split ------------------------------------------------------------------------------


def tile_split(utm_xy: np.ndarray, tile_m: float, test_fraction: float, seed: int) -> dict[tuple[int, int], str]:
    """Every tile touched by ``utm_xy`` labelled train or test, at random but reproducibly: tiles
    are taken in random order into the test split until it holds ``test_fraction`` of the points
    (so the test split gets its share of the mapped places, not of empty tiles); at least one
    tile stays in each split when there are two or more."""
    keys, counts = np.unique(np.floor(utm_xy / tile_m).astype(np.int64), axis=0, return_counts=True)
    keys = [tuple(int(v) for v in k) for k in keys]
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


def split_of(utm_xy: np.ndarray, tiles: dict[tuple[int, int], str], tile_m: float, buffer_m: float) -> np.ndarray:
    """Per point: "train", "test", or "" when within ``buffer_m`` of a tile of the other split."""
    ij = np.floor(utm_xy / tile_m).astype(np.int64)
    own = np.array([tiles.get((int(a), int(b)), "train") for a, b in ij], dtype=object)
    u = utm_xy - ij * tile_m  # position inside the tile, [0, tile_m)
    dmin = np.full(len(utm_xy), np.inf)
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            if di == dj == 0:
                continue
            other = np.array([tiles.get((int(a) + di, int(b) + dj)) for a, b in ij], dtype=object)
            differs = np.array([o is not None and o != s for o, s in zip(other, own)])
            dx = np.where(di < 0, u[:, 0], np.where(di > 0, tile_m - u[:, 0], 0.0))
            dy = np.where(dj < 0, u[:, 1], np.where(dj > 0, tile_m - u[:, 1], 0.0))
            d = np.hypot(dx, dy)
            dmin = np.where(differs, np.minimum(dmin, d), dmin)
    return np.where(dmin < buffer_m, "", own).astype(object)


# --- patches ------------------------------------------------------------------------------------------


def places_by_cell(kp_session, kp_index, kp_split, sessions, cfg: TripletConfig, rng: np.random.Generator) -> np.ndarray:
    """Every usable keypoint, in the order places are drawn: in rounds over the cells (in random
    order), each round taking the next ``places_per_cell`` keypoints of each cell, one anchor
    session at a time (so a cell's ICPs serve many places)."""
    valid = np.flatnonzero(kp_split != "")
    if len(valid) == 0:
        return np.zeros(0, np.int64)
    pos = np.array([sessions[s].points[i, :2] for s, i in zip(kp_session[valid], kp_index[valid])]).reshape(-1, 2)
    _, cell_id = np.unique(np.floor(pos / cfg.icp_cell_m).astype(np.int64), axis=0, return_inverse=True)
    cell_id = cell_id.ravel()
    chunks_per_cell = []
    for c in rng.permutation(int(cell_id.max()) + 1):
        members = valid[cell_id == c]
        ordered = np.concatenate([rng.permutation(members[kp_session[members] == a]) for a in rng.permutation(np.unique(kp_session[members]))])
        chunks_per_cell.append([ordered[k : k + cfg.places_per_cell] for k in range(0, len(ordered), cfg.places_per_cell)])
    rounds = max(len(ch) for ch in chunks_per_cell)
    return np.concatenate([ch[r] for r in range(rounds) for ch in chunks_per_cell if r < len(ch)])


def make_patches(clouds: list[np.ndarray], centres: np.ndarray, observers: np.ndarray, cfg: TripletConfig):
    """Occupancy and density-comparison grids (bits packed) and yaws of one patch per cloud.

    ``clouds[k]`` holds the points around ``centres[k]``; ``observers[k]`` is the first observer
    of the keypoint in that cloud's session (the sign of the yaw).
    """
    d = cfg.domain
    counts, idx = [], []
    allpts = np.concatenate(clouds) if clouds else np.zeros((0, 3))
    offs = np.cumsum([0] + [len(c) for c in clouds])
    for k, c in enumerate(clouds):
        rel = c - centres[k]
        keep = (np.hypot(rel[:, 0], rel[:, 1]) <= d.patch_radius) & (np.abs(rel[:, 2]) <= d.patch_half_height)
        sel = np.flatnonzero(keep) + offs[k]
        idx.append(sel)
        counts.append(len(sel))
    indptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    indices = np.concatenate(idx) if idx else np.zeros(0, np.int64)
    local = gather_local(allpts, centres, indptr, indices)
    yaw, normalised = yaw_normalise_patches(local, indptr, observers[:, :2] - centres[:, :2])
    occ, dcg = voxelise_patches(normalised, indptr, d, cfg.grid, packed=True)
    return occ, dcg, yaw, np.asarray(counts)


class ShardWriter:
    """Patches go to ``patches-NNNNN.npz`` files of ``size`` patches (compressed, bits packed)."""

    def __init__(self, folder: Path, size: int):
        self.folder, self.size = folder, size
        self.buf_occ: list[np.ndarray] = []
        self.buf_dcg: list[np.ndarray] = []
        self.n = 0
        self.shards: list[dict] = []

    def add(self, occ: np.ndarray, dcg: np.ndarray) -> np.ndarray:
        ids = np.arange(self.n, self.n + len(occ))
        self.buf_occ.append(occ)
        self.buf_dcg.append(dcg)
        self.n += len(occ)
        if sum(len(b) for b in self.buf_occ) >= self.size:
            self.flush()
        return ids

    def flush(self) -> None:
        if not self.buf_occ:
            return
        occ, dcg = np.concatenate(self.buf_occ), np.concatenate(self.buf_dcg)
        first = self.n - len(occ)
        while len(occ):
            take = min(self.size, len(occ))
            name = f"patches-{len(self.shards):05d}.npz"
            with atomic_path(self.folder / name) as tmp:
                _savez_fast(tmp, occupancy=occ[:take], density_comparison=dcg[:take], first_id=np.int64(first))
            self.shards.append({"file": name, "first_id": int(first), "patches": int(take), "sha256": sha256_file(self.folder / name)})
            occ, dcg, first = occ[take:], dcg[take:], first + take
        self.buf_occ, self.buf_dcg = [], []


def _savez_fast(path: Path, **arrays: np.ndarray) -> None:
    """An ``.npz`` (readable by ``np.load``) deflated at level 1: the packed grids compress about
    as well as at the default level, five times faster."""
    import zipfile

    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
        for name, a in arrays.items():
            with zf.open(f"{name}.npy", "w", force_zip64=True) as f:
                np.lib.format.write_array(f, np.asanyarray(a), allow_pickle=False)


# --- the export ---------------------------------------------------------------------------------------


def export_triplets(workspace: str | Path, out: str | Path | None = None, config: str | Path | None = None,
                    overrides: Optional[dict] = None, progress: bool = True) -> Path:
    """Export a triplet dataset from an aligned workspace; returns its folder (default
    ``WORKSPACE/triplets``). Re-running with the same config and inputs does nothing."""
    from .align import IcpConfig, register_clouds

    workspace = Path(workspace)
    cfg = load_config(TripletConfig, config, overrides)
    out = Path(out) if out is not None else workspace / "triplets"
    align_done = json.loads((workspace / "align" / ".done").read_text()) if (workspace / "align" / ".done").is_file() else {}
    h = config_hash({"cfg": cfg, "align": align_done.get("config_hash")})
    if is_done(out, h):
        return out
    t0 = time.perf_counter()
    sessions, frame = load_aligned_sessions(workspace, cfg.sessions)
    final = out
    with building(final) as out:  # a partial folder, renamed into place last: an earlier dataset survives a failure
        atomic_write_text(out / "config.yaml", dump_config(cfg))
        rng = np.random.default_rng(cfg.seed)
        icp = IcpConfig(voxel_sizes_m=cfg.icp_voxel_sizes_m, max_correspondence_m=cfg.icp_max_correspondence_m, max_iterations=20,
                        lambda_icp_m=cfg.lambda_icp_m, min_fitness=cfg.min_fitness, min_structure_fitness=0.0)

        # keypoints per session, with their split
        all_utm = np.concatenate([frame.enu_to_utm(s.points[:: max(1, len(s.points) // 20000)])[:, :2] for s in sessions])
        tiles = tile_split(all_utm, cfg.tile_size_m, cfg.test_fraction, cfg.seed)
        kp_session, kp_index, kp_split = [], [], []
        for si, s in enumerate(sessions):
            k = np.sort(rng.choice(len(s.points), max(1, int(round(cfg.keypoint_fraction * len(s.points)))), replace=False))
            sp = split_of(frame.enu_to_utm(s.points[k])[:, :2], tiles, cfg.tile_size_m, cfg.buffer_m)
            kp_session.append(np.full(len(k), si))
            kp_index.append(k)
            kp_split.append(sp)
        kp_session, kp_index, kp_split = np.concatenate(kp_session), np.concatenate(kp_index), np.concatenate(kp_split)

        shards = ShardWriter(out, cfg.shard_patches)
        table: dict[str, list] = {k: [] for k in ("patch_id", "set_id", "split", "role", "session", "frame", "enu", "yaw", "points", "icp_rmse_m", "transform")}

        def record(ids, set_id, split, role, sess, frames, enu, yaw, npts, rmse, T):
            table["patch_id"].append(ids)
            table["set_id"].append(np.full(len(ids), set_id))
            table["split"].append(np.full(len(ids), split, dtype=object))
            table["role"].append(np.full(len(ids), role, dtype=object))
            table["session"].append(np.asarray(sess))
            table["frame"].append(np.asarray(frames))
            table["enu"].append(np.asarray(enu))
            table["yaw"].append(np.asarray(yaw))
            table["points"].append(np.asarray(npts))
            table["icp_rmse_m"].append(np.asarray(rmse))
            table["transform"].append(np.asarray(T))

        # negative pools: random keypoints of each split, patches as mapped (no ICP needed)
        pools = {}
        for split in SPLITS:
            cand = np.flatnonzero(kp_split == split)
            if len(cand) == 0:
                continue
            pick = rng.choice(cand, min(cfg.negative_pool, len(cand)), replace=False)
            clouds, centres, obs, sess, frames = [], [], [], [], []
            for j in pick:
                s = sessions[kp_session[j]]
                p = s.points[kp_index[j]]
                clouds.append(s.around(p, cfg.domain.patch_radius))
                centres.append(p)
                obs.append(s.observer_pos[kp_index[j]])
                sess.append(kp_session[j])
                frames.append(s.observer_frame[kp_index[j]])
            occ, dcg, yaw, npts = make_patches(clouds, np.array(centres), np.array(obs), cfg)
            ok = npts >= cfg.min_patch_points
            ids = shards.add(occ[ok], dcg[ok])
            record(ids, -1, split, "negative", np.array(sess)[ok], np.array(frames)[ok], np.array(centres)[ok], yaw[ok], npts[ok],
                   np.zeros(ok.sum()), np.repeat(np.eye(4)[None], ok.sum(), axis=0))
            pools[split] = (ids, np.array(centres)[ok])

        # correspondence sets
        triplets: dict[str, list] = {s: [] for s in SPLITS}
        order = places_by_cell(kp_session, kp_index, kp_split, sessions, cfg, rng)
        n_sets = rejected_members = tried = n_done = n_icp = 0
        icp_cache: dict[tuple, dict] = {}
        crop = cfg.domain.patch_radius + 2.0

        def _one_place(j: int, split: str) -> int:
            """Patches and triplets of the place at keypoint ``j``; returns the triplets made."""
            nonlocal n_sets, rejected_members, tried, n_icp
            tried += 1
            a = sessions[kp_session[j]]
            p = a.points[kp_index[j]]
            members = [(kp_session[j], kp_index[j])]
            for si, s in enumerate(sessions):
                if si == kp_session[j]:
                    continue
                d, nearest = s.tree3.query(p, distance_upper_bound=cfg.seen_radius_m)
                if np.isfinite(d):
                    members.append((si, nearest))
            if len(members) < 2:
                return 0
            members = members[: cfg.max_members]
            clouds, centres, obs, sess, frames, rmses, Ts = [], [], [], [], [], [], []
            for si, pi in members:
                s = sessions[si]
                cloud = s.around(p, crop)
                if len(cloud) < cfg.min_patch_points:
                    continue
                if si == kp_session[j]:
                    T, rmse = np.eye(4), 0.0
                else:
                    key = (si, int(kp_session[j]), *np.floor(p[:2] / cfg.icp_cell_m).astype(int).tolist())
                    r = icp_cache.get(key)
                    if r is None:
                        c = (np.floor(p[:2] / cfg.icp_cell_m) + 0.5) * cfg.icp_cell_m
                        centre = np.array([c[0], c[1], p[2]])
                        reach = crop + 0.71 * cfg.icp_cell_m
                        src = s.around(centre, reach)
                        tgt = a.around(centre, reach)
                        r = register_clouds(src, tgt, centre, icp, structure=False) if min(len(src), len(tgt)) >= cfg.min_patch_points else {"fitness": 0.0, "rmse_m": float("nan")}
                        icp_cache[key] = r
                        n_icp += 1
                    if r["fitness"] < cfg.min_fitness or not r["rmse_m"] <= cfg.lambda_icp_m:
                        rejected_members += 1
                        continue
                    T, rmse = r["target_from_source"], r["rmse_m"]
                clouds.append(cloud @ T[:3, :3].T + T[:3, 3])
                centres.append(p)
                obs.append(T[:3, :3] @ s.observer_pos[pi] + T[:3, 3])
                sess.append(si)
                frames.append(s.observer_frame[pi])
                rmses.append(rmse)
                Ts.append(T)
            if len(clouds) < 2 or sess[0] != kp_session[j]:
                return 0
            occ, dcg, yaw, npts = make_patches(clouds, np.array(centres), np.array(obs), cfg)
            ok = npts >= cfg.min_patch_points
            if ok.sum() < 2:
                return 0
            ids = shards.add(occ[ok], dcg[ok])
            set_rmse = float(max(np.array(rmses)[ok]))
            record(ids, n_sets, split, "positive", np.array(sess)[ok], np.array(frames)[ok], np.array(centres)[ok], yaw[ok], npts[ok],
                   np.full(ok.sum(), set_rmse), np.array(Ts)[ok])
            pool_ids, pool_pos = pools[split]
            far = np.flatnonzero(np.linalg.norm(pool_pos[:, :2] - p[:2], axis=1) > cfg.negative_min_distance_m)
            if len(far) == 0:
                return 0
            ii, jj = np.triu_indices(len(ids), 1)
            ii, jj = ii[: cfg.n_triplets - n_done], jj[: cfg.n_triplets - n_done]
            neg = pool_ids[rng.choice(far, len(ii))]
            triplets[split].append(np.stack([ids[ii], ids[jj], neg], axis=1))
            n_sets += 1
            if progress:
                print(f"\r[triplets] {n_done + len(ii)}/{cfg.n_triplets} triplets from {n_sets} places", end="", file=sys.stderr, flush=True)
            return len(ii)

        # each split gets its share (test_fraction of the triplets to test); what a split cannot fill
        # (too few places seen by two sessions) goes to the other in a second pass
        quota = {"test": int(round(cfg.test_fraction * cfg.n_triplets))}
        quota["train"] = cfg.n_triplets - quota["test"]
        made = {"train": 0, "test": 0}
        used = np.zeros(len(order), bool)
        for pass_no in (0, 1):
            for pos, j in enumerate(order):
                if n_done >= cfg.n_triplets:
                    break
                if used[pos]:
                    continue
                split = kp_split[j]
                if split not in pools or (pass_no == 0 and made[split] >= quota[split]):
                    continue
                used[pos] = True
                n_new = _one_place(j, split)
                made[split] += n_new
                n_done += n_new
        if progress:
            print(file=sys.stderr)
        shards.flush()

        tab = {k: np.concatenate(v) if v else np.zeros(0) for k, v in table.items()}
        order_ids = np.argsort(tab["patch_id"])
        tab = {k: v[order_ids] for k, v in tab.items()}
        utm = frame.enu_to_utm(tab["enu"]) if len(tab["enu"]) else np.zeros((0, 3))
        names = [s.name for s in sessions]
        with atomic_path(out / "patches.npz") as tmp:
            with open(tmp, "wb") as f:
                np.savez_compressed(f, patch_id=tab["patch_id"], set_id=tab["set_id"], split=tab["split"].astype(str),
                                    role=tab["role"].astype(str), session=tab["session"], frame=tab["frame"], enu=tab["enu"], utm=utm,
                                    yaw=tab["yaw"], points=tab["points"], icp_rmse_m=tab["icp_rmse_m"], transform=tab["transform"])
        _write_patches_csv(out / "patches.csv", tab, utm, names, cfg)
        counts = {}
        for split in SPLITS:
            t = np.concatenate(triplets[split]) if triplets[split] else np.zeros((0, 3), np.int64)
            with atomic_path(out / f"triplets_{split}.npy") as tmp:
                with open(tmp, "wb") as f:
                    np.save(f, t.astype(np.int64))
            counts[split] = int(len(t))
        seconds = time.perf_counter() - t0
        manifest = {
            "format_version": TRIPLETS_FORMAT_VERSION, "workspace": str(workspace), "sessions": names, "seed": cfg.seed,
            "config_hash": h, "frame": frame.to_dict(), "domain": cfg.domain.model_dump(), "grid": cfg.grid,
            "grids": {"occupancy": "(n, g, g, ceil(g/8)) uint8, bits packed along the last axis (np.packbits)",
                      "density_comparison": "(n, 3, g, g, ceil(g/8)) uint8, same packing; channel a = density above the +a neighbour's"},
            "tiles": [{"utm_min": [k[0] * cfg.tile_size_m, k[1] * cfg.tile_size_m], "split": v} for k, v in sorted(tiles.items())],
            "shards": shards.shards, "patches": int(shards.n), "triplets": counts,
            "files": {n: sha256_file(out / n) for n in ("patches.npz", "patches.csv", "triplets_train.npy", "triplets_test.npy")},
        }
        write_json(out / "manifest.json", manifest)
        metrics = {"triplets": counts, "quota": quota, "patches": int(shards.n), "places": n_sets, "places_tried": tried,
                   "members_rejected_by_icp": rejected_members, "icp_registrations": n_icp, "seconds": seconds,
                   "triplets_per_s": sum(counts.values()) / seconds if seconds > 0 else None}
        write_json(out / "metrics.json", metrics)
        from .plots import triplet_examples

        ds = TripletDataset(out)
        if counts["train"] or counts["test"]:
            triplet_examples(out / "examples.png", ds, n=4, seed=cfg.seed)
        mark_done(out, h)
    return final


def _write_patches_csv(path: Path, tab: dict, utm: np.ndarray, names: list[str], cfg: TripletConfig) -> None:
    import csv
    import io

    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["patch_id", "set_id", "split", "role", "session", "first_observer_frame", "easting_m", "northing_m", "up_m",
                "yaw_rad", "domain", "points", "icp_rmse_m"])
    dom = f"{cfg.domain.kind}:{cfg.domain.patch_radius:g}"
    for i in range(len(tab["patch_id"])):
        w.writerow([int(tab["patch_id"][i]), int(tab["set_id"][i]), tab["split"][i], tab["role"][i], names[int(tab["session"][i])],
                    int(tab["frame"][i]), f"{utm[i, 0]:.3f}", f"{utm[i, 1]:.3f}", f"{utm[i, 2]:.3f}", f"{tab['yaw'][i]:.6f}", dom,
                    int(tab["points"][i]), f"{tab['icp_rmse_m'][i]:.4f}"])
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
        if self.manifest.get("format_version") != TRIPLETS_FORMAT_VERSION:
            raise InputError(mpath, f"format version {self.manifest.get('format_version')!r}; this mapkit reads {TRIPLETS_FORMAT_VERSION}",
                             field="format_version")
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
            with np.load(self.folder / self.manifest["shards"][k]["file"]) as z:
                self._cache[k] = {"occupancy": z["occupancy"], "density_comparison": z["density_comparison"]}
        return self._cache[k]

    def grids(self, ids: np.ndarray, form: Literal["occupancy", "density_comparison"] = "occupancy") -> np.ndarray:
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
        return out if out is not None else np.zeros((0,) + ((3,) if form == "density_comparison" else ()) + (self.grid,) * 3, np.uint8)

    def batches(self, batch_size: int = 32, split: str = "train", form: str = "occupancy", shuffle: bool = True,
                seed: int = 0) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """(X1, X2, X3) batches of unpacked grids."""
        t = self.triplets(split)
        order = np.random.default_rng(seed).permutation(len(t)) if shuffle else np.arange(len(t))
        for b in range(0, len(t), batch_size):
            rows = t[order[b : b + batch_size]]
            yield tuple(self.grids(rows[:, c], form) for c in range(3))

    def torch_dataset(self, split: str = "train", form: str = "occupancy"):
        """A ``torch.utils.data.Dataset`` of float32 (X1, X2, X3) triplets (needs the learning extra)."""
        try:
            import torch
        except ImportError:
            raise InputError(None, "torch is not installed: pip install torch==2.13.0 (the CPU build), then the learning extra") from None
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


def evaluate_triplets(dataset: str | Path, workspace: str | Path, truth: str | Path) -> dict:
    """Fraction of positive pairs whose true offset is below 0.5 m (and its distribution).

    Member s of a place put, after its ICP transform T_s, the true point E_s^-1 T_s^-1 p at the
    patch centre p (E_s = T_est T_gt^-1 of the aligned session's pose nearest to p); the offset
    of a positive pair is the distance between the two true points.
    """
    from .evaluate import _error_transforms, _session_truth, ws_from_town
    from .trajectory import Trajectory

    ds = TripletDataset(dataset)
    workspace, truth = Path(workspace), Path(truth)
    ws_frame = LocalFrame.from_dict(json.loads((workspace / "origin.json").read_text()))
    town_to_ws = ws_from_town(truth, ws_frame)
    names = ds.manifest["sessions"]
    err = {}
    for k, n in enumerate(names):
        st, gt = _session_truth(truth, n)
        tr = Trajectory.load(workspace / "align" / "sessions" / n / "trajectory")
        pos, E = _error_transforms(tr.stamps_ns, tr.world_from_base, st, town_to_ws @ gt)
        err[k] = (cKDTree(pos[:, :2]), np.linalg.inv(E))
    t = ds.table
    true_pt = np.zeros((len(t["patch_id"]), 3))
    for i in range(len(true_pt)):
        tree, Einv = err[int(t["session"][i])]
        p = t["enu"][i]
        q = np.linalg.inv(t["transform"][i]) @ np.r_[p, 1.0]
        e = Einv[tree.query(q[:2])[1]]
        true_pt[i] = (e @ q)[:3]
    offsets = []
    for split in SPLITS:
        tr = ds.triplets(split)
        if len(tr):
            offsets.append(np.linalg.norm(true_pt[tr[:, 0]] - true_pt[tr[:, 1]], axis=1))
    off = np.concatenate(offsets) if offsets else np.zeros(0)
    res = {"positive_pairs": int(len(off)), "fraction_below_0.5m": float((off < 0.5).mean()) if len(off) else None,
           "offset_median_m": float(np.median(off)) if len(off) else None,
           "offset_p90_m": float(np.percentile(off, 90)) if len(off) else None}
    write_json(Path(dataset) / "eval_triplets.json", res)
    return res
