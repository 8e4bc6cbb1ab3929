"""A triplet dataset in the layout PointNetVLAD-style trainers read (issue #6).

PointNetVLAD (Uy and Lee, CVPR 2018; github.com/mikacuy/pointnetvlad) trains on submaps, each a
binary file of 4096 points (float64, x y z interleaved, coordinates within [-1, 1]), listed per
run in a CSV of locations (``timestamp,northing,easting``: the timestamp names the file), and on
one pickled dictionary per split (``generating_queries/generate_training_tuples_baseline.py``):
consecutive integer keys, each to ``{"query": file, "positives": [keys], "negatives": [keys]}``
where positives lie within 10 m and negatives farther than 50 m of the query.

Here the submaps are the patches of a :mod:`mapkit.triplets` dataset, from the same ground truth:
the same patches (each one's session points, moved by its ICP transform, cut to the patch and
turned by its yaw, as the CNN grids were made), their UTM positions and their train/test tiles
(so no test query has a training patch within the tiles' buffer). Per patch the cloud is drawn
to exactly ``points`` points and scaled by the domain's half size (keypoint at the origin), so
it lies in [-1, 1] with one metric scale for all patches; PointNetVLAD rescaled each submap to
a mean spread of 0.5 about its centroid instead, which here would make the scale vary with the
patch's content.

Layout of the output folder::

    <session>/pointcloud_patches/<patch_id>.bin      one cloud per patch
    <session>/pointcloud_locations.csv               timestamp (= patch id), northing, easting
    pointcloud_locations.csv                         all patches: file, northing, easting, split, ...
    training_queries_baseline.pickle                 the train split's query dictionary
    test_queries_baseline.pickle                     the test split's
    manifest.json, config.yaml
"""

from __future__ import annotations

import pickle
from pathlib import Path
from typing import Optional

import numpy as np
from pydantic import Field, model_validator

from .config import MapkitConfig, dump_config, load_config
from .runio import atomic_path, atomic_write_text, config_hash, is_done, mark_done, sha256_file, write_json

PNV_FORMAT_VERSION = 1
QUERY_FILES = {"train": "training_queries_baseline.pickle", "test": "test_queries_baseline.pickle"}


class PointNetVladConfig(MapkitConfig):
    enabled: bool = Field(False, description="Also write the triplet dataset in PointNetVLAD's layout, into ``folder``.")
    positive_distance_m: float = Field(10.0, gt=0, description="Positives of a query: patches of its split within this horizontal "
                                       "(UTM) distance (PointNetVLAD, generate_training_tuples_baseline.py: 10 m).")
    negative_distance_m: float = Field(50.0, gt=0, description="Negatives: patches of its split farther than this (same source: 50 m).")
    points: int = Field(4096, ge=16, description="Points per cloud (PointNetVLAD's submaps hold 4096). A patch with more is drawn "
                        "at random without replacement; one with fewer repeats random points of its own.")
    max_negatives: Optional[int] = Field(4000, ge=1, description="Negatives listed per query, a random sample when there are more: "
                                         "PointNetVLAD lists all, but its trainer only ever takes 4000 of them at a time "
                                         "(train_pointnetvlad.py, sampled_neg), and all of them would make the pickle grow with "
                                         "the square of the patches. None lists all.")
    folder: str = Field("pointnetvlad", description="Output folder, inside the triplet dataset's.")

    @model_validator(mode="after")
    def _check(self) -> "PointNetVladConfig":
        if self.negative_distance_m < self.positive_distance_m:
            raise ValueError(f"negative_distance_m ({self.negative_distance_m}) must not be below positive_distance_m ({self.positive_distance_m})")
        return self


