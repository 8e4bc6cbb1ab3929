"""Stage 4 of a session, ``imagedb/``: the georeferenced image database (:class:`mapkit.mapping.imagedb.ImageDbWriter`:
images, ``images.csv``, a COLMAP reconstruction whose points are the semi-dense map's) of the mapping camera's
frames, one every ``min_spacing_m`` and ``min_interval_s``, and the camera's mount on the vehicle."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pydantic import Field, field_validator

from mapkit.core.geodesy import LocalFrame
from mapkit.core.runio import write_json
from mapkit.core.workspace import SessionDirs
from mapkit.core.writers import writes_workspace
from mapkit.mapping.imagedb import ImageDbConfig, ImageDbWriter
from mapkit.mapping.semidense import SemiDenseMap
from mapkit.mapping.stages.common import ARBITRARY_UNITS
from mapkit.mapping.stages.frames import PosedFrames

#: the version of this stage's algorithm, bumped whenever its output for the same inputs changes (it reruns)
STAGE_VERSION = 2


class ImageDbStageConfig(ImageDbConfig):
    enabled: bool = Field(
        True, description="Write the image database (stage 4); `imagedb: false` is short for `enabled: false`."
    )

    @field_validator("min_spacing_m")
    @classmethod
    def _spacing(cls, v: float) -> float:
        if not np.isfinite(v) or v < 0:
            raise ValueError(f"must be a finite distance >= 0 m, not {v}")
        return v


@writes_workspace("dirs", within=True)
def write_imagedb(
    dirs: SessionDirs,
    frames: PosedFrames,
    cfg: ImageDbStageConfig,
    frame: LocalFrame | None,
    metric: bool,
    map_dir: Path | None = None,
) -> Path:
    """Write the image database of ``frames`` (undecoded: only the frames kept are decoded) into
    ``dirs.imagedb``, with the camera's mount and the metrics; returns the folder.

    ``frame``: the session's local frame (None when it is not georeferenced); ``metric``: whether its
    poses are in metres (a spacing in metres means nothing at a reconstruction's arbitrary scale: then every
    registered frame is kept); ``map_dir``: the semi-dense map whose points and observations go into the
    reconstruction (None: a database without points)."""
    out = dirs.imagedb
    camera = frames.camera
    write_json(
        dirs.camera_mount,
        {
            "camera": camera.name,
            "base_frame": frames.trajectory.body_frame,
            "base_from_camera": frames.base_from_camera.tolist(),
        },
    )
    writer = ImageDbWriter(out, cfg, {camera.name: camera.info})
    db_id_of_frame = _add_images(writer, frames, cfg, metric)
    m: dict = {"images": len(writer.images), "pose_units": "m" if metric else ARBITRARY_UNITS}
    if cfg.training_frames:
        m["training_frames"] = len(writer.training)
    if not metric:
        m["note"] = (
            "not georeferenced: poses (images.csv x_m/y_m/z_m, colmap/) are in the reconstruction's arbitrary "
            "units, and imagedb.min_spacing_m was not applied"
        )
    if map_dir is None:
        writer.close(frame)
        write_json(out / "metrics.json", {**m, "map": False})
        return out
    smap = SemiDenseMap.load(map_dir)
    writer.close(frame, smap.points_world, _observations_by_image(smap, db_id_of_frame))
    write_json(out / "metrics.json", m)
    return out


def _add_images(writer: ImageDbWriter, frames: PosedFrames, cfg: ImageDbStageConfig, metric: bool) -> dict[int, int]:
    """Add the database's images (and with ``training_frames`` the training images) to ``writer``;
    returns the database image id of each frame index kept in the database."""
    min_spacing = cfg.min_spacing_m if metric else 0.0
    # a tenth of an interval's slack for the jitter of real camera stamps
    # (2 Hz from a 4 Hz camera is every other frame)
    min_interval_ns, training_interval_ns = cfg.min_interval_s * 0.9e9, cfg.training_interval_s * 0.9e9
    last: np.ndarray | None = None  # position of the last database image
    last_ns = last_stored_ns = 0  # stamps of the last database image and the last stored one: read once last is set
    db_id_of_frame: dict[int, int] = {}
    for i, frame, T in frames:
        in_db = last is None or (
            np.linalg.norm(T[:3, 3] - last) >= min_spacing and frame.stamp_ns - last_ns >= min_interval_ns
        )
        if not in_db and not (cfg.training_frames and frame.stamp_ns - last_stored_ns >= training_interval_ns):
            continue
        if not frames.decodes(frame, i):
            continue
        im = writer.add(frame.stamp_ns, frames.camera.name, frame.image, T, frame.encoding, training=not in_db)
        last_stored_ns = frame.stamp_ns
        if in_db:
            last, last_ns = T[:3, 3], frame.stamp_ns
            db_id_of_frame[i] = im.image_id
    return db_id_of_frame


def _observations_by_image(smap: SemiDenseMap, db_id_of_frame: dict[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The map's observations (by frame index) as CSR over its points by database image id: (indptr, image
    ids); observations in frames the database did not keep are dropped."""
    point_of = np.repeat(np.arange(len(smap.points_world)), np.diff(smap.obs_indptr))
    ids = np.array([db_id_of_frame.get(int(f), 0) for f in smap.obs_frame_ids], np.int64)
    keep = ids > 0
    counts = np.bincount(point_of[keep], minlength=len(smap.points_world))
    indptr = np.concatenate([[0], np.cumsum(counts)])
    return indptr, ids[keep]
