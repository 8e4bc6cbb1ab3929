"""The reference 6-DoF localizer: a query image registered against the triangulated reference model
(:mod:`mapkit.localization.reference_model`), as hloc's ``localize_sfm`` and COLMAP's image
registrator do it.

Per query: COLMAP's SIFT with the model's own extraction settings (its ``config.yaml``: the same
octaves, feature budget and RootSIFT normalisation, so query and database descriptors compare);
each candidate database image's descriptors (retrieval's top-k, or the images nearest a prior
pose that look its way) matched by mutual nearest neighbour and Lowe's ratio test on the angle
between descriptors, as COLMAP's SIFT matcher does; the matched keypoints of the candidate that
carry a triangulated point give 2D-3D correspondences (each query keypoint and 3D point pair once);
``pycolmap.estimate_and_refine_absolute_pose`` (P3P in LO-RANSAC, then non-linear refinement) gives
``cam_from_world``. That pose, the caller's fallback pose and any neighbour's pose given as a guide then each
start a prior-guided matching (:func:`guided_matches`): the model's points near the guide projected into the
query, each matched only with the features near where it lands, RANSAC again, then again within a smaller radius;
the pose with the most inliers wins, unless it turned or slid beyond the first radius's reach of its guide. With
fewer than ``min_inliers`` inliers the pose is not trusted: the result keeps the caller's fallback (the filter's or
retrieval's pose) and says why.

Poses are camera poses in the model's frame (optical axes x right, y down, z forward);
``cam_from_world`` maps world points into the camera, ``world_from_cam`` is its inverse.
"""

from __future__ import annotations

import itertools
import logging
import os
import struct
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field

from mapkit.core.config import MapkitConfig, load_config
from mapkit.core.errors import ConfigError, InputError
from mapkit.core.geometry import invert_pose, rotation_angle_rad, skew
from mapkit.core.runio import progress_bar, write_json
from mapkit.core.types import CameraInfo
from mapkit.core.writers import writes_workspace
from mapkit.io.benchmark import (
    IMAGES,
    MODEL_CONFIG,
    PAIRS,
    QUERIES,
    model_image_root,
    read_pairs,
    read_queries_with_intrinsics,
)
from mapkit.io.colmap_db import ColmapDatabase
from mapkit.io.trajectory import write_benchmark_poses
from mapkit.localization.descriptor_matching import DESCRIPTOR_SCALE, nearest_two
from mapkit.localization.reference_model import (
    ReferenceModelConfig,
    colmap_camera,
    extract_sift,
    image_pixels,
    quiet_colmap,
    sift_extraction_options,
)

log = logging.getLogger(__name__)


