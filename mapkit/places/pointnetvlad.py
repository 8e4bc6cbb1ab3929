"""A triplet dataset in the layout PointNetVLAD's scripts read.

PointNetVLAD (Uy and Lee, CVPR 2018; github.com/mikacuy/pointnetvlad) works on submaps, each a
binary file of 4096 points (float64, x y z interleaved: an N x 3 array), centred on their
centroid, scaled to a mean distance of 0.5 from it and cut to [-1, 1], with the road plane
removed (``submap_generation/generate_submaps.m``). Each run (drive) lists its submaps in a CSV of
``timestamp,northing,easting``, the timestamp (an integer) naming the file; their query scripts
read the CSV with pandas and build ``<run>/<folder>/`` + str(timestamp) + ``.bin``, so a name
must be the decimal integer pandas parses (no leading zeros). From the CSVs they pickle:

* ``training_queries_baseline.pickle`` / ``test_queries_baseline.pickle``
  (``generate_training_tuples_baseline.py``): key k (consecutive, over the runs' CSV rows in
  order) -> ``{"query": file, "positives": [keys], "negatives": [keys]}``, positives within 10 m,
  negatives beyond 50 m;
* ``PREFIX_evaluation_database.pickle`` (``generate_test_sets.py``): a list, one dict per run,
  key -> ``{"query": file, "northing", "easting"}`` of all the run's submaps;
  ``PREFIX_evaluation_query.pickle``: the same of the run's test submaps, each with, for every
  other run i, ``[i]`` = the keys of run i's database within 25 m.

Here the submaps are the patches of a :mod:`mapkit.places.triplets` dataset, from the same ground truth:
the same patches (each one's session points, moved by its ICP transform, cut to the patch and
turned by its yaw, as the CNN grids were made), their UTM positions (the place's keypoint, shared
by the members of a correspondence set) and their train/test tiles (so no test query has a
training patch within the tiles' buffer). A run is a session; a patch's timestamp is the time (ns)
of the keyframe that first observed its keypoint, raised by a few ns where patches share one (a
unique, sortable integer per run). Per patch the ground plane is removed (RANSAC, near-horizontal
planes only), the cloud drawn to exactly ``points`` points, centred on its centroid, scaled to
PointNetVLAD's spread (mean distance 0.5) and kept inside [-1, 1] (a point outside is replaced by
another of the patch's that falls inside, then the cloud is centred again and, when needed,
shrunk to fit). generate_submaps.m also negates the coordinates (a point reflection); this export
does not, so the clouds keep the patch frame's handedness. The centroid and scale of every cloud
are listed (metric point = cloud point / scale + centroid, in the patch's yaw-normalised frame).

Layout of the output folder::

    <session>/pointcloud_patches/<timestamp>.bin     one cloud per patch, float64 (points, 3)
    <session>/pointcloud_locations.csv               timestamp, northing, easting (rows by timestamp)
    pointcloud_locations.csv                         all clouds: file, timestamp, northing, easting, split, role,
                                                     set_id, patch_id, session, centroid, scale
    training_queries_baseline.pickle                 the train split's query dictionary
    test_queries_baseline.pickle                     the test split's
    PREFIX_evaluation_database.pickle                per session: all its clouds
    PREFIX_evaluation_query.pickle                   per session: its test clouds and their true matches
    manifest.json, config.yaml
"""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np

from mapkit.core.bundle import building
from mapkit.core.config import dump_config, load_config
from mapkit.core.runio import (
    atomic_path,
    atomic_write_text,
    config_hash,
    is_done,
    mark_done,
    sha256_file,
    stage_digest,
    stage_hash,
    write_json,
)
from mapkit.core.writers import writes_workspace
from mapkit.places.pointnetvlad_config import PointNetVladConfig
from mapkit.places.triplets import (
    SPLITS,
    NoTripletsError,
    TripletConfig,
    TripletDataset,
    export_triplets,
    load_aligned_sessions,
)

