"""``mapkit eval places``: place-recognition precision, recall and AUC in the form of Table 2 of
the semi-dense place-recognition paper (Sec. 5.2).

For each pair of sessions (a database session and a query session) and each method, every
``query_stride``-th keyframe q of the query session is a query. Its ground-truth position p_q is
its aligned keyframe position, or the synthetic town's true camera position when ``truth`` is
given; database places d are the database session's frames with their positions (the same
source). With r_e = 25 m, Table 1 scores one query:

=========================  =========================================  ==  ==  ==
                                                                      tp  fp  fn
=========================  =========================================  ==  ==  ==
d matched to q             |p_q - p_d| <= r_e                          1   0   0
                           else, some d' of D within r_e of p_q         0   1   1
                           otherwise                                    0   1   0
no place matched to q      some d' of D within r_e of p_q               0   0   1
                           otherwise                                    0   0   0
=========================  =========================================  ==  ==  ==

A method gives each query its best place and a score; the match is accepted when the score
passes a threshold, and sweeping the threshold traces the precision-recall curve. Methods:

- ``nbld``, ``m2dp``, ``cnn`` (the trained model of ``structure.cnn_model``): the structure voting index of
  :mod:`mapkit.places.index_structure`, built on the database session alone; the score is the vote count
  v(d), the threshold lambda_v (Sec. 3.4).
- ``vlad``: the appearance baseline (the paper's is NetVLAD; mapkit's image index is dense-SIFT
  VLAD, :mod:`mapkit.retrieval.index_vlad`): the query is the image of the query session nearest in time
  to the keyframe, the match the nearest database image of the database session (top-1 by L2,
  restricted to that session), the score minus its squared distance.

The area under the PR curve is ``sum_i (R_i - R_{i-1}) P_i`` over the thresholds in decreasing
order from R_0 = 0 (the step-wise "average precision" form; the paper does not say which
integration it uses). Recall here cannot reach 1 when wrong matches of reachable queries remain
at the lowest threshold, as in the paper's curves.

Held-out places (Sec. 5.1): the paper divides each sequence into geographically non-overlapping
training and testing parts, trains on the first and scores only the second. Here the places are
split by the UTM tiles of :mod:`mapkit.places.triplets` (:func:`~mapkit.places.triplets.tile_split`,
:func:`~mapkit.places.triplets.split_of`): the tiles of the triplet dataset the CNN learned from
when there is one, so that no held-out query lies in (or within ``buffer_m`` of) a tile whose
patches trained it; else tiles drawn the way ``mapkit triplets`` would with its defaults. A held-out
query is a query whose true position lies in a test tile, outside the buffer strip. Every figure
is reported twice: over held-out queries (the headline, ``pairs[i].methods``) and over all
queries (``pairs[i].all_places.methods``). The paper matches the testing parts of two sequences
against each other; mapkit keeps the database session whole, so the places of training tiles
stay in the database as distractors (a held-out query can only be right in a test tile, since
the buffer is wider than r_e by default, but it can be wrongly matched anywhere).
"""

from __future__ import annotations

import csv
import io
import json
import logging
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field
from scipy.spatial import cKDTree

from mapkit.core.config import MapkitConfig, dump_config, load_config
from mapkit.core.errors import InputError, InputWarning
from mapkit.core.geodesy import LocalFrame
from mapkit.core.geometry import interpolate_poses
from mapkit.core.runio import atomic_write_text, write_json, write_timings
from mapkit.core.workspace import MapKind, Workspace
from mapkit.core.writers import writes_workspace
from mapkit.io.plots import _save
from mapkit.mapping.semidense import SemiDenseMap
from mapkit.places.index_structure import (
    StructureIndex,
    StructureIndexConfig,
    build_structure_index,
    load_session_map,
    session_descriptors,
    session_map_checksum,
)
from mapkit.places.lidar_observations import LIDAR_FRAME_SPACING_M
from mapkit.places.triplets import (
    TripletConfig,
    load_aligned_sessions,
    split_of,
    tile_split,
    tiles_from_manifest,
    tiles_to_manifest,
)
from mapkit.retrieval.index_vlad import VladIndex, read_session_images

log = logging.getLogger(__name__)

STRUCTURE_METHODS = ("nbld", "m2dp", "cnn")
METHOD_LABELS = {"nbld": "NBLD", "m2dp": "M2DP", "cnn": "CNN", "vlad": "VLAD"}


class PlacesEvalConfig(MapkitConfig):
    """The evaluation protocol of Sec. 5.2."""

    radius_m: float = Field(
        25.0,
        gt=0,
        description="r_e: a match within this distance of the query's true position is right (Sec. 5.2: 25 m).",
    )
    query_stride: int = Field(
        2, ge=1, description="Every n-th keyframe of the query session is a query (mapkit's choice, for speed)."
    )
    structure: StructureIndexConfig = Field(
        default_factory=StructureIndexConfig,
        description="The structure index (kind and database_sessions are set per method and pair; 5 % keypoints, PCA "
        "to 25).",
    )
    max_image_gap_s: float = Field(
        1.0,
        gt=0,
        description="VLAD: a query keyframe whose nearest image is farther than this in time has no image query "
        "(counted as no match).",
    )
    vlad_workers: int = Field(1, ge=1, description="Processes encoding VLAD query images.")
    vlad_encodings_dir: str | None = Field(
        None,
        description="A folder of VLAD encodings shared with other evaluations (e.g. `mapkit eval localize "
        "--cache-dir`): images already encoded there with the same bundle are not encoded again.",
    )
    descriptor_cache_dir: str | None = Field(
        None,
        description="A folder of structure descriptors shared with index builds (the demo shares "
        "WORKSPACE/indexes/cache): maps already described there with the same parameters are not described again; "
        "default: this evaluation's cache/.",
    )
    bootstrap: int = Field(
        500,
        ge=0,
        description="Resamples of the queries for the AUC's 90 % interval and the paired comparison of methods (0 = "
        "none). Not in the paper; ~100 queries per pair make differences of a few hundredths noise.",
    )
    split: Literal["triplets", "tiles", "none"] = Field(
        "triplets",
        description="Which queries are held out, i.e. scored in the headline figures (semi-dense paper, Sec. 5.1: each "
        "sequence is divided into geographically non-overlapping training and testing parts, and only testing places "
        "are evaluated). 'triplets': the UTM tiles of the triplet dataset (triplets_dir, else the CNN model's training "
        "dataset, else WORKSPACE/triplets), so the CNN is scored on places it never trained on; without a dataset, as "
        "'tiles'. 'tiles': tiles drawn as mapkit triplets draws them with TripletConfig's defaults (200 m, 25 % test, "
        "seed 0, 30 m buffer). 'none': no split, every query is scored (the all-places figures become the headline). A "
        "held-out query lies in a test tile, not within the buffer of a training tile. All-places figures are reported "
        "as well.",
    )
    triplets_dir: str | None = Field(
        None,
        description="The triplet dataset (mapkit triplets) whose tiles split the places when split = triplets; "
        "default: the CNN model's training dataset when it still exists, else WORKSPACE/triplets.",
    )


# --------------------------------------------------------------------------- pure computations


