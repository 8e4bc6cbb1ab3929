"""COLMAP's own image registrator on a benchmark folder (``mapkit export benchmark``), through pycolmap.

An outside localizer on mapkit's export: COLMAP's incremental mapper registers each query into the
reference model as ``colmap image_registrator`` does, with COLMAP's own 2D-3D correspondences (the
tracks its verified matches reach) and its own absolute pose estimation and options. On a copy of the
export's database (which holds the database images' keypoints and descriptors), in order:

1. the queries as images of the copy, one camera each from ``queries_with_intrinsics.txt``;
2. their SIFT with the model's extraction settings (``reference_model.yaml``);
3. the retrieval pairs (``pairs-query-retrieval.txt``) matched and geometrically verified;
4. the export's model loaded into the mapper, every query registered with the model held fixed
   (``fix_existing_frames``: the database poses are the reference, as in the benchmark).

The copy is kept beside the poses (``<poses stem>.colmap.db``) for COLMAP's GUI or a second look.
A query the mapper does not register is left out of the poses (a failure when scored).
"""

from __future__ import annotations

import logging
import shutil
import time
from pathlib import Path

import numpy as np
from pydantic import Field

from mapkit.core.config import MapkitConfig, load_config
from mapkit.core.errors import InputError
from mapkit.core.runio import progress_bar, write_json
from mapkit.core.writers import writes_workspace
from mapkit.io.benchmark import (
    DATABASE,
    IMAGES,
    MODEL_CONFIG,
    PAIRS,
    QUERIES,
    SFM,
    colmap_camera_params,
    read_pairs,
    read_queries_with_intrinsics,
)
from mapkit.io.trajectory import write_benchmark_poses
from mapkit.localization.reference_model import (
    extract_sift,
    match_and_verify,
    quiet_colmap,
    sift_extraction_options,
    sift_matching_options,
)
from mapkit.localization.sixdof import load_reference_reconstruction, model_features_config

log = logging.getLogger(__name__)


class ColmapRegistratorConfig(MapkitConfig):
    min_num_matches: int = Field(
        15, ge=1, description="A verified pair counts with this many inlier matches (COLMAP's mapper default)."
    )
    abs_pose_min_num_inliers: int = Field(
        30, ge=4, description="A query registers with this many absolute-pose inliers (COLMAP's default)."
    )
    abs_pose_max_error_px: float = Field(
        12.0, gt=0, description="RANSAC's reprojection threshold of the absolute pose (px; COLMAP's default)."
    )
    abs_pose_min_inlier_ratio: float = Field(
        0.25,
        ge=0,
        le=1,
        description="A query registers when at least this share of its 2D-3D correspondences are inliers (COLMAP's "
        "default).",
    )
    refine_intrinsics: bool = Field(
        False,
        description="Let the mapper estimate and refine each query's focal length and distortion (COLMAP's mapper "
        "default for a camera without a known focal length). Off: the queries' intrinsics are the benchmark's "
        "(queries_with_intrinsics.txt), as hloc's localize_sfm takes them and as `colmap feature_extractor "
        "--ImageReader.camera_params` marks them.",
    )
    num_threads: int = Field(2, ge=1, description="Threads of extraction and matching.")
    seed: int = Field(0, ge=0, description="Seed of COLMAP's RANSAC: the same queries give the same poses.")


def _add_queries(db_path: Path, cameras: dict, existing: set[str], known_focal: bool) -> None:
    """Each query as an image of its own camera, rig and frame (COLMAP's layout for a lone camera); ``known_focal``
    marks the camera's focal length as given, as COLMAP's reader marks camera parameters passed to it."""
    import pycolmap

    db = pycolmap.Database.open(str(db_path))
    try:
        for name, info in cameras.items():
            if name in existing:
                raise InputError(db_path, f"query {name} is already an image of the model's database", field="queries")
            model, params = colmap_camera_params(info)
            camera_id = db.write_camera(
                pycolmap.Camera(
                    model=model,
                    width=info.width,
                    height=info.height,
                    params=params,
                    has_prior_focal_length=known_focal,
                )
            )
            sensor = pycolmap.sensor_t(pycolmap.SensorType.CAMERA, camera_id)
            rig = pycolmap.Rig()
            rig.add_ref_sensor(sensor)
            rig_id = db.write_rig(rig)
            image_id = db.write_image(pycolmap.Image(name=name, camera_id=camera_id))
            frame = pycolmap.Frame()
            frame.rig_id = rig_id
            frame.add_data_id(pycolmap.data_t(sensor, image_id))
            db.write_frame(frame)
    finally:
        db.close()