__all__ = [
    "PointNetVladConfig",
    "export_pointnetvlad",
    "export_triplets_pointnetvlad",
    "evaluation_sets",
    "normalise_cloud",
    "patch_clouds",
    "query_dict",
    "remove_ground",
    "sample_cloud",
    "unique_stamps",
]

#: the version of this stage's algorithm, bumped whenever its output for the same inputs changes (it reruns)
STAGE_VERSION = 1
PNV_FORMAT_VERSION = 2  # 2: integer timestamps, zero-mean clouds scaled as PointNetVLAD's, evaluation pickles
QUERY_FILES = {"train": "training_queries_baseline.pickle", "test": "test_queries_baseline.pickle"}
CLOUD_FOLDER = "pointcloud_patches"
LOCATIONS_CSV = "pointcloud_locations.csv"


def evaluation_files(cfg: PointNetVladConfig) -> dict[str, str]:
    return {
        "database": f"{cfg.evaluation_prefix}_evaluation_database.pickle",
        "query": f"{cfg.evaluation_prefix}_evaluation_query.pickle",
    }


@writes_workspace("workspace")
def export_triplets_pointnetvlad(
    workspace: str | Path,
    out: str | Path | None = None,
    config: str | Path | None = None,
    overrides: dict | None = None,
    progress: bool = True,
) -> Path:
    """:func:`mapkit.places.triplets.export_triplets`, then, when the config's ``pointnetvlad.enabled``,
    :func:`export_pointnetvlad` into ``DATASET/<pointnetvlad.folder>`` (what ``mapkit triplets``
    runs). Each stage is skipped when already done with the same settings."""
    folder = export_triplets(workspace, out, config, overrides=overrides, progress=progress)
    cfg = load_config(TripletConfig, config, overrides)
    if cfg.pointnetvlad.enabled:
        export_pointnetvlad(folder, workspace, folder / cfg.pointnetvlad.folder, cfg.pointnetvlad, seed=cfg.seed)
    return folder


@writes_workspace("out", within=True, default="dataset")
def export_pointnetvlad(
    dataset: str | Path,
    workspace: str | Path,
    out: str | Path | None = None,
    config: PointNetVladConfig | str | Path | None = None,
    overrides: dict | None = None,
    seed: int = 0,
) -> Path:
    """Write the PointNetVLAD layout of the triplet dataset ``dataset`` (made from ``workspace``);
    returns its folder (default ``DATASET/<config.folder>``). Re-running with the same config and
    dataset does nothing. No cloud to write is a :class:`~mapkit.places.triplets.NoTripletsError`."""
    from mapkit.places.patches import PatchDomain

    cfg = config if isinstance(config, PointNetVladConfig) else load_config(PointNetVladConfig, config, overrides)
    dataset, workspace = Path(dataset), Path(workspace)
    ds = TripletDataset(dataset)
    out = Path(out) if out is not None else dataset / cfg.folder
    identity = {
        "cfg": cfg.model_dump(mode="json", exclude={"enabled"}),
        "seed": seed,
        "format": PNV_FORMAT_VERSION,
        "dataset": ds.manifest["config_hash"],
        "patches": ds.manifest["patches"],
    }
    h = stage_hash("pointnetvlad", STAGE_VERSION, identity)
    inputs = {"dataset": stage_digest(dataset)}  # a dataset made again from re-aligned maps: its clouds moved
    if is_done(out, h, inputs=inputs, legacy_hash=config_hash(identity), version=STAGE_VERSION):
        return out
    names = list(ds.manifest["sessions"])
    t = ds.table
    if len(t["patch_id"]) == 0:
        raise NoTripletsError(
            dataset / "manifest.json", "the triplet dataset holds no patch: nothing to write in PointNetVLAD's layout"
        )
    sessions, _ = load_aligned_sessions(workspace, names, ds.manifest.get("map_source", "semidense"))
    by_name = {s.name: s for s in sessions}
    domain = PatchDomain(**ds.manifest["domain"])
    n = len(t["patch_id"])
    stamps, files = _cloud_files(names, t, by_name)
    final = out
    with building(final) as out:  # a partial folder, renamed into place last
        atomic_write_text(out / "config.yaml", dump_config(cfg))
        written, centroid, scale = _write_clouds(out, names, t, by_name, domain, files, cfg, seed)
        if not written.any():
            raise NoTripletsError(
                dataset,
                f"no PointNetVLAD cloud written: all {n} patches are empty"
                + (
                    f" once the ground (within ground_distance_m={cfg.ground_distance_m:g}) is removed; "
                    "set ground_distance_m to null to keep it"
                    if cfg.ground_distance_m is not None
                    else ""
                ),
            )
        # the CSVs, and positions as their scripts read them back from the CSVs
        order, ne = _write_locations(out, names, t, files, stamps, written, centroid, scale)
        counts = _write_query_sets(out, names, t, files, order, ne, cfg, seed)
        runs, n_eval = _write_evaluation_sets(out, names, t, files, written, order, ne, cfg)
        dataset_ref = ".." if final.parent == dataset else str(dataset)
        left_out = int((~written).sum())
        manifest = _manifest(out, cfg, ds, dataset_ref, h, seed, counts, [names[k] for k in runs], n_eval, left_out)
        write_json(out / "manifest.json", manifest)
        mark_done(out, h, version=STAGE_VERSION, inputs=inputs)
    return final