def pr_curve(scores: np.ndarray, correct: np.ndarray, reachable: np.ndarray) -> dict:
    """Precision and recall over every threshold t of the scores (a match is accepted when its
    score >= t, i.e. > lambda just below t), in decreasing t.

    ``scores`` (n,), -inf (or NaN) for a query without any match; ``correct`` (n,) the matched
    place lies within r_e; ``reachable`` (n,) some database place does. Returns ``thresholds``,
    ``precision``, ``recall``, ``tp``, ``fp``, ``fn`` (arrays, one per distinct finite score)
    and ``reachable`` (count). A correct match of an unreachable query cannot happen and is an error.
    """
    s = np.asarray(scores, np.float64)
    correct, reachable = np.asarray(correct, bool), np.asarray(reachable, bool)
    if np.any(correct & ~reachable):
        raise InputError(None, "a query is 'correct' but has no database place within the radius", field="correct")
    s = np.where(np.isnan(s), -np.inf, s)
    finite = np.isfinite(s)
    order = np.argsort(-s[finite], kind="stable")
    s_sorted = s[finite][order]
    c_sorted = correct[finite][order]
    tp_c = np.cumsum(c_sorted)
    fp_c = np.cumsum(~c_sorted)
    # one point per distinct threshold: the last query with that score
    last = np.flatnonzero(np.r_[s_sorted[1:] != s_sorted[:-1], True]) if len(s_sorted) else np.zeros(0, np.int64)
    tp, fp = tp_c[last], fp_c[last]
    n_reach = int(reachable.sum())
    # every reachable query not counted as tp is a fn (accepted-and-wrong or not accepted)
    fn = n_reach - tp
    with np.errstate(invalid="ignore", divide="ignore"):
        precision = np.where(tp + fp > 0, tp / np.maximum(tp + fp, 1), 1.0)
        recall = tp / n_reach if n_reach else np.zeros(len(tp))
    return {
        "thresholds": s_sorted[last],
        "precision": precision,
        "recall": recall,
        "tp": tp,
        "fp": fp,
        "fn": fn,
        "reachable": n_reach,
    }


def pr_auc(recall: np.ndarray, precision: np.ndarray) -> float:
    """Area under a PR curve given in decreasing threshold: sum of (R_i - R_{i-1}) P_i, R_0 = 0."""
    r = np.asarray(recall, np.float64)
    p = np.asarray(precision, np.float64)
    if len(r) == 0:
        return 0.0
    return float(np.sum(np.diff(np.r_[0.0, r]) * p))


def best_f1(curve: dict) -> dict:
    """The operating point of highest F1 on a PR curve (threshold, precision, recall, f1)."""
    p, r = curve["precision"], curve["recall"]
    if len(p) == 0:
        return {"f1": 0.0, "precision": None, "recall": 0.0, "threshold": None}
    f1 = np.where(p + r > 0, 2 * p * r / np.maximum(p + r, 1e-12), 0.0)
    i = int(np.argmax(f1))
    return {
        "f1": float(f1[i]),
        "precision": float(p[i]),
        "recall": float(r[i]),
        "threshold": float(curve["thresholds"][i]),
    }


def bootstrap_auc(
    scores: np.ndarray, correct: np.ndarray, reachable: np.ndarray, n: int = 500, seed: int = 0
) -> np.ndarray:
    """(n,) AUCs of queries resampled with replacement. The resamples depend only on the number
    of queries and ``seed``, so two methods scored on the same queries are resampled alike
    (paired comparison)."""
    s, c, r = np.asarray(scores, np.float64), np.asarray(correct, bool), np.asarray(reachable, bool)
    if len(s) == 0:
        return np.zeros(0)
    idx = np.random.default_rng(seed).integers(0, len(s), (n, len(s)))
    out = np.empty(n)
    for i, j in enumerate(idx):
        cv = pr_curve(s[j], c[j], r[j])
        out[i] = pr_auc(cv["recall"], cv["precision"])
    return out


