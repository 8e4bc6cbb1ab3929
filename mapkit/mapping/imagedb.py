"""Stage 4 of map construction: the georeferenced image database of one session.

Every selected frame with its 6-DoF camera pose in the map (local ENU) and in UTM/WGS84, written
as a COLMAP reconstruction (cameras, rigs, frames, images with poses and, when a map is given,
its points with their tracks) plus ``images.csv`` with timestamp, image path, lat, lon, alt,
easting, northing, up and the camera orientation quaternion. Images are stored once, optionally
downscaled (intrinsics scaled with them).

MCVL records its training drives at the camera's rate and keeps 2 Hz of them as the database
(Sec. IV-B): ``min_interval_s`` sub-samples by time beside ``min_spacing_m``'s distance. With
``training_frames`` the frames the database skips are kept too (``training/`` and
``training.csv``, same columns), as images the retrieval encoder learns its vocabulary and
PCA-whitening from that are not database images (:mod:`mapkit.retrieval.vlad_build`).
"""

from __future__ import annotations

import csv
import io
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
from pydantic import Field

from mapkit.core.config import MapkitConfig
from mapkit.core.errors import InputError
from mapkit.core.geodesy import LocalFrame
from mapkit.core.geometry import invert_pose, matrix_to_quat_wxyz, pose_from_quat_wxyz
from mapkit.core.runio import atomic_write_bytes, atomic_write_text
from mapkit.core.types import CameraInfo
from mapkit.io.benchmark import colmap_camera_params

CSV_COLUMNS = [
    "image_id",
    "stamp_ns",
    "camera",
    "image",
    "lat_deg",
    "lon_deg",
    "alt_m",
    "easting_m",
    "northing_m",
    "up_m",
    "x_m",
    "y_m",
    "z_m",
    "qw",
    "qx",
    "qy",
    "qz",
    "utm_epsg",
]


class ImageDbConfig(MapkitConfig):
    min_spacing_m: float = Field(
        0.5,
        description="Keep a frame when the camera moved this far since the last kept one (MCVL sub-sampled its "
        "training sequences to 2 Hz; spacing is rate-independent).",
    )
    min_interval_s: float = Field(
        0.0,
        ge=0,
        description="... and at least this long after the last kept one (s; 0 = no time limit). MCVL's database is its "
        "training drives sub-sampled to 2 Hz (Sec. IV-B): 0.5 with a faster camera. A tenth of it is slack for stamp "
        "jitter.",
    )
    training_frames: bool = Field(
        False,
        description="Also store the frames the database skips (training/ and training.csv, at most one per "
        "training_interval_s): images the retrieval encoder (vocabulary, PCA-whitening) learns from beside the "
        "database's.",
    )
    training_interval_s: float = Field(
        0.0,
        ge=0,
        description="A skipped frame becomes a training frame at least this long after the last frame stored (s).",
    )
    downscale: int = Field(
        1, ge=1, le=8, description="Store images downscaled by this integer factor (intrinsics scaled too)."
    )
    image_format: Literal["png", "jpg"] = Field(
        "jpg", description="Stored image format; jpg at quality 95 keeps databases small."
    )
    jpeg_quality: int = Field(95, ge=50, le=100)
    max_track_points: int = Field(
        500_000, description="At most this many map points go into the COLMAP reconstruction."
    )


@dataclass
class DbImage:
    image_id: int
    stamp_ns: int
    camera: str
    relpath: str
    world_from_cam: np.ndarray  # 4x4 in the map (local ENU) frame


def select_by_spacing(positions: np.ndarray, min_spacing_m: float) -> np.ndarray:
    """Indices of positions kept so that consecutive kept ones are at least ``min_spacing_m`` apart."""
    keep = [0] if len(positions) else []
    last = positions[0] if len(positions) else None
    for i in range(1, len(positions)):
        if np.linalg.norm(positions[i] - last) >= min_spacing_m:
            keep.append(i)
            last = positions[i]
    return np.asarray(keep, dtype=np.int64)


def scaled_info(info: CameraInfo, factor: int) -> CameraInfo:
    if factor == 1:
        return info
    K = info.K.copy()
    K[:2, :] /= factor
    # pixel centres: (x + 0.5) / f - 0.5
    K[0, 2] = (info.K[0, 2] + 0.5) / factor - 0.5
    K[1, 2] = (info.K[1, 2] + 0.5) / factor - 0.5
    return CameraInfo(
        info.camera, info.width // factor, info.height // factor, K, info.distortion_model, info.D, info.stamp_ns
    )