def export_pointnetvlad(dataset: str | Path, workspace: str | Path, out: str | Path | None = None,
                        config: PointNetVladConfig | str | Path | None = None, overrides: Optional[dict] = None, seed: int = 0) -> Path:
    """Write the PointNetVLAD layout of the triplet dataset ``dataset`` (made from ``workspace``);
    returns its folder (default ``DATASET/<config.folder>``). Re-running with the same config and
    dataset does nothing."""
    from .bundle import building
    from .patches import PatchDomain
    from .triplets import SPLITS, TripletDataset, load_aligned_sessions

    cfg = config if isinstance(config, PointNetVladConfig) else load_config(PointNetVladConfig, config, overrides)
    dataset, workspace = Path(dataset), Path(workspace)
    ds = TripletDataset(dataset)
    out = Path(out) if out is not None else dataset / cfg.folder
    h = config_hash({"cfg": cfg, "seed": seed, "dataset": ds.manifest["config_hash"], "patches": ds.manifest["patches"]})
    if is_done(out, h):
        return out
    names = list(ds.manifest["sessions"])
    sessions, _ = load_aligned_sessions(workspace, names)
    by_name = {s.name: s for s in sessions}
    domain = PatchDomain(**ds.manifest["domain"])
    t = ds.table
    final = out
    with building(final) as out:
        atomic_write_text(out / "config.yaml", dump_config(cfg))
        files = np.array([f"{names[int(s)]}/pointcloud_patches/{int(p):06d}.bin" for p, s in zip(t["patch_id"], t["session"])], dtype=object)
        written = np.zeros(len(files), bool)
        for k, name in enumerate(names):
            rows = np.flatnonzero(t["session"] == k)
            if len(rows) == 0:
                continue
            (out / name / "pointcloud_patches").mkdir(parents=True, exist_ok=True)
            for b in range(0, len(rows), 64):  # 64 patches at a time bound the candidates' memory
                block = rows[b : b + 64]
                clouds = patch_clouds(by_name[name], t["enu"][block], t["transform"][block], t["yaw"][block], domain)
                for row, cloud in zip(block, clouds):
                    if len(cloud) == 0:
                        continue
                    pts = sample_cloud(cloud, cfg.points, np.random.default_rng([seed, int(t["patch_id"][row])]))
                    # inside the box, so within [-1, 1] (the folder as a whole is renamed into place last)
                    np.ascontiguousarray(pts / float(np.max(domain.box_half_extents)), np.float64).tofile(out / files[row])
                    written[row] = True
        utm = t["utm"]
        _write_locations(out, names, t, files, written, utm)
        counts = {}
        rng = np.random.default_rng(seed)
        for split in SPLITS:
            rows = np.flatnonzero((t["split"] == split) & written)
            queries = query_dict(utm[rows, 1], utm[rows, 0], cfg.positive_distance_m, cfg.negative_distance_m, cfg.max_negatives, rng)
            for key, row in enumerate(rows):
                queries[key].update({"query": str(files[row]), "patch_id": int(t["patch_id"][row]), "session": names[int(t["session"][row])]})
            with atomic_path(out / QUERY_FILES[split]) as tmp:
                with open(tmp, "wb") as f:
                    pickle.dump(queries, f, protocol=pickle.HIGHEST_PROTOCOL)
            counts[split] = len(rows)
            del queries
        write_json(out / "manifest.json", {
            "format_version": PNV_FORMAT_VERSION, "layout": "PointNetVLAD (github.com/mikacuy/pointnetvlad)",
            "dataset": ".." if final.parent == dataset else str(dataset),
            "dataset_config_hash": ds.manifest["config_hash"], "seed": seed, "config_hash": h, "queries": counts,
            "patches_left_out": int((~written).sum()), "points_per_cloud": cfg.points, "dtype": "float64, x y z interleaved",
            "scale_m": float(np.max(domain.box_half_extents)), "frame": "the patch's yaw-normalised frame, keypoint at the origin",
            "files": {n: sha256_file(out / n) for n in (*QUERY_FILES.values(), "pointcloud_locations.csv")},
        })
        mark_done(out, h)
    return final


def patch_clouds(session, centres: np.ndarray, transforms: np.ndarray, yaws: np.ndarray, domain) -> list[np.ndarray]:
    """The points of each patch in its normalised frame (metres): the session's points moved by
    the patch's ICP transform, cut to the patch about its centre as :mod:`mapkit.triplets` cut
    them (within 2 m of the patch radius before the move, within the radius and half height
    after), turned by -yaw, and cut to the domain's box as the voxel grids were."""
    centres = np.asarray(centres, np.float64).reshape(-1, 3)
    crop = domain.patch_radius + 2.0
    indptr, idx = session.grid.candidates_many(centres[:, :2], crop)
    counts = np.diff(indptr)
    owner = np.repeat(np.arange(len(centres)), counts)
    raw = session.points[idx]
    d = raw[:, :2] - centres[owner, :2]
    T = transforms[owner]
    moved = np.einsum("nij,nj->ni", T[:, :3, :3], raw) + T[:, :3, 3]
    rel = moved - centres[owner]
    keep = (np.einsum("ij,ij->i", d, d) <= crop * crop) & (np.hypot(rel[:, 0], rel[:, 1]) <= domain.patch_radius)
    keep &= np.abs(rel[:, 2]) <= domain.patch_half_height
    c, s = np.cos(yaws)[owner], np.sin(yaws)[owner]
    norm = np.stack([c * rel[:, 0] + s * rel[:, 1], c * rel[:, 1] - s * rel[:, 0], rel[:, 2]], axis=1)
    keep &= np.all(np.abs(norm) <= domain.box_half_extents, axis=1)
    bounds = np.concatenate([[0], np.cumsum(np.bincount(owner[keep], minlength=len(centres)))])
    kept = norm[keep]
    return [kept[bounds[k] : bounds[k + 1]] for k in range(len(centres))]