def _cloud_files(names: list[str], t: dict, by_name: dict) -> tuple[np.ndarray, np.ndarray]:
    """Per patch its timestamp and cloud file (``<session>/pointcloud_patches/<timestamp>.bin``):
    per session, unique integer stamps (ns) of the patches' first observer keyframes."""
    stamps = np.zeros(len(t["patch_id"]), np.int64)
    for k, name in enumerate(names):
        rows = np.flatnonzero(t["session"] == k)
        if len(rows):
            stamps[rows] = unique_stamps(by_name[name].frame_stamps_ns(t["frame"][rows]), t["patch_id"][rows])
    files = np.array(
        [f"{names[int(s)]}/{CLOUD_FOLDER}/{int(ts)}.bin" for s, ts in zip(t["session"], stamps, strict=True)],
        dtype=object,
    )
    return stamps, files


def _write_clouds(
    out: Path,
    names: list[str],
    t: dict,
    by_name: dict,
    domain,
    files: np.ndarray,
    cfg: PointNetVladConfig,
    seed: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every patch's cloud into ``out / files[row]``: cut from its session's points, the ground
    removed, drawn and normalised (each patch with its own generator, seeded by ``seed`` and its
    patch id). Returns which patches were written (not empty once the ground is removed), and
    their centroids (n, 3) and scales (n,)."""
    n = len(t["patch_id"])
    written = np.zeros(n, bool)
    centroid, scale = np.zeros((n, 3)), np.zeros(n)
    for k, name in enumerate(names):
        rows = np.flatnonzero(t["session"] == k)
        if len(rows) == 0:
            continue
        (out / name / CLOUD_FOLDER).mkdir(parents=True, exist_ok=True)
        for b in range(0, len(rows), 64):  # 64 patches at a time bound the candidates' memory
            block = rows[b : b + 64]
            clouds = patch_clouds(by_name[name], t["enu"][block], t["transform"][block], t["yaw"][block], domain)
            for row, cloud in zip(block, clouds, strict=True):
                rng = np.random.default_rng([seed, int(t["patch_id"][row])])
                if cfg.ground_distance_m is not None:
                    cloud = remove_ground(cloud, cfg.ground_distance_m, cfg.ground_max_tilt_deg, rng)
                if len(cloud) == 0:
                    continue
                pts, centroid[row], scale[row] = normalise_cloud(cloud, cfg.points, rng)
                np.ascontiguousarray(pts, "<f8").tofile(out / files[row])
                written[row] = True
    return written, centroid, scale


def _write_query_sets(
    out: Path,
    names: list[str],
    t: dict,
    files: np.ndarray,
    order: np.ndarray,
    ne: np.ndarray,
    cfg: PointNetVladConfig,
    seed: int,
) -> dict[str, int]:
    """The training and test query pickles: per split, its written clouds in the CSVs' ``order``
    with their positives and negatives (:func:`query_dict`, negatives drawn from one generator
    seeded by ``seed`` over the splits in turn), file, patch id and session. Returns the queries
    per split."""
    counts = {}
    rng = np.random.default_rng(seed)
    for split in SPLITS:
        rows = order[t["split"][order] == split]
        queries = query_dict(
            ne[rows, 0], ne[rows, 1], cfg.positive_distance_m, cfg.negative_distance_m, cfg.max_negatives, rng
        )
        for key, row in enumerate(rows):
            queries[key].update(
                {
                    "query": str(files[row]),
                    "patch_id": int(t["patch_id"][row]),
                    "session": names[int(t["session"][row])],
                }
            )
        _pickle(out / QUERY_FILES[split], queries)
        counts[split] = len(rows)
        del queries
    return counts


def _write_evaluation_sets(
    out: Path,
    names: list[str],
    t: dict,
    files: np.ndarray,
    written: np.ndarray,
    order: np.ndarray,
    ne: np.ndarray,
    cfg: PointNetVladConfig,
) -> tuple[list[int], int]:
    """The evaluation database and query pickles (:func:`evaluation_sets`), one run per session
    with a written cloud, its clouds in the CSVs' ``order``. Returns the runs (session indices)
    and the number of evaluation queries."""
    runs = [k for k in range(len(names)) if np.any(written & (t["session"] == k))]
    run_rows = [order[t["session"][order] == k] for k in runs]
    database, query = evaluation_sets(
        [ne[r] for r in run_rows], [t["split"][r] == "test" for r in run_rows], cfg.evaluation_distance_m
    )
    for sets in (database, query):
        for i, entries in enumerate(sets):
            for entry in entries.values():
                row = run_rows[i][entry.pop("row")]
                entry.update({"query": str(files[row]), "patch_id": int(t["patch_id"][row])})
    ev = evaluation_files(cfg)
    _pickle(out / ev["database"], database)
    _pickle(out / ev["query"], query)
    return runs, int(sum(len(q) for q in query))


def _manifest(
    out: Path,
    cfg: PointNetVladConfig,
    ds: TripletDataset,
    dataset_ref: str,
    config_digest: str,
    seed: int,
    counts: dict[str, int],
    runs: list[str],
    n_eval_queries: int,
    left_out: int,
) -> dict:
    """The manifest of the folder ``out`` (its pickles and CSV written): format, source dataset,
    settings, counts, the layout's conventions and the checksums of the files PointNetVLAD reads."""
    return {
        "format_version": PNV_FORMAT_VERSION,
        "layout": "PointNetVLAD (github.com/mikacuy/pointnetvlad)",
        "dataset": dataset_ref,
        "dataset_config_hash": ds.manifest["config_hash"],
        "seed": seed,
        "config_hash": config_digest,
        "queries": counts,
        "runs": runs,
        "evaluation_queries": n_eval_queries,
        "thresholds_m": {
            "positive": cfg.positive_distance_m,
            "negative": cfg.negative_distance_m,
            "evaluation": cfg.evaluation_distance_m,
        },
        "patches_left_out": left_out,
        "points_per_cloud": cfg.points,
        "dtype": "float64, x y z interleaved (points, 3)",
        "file_names": "<session>/pointcloud_patches/<timestamp>.bin, timestamp = first observer keyframe's "
        "time (ns), made unique per session",
        "normalisation": "ground plane removed, centred on the centroid, scaled to a mean distance of 0.5, "
        "within [-1, 1]; metric point = point / scale + centroid (pointcloud_locations.csv), in the patch's "
        "yaw-normalised frame",
        "files": {
            f: sha256_file(out / f) for f in (*QUERY_FILES.values(), *evaluation_files(cfg).values(), LOCATIONS_CSV)
        },
    }


def _pickle(path: Path, obj) -> None:
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        pickle.dump(obj, f, protocol=pickle.HIGHEST_PROTOCOL)


def unique_stamps(stamps_ns: np.ndarray, tiebreak: np.ndarray) -> np.ndarray:
    """Per patch a distinct integer from its time stamp: patches sharing a stamp (one keyframe
    first observed several keypoints) get it raised by 1, 2, ... ns in ``tiebreak`` order, and
    every stamp stays above those before it. Sorting the results sorts by time."""
    stamps_ns, tiebreak = np.asarray(stamps_ns, np.int64), np.asarray(tiebreak)
    order = np.lexsort((tiebreak, stamps_ns))
    s = stamps_ns[order]
    # s_u[i] = max(s[i], s_u[i-1] + 1), i.e. max over j <= i of s[j] + (i - j)
    idx = np.arange(len(s), dtype=np.int64)
    u = np.maximum.accumulate(s - idx) + idx if len(s) else s
    out = np.empty_like(u)
    out[order] = u
    return out


def remove_ground(
    points: np.ndarray,
    distance: float,
    max_tilt_deg: float,
    rng: np.random.Generator,
    hypotheses: int = 128,
    score_points: int = 1024,
) -> np.ndarray:
    """``points`` without those within ``distance`` of their dominant near-horizontal plane
    (RANSAC: planes through three of the lower half's points, normals within ``max_tilt_deg`` of
    vertical, scored on up to ``score_points`` of the points), as PointNetVLAD removed the road
    (generate_submaps.m: pcfitplane with 0.5 m). No such plane leaves the points as they are."""
    points = np.asarray(points, np.float64)
    if len(points) < 3:
        return points
    low = np.flatnonzero(points[:, 2] <= np.median(points[:, 2]))
    if len(low) < 3:
        return points
    tri = points[low[rng.integers(0, len(low), (hypotheses, 3))]]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(normal, axis=1)
    ok = length > 1e-9
    normal = normal[ok] / length[ok, None]
    ok2 = np.abs(normal[:, 2]) >= np.cos(np.radians(max_tilt_deg))
    normal, origin = normal[ok2], tri[ok][ok2, 0]
    if len(normal) == 0:
        return points
    score = points if len(points) <= score_points else points[rng.choice(len(points), score_points, replace=False)]
    offset = np.einsum("ij,ij->i", normal, origin)
    inliers = (np.abs(score @ normal.T - offset) <= distance).sum(axis=0)
    best = int(np.argmax(inliers))
    return points[np.abs(points @ normal[best] - offset[best]) > distance]


def normalise_cloud(points: np.ndarray, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, float]:
    """(``n`` points of ``points`` as PointNetVLAD scales a submap, their centroid, the scale):
    drawn by :func:`sample_cloud`, centred on their centroid and scaled so that their mean
    distance from it is 0.5 (generate_submaps.m, s = 0.5 / d); a point outside [-1, 1] is replaced
    by a random one of ``points`` inside; then centred again (zero mean) and shrunk when a
    coordinate still exceeds 1. Cloud point = (metric point - centroid) * scale."""
    points = np.asarray(points, np.float64)
    p = sample_cloud(points, n, rng).copy()
    c0 = p.mean(axis=0)
    d = float(np.mean(np.linalg.norm(p - c0, axis=1)))
    s0 = 0.5 / d if d > 0 else 1.0
    out = np.any(np.abs((p - c0) * s0) > 1.0, axis=1)
    if out.any():
        inside = np.flatnonzero(np.all(np.abs((points - c0) * s0) <= 1.0, axis=1))
        if len(inside):
            p[out] = points[rng.choice(inside, int(out.sum()))]
    c = p.mean(axis=0)
    m = float(np.abs((p - c) * s0).max()) if len(p) else 0.0
    s = s0 / max(1.0, m * (1 + 1e-12))
    return (p - c) * s, c, s


def patch_clouds(session, centres: np.ndarray, transforms: np.ndarray, yaws: np.ndarray, domain) -> list[np.ndarray]:
    """The points of each patch in its normalised frame (metres): the session's points moved by
    the patch's ICP transform, cut to the patch about its centre as :mod:`mapkit.places.triplets` cut
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


def query_dict(
    northing: np.ndarray,
    easting: np.ndarray,
    positive_m: float,
    negative_m: float,
    max_negatives: int | None,
    rng: np.random.Generator,
) -> dict[int, dict]:
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
        out[k] = {
            "northing": float(ne[k, 0]),
            "easting": float(ne[k, 1]),
            "positives": list(map(pick, pos[pos != k].tolist())),
            "negatives": list(map(pick, neg.tolist())),
        }
    return out


def evaluation_sets(
    positions: list[np.ndarray], is_query: list[np.ndarray], radius_m: float
) -> tuple[list[dict], list[dict]]:
    """PointNetVLAD's evaluation sets (generate_test_sets.py) of runs whose clouds lie at
    ``positions[i]`` ((n_i, 2) northing, easting): per run a database of all its clouds and a
    query set of those flagged in ``is_query[i]``, both key -> ``{"row", "northing", "easting"}``
    (``row`` indexes ``positions[i]``; the caller replaces it by the file), and in each query of
    run j, for every other run i, ``[i]`` = the ascending database keys of run i within
    ``radius_m``."""
    from scipy.spatial import cKDTree

    database: list[dict[int, dict[str, float]]] = []
    query: list[dict[int, dict[str | int, float | list[int]]]] = []  # [i]: the database keys of run i near it
    for ne, q in zip(positions, is_query, strict=True):
        database.append(
            {k: {"row": k, "northing": float(ne[k, 0]), "easting": float(ne[k, 1])} for k in range(len(ne))}
        )
        query.append(
            {
                key: {"row": int(k), "northing": float(ne[k, 0]), "easting": float(ne[k, 1])}
                for key, k in enumerate(np.flatnonzero(q))
            }
        )
    trees = [cKDTree(np.asarray(ne, np.float64).reshape(-1, 2)) for ne in positions]
    for j, qs in enumerate(query):
        if not qs:
            continue
        at = np.array([[e["northing"], e["easting"]] for e in qs.values()])
        for i, tree in enumerate(trees):
            if i == j:
                continue
            near = tree.query_ball_point(at, radius_m)
            for key, nb in zip(qs, near, strict=True):
                qs[key][i] = sorted(int(x) for x in nb)
    return database, query


def _write_locations(
    out: Path,
    names: list[str],
    t: dict,
    files: np.ndarray,
    stamps: np.ndarray,
    written: np.ndarray,
    centroid: np.ndarray,
    scale: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """PointNetVLAD's per-run CSVs (``timestamp,northing,easting``, by timestamp), one per
    session, and one of all clouds with their split, set, centroid and scale. Returns the
    written rows in the CSVs' order (sessions in order, each by timestamp) and every row's
    (northing, easting) as read back from the CSV text (so distances computed here are those
    PointNetVLAD's scripts compute from the files)."""
    utm = t["utm"]
    ne = np.full((len(files), 2), np.nan)
    order = []
    rows_all = [
        "file,timestamp,northing,easting,split,role,set_id,patch_id,session,centroid_x_m,centroid_y_m,centroid_z_m,scale"
    ]
    for k, name in enumerate(names):
        rows = np.flatnonzero(written & (t["session"] == k))
        if len(rows) == 0:
            continue
        rows = rows[np.argsort(stamps[rows], kind="stable")]
        order.append(rows)
        lines = ["timestamp,northing,easting"]
        for i in rows:
            n_txt, e_txt = f"{utm[i, 1]:.6f}", f"{utm[i, 0]:.6f}"
            ne[i] = float(n_txt), float(e_txt)
            lines.append(f"{int(stamps[i])},{n_txt},{e_txt}")
            c = centroid[i]
            rows_all.append(
                f"{files[i]},{int(stamps[i])},{n_txt},{e_txt},{t['split'][i]},{t['role'][i]},{int(t['set_id'][i])},"
                f"{int(t['patch_id'][i])},{name},{float(c[0])!r},{float(c[1])!r},{float(c[2])!r},{float(scale[i])!r}"
            )  # repr: exact round trip
        atomic_write_text(out / name / LOCATIONS_CSV, "\n".join(lines) + "\n")
    atomic_write_text(out / LOCATIONS_CSV, "\n".join(rows_all) + "\n")
    return (np.concatenate(order) if order else np.zeros(0, np.int64)), ne