class ImageDbWriter:
    """Streams images to disk as they come, then writes the reconstruction and table at ``close``."""

    def __init__(self, folder: str | Path, cfg: ImageDbConfig, infos: dict[str, CameraInfo]):
        self.folder = Path(folder)
        self.cfg = cfg
        self.infos = {name: scaled_info(info, cfg.downscale) for name, info in infos.items()}
        self.images: list[DbImage] = []
        self.training: list[DbImage] = []  # frames the database skipped, kept for encoder training
        (self.folder / "images").mkdir(parents=True, exist_ok=True)

    def add(
        self,
        stamp_ns: int,
        camera: str,
        image: np.ndarray,
        world_from_cam: np.ndarray,
        encoding: str = "mono8",
        training: bool = False,
    ) -> DbImage:
        """Store one image: a database image, or with ``training`` a training frame (not in the database)."""
        if camera not in self.infos:
            raise InputError(None, f"camera {camera!r} has no intrinsics (CameraInfo)", field="camera_info")
        if self.cfg.downscale > 1:
            image = cv2.resize(
                image,
                (image.shape[1] // self.cfg.downscale, image.shape[0] // self.cfg.downscale),
                interpolation=cv2.INTER_AREA,
            )
        if image.ndim == 3 and encoding.startswith("rgb"):
            image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
        ext = self.cfg.image_format
        params = [cv2.IMWRITE_JPEG_QUALITY, self.cfg.jpeg_quality] if ext == "jpg" else []
        ok, buf = cv2.imencode(f".{ext}", image, params)
        if not ok:
            raise InputError(None, f"could not encode image of {camera} at {stamp_ns}")
        kept = self.training if training else self.images
        rel = f"{'training' if training else 'images'}/{camera}/{stamp_ns}.{ext}"
        atomic_write_bytes(self.folder / rel, buf.tobytes())
        img = DbImage(len(kept) + 1, int(stamp_ns), camera, rel, np.asarray(world_from_cam, np.float64))
        kept.append(img)
        return img

    def close(
        self,
        frame: LocalFrame | None,
        points_world: np.ndarray | None = None,
        point_observers: tuple[np.ndarray, np.ndarray] | None = None,
        point_colors: np.ndarray | None = None,
    ) -> Path:
        """Write ``images.csv`` (and ``training.csv`` when training frames are kept) and the COLMAP
        reconstruction ``colmap/``.

        ``point_observers`` is CSR (indptr, image_ids) of database image ids observing each point.
        """
        self._write_csv(frame)
        self._write_colmap(points_world, point_observers, point_colors)
        return self.folder

    def _write_csv(self, frame: LocalFrame | None) -> None:
        tables = [("images.csv", self.images)] + ([("training.csv", self.training)] if self.cfg.training_frames else [])
        for name, images in tables:
            T = np.stack([im.world_from_cam for im in images]) if images else np.zeros((0, 4, 4))
            write_images_csv(
                self.folder / name,
                [im.image_id for im in images],
                [im.stamp_ns for im in images],
                [im.camera for im in images],
                [im.relpath for im in images],
                T,
                frame,
            )

    def _write_colmap(self, points_world, observers, colors) -> None:
        import pycolmap

        rec = pycolmap.Reconstruction()
        cameras = {}
        for i, (name, info) in enumerate(sorted(self.infos.items()), start=1):
            model, params = colmap_camera_params(info)
            cameras[name] = pycolmap.Camera(
                model=model, width=info.width, height=info.height, params=params, camera_id=i
            )
            rec.add_camera_with_trivial_rig(cameras[name])
        keypoints: dict[int, list[np.ndarray]] = {im.image_id: [] for im in self.images}
        tracks: list[list[tuple[int, int]]] = []
        track_points = np.zeros(0, np.int64)
        if points_world is not None and observers is not None and len(points_world):
            keypoints, tracks, track_points = self._tracks(points_world, observers, cameras)
        for im in self.images:
            kp = np.asarray(keypoints.get(im.image_id, []), np.float64).reshape(-1, 2)
            img = pycolmap.Image(
                name=im.relpath, keypoints=kp, camera_id=cameras[im.camera].camera_id, image_id=im.image_id
            )
            rec.add_image_with_trivial_frame(img, pycolmap.Rigid3d(invert_pose(im.world_from_cam)[:3, :]))
        for point, track_elems in zip(track_points, tracks, strict=True):
            track = pycolmap.Track()
            for image_id, kp_idx in track_elems:
                track.add_element(image_id, kp_idx)
            color = np.zeros(3, np.uint8) if colors is None else np.asarray(colors[point], np.uint8)
            rec.add_point3D(points_world[point], track, color)
        out = self.folder / "colmap"
        tmp = self.folder / "colmap.partial"
        if tmp.exists():
            shutil.rmtree(tmp)
        tmp.mkdir(parents=True)
        rec.write(str(tmp))
        if out.exists():
            shutil.rmtree(out)
        tmp.rename(out)

    def _tracks(self, points_world: np.ndarray, observers: tuple[np.ndarray, np.ndarray], cameras: dict):
        """Project each point into the database images that observed it, through the image's COLMAP camera
        (``cameras`` by camera name: its distortion and pixel convention): the 2D keypoints of its track.

        Returns (keypoints by image id, tracks, index into ``points_world`` of each track's point).
        """
        indptr, obs_ids = observers
        n = min(len(points_world), self.cfg.max_track_points)
        by_id = {im.image_id: im for im in self.images}
        keypoints: dict[int, list[np.ndarray]] = {im.image_id: [] for im in self.images}
        counts = {im.image_id: 0 for im in self.images}
        point_of = np.repeat(np.arange(len(points_world)), np.diff(indptr))
        sel = point_of < n
        pts_idx, img_ids = point_of[sel], obs_ids[sel]
        tracks: list[list[tuple[int, int]]] = [[] for _ in range(n)]
        for image_id in np.unique(img_ids):
            im = by_id.get(int(image_id))
            if im is None:
                continue
            m = img_ids == image_id
            idx = pts_idx[m]
            info = self.infos[im.camera]
            cam_from_world = invert_pose(im.world_from_cam)
            pc = points_world[idx] @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
            front = pc[:, 2] > 1e-6
            uv = np.asarray(cameras[im.camera].img_from_cam(pc[front]), np.float64).reshape(-1, 2)
            inside = np.isfinite(uv).all(axis=1)
            inside &= (uv[:, 0] >= 0) & (uv[:, 0] < info.width) & (uv[:, 1] >= 0) & (uv[:, 1] < info.height)
            for p, xy in zip(idx[front][inside], uv[inside], strict=True):
                keypoints[int(image_id)].append(xy)
                tracks[p].append((int(image_id), counts[int(image_id)]))
                counts[int(image_id)] += 1
        keep = [i for i, t in enumerate(tracks) if len(t) >= 1]
        return keypoints, [tracks[i] for i in keep], np.asarray(keep, dtype=np.int64)


def write_images_csv(
    path: str | Path, image_ids, stamps_ns, cameras, relpaths, world_from_cam: np.ndarray, frame: LocalFrame | None
) -> Path:
    """The database table (``CSV_COLUMNS``), atomically: local ENU pose, WGS84 and UTM position."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_COLUMNS)
    T = np.asarray(world_from_cam, np.float64).reshape(-1, 4, 4)
    xyz = T[:, :3, 3]
    q = matrix_to_quat_wxyz(T[:, :3, :3]) if len(T) else np.zeros((0, 4))
    epsg: int | str
    if frame is not None and len(T):
        lat, lon, alt = frame.enu_to_geodetic(xyz)
        utm = frame.enu_to_utm(xyz)
        epsg = frame.utm_epsg
    else:
        lat = lon = alt = np.full(len(xyz), np.nan)
        utm = np.full((len(xyz), 3), np.nan)
        epsg = ""
    for i in range(len(T)):
        w.writerow(
            [
                int(image_ids[i]),
                int(stamps_ns[i]),
                cameras[i],
                relpaths[i],
                f"{lat[i]:.9f}",
                f"{lon[i]:.9f}",
                f"{alt[i]:.4f}",
                f"{utm[i, 0]:.4f}",
                f"{utm[i, 1]:.4f}",
                f"{utm[i, 2]:.4f}",
                f"{xyz[i, 0]:.4f}",
                f"{xyz[i, 1]:.4f}",
                f"{xyz[i, 2]:.4f}",
                f"{q[i, 0]:.9f}",
                f"{q[i, 1]:.9f}",
                f"{q[i, 2]:.9f}",
                f"{q[i, 3]:.9f}",
                epsg,
            ]
        )
    return atomic_write_text(path, buf.getvalue())


def images_world_from_cam(table: dict[str, np.ndarray]) -> np.ndarray:
    """(N, 4, 4) camera poses in the local ENU frame from a table read by ``read_images_csv``."""

    q = np.stack([table["qw"], table["qx"], table["qy"], table["qz"]], axis=1)
    t = np.stack([table["x_m"], table["y_m"], table["z_m"]], axis=1)
    return np.stack([pose_from_quat_wxyz(t[i], q[i]) for i in range(len(t))]) if len(t) else np.zeros((0, 4, 4))


def read_images_csv(path: str | Path) -> dict[str, np.ndarray]:
    """The database table as columns (numbers as arrays, names and paths as lists)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "no image database table here")
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        if reader.fieldnames is None or [c for c in CSV_COLUMNS if c not in reader.fieldnames]:
            raise InputError(path, f"header must hold {CSV_COLUMNS}", field="header")
        rows = list(reader)
    out: dict[str, np.ndarray] = {}
    for c in CSV_COLUMNS:
        vals = [r[c] for r in rows]
        if c in ("camera", "image"):
            out[c] = np.asarray(vals, dtype=object)
        elif c in ("image_id", "stamp_ns"):
            out[c] = np.asarray([int(v) for v in vals], dtype=np.int64)
        elif c == "utm_epsg":
            out[c] = np.asarray([int(v) if v else 0 for v in vals], dtype=np.int64)
        else:
            out[c] = np.asarray([float(v) for v in vals], dtype=np.float64)
    return out