def sample_cloud(points: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """Exactly ``n`` of ``points``: a random subset without replacement, or all of them and random
    repeats when there are fewer."""
    if len(points) >= n:
        return points[np.sort(rng.choice(len(points), n, replace=False))]
    return np.concatenate([points, points[rng.choice(len(points), n - len(points))]])


def query_dict(northing: np.ndarray, easting: np.ndarray, positive_m: float, negative_m: float, max_negatives: Optional[int],
               rng: np.random.Generator) -> dict[int, dict]:
    """PointNetVLAD's query dictionary of one split, without the file names: key k (0..n-1) to
    its position, the keys within ``positive_m`` (itself left out) and those farther than
    ``negative_m`` (at most ``max_negatives``, drawn at random), both ascending lists."""
    from scipy.spatial import cKDTree

    ne = np.stack([northing, easting], axis=1).astype(np.float64)
    n = len(ne)
    keys = list(range(n))  # the lists share these int objects: 8 bytes per entry, not 36
    pick = keys.__getitem__
    out: dict[int, dict] = {}
    if n == 0:
        return out
    tree = cKDTree(ne)
    for k in range(n):
        if k % 256 == 0:  # neighbour lists a block at a time: all of them at once would hold n^2 Python ints
            near = tree.query_ball_point(ne[k : k + 256], positive_m)
            within = tree.query_ball_point(ne[k : k + 256], negative_m)
        pos = np.sort(np.asarray(near[k % 256], np.int64))
        excluded = np.zeros(n, bool)
        excluded[within[k % 256]] = True
        neg = np.flatnonzero(~excluded)
        if max_negatives is not None and len(neg) > max_negatives:
            neg = np.sort(rng.choice(neg, max_negatives, replace=False))
        out[k] = {"northing": float(ne[k, 0]), "easting": float(ne[k, 1]), "positives": list(map(pick, pos[pos != k].tolist())),
                  "negatives": list(map(pick, neg.tolist()))}
    return out


def _write_locations(out: Path, names: list[str], t: dict, files: np.ndarray, written: np.ndarray, utm: np.ndarray) -> None:
    """PointNetVLAD's per-run CSVs (timestamp = the file's name, northing, easting), one per
    session, and one of all patches with their split and set."""
    per_session: dict[int, list[str]] = {}
    rows_all = ["file,northing,easting,split,role,set_id,patch_id,session"]
    for i in np.flatnonzero(written):
        s = int(t["session"][i])
        per_session.setdefault(s, ["timestamp,northing,easting"]).append(f"{int(t['patch_id'][i]):06d},{utm[i, 1]:.3f},{utm[i, 0]:.3f}")
        rows_all.append(f"{files[i]},{utm[i, 1]:.3f},{utm[i, 0]:.3f},{t['split'][i]},{t['role'][i]},{int(t['set_id'][i])},"
                        f"{int(t['patch_id'][i])},{names[s]}")
    for s, lines in per_session.items():
        atomic_write_text(out / names[s] / "pointcloud_locations.csv", "\n".join(lines) + "\n")
    atomic_write_text(out / "pointcloud_locations.csv", "\n".join(rows_all) + "\n")


def read_queries(folder: str | Path, split: str = "train") -> dict[int, dict]:
    """The query dictionary of ``split`` in a PointNetVLAD folder."""
    with open(Path(folder) / QUERY_FILES[split], "rb") as f:
        return pickle.load(f)


def load_cloud(folder: str | Path, query: str, n: int = 4096) -> np.ndarray:
    """(n, 3) points of one cloud file, as PointNetVLAD's loader reads it."""
    return np.fromfile(Path(folder) / query, dtype=np.float64).reshape(n, 3)
