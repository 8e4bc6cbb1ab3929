"""The triangulated reference model: the database images as a COLMAP reconstruction whose images
carry 2D keypoints with triangulated 3D points, the map the field's 6-DoF localizers register
queries against (hloc's localize_sfm, COLMAP's image registrator).

The poses are not estimated here: each image keeps its known pose (``mapkit align``'s common frame,
or a single session's own) and camera. Local features are COLMAP's SIFT (``pycolmap.extract_features``)
with COLMAP's default descriptor normalisation L1_ROOT, which is RootSIFT (Arandjelovic and Zisserman
2012). Image pairs come from the poses, as COLMAP's spatial matcher chooses them plus a heading gate:
the ``pair_neighbours`` nearest camera centres within ``pair_max_distance_m`` whose viewing directions
differ by at most ``pair_max_angle_deg``. pycolmap matches and verifies them geometrically
(``match_image_pairs``) and triangulates with the poses and intrinsics held fixed
(``triangulate_points``: only the points are refined).

Output (default ``WORKSPACE/reference_model/``)::

    sfm/             the model, COLMAP binary (cameras, rigs, frames, images with keypoints, points3D)
    sfm_text/        the same model as COLMAP text
    database.db      the COLMAP database: keypoints, descriptors, matches, verified geometries
    pairs.txt        the image pairs matched, by image name
    config.yaml, metrics.json, statistics.png, top_view.png

Image names are paths relative to the images' common folder (the workspace root for a workspace),
and the database is written with the model's camera, rig, frame and image ids before extraction,
so COLMAP's image reader reuses each image by name and database and model agree on every id.
Every point is triangulated from matches alone; the maps then check it (:func:`depth_agreement`, in
``metrics.json`` as ``depth_check``) where both sides fix a depth at a keypoint: the session's semi-dense or LiDAR
map has points within ``depth_check_radius_px`` of it that lie on one surface (``depth_check_max_spread``), a
surface facing the camera where the map knows its normals (``depth_check_max_incidence_deg``), and the point's
rays fix its depth (``depth_check_max_depth_uncertainty``). The map's median depth there is compared with the
triangulated point's (``|z_tri - z_map| / z_map``: median, 90th percentile, share below 2 %, the fraction of
observations compared and what each condition left out). Both depths rest on the same database poses but reach
them by other routes (SIFT matches across images, the map's own depth estimates or the LiDAR's ranges), so a
large difference points at a wrong pose or a session aligned badly.
"""

from __future__ import annotations

import hashlib
import logging
import os
import time
from collections.abc import Iterator, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydantic import Field
from scipy.spatial import cKDTree

from mapkit.core.bundle import building
from mapkit.core.config import MapkitConfig, dump_config, load_config
from mapkit.core.errors import InputError, MapkitError
from mapkit.core.geometry import interpolate_poses, invert_pose
from mapkit.core.runio import atomic_write_text, config_hash, is_done, mark_done, sha256_file, write_json, write_timings
from mapkit.core.threads import single_thread_blas
from mapkit.core.types import CameraInfo
from mapkit.core.workspace import MAP_KINDS, Workspace
from mapkit.core.writers import writes_workspace
from mapkit.io.benchmark import camera_info_from_colmap, colmap_camera_params
from mapkit.io.colmap_db import ColmapDatabase
from mapkit.io.plots import map_top_view, reference_model_statistics
from mapkit.localization.descriptor_matching import sift_matches
from mapkit.retrieval.vlad_bundle import read_session_images

log = logging.getLogger(__name__)

#: the version of this stage's algorithm, bumped whenever its output for the same inputs changes (it reruns)
STAGE_VERSION = 4
#: the default output folder, under the workspace root
DEFAULT_FOLDER = "reference_model"


class ReferenceModelConfig(MapkitConfig):
    max_features: int = Field(8192, ge=16, description="SIFT features per image at most (COLMAP's default).")
    first_octave: int = Field(
        -1,
        ge=-1,
        le=1,
        description="SIFT's first octave: -1 upsamples the image twice first (COLMAP's default; most features), "
        "0 starts at full resolution (about three times faster, about a quarter of the features). mapkit keeps -1: "
        "on held-out training drives of the demo town (bench/sixdof_thresholds.py with --model-config) the 6-DoF "
        "localizer puts 14 % of the queries within (0.25 m, 2 deg) against a model built with 0, 28 % with -1.",
    )
    peak_threshold: float = Field(
        0.02 / 3, gt=0, description="SIFT's DoG peak threshold (COLMAP's default, 0.02 / octave_resolution)."
    )
    pair_neighbours: int = Field(
        10, ge=1, description="Each image is matched with at most this many nearest images (by camera centre)."
    )
    pair_max_distance_m: float = Field(
        30.0, gt=0, description="... whose camera centres lie within this distance (m; pose units without GPS)."
    )
    pair_max_angle_deg: float = Field(
        60.0,
        gt=0,
        le=180,
        description="... and whose viewing directions differ by at most this (deg): cameras facing apart share "
        "nothing to match.",
    )
    max_ratio: float = Field(0.8, gt=0, le=1, description="Lowe's ratio test (COLMAP's default).")
    min_num_inliers: int = Field(
        15, ge=5, description="A verified pair needs this many inlier matches (COLMAP's default)."
    )
    guided_matching: bool = Field(
        True,
        description="Once a pair's two-view geometry is verified, match its features again along that geometry "
        "(COLMAP's guided matching, off in COLMAP by default): a feature whose best match fails the ratio test "
        "against a look-alike elsewhere in the image (the next window of a facade) is matched where the geometry "
        "allows. mapkit's default: on the demo town's training drives it gives 1.7x the points (3,792 -> 6,328 "
        "on their true poses) for 1.6x the matching time (3.1 -> 5.1 s; extraction takes 13-17 s).",
    )
    exact_matching: bool = Field(
        True,
        description="Match descriptors exactly, as COLMAP's brute-force matcher (cpu_brute_force_matcher) does, "
        "instead of COLMAP's default approximate index on the CPU, which can give two builds of the same inputs "
        "different matches (on the demo town: two models 25 points apart, and a 6-DoF share within (0.25 m, 2 deg) "
        "3 points apart). mapkit's default, for the same model from the same inputs. mapkit finds the exact matches "
        "by matrix products (write_exact_matches) and COLMAP verifies them: on the demo town's training drives "
        "(bench/bench_sift_matching.py) matching and verification take about as long as with the approximate "
        "index, a third of the time of COLMAP's own brute-force loop.",
    )
    max_reprojection_error_px: float = Field(
        4.0, gt=0, description="Observations farther from their point's projection are dropped (COLMAP's default)."
    )
    min_triangulation_angle_deg: float = Field(
        1.5, gt=0, description="A point needs rays this far apart (COLMAP's default)."
    )
    min_depth_m: float = Field(
        0.5,
        ge=0,
        description="A point nearer than this to a camera that sees it is dropped (m; pose units without GPS). "
        "Near the epipole of a camera moving forward, a match along the epipolar line fits a point anywhere "
        "on the line of the camera centres, with rays wide apart: COLMAP's angle and reprojection filters keep "
        "it. Nothing a vehicle's camera maps lies this close.",
    )
    num_threads: int = Field(
        2,
        ge=1,
        description="Threads of feature extraction, matching and triangulation (fixed: pycolmap's -1 takes every "
        "core). The model does not depend on it: every image's features and every pair's verification are "
        "computed alone, with fixed seeds.",
    )
    seed: int = Field(0, ge=0, description="Seed of RANSAC (two-view verification) and of the triangulator.")
    depth_check_radius_px: float = Field(
        2.0,
        gt=0,
        description="The depth check takes the map points projecting within this distance of a keypoint (px): "
        "a few times the model's median reprojection error (0.5 px on KITTI), so a keypoint finds its own "
        "surface's points, and few enough pixels that they are not the next object's.",
    )
    depth_check_max_spread: float = Field(
        0.05,
        gt=0,
        description="... and compares a keypoint where those points lie on one surface: their interquartile range "
        "of depth at most this fraction of their median. A map holds what its sensors saw from everywhere, so at an "
        "edge or in front of a surface seen elsewhere the points around a keypoint lie at several depths and "
        "their median is none of them. mapkit choice, measured on the tiny town (which no claim is scored on) "
        "against its true surfaces with bench/depth_check_truth.py: the LiDAR map's depth at a keypoint lies 0.3 % "
        "off (median; 15 % at the 90th percentile) where its points agree, and 0.5 % (84 %) taken over all of them.",
    )
    depth_check_max_incidence_deg: float = Field(
        70.0,
        gt=0,
        le=90,
        description="... on a surface the camera sees at most this far from head-on (deg: the angle between the "
        "map's normals there and the rays to them; 90 compares every surface; a map without normals, the semi-dense "
        "one, is compared at any angle). On a surface seen obliquely (the road ahead, a facade along the street) a "
        "keypoint does not keep to one spot from image to image, and one pixel spans much depth. mapkit choice on "
        "the tiny town (which no claim is scored on) with bench/depth_check_truth.py: the widest angle at which the "
        "triangulated points the LiDAR check compares lie within 1 % of the true surfaces (median: 0.9 % at 70, "
        "1.2 % at 80).",
    )
    depth_check_max_depth_uncertainty: float = Field(
        0.02,
        gt=0,
        description="... at a triangulated point whose rays fix its depth to this fraction of it for a one-pixel "
        "error of each of its keypoints (from its track's geometry, the poses held fixed): the 2 % a check of the "
        "poses is read at. A point near a forward-moving camera's direction of travel, seen along its baseline, "
        "has no such depth.",
    )
    sessions: list[str] | None = Field(None, description="Sessions to use; every session with images if unset.")
    allow_unaligned: bool = Field(
        False,
        description="Build a model of several sessions that no finished `mapkit align` holds: only where their "
        "poses already share one frame (a pose stream from an INS); GPS-georeferenced sessions lie metres apart.",
    )