@writes_workspace("poses_file", within=True)
def register_benchmark(
    folder: str | Path,
    poses_file: str | Path,
    config: str | Path | ColmapRegistratorConfig | None = None,
    progress: bool | None = None,
) -> Path:
    """Every query of a benchmark folder registered by COLMAP's incremental mapper against the folder's model
    (see the module's docstring); writes the poses to ``poses_file`` (benchmark format, ``cam_from_world``) and
    each query's outcome to ``<poses stem>.queries.json``; returns the poses file."""
    import pycolmap

    folder, poses_file = Path(folder), Path(poses_file)
    cfg = load_config(ColmapRegistratorConfig, config)
    cameras = read_queries_with_intrinsics(folder / QUERIES)
    pairs = read_pairs(folder / PAIRS)
    rec = load_reference_reconstruction(folder / SFM)
    features = model_features_config(folder / MODEL_CONFIG)
    source_db = folder / DATABASE
    if not source_db.is_file():
        raise InputError(source_db, "no such file: the model's features are missing", field="database")
    missing = [name for name in cameras if not (folder / IMAGES / name).is_file()]
    if missing:
        raise InputError(
            folder / IMAGES / missing[0],
            f"no such query image ({len(missing)} of {len(cameras)} missing)",
            field=QUERIES,
        )
    t0 = time.perf_counter()
    poses_file.parent.mkdir(parents=True, exist_ok=True)
    db_path = poses_file.with_name(f"{poses_file.stem}.colmap.db")
    partial = db_path.with_name(db_path.name + ".partial")
    shutil.copyfile(source_db, partial)
    pairs_txt = partial.with_suffix(".pairs.txt")
    pairs_txt.write_text("".join(f"{q} {d}\n" for q, ds in pairs.items() if q in cameras for d in ds))
    try:
        _add_queries(partial, cameras, {im.name for im in rec.images.values()}, not cfg.refine_intrinsics)
        extraction = sift_extraction_options(features, cfg.num_threads)
        matching, verification = sift_matching_options(features, cfg.num_threads, cfg.seed)
        with quiet_colmap():
            extract_sift(partial, folder / IMAGES, list(cameras), extraction)
            match_and_verify(partial, pairs_txt, matching, verification)
            t_matched = time.perf_counter()
            results = _register(partial, rec, list(cameras), cfg, progress)
    except BaseException:
        partial.unlink(missing_ok=True)
        raise
    finally:
        pairs_txt.unlink(missing_ok=True)
    partial.replace(db_path)
    posed = [(name, T) for name, (T, _, _) in results.items() if T is not None]
    write_benchmark_poses(poses_file, [n for n, _ in posed], np.array([T for _, T in posed]).reshape(-1, 4, 4))
    registered = len(posed)
    write_json(
        poses_file.with_name(f"{poses_file.stem}.queries.json"),
        {
            "benchmark": str(folder),
            "localizer": "COLMAP image registrator (pycolmap.IncrementalMapper.register_next_image)",
            "pycolmap": pycolmap.__version__,
            "config": cfg.model_dump(mode="json"),
            "registered": registered,
            "queries": len(results),
            "seconds": round(time.perf_counter() - t0, 3),
            "seconds_registration": round(time.perf_counter() - t_matched, 3),
            "database": db_path.name,
            "per_query": {
                n: {"accepted": T is not None, "points3D": points, "camera_params": params}
                for n, (T, points, params) in results.items()
            },
        },
    )
    log.info("COLMAP registrator: %d of %d benchmark queries registered", registered, len(results))
    return poses_file


def _register(db_path: Path, rec, names: list[str], cfg: ColmapRegistratorConfig, progress: bool | None) -> dict:
    """name -> (cam_from_world (4, 4) or None, the 3D points its registration observes, its camera's parameters
    after registration (COLMAP's order; empty when not registered))."""
    import pycolmap

    db = pycolmap.Database.open(str(db_path))
    try:
        cache_options = pycolmap.DatabaseCacheOptions()
        cache_options.min_num_matches = cfg.min_num_matches
        cache_options.load_all_images = True  # the model's images that no verified pair reaches too
        cache = pycolmap.DatabaseCache.create(db, cache_options)
    finally:
        db.close()
    ids = {image.name: image_id for image_id, image in cache.images.items()}
    options = pycolmap.IncrementalMapperOptions()
    options.abs_pose_min_num_inliers = cfg.abs_pose_min_num_inliers
    options.abs_pose_max_error = cfg.abs_pose_max_error_px
    options.abs_pose_min_inlier_ratio = cfg.abs_pose_min_inlier_ratio
    options.abs_pose_refine_focal_length = cfg.refine_intrinsics
    options.abs_pose_refine_extra_params = cfg.refine_intrinsics
    options.fix_existing_frames = True
    options.num_threads = cfg.num_threads
    options.random_seed = cfg.seed
    mapper = pycolmap.IncrementalMapper(cache)
    mapper.begin_reconstruction(rec)
    out: dict[str, tuple[np.ndarray | None, int, list[float]]] = {}
    bar = progress_bar(len(names), progress, "COLMAP registrator", "image")
    for name in names:
        ok = name in ids and mapper.register_next_image(options, ids[name])
        image = rec.find_image_with_name(name) if ok else None
        if image is not None and image.has_pose:
            T = np.eye(4)
            T[:3, :] = image.cam_from_world().matrix()
            out[name] = (T, int(image.num_points3D), [float(v) for v in rec.cameras[image.camera_id].params])
        else:
            out[name] = (None, 0, [])
        bar.update()
    bar.close()
    mapper.end_reconstruction(False)
    return out