class SixDofConfig(MapkitConfig):
    max_candidates: int = Field(
        10,
        ge=1,
        description="Candidate database images matched per query at most, the first of the given list (hloc's "
        "pipelines retrieve 10 to 50; along a drive the 10 nearest views already overlap the query).",
    )
    prior_neighbours: int = Field(
        10, ge=1, description="Candidates from a prior pose: this many database images nearest its camera centre ..."
    )
    prior_max_distance_m: float = Field(
        30.0,
        gt=0,
        description="... within this distance (m; the reference model's pairing radius) ... A registered pose "
        "this far from every candidate image is not accepted either.",
    )
    prior_max_angle_deg: float = Field(
        60.0,
        gt=0,
        le=180,
        description="... whose viewing direction differs from the prior's by at most this (deg; the reference "
        "model's pairing gate: cameras facing apart share nothing to match). A registered pose that looks farther "
        "away than this from every candidate image near it is not accepted either.",
    )
    max_ratio: float = Field(
        0.8, gt=0, le=1, description="Lowe's ratio test on descriptor angles (COLMAP's SIFT matcher default)."
    )
    max_distance: float = Field(
        0.7,
        gt=0,
        le=np.pi,
        description="A match's descriptor angle (rad) at most this (COLMAP's SIFT matcher max_distance).",
    )
    ransac_max_error_px: float = Field(
        4.0,
        gt=0,
        description="RANSAC's inlier threshold on the reprojection error (px). Chosen with min_inliers on held-out "
        "training drives of the demo town (bench/sixdof_thresholds.py: the most queries within (0.25 m, 2 deg) "
        "while at most 5 % are accepted outside it). COLMAP's abs_pose_max_error and hloc's localize_sfm use "
        "12 px, meant for photos of 1,000-1,600 px: on 640 px images it accepts about twice as many wrong poses.",
    )
    min_inliers: int = Field(
        15,
        ge=4,
        description="A pose needs this many RANSAC inliers to be accepted, else the fallback pose stays. Chosen "
        "with ransac_max_error_px (above). COLMAP's mapper refuses to register an image below 30 "
        "(abs_pose_min_num_inliers): on the demo town that keeps two fifths of the right poses.",
    )
    sequence_max_m: float | None = Field(
        0.5,
        gt=0,
        description="In a sequence with odometry (mapkit eval localize): a pose that disagrees by more than this (m) "
        "or sequence_max_deg with each registered neighbour's pose moved by the odometry between them is not "
        "accepted; a pose without a registered neighbour stays. The (0.5 m, 5 deg) band: neighbours 0.5 s apart "
        "agree far better than that, a pose slid along a facade of repeated windows by metres does not. None: off.",
    )
    sequence_max_deg: float = Field(5.0, gt=0, description="The rotation part of sequence_max_m's check (deg).")
    guided_radii_px: list[float] = Field(
        [40.0, 10.0],
        description="Prior-guided matching (px; empty: off): from a starting pose (RANSAC's pose from the candidates, "
        "and the fallback pose), the model's points seen by the images near it are projected into the query and "
        "each is matched only with query features within the first radius, by the ratio test among those; RANSAC "
        "on these matches gives the next pose, matched again within the next radius. The starting pose that ends "
        "with the most inliers wins, against matching the candidates whole as well. Matching a whole image lets "
        "each feature pick any look-alike (the next window of a facade); a pose to within a metre leaves it the "
        "few within reach.",
    )
    smoothing: Literal["causal", "batch", "off"] = Field(
        "causal",
        description="In a sequence with odometry: the poses of a pose graph of the registrations and the odometry "
        "(mapkit.localization.sequence), beside each image's own registration. causal: each query's pose from it "
        "and the queries before it, as online; batch: from the queries on either side too; off: none.",
    )
    smoothing_sigma_m: float = Field(
        0.125,
        gt=0,
        description="A registration's prior in the pose graph: this std per position axis (m). mapkit choice: half "
        "the benchmarks' finest band (0.25 m, 2 deg), so that an accepted pose lies within it at two sigma.",
    )
    smoothing_sigma_deg: float = Field(1.0, gt=0, description="... and this std per rotation axis (deg), as above.")
    smoothing_covariance: bool = Field(
        True,
        description="Add each registration's own covariance (COLMAP's pose refinement, for a pixel of keypoint noise) "
        "to its prior's noise above: a pose its points fix poorly (most of them far ahead) counts for less along the "
        "view. false: the configured noise alone.",
    )
    smoothing_window_m: float = Field(
        200.0,
        gt=0,
        description="Each query's pose from the pose graph of this much driving (m) before it (causal), or half of "
        "it on either side (batch). mapkit choice: the training drives' odometry drifts 0.02-0.03 m in 17-19 m "
        "(bench/odometry_noise.py), so two right registrations 200 m apart still agree within the band; the cost per "
        "query stays bounded on long drives.",
    )
    odometry_sigma_m: float = Field(
        0.01,
        gt=0,
        description="The odometry's std per step and position axis: this (m) plus odometry_sigma_fraction of the "
        "step. mapkit choice, about three times what the demo town's training drives (never scored) measure: "
        "0.006-0.011 m rms per 0.5 s step of 4-5 m between their image poses and the truth.",
    )
    odometry_sigma_fraction: float = Field(0.005, ge=0, description="See odometry_sigma_m.")
    odometry_sigma_deg: float = Field(
        0.05,
        gt=0,
        description="The odometry's std per step and rotation axis (deg). mapkit choice, about four times the training "
        "drives' 0.013 deg rms per step (as odometry_sigma_m).",
    )
    num_threads: int = Field(
        2,
        ge=1,
        description="Threads of feature extraction (pycolmap's -1 takes every core) and of registering queries, each "
        "query on one thread (its matching and COLMAP's RANSAC leave Python's lock). The poses do not depend on it: "
        "a query's registration uses its own features and prior only, and RANSAC its own seed.",
    )
    seed: int = Field(0, ge=0, description="Seed of RANSAC: the same query gives the same pose.")


@dataclass
class SixDofQuery:
    """One query: its image (a grey or RGB uint8 array, or a path), the camera that took it, and the
    pose to keep when registration fails (``world_from_cam``, the filter's or retrieval's; may be None)."""

    name: str
    image: np.ndarray | str | Path
    camera: CameraInfo | None
    fallback_world_from_cam: np.ndarray | None = None


@dataclass
class SixDofResult:
    """The pose of one query. ``accepted``: registered with at least ``min_inliers`` inliers; else the
    poses are the caller's fallback (None without one) and ``reason`` says why."""

    name: str
    cam_from_world: np.ndarray | None
    world_from_cam: np.ndarray | None
    accepted: bool
    reason: str
    inliers: int
    matches: int
    candidates: list[str] = field(default_factory=list)
    seconds: float = 0.0  # with the query's share of a batch's feature extraction
    sequence_world_from_cam: np.ndarray | None = None  # the pose graph's pose (SixDofConfig.smoothing), if any
    # the registration's covariance (6, 6) in gtsam's Pose3 convention (see world_from_cam_covariance); None
    # where the query has no registration of its own
    covariance: np.ndarray | None = None


# --- the model on disk -----------------------------------------------------------------------------------


def _walk_binary(path: Path, kind: str) -> int:
    """The record count of a COLMAP ``images.bin`` / ``points3D.bin`` after checking that its records fill the
    file exactly. COLMAP's reader runs for minutes on a truncated points3D.bin (until it fails to allocate): a
    damaged file is refused here first."""
    if not path.is_file():
        raise InputError(path, "no such file: not a COLMAP binary model", field="sfm")
    data = path.read_bytes()
    size = len(data)

    def damaged(what: str) -> InputError:
        return InputError(path, f"damaged COLMAP {kind} file ({what}); rebuild with mapkit model", field="sfm")

    if size < 8:
        raise damaged(f"{size} bytes, no record count")
    (n,) = struct.unpack_from("<Q", data, 0)
    pos = 8
    for i in range(n):
        if kind == "points3D":
            # id u64, xyz 3 f64, rgb 3 u8, error f64, track length u64; then (image id u32, point2D idx u32) each
            if pos + 51 > size:
                raise damaged(f"ends inside point {i} of {n}")
            (track,) = struct.unpack_from("<Q", data, pos + 43)
            pos += 51 + 8 * track
        else:
            # id u32, qvec 4 f64, tvec 3 f64, camera id u32, name NUL-terminated, points2D u64; then (x, y f64, id u64)
            end = data.find(b"\0", pos + 64)
            if pos + 64 > size or end < 0 or end + 9 > size:
                raise damaged(f"ends inside image {i} of {n}")
            (points,) = struct.unpack_from("<Q", data, end + 1)
            pos = end + 9 + 24 * points
        if pos > size:
            raise damaged(f"ends inside {kind} record {i} of {n}")
    if pos != size:
        raise damaged(f"{size - pos} bytes after the last of its {n} records")
    return int(n)