@dataclass(frozen=True)
class PosedImage:
    """One image with its known pose: ``world_from_cam`` (4, 4) maps camera coordinates (x right,
    y down, z forward) into the model's frame."""

    path: Path
    camera: CameraInfo | None
    world_from_cam: np.ndarray


@dataclass
class ModelMetrics:
    """What a reference model holds (``metrics.json``)."""

    images: int
    registered_images: int
    images_with_points: int
    image_pairs: int
    verified_pairs: int
    points: int
    observations: int
    track_length_mean: float
    track_length_median: float
    reprojection_error_mean_px: float
    reprojection_error_median_px: float
    points_per_image: dict[str, float]


# --- the workspace's images ---------------------------------------------------------------------------


def workspace_images(ws: Workspace, sessions: list[str] | None) -> list[PosedImage]:
    """Every database image of ``sessions`` (all with images if None), with its aligned pose where a finished
    ``mapkit align`` holds the session, and its camera from the session's image database (``imagedb/colmap``)."""
    import pycolmap

    names = _session_names(ws, sessions)
    images: list[PosedImage] = []
    for name in names:
        table = read_session_images(ws, name)
        imagedb = ws.session(name).imagedb
        model = imagedb / "colmap"
        if not (model / "cameras.bin").is_file() and not (model / "cameras.txt").is_file():
            raise InputError(model, f"session {name!r}: no camera intrinsics (COLMAP cameras) here", field="cameras")
        rec = pycolmap.Reconstruction(str(model))
        for path, T, camera in zip(table.image_paths, table.world_from_cam, table.table["camera"], strict=True):
            im = rec.find_image_with_name(os.path.relpath(path, imagedb))
            if im is None:
                raise InputError(
                    model, f"session {name!r}: image {os.path.relpath(path, imagedb)} has no intrinsics", field="images"
                )
            images.append(PosedImage(Path(path), _camera_info(rec.cameras[im.camera_id], str(camera), model), T))
    return images


def _camera_info(cam, name: str, where: Path) -> CameraInfo:
    """A COLMAP camera of an image database as mapkit's :class:`CameraInfo` (pinhole models and OpenCV's
    distortion; :func:`mapkit.io.benchmark.camera_info_from_colmap`)."""
    try:
        return camera_info_from_colmap(name, cam.model_name, cam.width, cam.height, [float(v) for v in cam.params])
    except ValueError as e:
        raise InputError(where, f"camera {cam.camera_id}: {e}", field="cameras") from e


# --- pairs from poses -----------------------------------------------------------------------------------


def pairs_from_poses(
    world_from_cam: np.ndarray, neighbours: int, max_distance: float, max_angle_deg: float
) -> np.ndarray:
    """(M, 2) index pairs i < j, sorted: each image with its ``neighbours`` nearest images (by camera
    centre, ties by index) within ``max_distance`` whose viewing directions (camera z axes) differ
    by at most ``max_angle_deg``; a pair chosen from either side is kept once."""
    T = np.asarray(world_from_cam, np.float64).reshape(-1, 4, 4)
    centres, axes = T[:, :3, 3], T[:, :3, 2]
    min_cos = np.cos(np.radians(max_angle_deg)) - 1e-12
    pairs = set()
    for i, near in enumerate(cKDTree(centres).query_ball_point(centres, max_distance)):
        cand = np.asarray([j for j in near if j != i], np.int64)
        if not len(cand):
            continue
        cand = cand[axes[cand] @ axes[i] >= min_cos]
        d = np.linalg.norm(centres[cand] - centres[i], axis=1)
        for j in cand[np.lexsort((cand, d))][:neighbours]:
            pairs.add((min(i, int(j)), max(i, int(j))))
    return np.asarray(sorted(pairs), np.int64).reshape(-1, 2)


# --- the model ------------------------------------------------------------------------------------------