def score_queries(
    query_pos: np.ndarray, matched_pos: np.ndarray, has_match: np.ndarray, db_pos: np.ndarray, radius_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(correct, reachable, error_m) of queries: matched place within ``radius_m`` of the query's
    true position; some database place within it; the distance of the match (NaN without one)."""
    q = np.asarray(query_pos, np.float64).reshape(-1, 3)
    m = np.asarray(matched_pos, np.float64).reshape(-1, 3)
    has = np.asarray(has_match, bool) & np.all(np.isfinite(m), axis=1)
    err = np.where(has, np.linalg.norm(np.where(has[:, None], m, 0.0) - q, axis=1), np.nan)
    correct = has & (err <= radius_m)
    db = np.asarray(db_pos, np.float64).reshape(-1, 3)
    db = db[np.all(np.isfinite(db), axis=1)]
    if len(db) and len(q):
        nearest, _ = cKDTree(db).query(q)
        reachable = nearest <= radius_m
    else:
        reachable = np.zeros(len(q), bool)
    return correct, reachable | correct, err


# --------------------------------------------------------------------------- ground truth


class _Truth:
    """Positions of a session's frames at given stamps: aligned (as given) or the synthetic town's."""

    def __init__(self, workspace: Workspace, truth: Path | None):
        self.truth = truth
        self.ws_frame = Workspace(workspace).frame() if truth is not None else None
        self._cache: dict[str, tuple[np.ndarray, np.ndarray]] = {}

    @property
    def source(self) -> str:
        return (
            "synthetic town (true camera positions)" if self.truth is not None else "aligned keyframe / image positions"
        )

    def positions(self, session: str, stamps_ns: np.ndarray, aligned_pos: np.ndarray) -> np.ndarray:
        """(n, 3) positions: ``aligned_pos`` without a town, else the true camera positions
        interpolated at ``stamps_ns`` (NaN outside the truth's span or for stamps < 0)."""
        aligned_pos = np.asarray(aligned_pos, np.float64).reshape(-1, 3)
        if self.truth is None:
            return aligned_pos
        from mapkit.evaluation.truth import truth_camera_poses

        if session not in self._cache:
            self._cache[session] = truth_camera_poses(self.truth, session, self.ws_frame)
        t, T = self._cache[session]
        stamps = np.asarray(stamps_ns, np.int64)
        out = np.full((len(stamps), 3), np.nan)
        ok = stamps >= 0
        poses, inside = interpolate_poses(t, T, stamps[ok])
        idx = np.flatnonzero(ok)[inside]
        out[idx] = poses[:, :3, 3]
        return out


def _conditions(truth: Path | None) -> dict[str, dict]:
    from mapkit.evaluation.truth import town_sessions

    keys = ("condition", "season", "weather", "date", "time_of_day", "exposure_ev", "role")
    return {name: {k: s.get(k) for k in keys} for name, s in town_sessions(truth).items()}


# --------------------------------------------------------------------------- the held-out split (Sec. 5.1)

SPLIT_LABELS = ("test", "train", "buffer")


@dataclass
class PlaceSplit:
    """The places split into training and test UTM tiles (semi-dense paper, Sec. 5.1), as
    :mod:`mapkit.places.triplets` splits its patches; ``source`` ``"none"``: no split.

    ``tiles`` maps a tile's integer key ``floor(utm / tile_size_m)`` to ``"train"`` or ``"test"``;
    a tile missing from it counts as training (as in :func:`~mapkit.places.triplets.split_of`),
    so a query where the split's map never went is never held out."""

    source: str  # "triplets", "tiles" or "none"
    tiles: dict = field(default_factory=dict)
    tile_size_m: float | None = None
    buffer_m: float | None = None
    test_fraction: float | None = None
    seed: int | None = None
    frame: LocalFrame | None = None
    dataset: str | None = None  # the triplet dataset folder the tiles come from
    dataset_config_hash: str | None = None
    notes: list = field(default_factory=list)  # why this source (fallbacks), what to beware of

    def labels(self, enu: np.ndarray) -> np.ndarray:
        """Per position (the workspace's local ENU, (n, 3)): "test", "train" or "buffer" (within
        ``buffer_m`` of a tile of the other split); "" for every position without a split."""
        enu = np.asarray(enu, np.float64).reshape(-1, 3)
        if self.source == "none" or len(enu) == 0:
            return np.full(len(enu), "", object)
        # a split other than "none" has its frame, tile size and buffer
        assert self.frame is not None and self.tile_size_m is not None and self.buffer_m is not None
        lab = split_of(self.frame.enu_to_utm(enu)[:, :2], self.tiles, self.tile_size_m, self.buffer_m)
        return np.where(lab == "", "buffer", lab).astype(object)

    @property
    def tile_counts(self) -> dict[str, int]:
        return {s: sum(v == s for v in self.tiles.values()) for s in ("train", "test")}

    def held_out(self, enu: np.ndarray) -> np.ndarray:
        """(n,) bool: the position is a held-out place (in a test tile, outside the buffer)."""
        return self.labels(enu) == "test"

    def manifest_tiles(self) -> list[dict]:
        """The tiles in the triplet manifest's form (``utm_min`` corner, ``split``); [] without any."""
        if not self.tiles:
            return []
        assert self.tile_size_m is not None  # tiles come with their size
        return tiles_to_manifest(self.tiles, self.tile_size_m)

    def to_dict(self) -> dict:
        """What ``places.json`` records of the split: its source and parameters, and the tiles in
        the triplet manifest's form (``utm_min`` corner, ``split``)."""
        return {
            "source": self.source,
            "dataset": self.dataset,
            "dataset_config_hash": self.dataset_config_hash,
            "tile_size_m": self.tile_size_m,
            "buffer_m": self.buffer_m,
            "test_fraction": self.test_fraction,
            "seed": self.seed,
            "utm_crs_epsg": None if self.frame is None else int(self.frame.utm_epsg),
            "tile_counts": self.tile_counts,
            "notes": list(self.notes),
            "tiles": self.manifest_tiles(),
        }

    def describe(self) -> str:
        """One sentence for ``places.md``: which tiles, from where, with which buffer."""
        if self.source == "none":
            return "no geographic split (split = none, or no UTM frame): the headline figures are over all queries"
        n = self.tile_counts
        if self.source == "triplets":
            where = f"the triplet dataset {self.dataset}"
        else:
            assert self.test_fraction is not None  # drawn tiles record their test share
            where = f"tiles drawn as mapkit triplets draws them (seed {self.seed}, {100 * self.test_fraction:g} % test)"
        return (
            f"held-out queries lie in test tiles of {where}: UTM tiles of {self.tile_size_m:g} m, {n['test']} test and "
            f"{n['train']} training, and not within {self.buffer_m:g} m of a training tile"
        )


def split_from_dataset(folder: str | Path, frame: LocalFrame) -> PlaceSplit:
    """The split of a triplet dataset: its manifest's tiles and its config's ``tile_size_m`` and
    ``buffer_m``. ``frame`` is the workspace's; a dataset in another UTM zone is refused."""
    folder = Path(folder)
    mpath = folder / "manifest.json"
    if not mpath.is_file():
        raise InputError(mpath, "no such file (not a triplet dataset folder?)", field="triplets_dir")
    man = json.loads(mpath.read_text())
    tcfg = load_config(TripletConfig, folder / "config.yaml")
    epsg = (man.get("frame") or {}).get("utm_crs_epsg")
    if epsg is not None and int(epsg) != int(frame.utm_epsg):
        raise InputError(
            mpath,
            f"the dataset's tiles are in EPSG:{epsg}, the workspace's frame in EPSG:{frame.utm_epsg}",
            field="frame",
        )
    tile = float(tcfg.tile_size_m)
    try:
        tiles = tiles_from_manifest(man.get("tiles") or [], tile)
    except ValueError as exc:
        raise InputError(mpath, f"{exc} (config.yaml's tile_size_m)", field="tiles") from None
    return PlaceSplit(
        "triplets",
        tiles,
        tile,
        float(tcfg.buffer_m),
        float(tcfg.test_fraction),
        int(man.get("seed", tcfg.seed)),
        frame,
        str(folder.resolve()),
        man.get("config_hash"),
    )


def split_from_points(utm_xy: np.ndarray, frame: LocalFrame, tcfg: TripletConfig | None = None) -> PlaceSplit:
    """Tiles drawn over mapped points ``utm_xy`` (n, 2) by :func:`~mapkit.places.triplets.tile_split`
    with ``tcfg``'s tile size, test fraction, seed and buffer (default: TripletConfig's defaults)."""
    tcfg = tcfg or TripletConfig()
    tiles = tile_split(np.asarray(utm_xy, np.float64).reshape(-1, 2), tcfg.tile_size_m, tcfg.test_fraction, tcfg.seed)
    return PlaceSplit(
        "tiles", tiles, float(tcfg.tile_size_m), float(tcfg.buffer_m), float(tcfg.test_fraction), int(tcfg.seed), frame
    )


def tiles_split_of_workspace(
    ws: Workspace,
    frame: LocalFrame,
    tcfg: TripletConfig | None = None,
    fallback_maps: Callable[[], Sequence[SemiDenseMap]] = list,
) -> PlaceSplit:
    """The split ``mapkit triplets`` with ``tcfg`` would draw: :func:`split_from_points` over the
    same sample of points (every session's merged aligned points, at most ~20k of each, see
    ``_Keypoints.draw`` in :mod:`mapkit.places.triplets`). Without a finished alignment, over
    ``fallback_maps()`` (the evaluated sessions' maps, loaded only then), said in the split's notes."""
    try:
        sessions, _ = load_aligned_sessions(ws, (tcfg or TripletConfig()).sessions)
        clouds, note = [s.points for s in sessions], None
    except InputError as exc:
        clouds = [m.points_world for m in fallback_maps()]
        note = f"tiles drawn over the evaluated sessions' map points, not the aligned map's ({exc})"
    if not clouds or not sum(len(c) for c in clouds):
        raise InputError(ws.root, "no mapped points to draw the UTM tiles over", field="split")
    utm = np.concatenate([frame.enu_to_utm(c[:: max(1, len(c) // 20000)])[:, :2] for c in clouds if len(c)])
    split = split_from_points(utm, frame, tcfg)
    if note:
        split.notes.append(note)
    return split


def resolve_split(
    ws: Workspace, cfg: PlacesEvalConfig, fallback_maps: Callable[[], Sequence[SemiDenseMap]] = list
) -> PlaceSplit:
    """The split ``cfg.split`` asks for, with its fallbacks said in ``notes`` (and warned when
    the CNN's held-out figures could include places it trained on):

    - ``triplets``: ``cfg.triplets_dir`` (must exist), else the dataset the CNN model
      (``structure.cnn_model``) records, else ``WORKSPACE/triplets``; without any, ``tiles``.
    - ``tiles``: :func:`tiles_split_of_workspace` with TripletConfig's defaults.
    - ``none``, or a workspace without a geographic frame (no UTM): no split.
    """
    if cfg.split == "none":
        return PlaceSplit("none")
    frame = ws.frame()
    if frame is None:
        note = "the workspace has no geographic frame (origin.json): no UTM tiles, every query is scored (split none)"
        warnings.warn(f"places: {note}", InputWarning, stacklevel=3)
        return PlaceSplit("none", notes=[note])
    model_ds = _model_dataset(cfg)
    split, notes = None, []
    if cfg.split == "triplets":
        if cfg.triplets_dir is not None:
            split = split_from_dataset(cfg.triplets_dir, frame)
        else:
            candidates = [Path(model_ds["path"])] if model_ds and model_ds.get("path") else []
            candidates.append(ws.triplets_dir)
            found = [c for c in candidates if (c / "manifest.json").is_file()]
            if found:
                split = split_from_dataset(found[0], frame)
                if model_ds and model_ds.get("path") and found[0] != Path(model_ds["path"]):
                    notes.append(f"the CNN model's training dataset {model_ds['path']} is gone; tiles of {found[0]}")
            else:
                notes.append(
                    f"no triplet dataset ({', '.join(str(c) for c in candidates)}): tiles drawn with TripletConfig's "
                    "defaults"
                )
    if split is None:
        split = tiles_split_of_workspace(ws, frame, None, fallback_maps)
    split.notes = notes + split.notes
    # the model's manifest records its dataset's tiles: they must be the split's, else the
    # held-out queries may lie where the CNN trained
    if model_ds is not None and model_ds.get("tiles") is not None and model_ds["tiles"] != split.manifest_tiles():
        note = (
            "the CNN model was trained on a triplet dataset whose tiles differ from the split's: its held-out "
            "figures may include places it trained on (set triplets_dir to the model's dataset)"
        )
        warnings.warn(f"places: {note}", InputWarning, stacklevel=3)
        split.notes.append(note)
    return split


def _model_dataset(cfg: PlacesEvalConfig) -> dict | None:
    """What the CNN model's manifest records of its training dataset (path, config hash, tiles), or None."""
    if cfg.structure.cnn_model is None:
        return None
    from mapkit.places.cnn import read_model_manifest

    return read_model_manifest(cfg.structure.cnn_model).get("dataset") or None


def query_split_counts(labels: np.ndarray) -> dict:
    """How many queries fall in test tiles, training tiles and buffer strips."""
    labels = np.asarray(labels, object)
    return {s: int(np.sum(labels == s)) for s in SPLIT_LABELS}


# --------------------------------------------------------------------------- the VLAD baseline


class VladBaseline:
    """The appearance baseline through a VLAD bundle (:mod:`mapkit.retrieval.index_vlad`), same protocol.

    Database vectors of a session come from the bundle when it indexes that session, else the
    session's images are encoded with the bundle's encoder; query images are encoded with it too.
    Encodings are cached per bundle build in ``cache_dir`` (see ``VladIndex.encode_files``).
    """

    name = "vlad"

    def __init__(
        self,
        bundle: str | Path,
        workspace: str | Path,
        cache_dir: Path | None = None,
        workers: int = 1,
        progress: bool = False,
    ):
        self.index = VladIndex.load(bundle)
        self.ws = Path(workspace)
        self.cache_dir = cache_dir
        self.workers = workers
        self.progress = progress
        self._images: dict = {}

    @property
    def train_sessions(self) -> list[str]:
        """Sessions whose images learned the vocabulary and the PCA-whitening."""
        return list(self.index.train_sessions)

    def images(self, session: str):
        if session not in self._images:
            self._images[session] = read_session_images(self.ws, session, self.index.cfg.prefer_aligned_poses)
        return self._images[session]

    def encode(self, session: str, rows: np.ndarray) -> np.ndarray:
        """(len(rows), D) encodings of rows ``rows`` of the session's image table, through the
        bundle's encodings cache in ``cache_dir``: an image is encoded once per bundle."""
        s = self.images(session)
        if not len(rows):
            return np.zeros((0, self.index.dim), np.float32)
        return self.index.encode_files(
            [s.image_paths[r] for r in rows],
            self.progress,
            f"vlad {session}",
            cache_dir=self.cache_dir,
            workers=self.workers,
        )

    def database(self, session: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(vectors (n, D), stamps_ns (n,), positions (n, 3)) of the session's database images."""
        db = self.index.database
        rows = np.flatnonzero(db["session"] == session)
        if len(rows):
            return self.index.vectors()[rows], db["stamp_ns"][rows], self.index.world_from_cam[rows, :3, 3]
        s = self.images(session)
        return self.encode(session, np.arange(len(s))), s.table["stamp_ns"], s.world_from_cam[:, :3, 3]

    def query_rows(self, session: str, stamps_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(row of the session's image nearest in time to each stamp, the time gap in s)."""
        rows, gap_ns = nearest_stamp(self.images(session).table["stamp_ns"], stamps_ns)
        return rows, gap_ns * 1e-9


def nearest_stamp(stamps_ns: np.ndarray, query_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(index into ``stamps_ns`` of the stamp nearest to each query, |difference| in ns); -1 and
    a huge gap when there is no stamp at all. ``stamps_ns`` need not be sorted."""
    t = np.asarray(stamps_ns, np.int64)
    q = np.asarray(query_ns, np.int64)
    if len(t) == 0:
        return np.full(len(q), -1, np.int64), np.full(len(q), np.iinfo(np.int64).max, np.int64)
    order = np.argsort(t, kind="stable")
    ts = t[order]
    j = np.clip(np.searchsorted(ts, q), 1, len(ts) - 1) if len(ts) > 1 else np.zeros(len(q), np.int64)
    if len(ts) > 1:
        j = np.where(np.abs(ts[j - 1] - q) <= np.abs(ts[j] - q), j - 1, j)
    return order[j].astype(np.int64), np.abs(ts[j] - q)


def nearest_l2(queries: np.ndarray, database: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(index (n,), squared L2 (n,)) of the nearest database row of each query (exact)."""
    q = np.asarray(queries, np.float64)
    d = np.asarray(database, np.float64)
    if len(d) == 0 or len(q) == 0:
        return np.full(len(q), -1, np.int64), np.full(len(q), np.inf)
    d2 = (q * q).sum(1)[:, None] + (d * d).sum(1)[None, :] - 2.0 * q @ d.T
    j = np.argmin(d2, axis=1)
    return j.astype(np.int64), np.maximum(d2[np.arange(len(q)), j], 0.0)


# --------------------------------------------------------------------------- the workspace protocol


@dataclass
class _Scored:
    """Every query of one pair and method: its matched place's position (NaN without a match),
    the match's score (-inf without one), whether it is right, whether it could be, and its error;
    structure methods add each query's keypoints and best vote count, VLAD whether the query had
    an image and how far in time it was."""

    matched_pos: np.ndarray  # (n, 3)
    score: np.ndarray  # (n,)
    correct: np.ndarray  # (n,) bool
    reachable: np.ndarray  # (n,) bool
    error_m: np.ndarray  # (n,), NaN without a match
    keypoints: np.ndarray | None = None  # (n,) structure: query keypoints the frame observed
    votes: np.ndarray | None = None  # (n,) structure: v(d) of the best place
    has_image: np.ndarray | None = None  # (n,) VLAD: an image within max_image_gap_s
    image_gap_s: np.ndarray | None = None  # (n,) VLAD: time to the nearest image

    def summary(self, n_boot: int, mask: np.ndarray | None = None) -> dict:
        """The figures of the queries in ``mask`` (all by default): :func:`_summary`, then the
        method's per-query statistics over the same queries."""
        k = np.ones(len(self.score), bool) if mask is None else np.asarray(mask, bool)
        r = _summary(self.score[k], self.correct[k], self.reachable[k], self.error_m[k], n_boot)
        r["queries"] = int(k.sum())
        if self.keypoints is not None:
            t = r["best_f1"]["threshold"]
            assert self.votes is not None  # set with the keypoints (structure methods)
            kp, v = self.keypoints[k], self.votes[k]
            r.update(
                {
                    "lambda_v_best_f1": None if t is None else t - 1.0,  # integer votes: v >= t  <=>  v > t - 1
                    "keypoints_per_query_mean": float(np.mean(kp)) if len(kp) else None,
                    "keypoints_per_query_median": float(np.median(kp)) if len(kp) else None,
                    "votes_median": float(np.median(v)) if len(v) else None,
                }
            )
        if self.has_image is not None:
            assert self.image_gap_s is not None  # set with has_image (VLAD)
            ok = self.has_image[k]
            r.update(
                {
                    "queries_without_image": int((~ok).sum()),
                    "image_gap_s_max": float(np.max(self.image_gap_s[k][ok])) if np.any(ok) else None,
                }
            )
        return r


@dataclass
class _Queries:
    """The queries of a pair: every ``query_stride``-th keyframe of the query session that has a
    true position, and where each lies in the split ("test", "train", "buffer"; "" without one)."""

    ids: np.ndarray  # (n,) keyframe ids
    stamps_ns: np.ndarray  # (n,)
    positions: np.ndarray  # (n, 3) ground truth
    without_truth: int
    split: np.ndarray  # (n,) object

    @property
    def held_out(self) -> np.ndarray:
        return np.asarray(self.split == "test", bool)


class _Maps:
    """The maps of the workspace's sessions (aligned when ``mapkit align`` holds them) of one map source, the
    semi-dense maps or the LiDAR maps (read as the structure index reads them), loaded once: (map, checksum,
    where it came from: ``align`` or ``build``)."""

    def __init__(
        self, ws: Workspace, prefer_aligned: bool, source: MapKind = "semidense", lidar_voxel_m: float | None = None
    ):
        self.ws, self.prefer_aligned, self.source, self.lidar_voxel_m = ws, prefer_aligned, source, lidar_voxel_m
        self._maps: dict[str, tuple] = {}

    def __call__(self, name: str) -> tuple:
        if name not in self._maps:
            d, src = self.ws.session_map(name, self.prefer_aligned, self.source)
            how = (self.ws, name, d, src, self.source, self.lidar_voxel_m)
            self._maps[name] = (load_session_map(*how), session_map_checksum(*how), src)
        return self._maps[name]


@writes_workspace("workspace")
def evaluate_places(
    workspace: str | Path | Workspace,
    pairs: Sequence[tuple[str, str]],
    methods: Sequence[str] = ("nbld", "m2dp", "vlad"),
    out: str | Path | None = None,
    truth: str | Path | None = None,
    vlad_bundle: str | Path | None = None,
    config: PlacesEvalConfig | str | Path | None = None,
    overrides: dict | None = None,
    progress: bool = False,
    appearance=None,
) -> dict:
    """Precision/recall and AUC of ``methods`` for each ``(database_session, query_session)`` pair,
    over the held-out queries (the headline: ``pairs[i].methods``) and over all queries
    (``pairs[i].all_places``); the split is ``results["split"]`` (see :func:`resolve_split`).

    Writes into ``out`` (default ``WORKSPACE/eval/places``): ``places.json`` (everything,
    including the PR curves), ``places.md`` (the AUC tables in the form of the paper's Table 2,
    held-out first), ``pr_curves.png``, ``queries.csv`` (one row per pair, method and query, with
    its split), ``config.yaml``; structure indexes under ``indexes/`` and descriptor / VLAD caches
    under ``cache/`` (re-runs reuse them). ``vlad_bundle`` defaults to ``WORKSPACE/indexes/vlad``; if
    absent, the VLAD column is reported as not available. ``appearance`` replaces the VLAD bundle by
    any object with :class:`VladBaseline`'s ``database``, ``query_rows`` and ``encode`` (another
    image descriptor, e.g. NetVLAD, plugs in there). A pair without any held-out query has no
    held-out figures: its methods say so in a note (and a warning), its all-places figures stand.
    """
    ws = Workspace(workspace)
    cfg = load_config(PlacesEvalConfig, config, overrides)
    truth = None if truth is None else Path(truth)
    out = Path(out) if out is not None else ws.places_eval_folder(cfg.structure.map_source)
    cache = out / "cache"
    pairs = [(str(a), str(b)) for a, b in pairs]
    if not pairs:
        raise InputError(ws.root, "no session pair given", field="pairs")
    _check_methods(methods, cfg)
    gt = _Truth(ws, truth)
    cond = _conditions(truth)
    maps = _Maps(ws, cfg.structure.prefer_aligned_maps, cfg.structure.map_source, cfg.structure.lidar_voxel_m)
    split = resolve_split(ws, cfg, lambda: [maps(n)[0] for n in sorted({s for p in pairs for s in p})])
    vlad, vlad_note = (
        (appearance, None)
        if appearance is not None or "vlad" not in methods
        else _vlad_baseline(ws, vlad_bundle, cfg, cache, progress)
    )

    results: dict = {
        "workspace": str(ws.root),
        "truth": None if truth is None else str(truth),
        "ground_truth": gt.source,
        "map_source": cfg.structure.map_source,
        "radius_m": cfg.radius_m,
        "query_stride": cfg.query_stride,
        "methods": list(methods),
        "config": cfg.model_dump(mode="json"),
        "vlad_bundle": None
        if vlad is None
        else str(getattr(getattr(vlad, "index", None), "path", type(vlad).__name__)),
        "vlad_note": vlad_note,
        "headline": "all_places" if split.source == "none" else "held_out",
        "split": split.to_dict(),
        "split_description": split.describe(),
        "pairs": [],
        "maps": map_densities(maps, sorted({s for p in pairs for s in p})),
    }
    if "cnn" in methods and cfg.structure.cnn_model is not None:
        from mapkit.places.cnn import model_fingerprint

        results["cnn_model"] = model_fingerprint(cfg.structure.cnn_model)
    rows: list[list] = []
    timings: dict = {}
    for db, query in pairs:
        results["pairs"].append(
            _eval_pair(
                ws, db, query, methods, cfg, gt, cond, vlad, vlad_note, maps, split, out, cache, progress, rows, timings
            )
        )

    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "config.yaml", dump_config(cfg))
    write_json(out / "places.json", results)
    write_timings(out, pairs=timings)
    atomic_write_text(out / "places.md", format_places(results))
    _write_queries_csv(out / "queries.csv", rows)
    plot_pr_curves(out / "pr_curves.png", results)
    return results


#: a method's wall-clock figures on a pair: the evaluation's run record (timings.json), not places.json
TIMING_FACTS = ("seconds", "query_describe_s", "query_match_and_vote_s", "vote_ms_per_frame", "encode_and_load_s")


def _check_methods(methods: Sequence[str], cfg: PlacesEvalConfig) -> None:
    """Refuse an unknown method, and ``cnn`` without a model to run."""
    unknown = [m for m in methods if m not in STRUCTURE_METHODS and m != "vlad"]
    if unknown:
        raise InputError(None, f"unknown method(s) {unknown}; known: nbld, m2dp, cnn, vlad", field="methods")
    if "cnn" in methods and cfg.structure.cnn_model is None:
        from mapkit.places.index_structure import _DESCRIBERS

        if "cnn" not in _DESCRIBERS:
            raise InputError(
                None,
                "method cnn needs a trained model: set structure.cnn_model to a mapkit train output folder",
                field="structure.cnn_model",
            )


def _vlad_baseline(
    ws: Workspace, vlad_bundle: str | Path | None, cfg: PlacesEvalConfig, cache: Path, progress: bool
) -> tuple[VladBaseline | None, str | None]:
    """(the VLAD baseline, None), or (None, why not) with a warning when there is no bundle."""
    bundle = Path(vlad_bundle) if vlad_bundle is not None else ws.vlad_index
    if not (bundle / "manifest.json").is_file():
        note = f"no VLAD bundle at {bundle} (build it with mapkit index vlad)"
        warnings.warn(f"vlad: {note}; the VLAD column is left empty", InputWarning, stacklevel=3)
        return None, note
    # encodings shared with other evaluations (eval localize --cache-dir), else this run's cache
    encodings = Path(cfg.vlad_encodings_dir) if cfg.vlad_encodings_dir else cache
    return VladBaseline(bundle, ws.root, encodings, cfg.vlad_workers, progress), None


def _pair_queries(
    maps: _Maps, query: str, cfg: PlacesEvalConfig, gt: _Truth, split: PlaceSplit
) -> tuple[_Queries, str]:
    """The pair's queries, and where the query session's map came from (``align`` or ``build``)."""
    qmap, _, qsrc = maps(query)
    kf_ids = np.asarray(qmap.keyframe_ids, np.int64)
    sel = np.arange(0, len(kf_ids), cfg.query_stride)
    ids, stamps = kf_ids[sel], np.asarray(qmap.keyframe_stamps_ns, np.int64)[sel]
    pos = gt.positions(query, stamps, qmap.keyframe_world_from_cam[sel, :3, 3])
    has_truth = np.all(np.isfinite(pos), axis=1)
    pos = pos[has_truth]
    return _Queries(ids[has_truth], stamps[has_truth], pos, int((~has_truth).sum()), split.labels(pos)), qsrc


def no_held_out_note(query: str, counts: dict, split: PlaceSplit) -> str:
    """Why a pair has no held-out figures: where its queries lie instead."""
    return (
        f"no held-out query: none of the {sum(counts.values())} queries of {query!r} lies in a test tile outside the "
        f"{split.buffer_m:g} m buffer ({counts['train']} in training tiles, {counts['buffer']} in buffer strips); "
        "see the all-places figures"
    )


def _eval_pair(
    ws: Workspace,
    db: str,
    query: str,
    methods: Sequence[str],
    cfg: PlacesEvalConfig,
    gt: _Truth,
    cond: dict,
    vlad,
    vlad_note: str | None,
    maps: _Maps,
    split: PlaceSplit,
    out: Path,
    cache: Path,
    progress: bool,
    rows: list[list],
    timings: dict,
) -> dict:
    """One pair's entry of ``places.json``: every method on the same queries, scored over the
    held-out queries (``methods``, the headline; all queries when there is no split) and over all
    (``all_places``), each with the paired bootstrap comparison of the methods' AUCs; appends the
    per-query rows of ``queries.csv`` to ``rows`` and each method's timings to ``timings``."""
    q, qsrc = _pair_queries(maps, query, cfg, gt, split)
    held = q.held_out
    scoped = split.source != "none"
    counts = query_split_counts(q.split) if scoped else None
    note = no_held_out_note(query, counts, split) if counts is not None and not held.any() else None
    if note:
        warnings.warn(f"places {query} to {db}: {note}", InputWarning, stacklevel=3)
    entry: dict[str, Any] = {
        "database": db,
        "query": query,
        "conditions": {"database": cond.get(db), "query": cond.get(query)},
        "queries": int(held.sum()) if scoped else int(len(q.ids)),
        "queries_without_truth": q.without_truth,
        "query_map_source": qsrc,
        "scope": "held_out" if scoped else "all_places",
        "held_out_queries": int(held.sum()) if scoped else None,
        "query_split": counts,
        "held_out_note": note,
        "methods": {},
        "all_places": {"queries": int(len(q.ids)), "methods": {}},
    }
    for method in methods:
        t0 = time.perf_counter()
        if method in STRUCTURE_METHODS:
            facts, scored = _eval_structure(
                method, ws, db, query, q.ids, q.positions, cfg, gt, out, cache, maps, progress
            )
        elif vlad is not None and query in (getattr(vlad, "train_sessions", None) or ()):
            # a whitening learned on n images with n - 1 dimensions maps its training images to
            # (nearly) orthogonal vectors: two training sessions cannot be compared (measured on
            # the demo bundle: cosines of -1/683 between all of them)
            why = f"query session {query!r} trained the VLAD encoder (its vectors are not comparable); no score"
            warnings.warn(f"vlad: {why}", InputWarning, stacklevel=3)
            entry["methods"][method] = entry["all_places"]["methods"][method] = {"available": False, "note": why}
            continue
        elif vlad is not None:
            facts, scored = _eval_vlad(vlad, db, query, q.stamps_ns, q.positions, cfg, gt)
        else:
            entry["methods"][method] = entry["all_places"]["methods"][method] = {"available": False, "note": vlad_note}
            continue
        facts["seconds"] = time.perf_counter() - t0
        timings[f"{db}:{query}:{method}"] = {k: facts.pop(k) for k in TIMING_FACTS if k in facts}
        everywhere = {**scored.summary(cfg.bootstrap), **facts}
        entry["all_places"]["methods"][method] = everywhere
        if not scoped:
            entry["methods"][method] = everywhere
        elif note:
            entry["methods"][method] = {"available": False, "queries": 0, "note": note}
        else:
            entry["methods"][method] = {**scored.summary(cfg.bootstrap, held), **facts}
        rows += _query_rows(db, query, method, q, scored)
    # paired bootstrap (the same resamples of the same queries for every method)
    for block in (entry, entry["all_places"]) if scoped else (entry["all_places"],):
        boots = {m: r.pop("_boot") for m, r in block["methods"].items() if "_boot" in r}
        block["p_auc_above"] = {
            f"{a}>{b}": float(np.mean(boots[a] > boots[b]))
            for a in boots
            for b in boots
            if a != b and len(boots[a]) and len(boots[a]) == len(boots[b])
        }
    if not scoped:
        entry["p_auc_above"] = entry["all_places"]["p_auc_above"]
    return entry


def _query_rows(db: str, query: str, method: str, q: _Queries, s: _Scored) -> list[list]:
    """Rows of ``queries.csv`` (:data:`_QUERY_COLUMNS`) of one pair and method."""
    return [
        [
            db,
            query,
            method,
            int(q.ids[i]),
            int(q.stamps_ns[i]),
            *np.round(q.positions[i], 3),
            *np.round(s.matched_pos[i], 3),
            s.score[i],
            int(s.correct[i]),
            int(s.reachable[i]),
            None if np.isnan(s.error_m[i]) else round(float(s.error_m[i]), 2),
            q.split[i],
            int(q.split[i] == "test"),
            None if s.keypoints is None else int(s.keypoints[i]),
        ]
        for i in range(len(q.ids))
    ]


def _summary(scores, correct, reachable, err, n_boot: int) -> dict:
    """The figures of a set of scored queries. Without a reachable query (no database place
    within r_e of any) recall is 0/0: the AUC is None and ``auc_undefined`` says why, rather
    than a 0 that reads as a method failing."""
    curve = pr_curve(scores, correct, reachable)
    matched = np.isfinite(np.where(np.isnan(scores), -np.inf, scores))
    defined = curve["reachable"] > 0
    boot = bootstrap_auc(scores, correct, reachable, n_boot) if defined else np.zeros(0)
    return {
        "available": True,
        "auc": pr_auc(curve["recall"], curve["precision"]) if defined else None,
        "auc_undefined": None
        if defined
        else f"none of the {len(scores)} queries has a database place within r_e: recall and AUC undefined",
        "auc_ci90": [float(np.percentile(boot, 5)), float(np.percentile(boot, 95))] if len(boot) else None,
        "_boot": boot,
        "reachable": int(curve["reachable"]),
        "matched": int(matched.sum()),
        "top1_correct_of_reachable": float(np.sum(correct & matched) / max(curve["reachable"], 1)),
        "max_recall": float(curve["recall"][-1]) if len(curve["recall"]) else 0.0,
        "precision_at_max_recall": float(curve["precision"][-1]) if len(curve["precision"]) else None,
        "best_f1": best_f1(curve),
        "median_error_m": float(np.nanmedian(err)) if np.any(np.isfinite(err)) else None,
        "curve": {k: np.asarray(curve[k]).tolist() for k in ("thresholds", "precision", "recall")},
    }


def _eval_structure(
    kind,
    ws: Workspace,
    db,
    query,
    q_ids,
    q_pos,
    cfg: PlacesEvalConfig,
    gt: _Truth,
    out: Path,
    cache: Path,
    maps: _Maps,
    progress,
) -> tuple[dict, _Scored]:
    """(the facts of the method that do not depend on which queries are summarised, every query scored)."""
    scfg = cfg.structure.model_copy(update={"kind": kind, "database_sessions": [db]})
    cache = Path(cfg.descriptor_cache_dir) if cfg.descriptor_cache_dir else cache
    own = out / "indexes" / f"{kind}-{db}"  # own output folder
    bundle = build_structure_index(ws.root, kind, own, [db], scfg, cache_dir=cache, progress=progress)
    idx = StructureIndex.load(bundle, verify=False)  # just built or verified by its build hash
    qmap, qsha, _ = maps(query)
    t0 = time.perf_counter()
    _, raw, describe_s = session_descriptors(qmap, query, kind, idx.cfg, cache, qsha, progress)
    prep = idx.prepare_query(qmap, query, raw)
    t1 = time.perf_counter()
    m = idx.vote_frames(prep, q_ids)
    vote_s = time.perf_counter() - t1
    rows = idx.frame_rows(db)
    fr = idx.frames
    db_pos = gt.positions(db, fr["stamp_ns"][rows], fr["world_from_cam"][rows, :3, 3])
    db_pos[fr["pose_source"][rows] == 0] = np.nan
    all_pos = np.full((idx.n_frames, 3), np.nan)
    all_pos[rows] = db_pos
    has = m.best_frame >= 0
    matched_pos = np.where(has[:, None], all_pos[np.maximum(m.best_frame, 0)], np.nan)
    correct, reachable, err = score_queries(q_pos, matched_pos, has, db_pos, cfg.radius_m)
    scored = _Scored(
        matched_pos,
        np.where(has, m.best_votes.astype(np.float64), -np.inf),
        correct,
        reachable,
        err,
        keypoints=np.asarray(m.n_keypoints, np.int64),
        votes=np.asarray(m.best_votes, np.int64),
    )
    facts = {
        "database_entries": len(idx),
        "database_frames": int(np.sum(fr["pose_source"][rows] > 0)),
        "query_keypoints": int(len(prep.keypoints)),
        "query_describe_s": describe_s,
        "query_match_and_vote_s": (time.perf_counter() - t0) - describe_s,
        "vote_ms_per_frame": 1e3 * vote_s / max(len(m), 1),
        "index": str(bundle),
    }
    return facts, scored


def _eval_vlad(vlad, db, query, q_stamps, q_pos, cfg: PlacesEvalConfig, gt: _Truth) -> tuple[dict, _Scored]:
    """(the facts of the baseline that do not depend on which queries are summarised, every query scored)."""
    t0 = time.perf_counter()
    db_vec, db_stamps, db_aligned = vlad.database(db)
    db_pos = gt.positions(db, db_stamps, db_aligned)
    rows, gap_s = vlad.query_rows(query, q_stamps)
    ok = (rows >= 0) & (gap_s <= cfg.max_image_gap_s)
    q_vec = vlad.encode(query, rows[ok])
    encode_s = time.perf_counter() - t0
    j, d2 = nearest_l2(q_vec, db_vec)
    n = len(q_stamps)
    best = np.full(n, -1, np.int64)
    best[ok] = j
    scores = np.full(n, -np.inf)
    scores[ok] = -d2
    has = best >= 0
    matched_pos = np.where(has[:, None], db_pos[np.maximum(best, 0)] if len(db_pos) else np.nan, np.nan)
    correct, reachable, err = score_queries(q_pos, matched_pos, has, db_pos, cfg.radius_m)
    scored = _Scored(
        matched_pos, scores, correct, reachable, err, has_image=ok, image_gap_s=np.asarray(gap_s, np.float64)
    )
    return {"database_images": int(len(db_vec)), "encode_and_load_s": encode_s}, scored


_QUERY_COLUMNS = [
    "database",
    "query",
    "method",
    "query_frame_id",
    "stamp_ns",
    "x_m",
    "y_m",
    "z_m",
    "match_x_m",
    "match_y_m",
    "match_z_m",
    "score",
    "correct",
    "reachable",
    "error_m",
    "split",
    "held_out",
    "keypoints",
]


def _write_queries_csv(path: Path, rows: list[list]) -> None:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(_QUERY_COLUMNS)
    w.writerows(rows)
    atomic_write_text(path, buf.getvalue())


# --------------------------------------------------------------------------- reporting


def _cond_label(c: dict | None) -> str:
    if not c:
        return ""
    parts = [c.get("condition"), c.get("season")]
    if c.get("exposure_ev"):
        parts.append(f"{c['exposure_ev']:+g} EV")
    return ", ".join(str(p) for p in parts if p)


def _held_out(results: dict) -> bool:
    """Whether the headline figures are over held-out queries (a split) or all (none); results
    written before the split existed have no ``headline`` and are all-places."""
    return results.get("headline") == "held_out"


def _scopes(results: dict) -> list[tuple[str, str]]:
    """The tables to show, headline first: (key, title)."""
    if _held_out(results):
        return [
            ("held_out", "Held-out places (the headline)"),
            ("all_places", "All places (training tiles and buffer strips too)"),
        ]
    return [("all_places", "All places")]


def _block(p: dict, scope: str) -> dict:
    """A pair's figures of one scope: ``{"queries", "methods", "p_auc_above"}``."""
    if scope == "held_out" or "all_places" not in p:
        return {"queries": p["queries"], "methods": p["methods"], "p_auc_above": p.get("p_auc_above", {})}
    return p["all_places"]


def map_densities(maps: Callable[[str], tuple], names: Sequence[str]) -> dict[str, dict]:
    """Each evaluated session's semi-dense map (``maps(name)[0]``, the map the pairs use): keyframes,
    points, the keyframes' path and points per 100 m of it (NBLD compares densities: maps of
    unequal density are one reason its votes fail)."""
    out: dict[str, dict] = {}
    for name in names:
        st = maps(name)[0].stats()
        out[name] = {k: st.get(k) for k in ("keyframes", "points", "keyframe_path_m", "points_per_100m")}
    return out


def _maps_table(results: dict) -> list[str]:
    """Query and database map densities side by side, per pair."""
    maps = results.get("maps") or {}
    if not maps:
        return []
    f = lambda v, d=0: "" if v is None else f"{v:,.{d}f}"  # noqa: E731 (a one-line helper local to this function)
    lines = [
        "| pair | query: keyframes / points / per 100 m | database: keyframes / points / per 100 m "
        "| density query / database |",
        "|---|---|---|---|",
    ]
    for p in results["pairs"]:
        q, d = maps.get(p["query"], {}), maps.get(p["database"], {})
        ratio = (
            (q["points_per_100m"] / d["points_per_100m"])
            if q.get("points_per_100m") and d.get("points_per_100m")
            else None
        )
        lines.append(
            f"| {p['query']} to {p['database']} | {f(q.get('keyframes'))} / {f(q.get('points'))} / "
            f"{f(q.get('points_per_100m'))} | {f(d.get('keyframes'))} / {f(d.get('points'))} / "
            f"{f(d.get('points_per_100m'))} | {f(ratio, 2)} |"
        )
    return lines


def format_places(results: dict) -> str:
    """The AUC tables in the form of the paper's Table 2 (rows: pairs, columns: methods), held-out
    queries first, then over all queries; each method's best F1 operating point, keypoints per
    query, the AUCs' bootstrap intervals, and what was not evaluated."""
    lines = _protocol(results)
    for scope, title in _scopes(results):
        lines += ["", f"## {title}", ""] + _auc_table(results, scope)
    lines += ["", "## Operating points and keypoints", ""] + _best_f1_table(results) + [""] + _keypoints_table(results)
    lines += [""] + _bootstrap_table(results)
    if results.get("maps"):
        lines += [
            "",
            "## Map densities",
            "",
            f"The {'LiDAR maps (voxels)' if results.get('map_source') == 'lidar' else 'semi-dense maps'} compared, "
            "points per 100 m of their keyframes' path:",
            "",
        ] + _maps_table(results)
    notes = [
        f"{p['query']} to {p['database']}: {p['held_out_note']}" for p in results["pairs"] if p.get("held_out_note")
    ]
    notes += [
        f"{p['query']} to {p['database']}, {METHOD_LABELS.get(m, m)}: {r['note']}"
        for p in results["pairs"]
        for m, r in p["methods"].items()
        if not r.get("available") and r.get("note") and r["note"] != p.get("held_out_note")
    ]
    if notes:
        lines += ["", "Not evaluated:", ""] + [f"- {n}" for n in dict.fromkeys(notes)]
    undefined: dict[str, list[str]] = {}  # one line per pair, scope and reason, naming the methods
    for p in results["pairs"]:
        for scope, title in _scopes(results):
            for m, r in _block(p, scope)["methods"].items():
                if r.get("auc_undefined"):
                    key = f"{p['query']} to {p['database']}, {title.split(' (')[0].lower()}: {r['auc_undefined']}"
                    undefined.setdefault(key, []).append(METHOD_LABELS.get(m, m))
    if undefined:
        lines += ["", "AUC undefined (n/a in the tables):", ""] + [
            f"- {k} ({', '.join(v)})" for k, v in undefined.items()
        ]
    return "\n".join(lines) + "\n"


def _protocol(results: dict) -> list[str]:
    """Title, the protocol and the split."""
    methods = results["methods"]
    sc = results["config"]["structure"]
    split = results.get("split") or {}
    lines = [
        "# Place recognition: area under the precision-recall curve",
        "",
        f"Protocol of the semi-dense place-recognition paper (Sec. 5.2, Table 1): r_e = {results['radius_m']:g} m, "
        f"one keyframe in {results['query_stride']} of the query session is a query; ground truth: "
        f"{results['ground_truth']}. Structure "
        f"({', '.join(METHOD_LABELS[m] for m in methods if m in STRUCTURE_METHODS) or 'none'}"
        + (
            f"; from the LiDAR maps: voxel centroids, queries the frames every {LIDAR_FRAME_SPACING_M:g} m of the "
            "query drive"
            if results.get("map_source") == "lidar"
            else ""
        )
        + (f"; CNN model {results['cnn_model']['path']}" if results.get("cnn_model") else "")
        + f"): {100 * sc['keypoint_fraction']:g} % keypoints, PCA to {sc['pca_dim']}, voting; lambda_v swept. "
        "VLAD: top-1 database image of the database session; minus its squared distance swept.",
    ]
    if results.get("split_description"):
        lines += [
            "",
            f"Held-out places (the paper's geographic split, Sec. 5.1): {results['split_description']}. "
            "The database is the database session's whole map (places of training tiles stay in it as distractors)."
            + "".join(f" Note: {n}." for n in split.get("notes") or []),
        ]
    return lines


def _auc_table(results: dict, scope: str = "held_out") -> list[str]:
    """Table 2 over one scope's queries: the AUC of every method per pair, the best one in bold."""
    methods = results["methods"]
    head = ["Sequence pair (query to database)", "conditions (query / database)"] + [
        METHOD_LABELS.get(m, m) for m in methods
    ]
    with_held = scope == "all_places" and _held_out(
        results
    )  # the all-places table says how many of its queries are held out
    head += ["queries", "reachable"] + (["held out"] if with_held else [])
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for p in results["pairs"]:
        b = _block(p, scope)
        aucs = {m: b["methods"].get(m, {}).get("auc") for m in methods}
        best = max((a for a in aucs.values() if a is not None), default=None)
        cells = []
        for m in methods:
            a = aucs[m]
            cells.append(
                "n/a"
                if a is None
                else (f"**{a:.3f}**" if a == best and sum(x == best for x in aucs.values()) == 1 else f"{a:.3f}")
            )
        reach = [v.get("reachable") for v in b["methods"].values() if v.get("available")]
        cond = (
            f"{_cond_label(p['conditions']['query'])} / {_cond_label(p['conditions']['database'])}"
            if p["conditions"]["query"]
            else ""
        )
        extra = [str(p.get("held_out_queries"))] if with_held else []
        cells += [str(b["queries"]), str(reach[0] if reach else "")] + extra
        lines.append(f"| {p['query']} to {p['database']} | {cond} | " + " | ".join(cells) + " |")
    return lines


def _best_f1_table(results: dict) -> list[str]:
    lines = [
        "Best F1 operating point per method (accepted: score >= threshold; structure: votes, i.e. lambda_v = threshold "
        "- 1; VLAD: minus the squared distance):",
        "",
        "| pair | places | method | F1 | precision | recall | threshold | top-1 right of reachable |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for p in results["pairs"]:
        for scope, _ in _scopes(results):
            for m in results["methods"]:
                r = _block(p, scope)["methods"].get(m, {})
                if not r.get("available"):
                    continue
                b = r["best_f1"]
                prec = "" if b["precision"] is None else f"{b['precision']:.2f}"
                thr = "" if b["threshold"] is None else f"{b['threshold']:.3g}"
                lines.append(
                    f"| {p['query']} to {p['database']} | {scope.replace('_', '-')} | {METHOD_LABELS.get(m, m)} | "
                    f"{b['f1']:.2f} | {prec} | {b['recall']:.2f} | {thr} | {r['top1_correct_of_reachable']:.2f} |"
                )
    return lines


def _keypoints_table(results: dict) -> list[str]:
    """Query keypoints per query frame of the structure methods (the keypoints a frame observed)."""
    methods = [m for m in results["methods"] if m in STRUCTURE_METHODS]
    if not methods:
        return []
    scopes = _scopes(results)
    head = ["pair", "method"] + [f"{s.replace('_', '-')} keypoints per query: mean / median" for s, _ in scopes]
    lines = ["Keypoints per query (structure methods):", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for p in results["pairs"]:
        for m in methods:
            cells = []
            for s, _ in scopes:
                r = _block(p, s)["methods"].get(m, {})
                mean, med = r.get("keypoints_per_query_mean"), r.get("keypoints_per_query_median")
                cells.append("n/a" if mean is None or med is None else f"{mean:.1f} / {med:g}")
            lines.append(f"| {p['query']} to {p['database']} | {METHOD_LABELS.get(m, m)} | " + " | ".join(cells) + " |")
    return lines


def _bootstrap_table(results: dict) -> list[str]:
    methods = results["methods"]
    scope = _scopes(results)[0][0]
    lines = [
        f"AUC ({scope.replace('_', '-')} queries), 90 % bootstrap interval over the queries, and how often (paired "
        "resamples) each structure method's AUC is above VLAD's:",
        "",
        "| pair | "
        + " | ".join(METHOD_LABELS.get(m, m) for m in methods)
        + " | "
        + " | ".join(f"P({METHOD_LABELS.get(m, m)} > VLAD)" for m in methods if m != "vlad")
        + " |",
        "|" + "---|" * (1 + len(methods) + sum(m != "vlad" for m in methods)),
    ]
    for p in results["pairs"]:
        b = _block(p, scope)
        cells = []
        for m in methods:
            ci = b["methods"].get(m, {}).get("auc_ci90")
            cells.append("n/a" if not ci else f"{b['methods'][m]['auc']:.2f} [{ci[0]:.2f}, {ci[1]:.2f}]")
        probs = [b.get("p_auc_above", {}).get(f"{m}>vlad") for m in methods if m != "vlad"]
        cells += ["n/a" if x is None else f"{x:.2f}" for x in probs]
        lines.append(f"| {p['query']} to {p['database']} | " + " | ".join(cells) + " |")
    return lines


def plot_pr_curves(path: Path, results: dict) -> Path:
    """One panel per pair: the precision-recall curve of each method over the held-out queries
    (solid) and over all queries (dashed, thin)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(results["pairs"])
    cols = min(3, max(n, 1))
    rows_n = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows_n, cols, figsize=(4.6 * cols, 4.2 * rows_n), dpi=100, squeeze=False)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for ax, p in zip(axes.ravel(), results["pairs"], strict=False):
        for k, m in enumerate(results["methods"]):
            for scope, _ in _scopes(results):
                r = _block(p, scope)["methods"].get(m, {})
                if not r.get("available"):
                    continue
                c = r["curve"]
                auc = "n/a" if r.get("auc") is None else f"{r['auc']:.2f}"
                label = (
                    f"{METHOD_LABELS.get(m, m)} (AUC {auc})"
                    if scope == _scopes(results)[0][0]
                    else f"{METHOD_LABELS.get(m, m)}, all places ({auc})"
                )
                ax.step(
                    np.r_[0.0, c["recall"]],
                    np.r_[c["precision"][:1] if c["precision"] else [1.0], c["precision"]],
                    where="pre",
                    color=colours[k % len(colours)],
                    lw=1.6 if scope == "held_out" or not _held_out(results) else 0.8,
                    ls="-" if scope == "held_out" or not _held_out(results) else "--",
                    label=label,
                )
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1.02)
        ax.set_xlabel("recall")
        ax.set_ylabel("precision")
        qc, dc = _cond_label(p["conditions"]["query"]), _cond_label(p["conditions"]["database"])
        held = f", {p['held_out_queries']} held-out queries" if p.get("held_out_queries") is not None else ""
        ax.set_title(f"{p['query']} to {p['database']}{held}" + (f"\n{qc} / {dc}" if qc else ""), fontsize=9)
        ax.grid(alpha=0.3)
        ax.legend(loc="lower left", fontsize=7)
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    fig.tight_layout()
    return _save(plt, fig, path)


__all__ = [
    "PlacesEvalConfig",
    "pr_curve",
    "pr_auc",
    "best_f1",
    "score_queries",
    "VladBaseline",
    "nearest_l2",
    "nearest_stamp",
    "bootstrap_auc",
    "evaluate_places",
    "format_places",
    "plot_pr_curves",
    "PlaceSplit",
    "split_from_dataset",
    "map_densities",
    "split_from_points",
    "tiles_split_of_workspace",
    "resolve_split",
    "query_split_counts",
    "no_held_out_note",
]