def load_reference_reconstruction(sfm: Path):
    import pycolmap

    if not sfm.is_dir():
        raise InputError(sfm, "no reference model here (run mapkit model)", field="sfm")
    for name in ("cameras.bin", "images.bin", "points3D.bin"):
        if not (sfm / name).is_file():
            raise InputError(sfm / name, "no such file: the reference model is incomplete", field="sfm")
    n_images = _walk_binary(sfm / "images.bin", "images")
    n_points = _walk_binary(sfm / "points3D.bin", "points3D")
    try:
        rec = pycolmap.Reconstruction(str(sfm))
    except (RuntimeError, ValueError, IndexError) as exc:
        raise InputError(sfm, f"COLMAP cannot read the model: {exc}", field="sfm") from None
    if rec.num_images() != n_images or rec.num_points3D() != n_points:
        raise InputError(sfm, "COLMAP read fewer images or points than the files hold", field="sfm")
    if n_points == 0:
        raise InputError(sfm / "points3D.bin", "the model has no 3D points to register against", field="sfm")
    return rec


def model_features_config(path: Path) -> ReferenceModelConfig:
    """The extraction settings the model was built with (its ``config.yaml``); COLMAP's defaults without one."""
    if not path.is_file():
        log.info("%s: no such file, query features use COLMAP's SIFT defaults", path)
        return ReferenceModelConfig()
    try:
        return load_config(ReferenceModelConfig, path)
    except ConfigError as exc:
        raise InputError(path, f"not the config of a reference model ({exc})", field="config") from None


@dataclass
class _DatabaseImage:
    image_id: int
    point3D_ids: np.ndarray  # (M,) int64 per keypoint, -1 where not triangulated
    centre: np.ndarray  # (3,) camera centre in the world
    axis: np.ndarray  # (3,) viewing direction (camera z) in the world