def _check_images(images: Sequence[PosedImage]) -> None:
    if not images:
        raise InputError(None, "no images to build a reference model from")
    seen: set[Path] = set()
    for im in images:
        if not Path(im.path).is_file():
            raise InputError(im.path, "no such image")
        cam = im.camera
        if cam is None or not (np.all(np.isfinite(cam.K)) and cam.fx > 0 and cam.fy > 0):
            raise InputError(
                im.path, "image without intrinsics (a camera with a positive focal length)", field="camera"
            )
        if cam.width <= 0 or cam.height <= 0:
            raise InputError(im.path, f"camera {cam.camera!r} has no image size", field="camera")
        if np.any(cam.D) and cam.distortion_model not in ("plumb_bob", "rational_polynomial"):
            raise InputError(
                im.path, f"distortion model {cam.distortion_model!r}: only plumb_bob and rational_polynomial", field="D"
            )
        T = np.asarray(im.world_from_cam, np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise InputError(im.path, "world_from_cam is not a finite 4x4 pose", field="world_from_cam")
        key = Path(im.path).resolve()
        if key in seen:
            raise InputError(im.path, "image given twice")
        seen.add(key)


def colmap_camera(info: CameraInfo, camera_id: int):
    """COLMAP's camera of ``info`` (:func:`mapkit.io.benchmark.colmap_camera_params`: PINHOLE without distortion,
    OPENCV / FULL_OPENCV with plumb-bob coefficients)."""
    import pycolmap

    model, params = colmap_camera_params(info)
    return pycolmap.Camera(model=model, width=info.width, height=info.height, params=params, camera_id=camera_id)


def _image_names(images: Sequence[PosedImage], image_root: str | Path | None) -> tuple[Path, list[str]]:
    """The folder the image names are relative to (``image_root``, else the images' common folder) and each
    image's name (COLMAP's image names)."""
    paths = [Path(os.path.abspath(im.path)) for im in images]
    root = (
        Path(os.path.abspath(image_root))
        if image_root is not None
        else Path(os.path.commonpath([p.parent for p in paths]))
    )
    names = []
    for im, p in zip(images, paths, strict=True):
        if not p.is_relative_to(root):
            raise InputError(im.path, f"image outside the image root {root}", field="image_root")
        names.append(p.relative_to(root).as_posix())
    return root, names


def _posed_reconstruction(images: Sequence[PosedImage], names: list[str]):
    """A reconstruction with the images' cameras (one per distinct camera) and known poses, no points."""
    import pycolmap

    rec = pycolmap.Reconstruction()
    cameras: list[CameraInfo] = []
    for k, (im, name) in enumerate(zip(images, names, strict=True), start=1):
        assert im.camera is not None  # checked by _check_images
        idx = next((i for i, c in enumerate(cameras) if c == im.camera), None)
        if idx is None:
            cameras.append(im.camera)
            idx = len(cameras) - 1
            rec.add_camera_with_trivial_rig(colmap_camera(im.camera, idx + 1))
        cam_from_world = invert_pose(np.asarray(im.world_from_cam, np.float64))
        img = pycolmap.Image(name=name, camera_id=idx + 1, image_id=k)
        rec.add_image_with_trivial_frame(img, pycolmap.Rigid3d(cam_from_world[:3, :]))
    return rec


def _write_database(rec, path: Path) -> None:
    """Cameras, rigs, frames and images of ``rec`` into a new COLMAP database, with the model's ids."""
    import pycolmap

    db = pycolmap.Database.open(str(path))
    try:
        for cam in rec.cameras.values():
            db.write_camera(cam, use_camera_id=True)
        for rig in rec.rigs.values():
            db.write_rig(rig, use_rig_id=True)
        for frame in rec.frames.values():
            db.write_frame(frame, use_frame_id=True)
        for image in rec.images.values():
            db.write_image(image, use_image_id=True)
    finally:
        db.close()


@contextmanager
def quiet_colmap() -> Iterator[None]:
    """COLMAP's own log (a few lines per image and pair) down to warnings while it runs."""
    import pycolmap

    level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 1
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = level


def sift_extraction_options(cfg: ReferenceModelConfig, num_threads: int):
    """COLMAP's SIFT extraction with a model's settings: the database images and any query extracted with them
    give descriptors that compare (RootSIFT, COLMAP's default normalisation, kept)."""
    import pycolmap

    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = num_threads
    extraction.sift.max_num_features = cfg.max_features
    extraction.sift.first_octave = cfg.first_octave
    extraction.sift.peak_threshold = cfg.peak_threshold
    assert extraction.sift.normalization == pycolmap.Normalization.L1_ROOT
    return extraction


def sift_matching_options(cfg: ReferenceModelConfig, num_threads: int, seed: int):
    """COLMAP's SIFT matching and two-view verification options with a model's settings (ratio test, inliers a
    verified pair needs): (FeatureMatchingOptions, TwoViewGeometryOptions)."""
    import pycolmap

    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = num_threads
    matching.sift.max_ratio = cfg.max_ratio
    matching.guided_matching = cfg.guided_matching
    matching.sift.cpu_brute_force_matcher = cfg.exact_matching
    verification = pycolmap.TwoViewGeometryOptions()
    verification.min_num_inliers = cfg.min_num_inliers
    verification.ransac.random_seed = seed
    return matching, verification


def extract_sift(db_path: Path, root: Path, names: Sequence[str], extraction) -> None:
    """COLMAP's SIFT of the images ``names`` (relative to ``root``) into the database ``db_path``, on the CPU, with
    :func:`sift_extraction_options`' settings: the model's images and a batch of queries extract the same way."""
    import pycolmap

    pycolmap.extract_features(
        db_path,
        root,
        image_names=list(names),
        camera_mode=pycolmap.CameraMode.PER_IMAGE,
        extraction_options=extraction,
        device=pycolmap.Device.cpu,
    )


def _run_colmap(rec, root: Path, names: list[str], pairs: np.ndarray, folder: Path, cfg: ReferenceModelConfig):
    """Extract, match, verify and triangulate in ``folder``; returns the triangulated reconstruction."""
    import pycolmap

    db_path = folder / "database.db"
    _write_database(rec, db_path)
    extraction = sift_extraction_options(cfg, cfg.num_threads)
    matching, verification = sift_matching_options(cfg, cfg.num_threads, cfg.seed)
    tri = pycolmap.IncrementalPipelineOptions()
    tri.num_threads = cfg.num_threads
    tri.random_seed = cfg.seed
    tri.mapper.num_threads = cfg.num_threads
    tri.mapper.random_seed = cfg.seed
    tri.triangulation.random_seed = cfg.seed
    tri.mapper.filter_max_reproj_error = cfg.max_reprojection_error_px
    tri.mapper.filter_min_tri_angle = cfg.min_triangulation_angle_deg
    tri.triangulation.min_angle = cfg.min_triangulation_angle_deg
    tri.triangulation.complete_max_reproj_error = cfg.max_reprojection_error_px
    tri.triangulation.merge_max_reproj_error = cfg.max_reprojection_error_px
    (folder / "sfm").mkdir()
    with quiet_colmap():
        t0 = time.perf_counter()
        extract_sift(db_path, root, names, extraction)
        _check_database(db_path, rec)
        t1 = time.perf_counter()
        if len(pairs):
            match_and_verify(db_path, folder / "pairs.txt", matching, verification)
        t2 = time.perf_counter()
        model = pycolmap.triangulate_points(rec, db_path, root, folder / "sfm", clear_points=True, options=tri)
        drop_near_points(model, cfg.min_depth_m)
        compact_database(db_path)
        write_timings(folder, extraction_s=t1 - t0, matching_s=t2 - t1, triangulation_s=time.perf_counter() - t2)
    return model


def match_and_verify(db_path: Path, pairs_txt: Path, matching, verification) -> None:
    """The image pairs listed in ``pairs_txt`` (two names a line) matched, verified and (where ``matching`` asks)
    matched again along their geometry by ``pycolmap.match_image_pairs`` in the database ``db_path``, with
    :func:`sift_matching_options`' options; where they ask for COLMAP's brute-force matches, mapkit computes them
    first (:func:`write_exact_matches`) and COLMAP verifies and guides those."""
    if matching.sift.cpu_brute_force_matcher:
        pairs = [(a, b) for a, b in (line.split() for line in pairs_txt.read_text().splitlines() if line.strip())]
        write_exact_matches(db_path, pairs, matching.sift, matching.num_threads)
    colmap_match_pairs(db_path, pairs_txt, matching, verification)


def colmap_match_pairs(db_path: Path, pairs_txt: Path, matching, verification) -> None:
    """COLMAP alone on the pairs listed in ``pairs_txt``: ``pycolmap.match_image_pairs`` on the CPU, matching the
    pairs without stored matches, then verifying and (where ``matching`` asks) guiding them all."""
    import pycolmap

    pairing = pycolmap.ImportedPairingOptions()
    pairing.match_list_path = str(pairs_txt)
    pycolmap.match_image_pairs(
        db_path,
        matching_options=matching,
        pairing_options=pairing,
        verification_options=verification,
        device=pycolmap.Device.cpu,
    )


def write_exact_matches(db_path: Path, pairs: Sequence[tuple[str, str]], options, num_threads: int = 1) -> None:
    """The matches of every pair of images (by name) into the COLMAP database ``db_path``, as COLMAP's brute-force
    CPU matcher finds them with ``options`` (pycolmap's ``SiftMatchingOptions``: ratio, distance, cross check), by
    :func:`~mapkit.localization.descriptor_matching.sift_matches` (the same matches in the same order), before
    ``pycolmap.match_image_pairs``: COLMAP's matcher takes the pairs whose matches it finds there straight to
    geometric verification and guided matching. ``num_threads`` pairs are matched at a time, in blocks of pairs
    whose images' descriptors are read once. A pair naming an image the database does not hold is skipped with a
    warning, as COLMAP's matcher skips it."""
    import pycolmap

    def match(ab: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        return sift_matches(ab[0], ab[1], options.max_ratio, options.max_distance, options.cross_check)

    db = pycolmap.Database.open(str(db_path))
    try:
        ids = {im.name: im.image_id for im in db.read_all_images()}
        unknown = [n for p in pairs for n in p if n not in ids]
        if unknown:
            log.warning(
                "%s: %d image pairs name images it does not hold (first: %s): skipped",
                db_path,
                sum(a not in ids or b not in ids for a, b in pairs),
                unknown[0],
            )
        id_pairs = [(ids[a], ids[b]) for a, b in pairs if a in ids and b in ids]
        with single_thread_blas(), ThreadPoolExecutor(max(1, num_threads)) as pool:
            for s in range(0, len(id_pairs), _MATCH_BLOCK):
                block = id_pairs[s : s + _MATCH_BLOCK]
                desc = {i: np.asarray(db.read_descriptors(i).data) for i in sorted({i for p in block for i in p})}
                for (ia, ib), m in zip(block, pool.map(match, [(desc[a], desc[b]) for a, b in block]), strict=True):
                    db.write_matches(ia, ib, m)
    finally:
        db.close()


#: image pairs matched per block (their images' descriptors in memory at once)
_MATCH_BLOCK = 256


def drop_near_points(rec, min_depth: float) -> int:
    """Delete the points of ``rec`` that lie nearer than ``min_depth`` (camera z) to any image that sees them;
    returns how many."""
    near: set[int] = set()
    for im in rec.images.values():
        ids = [p.point3D_id for p in im.points2D if p.has_point3D()]
        if not ids:
            continue
        X = np.array([rec.points3D[i].xyz for i in ids], np.float64)
        T = np.asarray(im.cam_from_world().matrix(), np.float64)
        z = X @ T[2, :3] + T[2, 3]
        near.update(int(i) for i, zi in zip(ids, z, strict=True) if zi < min_depth)
    for pid in sorted(near):
        rec.delete_point3D(pid)
    if near:
        log.info("dropped %d points nearer than %g to a camera that sees them", len(near), min_depth)
    return len(near)


def compact_database(db_path: Path) -> None:
    """Rewrite a COLMAP database afresh in its rows' order (SQLite's ``VACUUM INTO`` a new file, which then replaces
    it): matching threads insert the pairs in whatever order they finish, which leaves the same rows in other pages
    and another count of writes in the header, so two builds of the same model would differ in their bytes (and
    checksums) though not in what they hold. The copy keeps SQLite's rollback journal instead of the write-ahead
    log COLMAP switches to: a reader of a WAL database leaves ``-wal`` and ``-shm`` files beside it (and cannot
    open it in a folder it may not write to), which a model handed to others should not ask of them."""
    import sqlite3

    fresh = db_path.with_name(db_path.name + ".compact")
    fresh.unlink(missing_ok=True)
    con = sqlite3.connect(db_path)
    try:
        con.execute("VACUUM INTO ?", (str(fresh),))
    finally:
        con.close()
    con = sqlite3.connect(fresh)
    try:
        con.execute("PRAGMA journal_mode=DELETE")
    finally:
        con.close()
    os.replace(fresh, db_path)


def _check_database(db_path: Path, rec) -> None:
    """The extractor reused every image of the model by name: same ids, no image added."""
    import pycolmap

    db = pycolmap.Database.open(str(db_path))
    try:
        by_id = {im.image_id: im.name for im in db.read_all_images()}
        want = {i: im.name for i, im in rec.images.items()}
        if by_id != want or db.num_cameras() != rec.num_cameras():
            raise RuntimeError("COLMAP's database does not hold the model's images and cameras")
    finally:
        db.close()


def observation_errors_px(rec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per observation of every 3D point: (point id, image id, reprojection error in px), ordered by image id."""
    ids = sorted(rec.points3D)
    xyz = {pid: rec.points3D[pid].xyz for pid in ids}
    pid_out, iid_out, err_out = [], [], []
    for image_id in sorted(rec.images):
        im = rec.images[image_id]
        obs = [(p.point3D_id, p.xy) for p in im.points2D if p.has_point3D()]
        if not obs:
            continue
        pids = np.array([o[0] for o in obs], np.int64)
        uv = np.array([o[1] for o in obs], np.float64)
        X = np.array([xyz[p] for p in pids], np.float64)
        T = np.asarray(im.cam_from_world().matrix(), np.float64)
        Xc = X @ T[:, :3].T + T[:, 3]
        proj = np.asarray(im.camera.img_from_cam(Xc), np.float64)
        pid_out.append(pids)
        iid_out.append(np.full(len(pids), image_id, np.int64))
        err_out.append(np.linalg.norm(proj - uv, axis=1))
    if not pid_out:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    return np.concatenate(pid_out), np.concatenate(iid_out), np.concatenate(err_out)


def model_metrics(rec, pairs: int = 0, verified: int = 0) -> ModelMetrics:
    """The figures ``metrics.json`` holds, computed from the reconstruction ``rec``."""
    _, image_ids, err = observation_errors_px(rec)
    lengths = np.array([p.track.length() for p in rec.points3D.values()], np.int64)
    per_image = np.array([np.sum(image_ids == i) for i in sorted(rec.images)], np.int64)
    pct = [0, 5, 25, 50, 75, 95, 100]

    def stat(fn, v) -> float:
        return round(float(fn(v)), 4) if len(v) else 0.0

    return ModelMetrics(
        images=rec.num_images(),
        registered_images=rec.num_reg_images(),
        images_with_points=int(np.sum(per_image > 0)),
        image_pairs=pairs,
        verified_pairs=verified,
        points=rec.num_points3D(),
        observations=int(len(err)),
        track_length_mean=stat(np.mean, lengths),
        track_length_median=stat(np.median, lengths),
        reprojection_error_mean_px=stat(np.mean, err),
        reprojection_error_median_px=stat(np.median, err),
        points_per_image={
            f"p{q}": round(float(v), 1)
            for q, v in zip(pct, np.percentile(per_image, pct) if len(per_image) else [0] * 7, strict=True)
        },
    )


def _observations(im, xyz: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The keypoints (K, 2) of image ``im`` that have a triangulated point, the points (K, 3) and their ids (K,)."""
    obs = [(p.xy, xyz[p.point3D_id], p.point3D_id) for p in im.points2D if p.has_point3D()]
    uv = np.array([o[0] for o in obs], np.float64).reshape(-1, 2)
    ids = np.array([o[2] for o in obs], np.int64)
    return uv, np.array([o[1] for o in obs], np.float64).reshape(-1, 3), ids


def _project_into(
    im,
    X_world: np.ndarray,
    max_depth: float = np.inf,
    origin: np.ndarray | None = None,
    keypoints: np.ndarray | None = None,
    radius_px: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixels (M, 2), camera z (M,) and row in ``X_world`` (M,) of the points of ``X_world`` (relative to
    ``origin`` where given, float32 or float64) in front of image ``im``'s camera, at most ``max_depth`` deep, that
    project inside its image (pycolmap's camera model, distortion included); with ``keypoints`` (K, 2), only those
    whose pixel lies in the ``radius_px`` cell of a keypoint or next to it (:func:`pixels_near`'s superset of the
    pixels within ``radius_px``). The points are moved to the camera in their own precision by OpenCV's
    ``cv2.transform`` (one pass in C++; float32 about an origin within kilometres: a tenth of a millimetre), the
    pinhole projection and the tests follow column by column, and only the points that pass are gathered."""
    import cv2

    cam = im.camera
    T = np.asarray(im.cam_from_world().matrix(), np.float64)
    centre = np.asarray(im.projection_center(), np.float64) - (0.0 if origin is None else origin)
    X = np.ascontiguousarray(X_world)
    if X.dtype not in (np.float32, np.float64):
        X = X.astype(np.float64)
    if not len(X):
        return np.zeros((0, 2)), np.zeros(0), np.zeros(0, np.int64)
    cam_from_origin = np.c_[T[:, :3], -T[:, :3] @ centre]  # camera coordinates of the points as given
    Xc: np.ndarray = cv2.transform(X.reshape(-1, 1, 3), cam_from_origin).reshape(-1, 3)
    x, y, z = Xc[:, 0], Xc[:, 1], Xc[:, 2]
    ahead = (z > 1e-6) & (z <= max_depth)
    if cam.model_name in ("PINHOLE", "SIMPLE_PINHOLE"):  # the projection is the pinhole's
        fx, fy, cx, cy = (float(v) for v in np.asarray(cam.calibration_matrix())[[0, 1, 0, 1], [0, 1, 2, 2]])
        w, h = float(cam.width), float(cam.height)
        with np.errstate(divide="ignore", invalid="ignore"):  # behind the camera: masked out with ahead
            u0, v0 = x / z, y / z
            u0 *= fx
            u0 += cx
            v0 *= fy
            v0 += cy
        ahead &= (u0 >= 0) & (u0 < w) & (v0 >= 0) & (v0 < h)
        rows = np.flatnonzero(ahead)
        u, v = u0[rows], v0[rows]
        if keypoints is not None:  # before the pixels are stacked: most are dropped
            keep = _near_cells(u, v, keypoints, radius_px, (0.0, 0.0, w, h))
            rows, u, v = rows[keep], u[keep], v[keep]
        return np.stack([u, v], axis=1).astype(np.float64), z[rows].astype(np.float64), rows
    near = np.flatnonzero(ahead)  # the camera model, distortion included
    inside, uv = image_pixels(cam, x[near], y[near], z[near])
    rows = near[inside]
    if keypoints is not None:
        keep = pixels_near(uv, keypoints, radius_px)
        rows, uv = rows[keep], uv[keep]
    return uv, z[rows].astype(np.float64), rows


def image_pixels(cam, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Which camera-frame points (``x``, ``y``, ``z`` > 0) land inside ``cam``'s image (pycolmap's camera,
    distortion included) and their pixels: (indices (K,), pixels (K, 2) float64)."""
    # the pinhole projection first; with distortion, within half an image of the frame before the camera model: a
    # distortion polynomial folds points far outside the field of view back into the image
    fx, fy, cx, cy = (float(v) for v in np.asarray(cam.calibration_matrix())[[0, 1, 0, 1], [0, 1, 2, 2]])
    u0, v0 = fx * x / z + cx, fy * y / z + cy
    w, h = float(cam.width), float(cam.height)
    if cam.model_name in ("PINHOLE", "SIMPLE_PINHOLE"):  # the projection is the pinhole's
        inside = np.flatnonzero((u0 >= 0) & (u0 < w) & (v0 >= 0) & (v0 < h))
        return inside, np.stack([u0[inside], v0[inside]], axis=1).astype(np.float64)
    near = np.flatnonzero((u0 > -w / 2) & (u0 < 1.5 * w) & (v0 > -h / 2) & (v0 < 1.5 * h))
    cam_points = np.stack([x[near], y[near], z[near]], axis=1).astype(np.float64)
    uv = np.asarray(cam.img_from_cam(cam_points), np.float64).reshape(-1, 2)
    ok = np.all(np.isfinite(uv), axis=1) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    return near[ok], uv[ok]


def pixels_near(uv: np.ndarray, keypoints: np.ndarray, radius: float) -> np.ndarray:
    """A mask over pixels ``uv`` (M, 2) keeping every one within ``radius`` of a keypoint (K, 2), and some
    farther: those in the radius-sized grid cells next to a keypoint's cell (a superset, so that a radius
    search over what it keeps finds what a search over all of ``uv`` finds). One boolean grid of cells, marked
    around the keypoints and read at the pixels: linear in both."""
    if not len(uv) or not len(keypoints):
        return np.zeros(len(uv), bool)
    u, v = np.ascontiguousarray(uv[:, 0]), np.ascontiguousarray(uv[:, 1])
    return _near_cells(u, v, keypoints, radius, (float(u.min()), float(v.min()), float(u.max()), float(v.max())))


def _near_cells(
    u: np.ndarray, v: np.ndarray, keypoints: np.ndarray, radius: float, box: tuple[float, float, float, float]
) -> np.ndarray:
    """:func:`pixels_near` for pixels given as columns ``u``, ``v`` that lie within ``box`` (u_min, v_min, u_max,
    v_max)."""
    if not len(u) or not len(keypoints):
        return np.zeros(len(u), bool)
    # cells a thousandth wider than the radius: a pixel within the radius of a keypoint lies in its cell or the
    # next one whatever the rounding of the division
    inv = 1.0 / (max(float(radius), 1e-9) * 1.001)
    kp = np.asarray(keypoints, np.float64)
    lo_u = np.floor(min(float(kp[:, 0].min()), box[0]) * inv) - 1
    lo_v = np.floor(min(float(kp[:, 1].min()), box[1]) * inv) - 1
    size_u = int(np.floor(max(float(kp[:, 0].max()), box[2]) * inv) - lo_u) + 2
    size_v = int(np.floor(max(float(kp[:, 1].max()), box[3]) * inv) - lo_v) + 2

    def cells(cu: np.ndarray, cv: np.ndarray) -> np.ndarray:
        # shifted to be positive, so that truncation is the floor
        iu = (cu * inv - lo_u).astype(np.int64)
        iu *= size_v
        iu += (cv * inv - lo_v).astype(np.int64)
        return iu

    marked = np.zeros(size_u * size_v, bool)
    k = cells(kp[:, 0], kp[:, 1])
    for i in (-1, 0, 1):
        for j in (-1, 0, 1):
            marked[k + (i * size_v + j)] = True
    return marked[cells(u, v)]


def _row_quartiles(z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The 25th, 50th and 75th percentiles of each row of ``z`` (NaN where a row has fewer values), linearly
    interpolated as ``np.nanpercentile`` gives them, in a few array operations instead of one call per row."""
    s = np.sort(z, axis=1)  # NaN last
    n = np.isfinite(s).sum(axis=1)
    rows = np.arange(len(s))
    out = []
    for q in (0.25, 0.5, 0.75):
        pos = q * (np.maximum(n, 1) - 1)
        below = np.floor(pos).astype(np.intp)
        above = np.minimum(below + 1, np.maximum(n - 1, 0))
        frac = pos - below
        out.append(s[rows, below] + frac * (s[rows, above] - s[rows, below]))
    return out[0], out[1], out[2]


#: the depth check keeps the map points within this many times an image's farthest triangulated depth of its camera:
#: farther ones can only lie behind what the image sees
DEPTH_CHECK_REACH = 2.0
#: edge of the ground grid (m) the depth check gathers each camera's map points from
DEPTH_CHECK_CELL_M = 8.0


class _GroundGrid:
    """Map points sorted by the ground cell (x, y) they fall in, each cell with its span of heights: the cells a
    camera's view reaches are found by a box-and-frustum test on the cells, and their points gathered in slices."""

    def __init__(self, points: np.ndarray, cell_m: float, normals: np.ndarray | None = None):
        self.cell = float(cell_m)
        ij = np.floor(points[:, :2] / self.cell).astype(np.int64)
        self.lo = ij.min(axis=0) if len(ij) else np.zeros(2, np.int64)
        ij -= self.lo
        self.shape = ij.max(axis=0) + 1 if len(ij) else np.ones(2, np.int64)
        key = ij[:, 0] * self.shape[1] + ij[:, 1]
        order = np.argsort(key, kind="stable")
        # float32 about the points' mean: half the bytes to gather, millimetres over kilometres
        self.origin = points.mean(axis=0) if len(points) else np.zeros(3)
        self.points, key = (points[order] - self.origin).astype(np.float32), key[order]
        # each point's unit surface normal (NaN where unknown), in the same order
        self.normals = None if normals is None else np.asarray(normals, np.float32)[order]
        # per non-empty cell: its key, where its points start and stop, and its lowest and highest point
        edge = np.r_[True, key[1:] != key[:-1]] if len(key) else np.zeros(0, bool)
        self.start = np.flatnonzero(edge)
        self.stop = np.r_[self.start[1:], len(key)].astype(np.int64)
        self.keys = key[self.start]
        z = self.points[:, 2] + self.origin[2]
        self.z_lo = np.minimum.reduceat(z, self.start) if len(z) else np.zeros(0)
        self.z_hi = np.maximum.reduceat(z, self.start) if len(z) else np.zeros(0)

    def cells_within(self, lo_xy: np.ndarray, hi_xy: np.ndarray) -> np.ndarray:
        """Indices of the non-empty cells that the box ``lo_xy``..``hi_xy`` (m) touches."""
        i0, j0 = np.maximum(np.floor(lo_xy / self.cell).astype(np.int64) - self.lo, 0)
        i1, j1 = np.minimum(np.floor(hi_xy / self.cell).astype(np.int64) - self.lo, self.shape - 1)
        if i1 < i0 or j1 < j0:
            return np.zeros(0, np.int64)
        rows = np.arange(i0, i1 + 1) * self.shape[1]
        first = np.searchsorted(self.keys, rows + j0)
        last = np.searchsorted(self.keys, rows + j1, side="right")
        return np.concatenate([np.arange(a, b) for a, b in zip(first, last, strict=True)])

    def gather(self, cells: np.ndarray) -> np.ndarray:
        """The points of ``cells`` (indices of non-empty cells), relative to ``origin``."""
        if not len(cells):
            return self.points[:0]
        return np.concatenate([self.points[a:b] for a, b in zip(self.start[cells], self.stop[cells], strict=True)])

    def rows_of(self, cells: np.ndarray | None, positions: np.ndarray) -> np.ndarray:
        """Rows of ``points`` of the points at ``positions`` of :meth:`gather`'s output for ``cells`` (None: the
        positions are rows of ``points`` already)."""
        if cells is None:
            return np.asarray(positions, np.int64)
        counts = self.stop[cells] - self.start[cells]
        first = np.cumsum(counts) - counts  # where each cell's points begin in the gathered array
        k = np.searchsorted(first, positions, side="right") - 1
        return self.start[cells][k] + (positions - first[k])

    def seen_by(self, im, reach: float) -> tuple[np.ndarray, np.ndarray | None]:
        """The points of every cell whose column (its ground square between its lowest and highest point) reaches
        into image ``im``'s view out to depth ``reach``: a cell all of whose eight corners lie outside one face of
        the view's pyramid (its four sides through the image's border, the camera's plane, depth ``reach``) is
        left out; the others are kept whole (relative to ``origin``), returned with the cells they come from
        (:meth:`rows_of`)."""
        cam = im.camera
        T = np.asarray(im.cam_from_world().matrix(), np.float64)
        w, h = float(cam.width), float(cam.height)
        # the image's border rays (corners and edge middles: distortion can bow an edge beyond its corners)
        border = np.array([[0, 0], [w / 2, 0], [w, 0], [w, h / 2], [w, h], [w / 2, h], [0, h], [0, h / 2]], np.float64)
        xn = np.asarray(cam.cam_from_img(border), np.float64)
        (x_lo, y_lo), (x_hi, y_hi) = xn.min(axis=0), xn.max(axis=0)
        far = np.c_[xn, np.ones(len(xn))] * reach
        xy = np.vstack([(far - T[:, 3]) @ T[:, :3], im.projection_center()])[:, :2]  # the pyramid's ground box
        cells = self.cells_within(xy.min(axis=0), xy.max(axis=0))
        if not len(cells):
            return self.points[:0], cells
        ij = np.stack([self.keys[cells] // self.shape[1], self.keys[cells] % self.shape[1]], axis=1) + self.lo
        square = np.array([[0, 0], [0, 1], [1, 0], [1, 1]], np.float64)
        ground = np.tile((ij[:, None, :] + square[None]) * self.cell, (1, 2, 1))  # (C, 8, 2)
        height = np.repeat(np.stack([self.z_lo[cells], self.z_hi[cells]], axis=1), 4, axis=1)  # (C, 8)
        c = np.concatenate([ground, height[..., None]], axis=2) @ T[:, :3].T + T[:, 3]
        x, y, z = c[..., 0], c[..., 1], c[..., 2]
        outside = np.zeros(len(cells), bool)
        for face in (x - x_lo * z, x_hi * z - x, y - y_lo * z, y_hi * z - y, z, reach - z):
            outside |= np.all(face < 0, axis=1)
        return self.gather(cells[~outside]), cells[~outside]


def map_depths(
    im, grid: _GroundGrid, keypoints: np.ndarray, reach: float, radius_px: float, min_points: int, max_points: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The map's depth at each keypoint (K, 2) of image ``im``, how far its points there spread and how obliquely
    the camera sees their surface: the median and the interquartile range of the depths of the ``max_points`` map
    points (of ``grid``, at most ``reach`` deep) nearest the keypoint within ``radius_px``, NaN where fewer than
    ``min_points`` lie there; and the median angle (deg) between their normals and the rays to them, NaN where the
    grid has no normals or none of theirs is known."""
    z_ref, spread, incidence = (np.full(len(keypoints), np.nan) for _ in range(3))
    seen, cells = grid.seen_by(im, reach)
    # the tree is then built over the few near a keypoint only
    uv_map, z_map, at = _project_into(im, seen, reach, grid.origin, keypoints, radius_px)
    if len(z_map) < min_points:
        return z_ref, spread, incidence
    # built for one query (unbalanced, uncompacted: half the time of scipy's default tree, the same neighbours)
    tree = cKDTree(uv_map, balanced_tree=False, compact_nodes=False)
    dist, idx = tree.query(keypoints, k=max_points, distance_upper_bound=radius_px)
    dist, idx = dist.reshape(len(keypoints), -1), idx.reshape(len(keypoints), -1)
    found = np.isfinite(dist)
    ok = found.sum(axis=1) >= min_points
    near = np.minimum(idx[ok], len(z_map) - 1)
    z_near = np.where(found[ok], z_map[near], np.nan)
    q25, z_ref[ok], q75 = _row_quartiles(z_near)
    spread[ok] = q75 - q25
    if grid.normals is not None:
        rows = grid.rows_of(cells, at)
        ray = seen[at] - (np.asarray(im.projection_center(), np.float64) - grid.origin).astype(np.float32)
        n = grid.normals[rows]
        with np.errstate(invalid="ignore", divide="ignore"):  # a zero normal is as unknown as a NaN one
            cos = np.abs(np.sum(n * ray, axis=1)) / (np.linalg.norm(n, axis=1) * np.linalg.norm(ray, axis=1))
        angle = np.degrees(np.arccos(np.clip(cos, 0.0, 1.0)))  # NaN where the normal is unknown
        incidence[ok] = _row_quartiles(np.where(found[ok], angle[near], np.nan))[1]
    return z_ref, spread, incidence


def facing_surface(incidence_deg: np.ndarray, max_incidence_deg: float, has_normals: bool) -> np.ndarray:
    """Where the depth check takes a map's surface as facing the camera: at most ``max_incidence_deg`` from head-on
    (:func:`map_depths`' angles; unknown ones do not face it), everywhere for a map without normals or a bound of
    90 deg."""
    if not has_normals or max_incidence_deg >= 90:
        return np.ones(len(incidence_deg), bool)
    return incidence_deg <= max_incidence_deg  # NaN compares false


def point_depth_uncertainty(rec, image_id: int, point_ids: np.ndarray, cov: Mapping[int, np.ndarray]) -> np.ndarray:
    """How well the rays of each point fix its depth in image ``image_id``: the standard deviation of the camera
    depth of each of ``point_ids`` for a one-pixel error of every keypoint of its track, over the depth (``cov``:
    :func:`point_covariances`)."""
    T = np.asarray(rec.images[image_id].cam_from_world().matrix(), np.float64)
    if not len(point_ids):
        return np.zeros(0)
    C = np.stack([cov[int(p)] for p in point_ids])
    X = np.stack([rec.points3D[int(p)].xyz for p in point_ids])
    z = X @ T[2, :3] + T[2, 3]
    var = np.einsum("i,kij,j->k", T[2, :3], C, T[2, :3])
    return np.sqrt(np.maximum(var, 0.0)) / np.abs(z)


def point_covariances(rec) -> dict[int, np.ndarray]:
    """Each point's 3x3 covariance (model units squared) for a one-pixel error of each of its keypoints, the poses
    held fixed: the inverse of the sum over its track of J^T J, J the pinhole projection's 2x3 Jacobian at the
    point (the cameras' focal lengths; a lens's distortion left out). Infinite where the rays do not fix it."""
    ids = np.array(sorted(rec.points3D), np.int64)
    if not len(ids):
        return {}
    row = {int(p): i for i, p in enumerate(ids)}
    xyz = np.stack([rec.points3D[int(p)].xyz for p in ids])
    info = np.zeros((len(ids), 3, 3))
    for image_id in sorted(rec.images):
        im = rec.images[image_id]
        r = np.array([row[p.point3D_id] for p in im.points2D if p.has_point3D()], np.int64)
        if not len(r):
            continue
        T = np.asarray(im.cam_from_world().matrix(), np.float64)
        Xc = xyz[r] @ T[:, :3].T + T[:, 3]
        x, y, z = Xc[:, 0] / Xc[:, 2], Xc[:, 1] / Xc[:, 2], Xc[:, 2]
        J = np.zeros((len(r), 2, 3))
        J[:, 0, 0], J[:, 0, 2] = im.camera.focal_length_x / z, -im.camera.focal_length_x * x / z
        J[:, 1, 1], J[:, 1, 2] = im.camera.focal_length_y / z, -im.camera.focal_length_y * y / z
        J = J @ T[:, :3]
        np.add.at(info, r, np.einsum("kai,kaj->kij", J, J))
    cov = np.full_like(info, np.inf)
    solid = np.linalg.cond(info) < 1e12
    cov[solid] = np.linalg.inv(info[solid])
    return {int(p): c for p, c in zip(ids, cov, strict=True)}


def depth_agreement(
    rec,
    map_points_world: np.ndarray,
    radius_px: float = 2.0,
    min_points: int = 3,
    max_points: int = 16,
    max_spread: float = 0.05,
    max_incidence_deg: float = 90.0,
    max_depth_uncertainty: float = np.inf,
    num_threads: int = 1,
) -> dict:
    """How far the triangulated points lie from a map's depth at their keypoints: a check of the poses
    the model was triangulated on against a map made on the same poses by other means (the semi-dense
    map's depths, the LiDAR's ranges).

    Per image, the map's points (``map_points_world``: (M, 3) in the model's frame, or (M, 6) with their unit
    normals, NaN where unknown) within
    ``DEPTH_CHECK_REACH`` times the image's farthest triangulated depth are projected into the camera. A keypoint
    with a triangulated point is compared where both sides fix a depth there:

    * the map: at least ``min_points`` of its points (the ``max_points`` nearest) lie within ``radius_px`` and on
      one surface (their interquartile range of depth at most ``max_spread`` of their median, which is the map's
      depth there) and, where the map has normals, a surface the camera sees at most ``max_incidence_deg`` from
      head-on (the median angle between their normals and the rays to them; not compared where none is known);
    * the point: its rays fix its depth to ``max_depth_uncertainty`` of it for a one-pixel error of every keypoint
      of its track (:func:`point_depth_uncertainty`).

    The relative difference is ``|z_tri - z_map| / z_map``. Returns the observations (keypoints with a point), how
    many and which fraction were compared, how many each condition left out (in this order: no map depth, several
    surfaces, an oblique surface or one of unknown orientation, a weakly fixed point), the median and 90th
    percentile of the relative difference, its share below 2 %, and per image (by name) the observations compared
    and their median. ``num_threads`` images are projected at a time; the figures do not depend on it."""
    if min_points < 1 or max_points < min_points:
        raise ValueError(f"need 1 <= min_points <= max_points, got {min_points}, {max_points}")
    X = np.asarray(map_points_world, np.float64)
    if X.ndim != 2 or X.shape[1] not in (3, 6):
        raise ValueError(f"map points must be (M, 3) or (M, 6) with normals, got shape {X.shape}")
    X = X[np.isfinite(X[:, :3] @ np.ones(3))]  # a NaN or an infinity in any coordinate
    grid = _GroundGrid(X[:, :3], DEPTH_CHECK_CELL_M, X[:, 3:] if X.shape[1] == 6 else None)
    xyz = {pid: p.xyz for pid, p in rec.points3D.items()}
    cov = point_covariances(rec) if np.isfinite(max_depth_uncertainty) else {}
    observations = 0
    left_out = {"no_map_depth": 0, "several_surfaces": 0, "oblique_or_unknown_surface": 0, "weakly_fixed_point": 0}
    rel_all: list[np.ndarray] = []
    per_image: dict[str, dict] = {}
    images = [(image_id, rec.images[image_id]) for image_id in sorted(rec.images)]
    observed = [_observations(im, xyz) for _, im in images]

    def image_depths(k: int) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray] | None]:
        """Image k's triangulated depths and the map's (None where it has nothing to compare)."""
        im, (kp, X_tri, _) = images[k][1], observed[k]
        T = np.asarray(im.cam_from_world().matrix(), np.float64)
        z_tri = X_tri @ T[2, :3] + T[2, 3]
        reach = DEPTH_CHECK_REACH * float(z_tri.max()) if len(z_tri) else 0.0
        if not len(kp) or not len(X) or not reach > 0:
            return z_tri, None
        return z_tri, map_depths(im, grid, kp, reach, radius_px, min_points, max_points)

    # images in parallel (their projections are numpy and OpenCV passes that leave Python's lock), summed in order
    with ThreadPoolExecutor(max_workers=max(1, int(num_threads))) as pool:
        found = list(pool.map(image_depths, range(len(images))))
    for (image_id, im), (kp, _, pids), (z_tri, depths) in zip(images, observed, found, strict=True):
        observations += len(kp)
        if not len(kp):
            continue
        if depths is None:
            left_out["no_map_depth"] += len(kp)
            continue
        z_ref, spread, incidence = depths
        has = np.isfinite(z_ref)
        one = has & (spread <= max_spread * z_ref)
        facing = one & facing_surface(incidence, max_incidence_deg, grid.normals is not None)
        fixed = facing.copy()
        if np.isfinite(max_depth_uncertainty) and facing.any():
            fixed[facing] = point_depth_uncertainty(rec, image_id, pids[facing], cov) <= max_depth_uncertainty
        left_out["no_map_depth"] += int(np.sum(~has))
        left_out["several_surfaces"] += int(np.sum(has & ~one))
        left_out["oblique_or_unknown_surface"] += int(np.sum(one & ~facing))
        left_out["weakly_fixed_point"] += int(np.sum(facing & ~fixed))
        if not np.any(fixed):
            continue
        rel = np.abs(z_tri[fixed] - z_ref[fixed]) / z_ref[fixed]
        rel_all.append(rel)
        per_image[im.name] = {"compared": int(len(rel)), "median_relative_difference": round(float(np.median(rel)), 5)}
    rel = np.concatenate(rel_all) if rel_all else np.zeros(0)
    has = len(rel) > 0
    return {
        "map_points": int(len(X)),
        "radius_px": float(radius_px),
        "min_points": int(min_points),
        "max_spread": float(max_spread),
        "max_incidence_deg": float(max_incidence_deg),
        "max_depth_uncertainty": float(max_depth_uncertainty) if np.isfinite(max_depth_uncertainty) else None,
        "observations": int(observations),
        "compared": int(len(rel)),
        "fraction_compared": round(len(rel) / observations, 4) if observations else 0.0,
        "left_out": left_out,
        "median_relative_difference": round(float(np.median(rel)), 5) if has else None,
        "p90_relative_difference": round(float(np.percentile(rel, 90)), 5) if has else None,
        "share_below_2pct": round(float(np.mean(rel < 0.02)), 4) if has else None,
        "images": per_image,
    }


def _depth_check(rec, maps: Mapping[str, np.ndarray | None], cfg: ReferenceModelConfig) -> dict:
    """``metrics.json``'s ``depth_check``: :func:`depth_agreement` per map source, ``"absent"`` for a source
    without a map; per image only the five images that disagree most (by their median, of those with at least
    20 observations compared)."""
    out: dict[str, dict | str] = {}
    for kind, points in maps.items():
        if points is None:
            out[kind] = "absent"
            continue
        d = depth_agreement(
            rec,
            points,
            cfg.depth_check_radius_px,
            max_spread=cfg.depth_check_max_spread,
            max_incidence_deg=cfg.depth_check_max_incidence_deg,
            max_depth_uncertainty=cfg.depth_check_max_depth_uncertainty,
            num_threads=cfg.num_threads,
        )
        images = d.pop("images")
        enough = [(v["median_relative_difference"], k) for k, v in images.items() if v["compared"] >= 20]
        d["worst_images"] = {k: m for m, k in sorted(enough, reverse=True)[:5]}
        out[kind] = d
    return out


def _verified_pairs(db_path: Path) -> int:
    with ColmapDatabase(db_path) as db:  # read-only: the compacted file stays as written
        return db.num_verified_pairs()


def _input_hash(
    cfg: ReferenceModelConfig,
    images: Sequence[PosedImage],
    names: list[str],
    maps: Mapping[str, np.ndarray | None] | None = None,
) -> str:
    """The config, every image's name, pose, camera and file content, and the maps' points: a changed input
    rebuilds (the same files written again do not, and two builds of the same inputs record the same hash)."""
    rows = []
    for im, name in zip(images, names, strict=True):
        path = Path(im.path)
        assert im.camera is not None
        cam = im.camera
        rows.append(
            [
                name,
                np.round(np.asarray(im.world_from_cam, np.float64), 9).tolist(),
                [cam.width, cam.height, np.round(cam.K, 9).tolist(), np.round(np.asarray(cam.D), 12).tolist()],
                path.stat().st_size,
                sha256_file(path),
            ]
        )
    h = {"cfg": cfg.model_dump(mode="json", exclude={"sessions"}), "images": rows, "v": STAGE_VERSION}
    if maps is not None:
        h["maps"] = {
            k: None if v is None else hashlib.sha256(np.ascontiguousarray(v, np.float64).tobytes()).hexdigest()
            for k, v in sorted(maps.items())
        }
    return config_hash(h)


@writes_workspace("out", within=True)
def triangulate_reference_model(
    images: Sequence[PosedImage],
    out: str | Path,
    config: ReferenceModelConfig | None = None,
    image_root: str | Path | None = None,
    maps: Mapping[str, np.ndarray | None] | None = None,
) -> Path:
    """Build the reference model of ``images`` (known poses and cameras) into the folder ``out``;
    returns it. Image names are paths relative to ``image_root`` (default: the images' common
    folder). ``maps`` (source name to map points (M, 3) in the images' frame, or None where the source
    has no map) are checked against the triangulated points (:func:`depth_agreement`, ``depth_check`` in
    ``metrics.json``). The folder is written aside and renamed into place when complete: a failure leaves any
    earlier model as it was. Re-running with the same images, maps and config does nothing."""
    cfg = config if config is not None else ReferenceModelConfig()
    _check_images(images)
    root, names = _image_names(images, image_root)
    final = Path(out)
    h = _input_hash(cfg, images, names, maps)
    if is_done(final, h):
        return final
    t0 = time.perf_counter()
    T = np.stack([np.asarray(im.world_from_cam, np.float64) for im in images])
    pairs = pairs_from_poses(T, cfg.pair_neighbours, cfg.pair_max_distance_m, cfg.pair_max_angle_deg)
    rec = _posed_reconstruction(images, names)
    with building(final) as folder:
        atomic_write_text(folder / "config.yaml", dump_config(cfg))
        atomic_write_text(folder / "pairs.txt", "".join(f"{names[i]} {names[j]}\n" for i, j in pairs))
        log.info("reference model: %d images, %d pairs", len(images), len(pairs))
        model = _run_colmap(rec, root, names, pairs, folder, cfg)
        model.write_binary(str(folder / "sfm"))  # pycolmap writes its default format there: binary, said once
        (folder / "sfm_text").mkdir()
        model.write_text(str(folder / "sfm_text"))
        m = model_metrics(model, len(pairs), _verified_pairs(folder / "database.db"))
        metrics: dict = {**m.__dict__, "image_root": os.path.relpath(root, final.resolve())}
        depth_check_s = 0.0
        if maps is not None:
            t_check = time.perf_counter()
            metrics["depth_check"] = _depth_check(model, maps, cfg)
            depth_check_s = time.perf_counter() - t_check
        write_json(folder / "metrics.json", metrics)
        _, _, err = observation_errors_px(model)
        reference_model_statistics(
            folder / "statistics.png",
            np.array([model.images[i].num_points3D for i in sorted(model.images)]),
            np.array([p.track.length() for p in model.points3D.values()]),
            err,
        )
        xyz = np.array([p.xyz for p in model.points3D.values()]).reshape(-1, 3)
        map_top_view(folder / "top_view.png", xyz, T[:, :3, 3], f"reference model: {len(xyz)} points")
        write_timings(folder, depth_check_s=depth_check_s, seconds=time.perf_counter() - t0)
        mark_done(folder, h, version=STAGE_VERSION, outputs=["sfm", "sfm_text", "metrics.json"])
    log.info(
        "reference model: %d points, median track %.1f, median reprojection error %.2f px",
        m.points,
        m.track_length_median,
        m.reprojection_error_median_px,
    )
    return final


def _on_true_poses(ws: Workspace, names: list[str], images: list[PosedImage], truth: Path) -> list[PosedImage]:
    """``images`` (of sessions ``names``) with the synthetic town's true camera poses at their stamps, in the
    workspace's frame. An image without a true pose (a session the town did not drive) is one error."""
    from mapkit.synth import camera_poses, town_frame

    try:
        ws_from_town = town_frame(truth).to_frame(ws.require_frame("a model on the town's true poses"))
    except MapkitError as exc:
        raise InputError(truth, str(exc), field="truth") from None
    true: dict[Path, np.ndarray] = {}
    for name in names:
        table = read_session_images(ws, name)
        try:
            stamps, T = camera_poses(truth, name)
        except MapkitError as exc:
            raise InputError(truth, f"session {name!r}: {exc}", field="truth") from None
        poses, ok = interpolate_poses(stamps, ws_from_town @ T, np.asarray(table.table["stamp_ns"], np.int64))
        true.update({Path(p): pose for p, pose, good in zip(table.image_paths, poses, ok, strict=True) if good})
    missing = [im.path for im in images if im.path not in true]
    if missing:
        raise InputError(
            truth, f"{len(missing)} database images have no true pose in the town (first: {missing[0]})", field="truth"
        )
    return [PosedImage(im.path, im.camera, true[im.path]) for im in images]


def _session_names(ws: Workspace, sessions: list[str] | None) -> list[str]:
    """The sessions the model holds: ``sessions``, or every session with an image database if None."""
    names = ws.sessions_with_images()
    if not names:
        raise InputError(ws.sessions_dir, "no session with an image database here (run mapkit build)")
    if sessions is not None:
        missing = sorted(set(sessions) - set(names))
        if missing:
            raise InputError(ws.sessions_dir, f"sessions {missing} have no image database", field="sessions")
        names = [n for n in names if n in sessions]
    return names


def _workspace_maps(ws: Workspace, names: list[str]) -> dict[str, np.ndarray | None]:
    """The map points of sessions ``names`` per map source (semi-dense points, LiDAR voxel centroids), in the
    frame their images are in (aligned maps with aligned images); None for a source no session has. A map in
    another frame than its session's images (built but not aligned) is left out, with a warning."""
    from mapkit.mapping.lidar_map import load_voxel_stats
    from mapkit.mapping.semidense import SemiDenseMap

    out: dict[str, np.ndarray | None] = {}
    for kind in MAP_KINDS:
        parts = []
        for name in names:
            aligned = ws.session_images_csv(name) == ws.aligned(name).images_csv
            try:
                folder, source = ws.session_map(name, prefer_aligned=aligned, source=kind)
            except InputError:
                continue  # the session has no such map
            if aligned and source != "align":
                log.warning("depth check: session %r's %s map is not aligned with its images: left out", name, kind)
                continue
            if kind == "semidense":  # no normals: the check compares it at any surface angle
                parts.append(SemiDenseMap.load(folder).points_world)
            else:
                voxels = load_voxel_stats(folder)
                parts.append(np.c_[voxels.centroid, voxels.normal])
        out[kind] = np.concatenate(parts) if parts else None
    return out


def session_maps(ws: Workspace, sessions: list[str] | None) -> dict[str, np.ndarray | None]:
    """The map points per source that a model of ``sessions`` (``ReferenceModelConfig.sessions``: every session with
    images where None) has its depth check compare with."""
    return _workspace_maps(ws, _session_names(ws, sessions))


@writes_workspace("workspace")
def build_reference_model(
    workspace: str | Path | Workspace,
    sessions: list[str] | None = None,
    out: str | Path | None = None,
    config: str | Path | ReferenceModelConfig | None = None,
    truth: str | Path | None = None,
) -> Path:
    """The reference model of the workspace's database images (``mapkit align``'s common frame when
    it finished, else each session's own) into ``out`` (default ``WORKSPACE/reference_model``); returns it.
    Several sessions that no finished alignment holds are refused (``allow_unaligned`` overrides).

    ``truth`` (a synthetic town): the images take their true camera poses in the workspace's frame instead of
    their recorded ones, a model that measures a localizer alone, without the map's own errors; the depth check
    is then left out (the maps lie on the recorded poses)."""
    ws = Workspace(workspace)
    cfg = load_config(ReferenceModelConfig, config, {"sessions": sessions} if sessions is not None else None)
    names = _session_names(ws, cfg.sessions)
    if truth is not None:
        images = _on_true_poses(ws, names, workspace_images(ws, cfg.sessions), Path(truth))
        target = Path(out) if out is not None else ws.root / DEFAULT_FOLDER
        return triangulate_reference_model(images, target, cfg, image_root=ws.root, maps=None)
    aligned = set(ws.aligned_sessions())
    unaligned = [n for n in names if n not in aligned]
    if len(names) > 1 and unaligned and not cfg.allow_unaligned:
        raise InputError(
            ws.align_dir,
            f"sessions {unaligned} are not aligned: a model of several sessions needs them in one frame (each "
            f"GPS-georeferenced session lies metres off the others). Run mapkit align {ws.root} first, give one "
            "session, or set allow_unaligned where their poses already share a frame (an INS pose stream)",
            field="align",
        )
    images = workspace_images(ws, cfg.sessions)
    maps = _workspace_maps(ws, names)
    target = Path(out) if out is not None else ws.root / DEFAULT_FOLDER
    return triangulate_reference_model(images, target, cfg, image_root=ws.root, maps=maps)