class SixDofLocalizer:
    """Registers queries against one reference model folder (``mapkit model``'s output: ``sfm/`` and
    ``database.db``). The model is read once; each database image's descriptors are read from the
    database on first use and kept in memory (uint8, as COLMAP stores them)."""

    def __init__(
        self, model_folder: str | Path, config: SixDofConfig | None = None, model_config: str | Path | None = None
    ):
        """``model_config``: the model's extraction settings (default ``model_folder/config.yaml``)."""
        import pycolmap

        self.folder = Path(model_folder)
        self.cfg = config if config is not None else SixDofConfig()
        if not self.folder.is_dir():
            raise InputError(self.folder, "no reference model folder here (run mapkit model)")
        self.rec = load_reference_reconstruction(self.folder / "sfm")
        self.features = model_features_config(
            Path(model_config) if model_config is not None else self.folder / "config.yaml"
        )
        db_path = self.folder / "database.db"
        # read-only: COLMAP's own Database.open rewrites the file's header, and a bundle checksums it
        self._db: ColmapDatabase | None = ColmapDatabase(db_path)
        db = self._db
        stored = db.image_names
        self._images: dict[str, _DatabaseImage] = {}
        self._descriptors: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        self._cache_lock = threading.Lock()
        for image_id, im in self.rec.images.items():
            if stored.get(image_id) != im.name:
                self.close()
                raise InputError(db_path, f"image {image_id} ({im.name}) of the model is not there", field="database")
            n = db.num_rows("keypoints", image_id)
            if n != im.num_points2D() or db.num_rows("descriptors", image_id) != n:
                self.close()
                raise InputError(
                    db_path, f"image {im.name}: {n} keypoints, the model has {im.num_points2D()}", field="database"
                )
            world_from_cam = invert_pose(np.vstack([im.cam_from_world().matrix(), [0, 0, 0, 1]]))
            ids = np.array([p.point3D_id if p.has_point3D() else -1 for p in im.points2D], np.int64)
            self._images[im.name] = _DatabaseImage(image_id, ids, world_from_cam[:3, 3], world_from_cam[:3, 2])
        self._xyz = {pid: np.asarray(p.xyz, np.float64) for pid, p in self.rec.points3D.items()}
        self._names = sorted(self._images)
        self._centres = np.array([self._images[n].centre for n in self._names]).reshape(-1, 3)
        self._axes = np.array([self._images[n].axis for n in self._names]).reshape(-1, 3)
        extraction = sift_extraction_options(self.features, self.cfg.num_threads)
        with quiet_colmap():  # COLMAP logs the extractor's creation at INFO
            self._extractor = pycolmap.FeatureExtractor.create(extraction, device=pycolmap.Device.cpu)

    # --- lifetime

    def close(self) -> None:
        if self._db is not None:
            self._db.close()
            self._db = None

    def __enter__(self) -> SixDofLocalizer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # --- candidates

    @property
    def image_names(self) -> list[str]:
        """The model's database image names, sorted."""
        return list(self._names)

    @property
    def image_root(self) -> Path:
        """The folder the model's image names are relative to: its metrics.json's ``image_root`` (relative to the
        model folder; ``mapkit model`` builds on the workspace root), else the model folder's parent."""
        return model_image_root(self.folder)

    def names_by_path(self) -> dict[Path, str]:
        """The model's image names by resolved path: how a table naming the same files relative to another
        folder (a VLAD bundle's database.csv, a session's images.csv) finds them in the model."""
        root = self.image_root
        return {(root / n).resolve(): n for n in self._names}

    def world_from_cam(self, name: str) -> np.ndarray:
        """The known pose of database image ``name`` (4, 4)."""
        im = self.rec.find_image_with_name(name)
        if im is None:
            raise KeyError(name)
        return invert_pose(np.vstack([im.cam_from_world().matrix(), [0, 0, 0, 1]]))

    def candidates_near(self, world_from_cam: np.ndarray) -> list[str]:
        """The database images nearest a prior camera pose (by camera centre, within ``prior_max_distance_m``)
        whose viewing direction is within ``prior_max_angle_deg`` of the prior's, nearest first, at most
        ``prior_neighbours``."""
        T = np.asarray(world_from_cam, np.float64)
        d = np.linalg.norm(self._centres - T[:3, 3], axis=1)
        ok = (d <= self.cfg.prior_max_distance_m) & (
            self._axes @ T[:3, 2] >= np.cos(np.radians(self.cfg.prior_max_angle_deg)) - 1e-12
        )
        idx = np.nonzero(ok)[0]
        idx = idx[np.argsort(d[idx], kind="stable")][: self.cfg.prior_neighbours]
        return [self._names[i] for i in idx]

    # --- features and matches

    def _database_features(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """(descriptors (M, 128) uint8, point3D ids (M,)) of a database image, read once."""
        with self._cache_lock:  # registering threads share the cache; each image is read once
            if name not in self._descriptors:
                assert self._db is not None, "the localizer is closed"
                im = self._images[name]
                self._descriptors[name] = (self._db.descriptors(im.image_id), im.point3D_ids)
            return self._descriptors[name]

    def extract(self, image: np.ndarray | str | Path) -> tuple[np.ndarray, np.ndarray]:
        """(keypoints (N, 2) in COLMAP's pixel convention, descriptors (N, 128) uint8) of a query image."""
        import pycolmap

        if isinstance(image, (str, Path)):
            if not Path(image).is_file():
                raise InputError(image, "no such image")
            bitmap = pycolmap.Bitmap.read(str(image), as_rgb=False)  # COLMAP's own reader, as the model's images
            if bitmap is None:
                raise InputError(image, "not an image COLMAP can read")
            kp, desc = self._extractor.extract(bitmap)
        else:
            arr = np.asarray(image)
            if arr.dtype != np.uint8 or arr.ndim not in (2, 3) or (arr.ndim == 3 and arr.shape[2] != 3):
                raise InputError(None, f"query image of {arr.dtype} {arr.shape}: expected uint8 grey or RGB")
            kp, desc = self._extractor.extract_from_uint8_array(np.ascontiguousarray(arr))
        xy = np.array([[k.x, k.y] for k in kp], np.float64).reshape(-1, 2)
        return xy, np.ascontiguousarray(np.asarray(desc.data, np.uint8)).reshape(-1, 128)

    def extract_many(
        self, images: Sequence[np.ndarray | str | Path], progress: bool = False
    ) -> list[tuple[np.ndarray, np.ndarray]]:
        """:meth:`extract` of every image, the same features. Image files go through COLMAP's own extraction
        pipeline, ``num_threads`` images at a time (one image's SIFT holds the interpreter: threads of
        :meth:`extract` would take turns), in batches so that progress shows; arrays are extracted one by one."""
        out: list[tuple[np.ndarray, np.ndarray] | None] = [None] * len(images)
        files: dict[Path, list[int]] = {}
        for k, image in enumerate(images):
            if isinstance(image, (str, Path)):
                if not Path(image).is_file():
                    raise InputError(image, "no such image")
                files.setdefault(Path(image).resolve(), []).append(k)
        bar = progress_bar(len(images), progress, "SIFT", "image")
        if files:
            paths = list(files)
            root = Path(os.path.commonpath([p.parent for p in paths]))
            extraction = sift_extraction_options(self.features, self.cfg.num_threads)
            batch = 8 * self.cfg.num_threads
            with tempfile.TemporaryDirectory(prefix="mapkit-sift-") as tmp, quiet_colmap():
                db_path = Path(tmp) / "queries.db"
                for start in range(0, len(paths), batch):
                    names = [p.relative_to(root).as_posix() for p in paths[start : start + batch]]
                    extract_sift(db_path, root, names, extraction)
                    bar.update(sum(len(files[p]) for p in paths[start : start + batch]))
                with ColmapDatabase(db_path) as db:
                    stored = {name: image_id for image_id, name in db.image_names.items()}
                    for p, ks in files.items():
                        image_id = stored.get(p.relative_to(root).as_posix())
                        if image_id is None:
                            raise InputError(p, "not an image COLMAP can read")
                        xy = db.keypoints(image_id)[:, :2].astype(np.float64)
                        desc = db.descriptors(image_id)
                        for k in ks:
                            out[k] = (xy, desc)
        for k, image in enumerate(images):
            if out[k] is None:
                out[k] = self.extract(image)
                bar.update(1)
        bar.close()
        return [o for o in out if o is not None]

    def localize(
        self,
        image: np.ndarray | str | Path,
        camera: CameraInfo | None,
        candidates: Sequence[str],
        fallback_world_from_cam: np.ndarray | None = None,
        name: str = "",
        features: tuple[np.ndarray, np.ndarray] | None = None,
        guides: Sequence[np.ndarray] = (),
    ) -> SixDofResult:
        """The pose of one query image taken by ``camera`` from its ``candidates`` (database image names,
        best first); the fallback pose, not accepted, when it does not register. ``features``: the image's
        :meth:`extract`, when the caller has them already (a second attempt with other candidates).
        ``guides``: more starting poses of the guided matching (``world_from_cam``; a neighbour's pose moved by
        the odometry), tried before the fallback."""
        t0 = time.perf_counter()
        label = name or (str(image) if isinstance(image, (str, Path)) else "query")
        cam = _check_camera(camera, image if isinstance(image, (str, Path)) else None, label)
        unknown = [c for c in candidates if c not in self._images]
        if unknown:
            raise InputError(self.folder / "sfm", f"{label}: candidate {unknown[0]!r} is not an image of the model")
        used = list(dict.fromkeys(candidates))[: self.cfg.max_candidates]

        def result(
            accepted: bool, reason: str, inliers: int, matches: int, T: np.ndarray | None, cov: np.ndarray | None = None
        ) -> SixDofResult:
            world_from_cam = None if T is None else invert_pose(T)
            if T is None and fallback_world_from_cam is not None:
                world_from_cam = np.array(fallback_world_from_cam, np.float64)  # kept as given
                T = invert_pose(world_from_cam)
            return SixDofResult(
                label,
                T,
                world_from_cam,
                accepted,
                reason,
                inliers,
                matches,
                used,
                time.perf_counter() - t0,
                covariance=cov,
            )

        guided_starts = [invert_pose(np.asarray(g, np.float64)) for g in guides]
        if fallback_world_from_cam is not None:
            guided_starts.append(invert_pose(np.asarray(fallback_world_from_cam, np.float64)))
        if not self.cfg.guided_radii_px:
            guided_starts = []  # off: the candidates alone
        if not used and not guided_starts:
            return result(False, "no candidate database images", 0, 0, None)
        if isinstance(image, np.ndarray) and image.shape[:2] != (cam.height, cam.width):
            raise InputError(None, f"{label}: image {image.shape[1]}x{image.shape[0]}, camera {cam.width}x{cam.height}")
        xy, desc = features if features is not None else self.extract(image)
        pairs = []
        for c in used:
            db_desc, pids = self._database_features(c)
            qi, dj = mutual_ratio_matches(desc, db_desc, self.cfg.max_ratio, self.cfg.max_distance)
            keep = pids[dj] >= 0
            pairs.append(np.stack([qi[keep], pids[dj[keep]]], axis=1))
        pair = np.unique(np.concatenate(pairs or [np.zeros((0, 2), np.int64)]).reshape(-1, 2), axis=0)
        n_matches, T, inliers, how, cov = len(pair), None, 0, "", None
        if n_matches >= self.cfg.min_inliers:
            points3D = np.array([self._xyz[int(p)] for p in pair[:, 1]], np.float64)
            T, inliers, _, cov = self._absolute_pose(xy[pair[:, 0]], points3D, cam)
        starts = [
            ("a neighbour's pose moved by the odometry" if k < len(guides) else "the fallback pose", S)
            for k, S in enumerate(guided_starts)
        ]
        if T is not None and self.cfg.guided_radii_px:
            starts.insert(0, ("RANSAC's pose", T))
        for what, start in starts:
            guided = self._guided(xy, desc, cam, start)
            if guided is not None and guided[1] > inliers:
                T, inliers, n_matches, near, cov = guided
                used = list(dict.fromkeys([*used, *near]))
                how = f", matched guided from {what}"
        if T is None:
            if n_matches < self.cfg.min_inliers:
                why = f"{n_matches} 2D-3D matches, fewer than min_inliers {self.cfg.min_inliers}"
            else:
                why = f"RANSAC found no pose from {n_matches} 2D-3D matches"
            return result(False, why, 0, n_matches, None)
        found = f"{inliers} inliers of {n_matches} 2D-3D matches{how}"
        if inliers < self.cfg.min_inliers:
            return result(False, f"{found}, fewer than min_inliers {self.cfg.min_inliers}", inliers, n_matches, None)
        far = self._off_candidates(T, used)
        if far:
            return result(False, f"{found}, but {far}", inliers, n_matches, None)
        return result(True, found, inliers, n_matches, T, cov)

    def _guided(self, xy: np.ndarray, desc: np.ndarray, cam: CameraInfo, start: np.ndarray):
        """RANSAC on prior-guided matches from ``start`` (cam_from_world), once per radius of ``guided_radii_px``:
        (cam_from_world, inliers, matches, the images whose points were matched, the pose's covariance), or None
        when no pose follows."""
        near = self.candidates_near(invert_pose(start))
        if not near:
            return None
        obs_desc, obs_pid = self._observations(near)
        colmap_cam = colmap_camera(cam, 1)
        T, out, kept = start, None, np.zeros((0, 3))
        for radius in self.cfg.guided_radii_px:
            pair = guided_matches(
                xy, desc, obs_desc, obs_pid, self._xyz, T, colmap_cam, radius, self.cfg.max_ratio, self.cfg.max_distance
            )
            if len(pair) < self.cfg.min_inliers:
                break
            points3D = np.array([self._xyz[int(p)] for p in pair[:, 1]], np.float64)
            T_next, inliers, mask, cov = self._absolute_pose(xy[pair[:, 0]], points3D, cam)
            if T_next is None:
                break
            T, out, kept = T_next, (T_next, inliers, len(pair), near, cov), points3D[mask]
        if out is None:
            return None
        reach = self.cfg.guided_radii_px[0]
        turned = rotation_angle_rad(T[:3, :3] @ start[:3, :3].T)
        if _drift_px(kept, start, T, colmap_cam) > reach or turned > np.arctan(reach / max(cam.fx, cam.fy)):
            return None  # the pose left the reach its matches were made in: they assumed the start was near
        return out

    def _observations(self, names: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
        """The descriptors (K, 128) and point ids (K,) of the triangulated keypoints of the images ``names``."""
        descs, pids = [], []
        for name in names:
            d, p = self._database_features(name)
            keep = p >= 0
            descs.append(d[keep])
            pids.append(p[keep])
        return np.concatenate(descs).reshape(-1, 128), np.concatenate(pids).astype(np.int64)

    def _off_candidates(self, cam_from_world: np.ndarray, used: Sequence[str]) -> str:
        """Why a registered pose cannot have seen what its candidate images saw ('' when it can): it lies farther
        than ``prior_max_distance_m`` from every candidate's camera, or looks more than ``prior_max_angle_deg`` away
        from each one near it (the co-visibility gate of the model's pairs). A pose RANSAC fits to a handful of
        wrong matches lands anywhere, hundreds of metres off or turned round."""
        T = invert_pose(cam_from_world)
        centres = np.array([self._images[c].centre for c in used]).reshape(-1, 3)
        axes = np.array([self._images[c].axis for c in used]).reshape(-1, 3)
        d = np.linalg.norm(centres - T[:3, 3], axis=1)
        near = d <= self.cfg.prior_max_distance_m
        if not np.any(near):
            limit = self.cfg.prior_max_distance_m
            return f"the pose lies {d.min():.1f} m from the nearest candidate image (more than {limit:g})"
        cos = axes[near] @ T[:3, 2]
        if np.all(cos < np.cos(np.radians(self.cfg.prior_max_angle_deg)) - 1e-12):
            turned = np.degrees(np.arccos(np.clip(cos.max(), -1.0, 1.0)))
            limit = self.cfg.prior_max_angle_deg
            return f"the pose looks {turned:.0f} deg away from the candidate images near it (more than {limit:g})"
        return ""

    def _absolute_pose(self, points2D: np.ndarray, points3D: np.ndarray, camera: CameraInfo):
        """(cam_from_world (4, 4), inliers, inlier mask, covariance (:func:`world_from_cam_covariance`)), or (None, 0,
        None, None) when RANSAC finds no pose."""
        import pycolmap

        options = pycolmap.AbsolutePoseEstimationOptions()
        options.ransac.max_error = self.cfg.ransac_max_error_px
        options.ransac.random_seed = self.cfg.seed
        out = pycolmap.estimate_and_refine_absolute_pose(
            points2D, points3D, colmap_camera(camera, 1), options, return_covariance=True
        )
        if out is None:
            return None, 0, None, None
        T = np.eye(4)
        T[:3] = out["cam_from_world"].matrix()
        cov = world_from_cam_covariance(T, np.asarray(out["covariance"], np.float64))
        return T, int(out["num_inliers"]), np.asarray(out["inlier_mask"], bool), cov


def world_from_cam_covariance(cam_from_world: np.ndarray, colmap_covariance: np.ndarray) -> np.ndarray:
    """The covariance (6, 6) of a registered camera's ``world_from_cam`` in gtsam's Pose3 convention (a perturbation
    on the right, in the camera's axes: rotation (rad), then translation (m)), from the covariance COLMAP's
    absolute pose refinement gives of ``cam_from_world`` (keypoints of one pixel's std): its rotation block is of
    the quaternion's tangent (Ceres' quaternion manifold, ``q <- exp(d) q``: half the rotation vector ``a = 2 d``
    applied on the left), its translation block of ``t`` itself. With ``cam_from_world = (R, t)`` moved to
    ``(exp(a) R, t + b)``, the camera's pose moves by ``(-a, -b - [t]x a)``."""
    t = np.asarray(cam_from_world, np.float64)[:3, 3]
    J = np.zeros((6, 6))
    J[:3, :3] = -2.0 * np.eye(3)
    J[3:, :3] = -2.0 * skew(t)
    J[3:, 3:] = -np.eye(3)
    C = np.asarray(colmap_covariance, np.float64).reshape(6, 6)
    return J @ C @ J.T


def _drift_px(points3D: np.ndarray, cam_from_world_a: np.ndarray, cam_from_world_b: np.ndarray, camera) -> float:
    """The median distance between where two camera poses project the same points, in pixels at the camera's focal
    length on the undistorted image plane (inf when none lies in front of both). Not through the lens model: a
    distortion polynomial folds points beyond its reach back into the image, where two far-apart rays land close."""
    za = points3D @ cam_from_world_a[2, :3] + cam_from_world_a[2, 3]
    zb = points3D @ cam_from_world_b[2, :3] + cam_from_world_b[2, 3]
    front = (za > 1e-6) & (zb > 1e-6)
    if not front.any():
        return float("inf")
    X = points3D[front]
    a = X @ cam_from_world_a[:2, :3].T + cam_from_world_a[:2, 3]
    b = X @ cam_from_world_b[:2, :3].T + cam_from_world_b[:2, 3]
    shift = (a / za[front, None] - b / zb[front, None]) * [camera.focal_length_x, camera.focal_length_y]
    return float(np.median(np.linalg.norm(shift, axis=1)))


def _check_camera(camera: CameraInfo | None, path: str | Path | None, label: str) -> CameraInfo:
    if camera is None or not (np.all(np.isfinite(camera.K)) and camera.fx > 0 and camera.fy > 0):
        raise InputError(path, f"{label}: query without intrinsics (a camera with a positive focal length)")
    if camera.width <= 0 or camera.height <= 0:
        raise InputError(path, f"{label}: camera {camera.camera!r} has no image size", field="camera")
    return camera


def mutual_ratio_matches(
    desc_a: np.ndarray, desc_b: np.ndarray, max_ratio: float, max_distance: float
) -> tuple[np.ndarray, np.ndarray]:
    """Indices (i in a, j in b) of mutual nearest neighbours between two sets of COLMAP SIFT descriptors (uint8,
    unit vectors times 512) whose angle is at most ``max_distance`` (rad) and below ``max_ratio`` times the angle
    to a's second nearest neighbour in b (Lowe's ratio test on angles, as COLMAP's matcher)."""
    if len(desc_a) == 0 or len(desc_b) < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    rows, col_arg = nearest_two(desc_a, desc_b)  # exact integer dot products
    scale = np.float32(1.0 / DESCRIPTOR_SCALE**2)  # a power of two: the cosines are exact too
    best, second, best_j = rows.best * scale, rows.second * scale, rows.arg
    d1 = np.arccos(np.clip(best, -1.0, 1.0))
    d2 = np.arccos(np.clip(second, -1.0, 1.0))
    i = np.arange(len(desc_a))
    ok = (d1 <= max_distance) & (d1 < max_ratio * d2) & (col_arg[best_j] == i)
    return i[ok], best_j[ok]


def guided_matches(
    xy: np.ndarray,
    desc: np.ndarray,
    obs_desc: np.ndarray,
    obs_pid: np.ndarray,
    xyz: dict,
    cam_from_world: np.ndarray,
    camera,
    radius_px: float,
    max_ratio: float,
    max_distance: float,
) -> np.ndarray:
    """2D-3D matches (K, 2: query keypoint, point id) guided by a pose: each observation of a model point (its
    descriptor ``obs_desc[k]`` and point ``obs_pid[k]``) is projected into the query at ``cam_from_world`` through
    ``camera`` (pycolmap's) and matched with the query keypoints ``xy`` within ``radius_px`` of it, the nearest
    descriptor by angle if within ``max_distance`` and below ``max_ratio`` times the second nearest's there; each
    query keypoint and each point keeps its closest match."""
    from scipy.spatial import cKDTree

    none = np.zeros((0, 2), np.int64)
    if len(xy) == 0 or len(obs_pid) == 0:
        return none
    pids, inv = np.unique(obs_pid, return_inverse=True)
    X = np.array([xyz[int(p)] for p in pids], np.float64).reshape(-1, 3)
    Xc = X @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    front = np.flatnonzero(Xc[:, 2] > 1e-6)
    seen, pixels = image_pixels(camera, *Xc[front].T)
    inside = np.zeros(len(X), bool)
    inside[front[seen]] = True
    uv = np.full((len(X), 2), np.inf)
    uv[front[seen]] = pixels
    obs = np.nonzero(inside[inv])[0]
    if len(obs) == 0:
        return none
    points = np.nonzero(inside)[0]  # each point's keypoints in reach once, shared by its observations
    reach = cKDTree(np.asarray(xy, np.float64)).query_ball_point(uv[points], radius_px)
    per_point = np.fromiter((len(r) for r in reach), np.int64, len(reach))
    flat = np.fromiter(itertools.chain.from_iterable(reach), np.int64, int(per_point.sum()))
    slot = np.zeros(len(X), np.int64)
    slot[points] = np.arange(len(points))
    counts = per_point[slot[inv[obs]]]
    if counts.sum() == 0:
        return none
    o = np.repeat(obs, counts)
    begin = np.cumsum(per_point) - per_point  # where each point's keypoints start in flat
    within = np.arange(len(o)) - np.repeat(np.cumsum(counts) - counts, counts)
    q = flat[np.repeat(begin[slot[inv[obs]]], counts) + within]
    a = np.asarray(obs_desc)[o].astype(np.float32)  # gathered as uint8: a quarter of the bytes
    b = np.asarray(desc)[q].astype(np.float32)
    sim = np.einsum("ij,ij->i", a, b) / np.float32(DESCRIPTOR_SCALE**2)  # cosines; o runs in blocks
    starts = np.r_[0, np.cumsum(counts[counts > 0])[:-1]]
    group = np.repeat(np.arange(len(starts)), counts[counts > 0])
    top = np.maximum.reduceat(sim, starts)
    at_top = np.flatnonzero(sim == top[group])
    at_top = at_top[np.r_[True, group[at_top][1:] != group[at_top][:-1]]]  # each block's first best
    sim[at_top] = -np.inf
    runner_up = np.maximum.reduceat(sim, starts)  # -inf for a block of one: no second, the ratio test passes
    angle = np.arccos(np.clip(top, -1.0, 1.0))
    second = np.where(np.isfinite(runner_up), np.arccos(np.clip(runner_up, -1.0, 1.0)), np.inf)
    o, q = o[at_top], q[at_top]
    keep = (angle <= max_distance) & (angle < max_ratio * second)
    if not keep.any():
        return none
    o, q, angle = o[keep], q[keep], angle[keep]
    pid = obs_pid[o]
    best = np.lexsort((angle, q))  # per query keypoint, its closest observation
    best = best[np.r_[True, q[best][1:] != q[best][:-1]]]
    q, pid, angle = q[best], pid[best], angle[best]
    best = np.lexsort((angle, pid))  # per point, its closest query keypoint
    best = best[np.r_[True, pid[best][1:] != pid[best][:-1]]]
    return np.stack([q[best], pid[best]], axis=1).astype(np.int64)


def map_queries(register: Callable[[int], SixDofResult], n: int, num_threads: int, bar) -> list[SixDofResult]:
    """``register(k)`` of every query k < n on ``num_threads`` threads, in query order, ticking ``bar``."""
    results = []
    with ThreadPoolExecutor(max_workers=max(1, num_threads)) as pool:
        for r in pool.map(register, range(n)):
            results.append(r)
            bar.update(1)
    bar.close()
    return results


def extract_with_shares(
    loc: SixDofLocalizer, images: Sequence[np.ndarray | str | Path], progress: bool | None
) -> list[tuple[tuple[np.ndarray, np.ndarray], float]]:
    """Every image's features (:meth:`SixDofLocalizer.extract_many`), each with its share of the extraction's
    seconds, which a query's result counts as its own."""
    t0 = time.perf_counter()
    features = loc.extract_many(images, bool(progress))
    share = (time.perf_counter() - t0) / max(len(images), 1)
    return [(f, share) for f in features]


def register_queries(
    loc: SixDofLocalizer,
    queries: Sequence[SixDofQuery],
    candidates_per_query: Sequence[Sequence[str] | None],
    progress: bool | None,
) -> list[SixDofResult]:
    """Every query registered by ``loc`` from its candidates (None: the images near its fallback pose), their
    features extracted first in one batch, then ``loc.cfg.num_threads`` queries registered at a time."""
    features = extract_with_shares(loc, [q.image for q in queries], progress)

    def register(k: int) -> SixDofResult:
        q, cands, (f, share) = queries[k], candidates_per_query[k], features[k]
        if cands is None:
            cands = [] if q.fallback_world_from_cam is None else loc.candidates_near(q.fallback_world_from_cam)
        r = loc.localize(q.image, q.camera, cands, q.fallback_world_from_cam, q.name, f)
        r.seconds += share
        return r

    bar = progress_bar(len(queries), progress, "6-DoF", "image")
    return map_queries(register, len(queries), loc.cfg.num_threads, bar)


def localize_images(
    model_folder: str | Path,
    queries: Sequence[SixDofQuery],
    candidates_per_query: Sequence[Sequence[str] | None],
    config: str | Path | SixDofConfig | None = None,
    progress: bool | None = None,
) -> list[SixDofResult]:
    """Every query registered against the reference model in ``model_folder``, from its candidates (database image
    names, best first; None: the images nearest the query's fallback pose that look its way)."""
    cfg = load_config(SixDofConfig, config)
    if len(candidates_per_query) != len(queries):
        raise InputError(None, f"{len(queries)} queries but {len(candidates_per_query)} candidate lists")
    with SixDofLocalizer(model_folder, cfg) as loc:
        results = register_queries(loc, queries, candidates_per_query, progress)
    n = sum(r.accepted for r in results)
    log.info("6-DoF: %d of %d queries registered", n, len(results))
    return results


@writes_workspace("poses_file", within=True)
def localize_benchmark(
    folder: str | Path,
    poses_file: str | Path,
    config: str | Path | SixDofConfig | None = None,
    retrieval_fallback: bool = False,
    progress: bool | None = None,
) -> Path:
    """Every query of a benchmark folder (``mapkit export benchmark``) registered against its reference model
    from its retrieval pairs; writes the registered poses to ``poses_file`` in the benchmark format
    (``cam_from_world``) and each query's outcome beside it (``<poses stem>.queries.json``); returns the poses
    file. A query that does not register is left out (a failure when scored), or with ``retrieval_fallback``
    given its best retrieved database image's pose."""
    folder, poses_file = Path(folder), Path(poses_file)
    cfg = load_config(SixDofConfig, config)
    cameras = read_queries_with_intrinsics(folder / QUERIES)
    pairs = read_pairs(folder / PAIRS)
    t0 = time.perf_counter()
    with SixDofLocalizer(folder, cfg, model_config=folder / MODEL_CONFIG) as loc:
        queries, candidates = [], []
        for name, camera in cameras.items():
            cands = [c for c in pairs.get(name, []) if c in loc._images]
            fallback = loc.world_from_cam(cands[0]) if retrieval_fallback and cands else None
            queries.append(SixDofQuery(name, folder / IMAGES / name, camera, fallback))
            candidates.append(cands)
        results = register_queries(loc, queries, candidates, progress)
    posed = [r for r in results if r.cam_from_world is not None]
    write_benchmark_poses(poses_file, [r.name for r in posed], np.array([r.cam_from_world for r in posed]))
    write_json(
        poses_file.with_name(f"{poses_file.stem}.queries.json"),
        {
            "benchmark": str(folder),
            "config": cfg.model_dump(mode="json"),
            "retrieval_fallback": retrieval_fallback,
            "registered": sum(r.accepted for r in results),
            "queries": len(results),
            "seconds": round(time.perf_counter() - t0, 3),
            "per_query": {
                r.name: {"accepted": r.accepted, "inliers": r.inliers, "matches": r.matches, "reason": r.reason}
                for r in results
            },
        },
    )
    log.info("6-DoF: %d of %d benchmark queries registered", sum(r.accepted for r in results), len(results))
    return poses_file
