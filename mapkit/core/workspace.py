"""The workspace: every path of a mapkit project folder, spelled in one place.

A workspace holds one folder per drive (session) and the multi-session stages built on them::

    WORKSPACE/
      .lock                       held by the command writing the workspace (pid, command)
      origin.json                 the local ENU frame (geodetic origin) of every map here
      build_config.yaml           the resolved build config
      metrics.json                the build's per-session summary
      eval_build.json, .md        mapkit eval build (synthetic town, TUM / KITTI file or pose topic)
      sessions/<name>/            one drive: mapkit build
        config.yaml, metrics.json
        trajectory/               odometry (trajectory.npz, TUM, KITTI)
        georef/                   GPS-aligned trajectory_enu/, gps_alignment.json
        map/                      semi-dense map: points.ply, observations.npz
        imagedb/                  images/, images.csv, colmap/, camera_mount.json;
                                  training/, training.csv: frames the database skipped (encoder training)
      align/                      mapkit align; .done lists the sessions it holds
        sessions/<name>/          trajectory/, map/, lidar_map/ (where built), images.csv in the common frame
        tiles/                    merged map in UTM tiles
        pairs.json, registrations.json, qa.md, eval_align.json, .md
      triplets/                   mapkit triplets (triplets-lidar/ from the LiDAR maps)
      cnn/                        mapkit train
      indexes/vlad/               mapkit index vlad
      indexes/structure-<kind>/   mapkit index structure (structure-<kind>-lidar/ from the LiDAR maps)
      indexes/cache/              structure descriptors of session maps, shared by index builds and evaluations
      localize/                   mapkit eval localize (cache/ holds retrieved hits)
      eval/places/                mapkit eval places

Stages take a :class:`Workspace` (or its root) and return the paths they wrote; no other module
joins workspace paths by hand. A session's folders are a :class:`SessionDirs`, its aligned
counterpart an :class:`AlignedDirs`.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from mapkit.core.errors import InputError
from mapkit.core.geodesy import LocalFrame
from mapkit.core.lock import workspace_lock

#: the workspace's local frame; every map and pose in the workspace is in this ENU frame
ORIGIN = "origin.json"
DONE = ".done"

Stage = Literal["trajectory", "georef", "map", "lidar_map", "imagedb"]
MapSource = Literal["align", "build"]
#: which of a session's maps: the semi-dense map made from images (``map/``) or the LiDAR map (``lidar_map/``)
MapKind = Literal["semidense", "lidar"]
MAP_KINDS: tuple[MapKind, ...] = ("semidense", "lidar")
#: the file whose presence makes a map folder of each kind readable
_MAP_FILE: dict[MapKind, str] = {"semidense": "observations.npz", "lidar": "voxels.npz"}
_MAP_NAME: dict[MapKind, str] = {"semidense": "semi-dense map", "lidar": "LiDAR map"}


@dataclass(frozen=True)
class SessionDirs:
    """The folders ``mapkit build`` writes for one session (``WORKSPACE/sessions/<name>``)."""

    root: Path

    @property
    def name(self) -> str:
        return self.root.name

    @property
    def config(self) -> Path:
        return self.root / "config.yaml"

    @property
    def metrics(self) -> Path:
        return self.root / "metrics.json"

    @property
    def trajectory(self) -> Path:
        return self.root / "trajectory"

    @property
    def georef(self) -> Path:
        return self.root / "georef"

    @property
    def georef_trajectory(self) -> Path:
        """The GPS-aligned trajectory (workspace ENU), a :class:`~mapkit.mapping.trajectory.Trajectory` folder."""
        return self.georef / "trajectory_enu"

    @property
    def fused_trajectory(self) -> Path:
        """The factor graph's trajectory (workspace ENU; ``georef.fuse``), a
        :class:`~mapkit.mapping.trajectory.Trajectory` folder."""
        return self.georef / "trajectory_fused"

    @property
    def enu_trajectory(self) -> Path:
        """The trajectory the session's map and image database were made with: the factor graph's
        when the georef stage wrote one (``georef.fuse``; a georef run without it clears it), else the
        rigid GPS fit's."""
        return self.fused_trajectory if self.fused_trajectory.is_dir() else self.georef_trajectory

    @property
    def fused_covariances(self) -> Path:
        """Per pose of the fused trajectory: ``stamps_ns`` and ``covariances`` (N, 6, 6: rotation in ENU axes rad,
        position ENU m), and ``georef_covariance`` (6, 6: how well the session is tied to ENU)."""
        return self.georef / "trajectory_fused_covariances.npz"

    @property
    def gps_alignment(self) -> Path:
        return self.georef / "gps_alignment.json"

    @property
    def gps_fixes(self) -> Path:
        """The fixes the georef stage used, in the workspace ENU frame (``stamps_ns``, ``enu``, ``sigma_m``,
        ``associated``, ``inlier``), after screening."""
        return self.georef / "gps_fixes.npz"

    @property
    def map(self) -> Path:
        return self.root / "map"

    @property
    def lidar_map(self) -> Path:
        """The LiDAR map (:mod:`mapkit.mapping.stages.lidar_map`)."""
        return self.root / "lidar_map"

    @property
    def imagedb(self) -> Path:
        return self.root / "imagedb"

    @property
    def images_csv(self) -> Path:
        return self.imagedb / "images.csv"

    @property
    def training_csv(self) -> Path:
        """The frames the image database skipped but kept for learning the retrieval encoder
        (``imagedb.training_frames``; images under ``imagedb/training/``)."""
        return self.imagedb / "training.csv"

    @property
    def camera_mount(self) -> Path:
        """The image database's camera and its mount on the vehicle (``base_from_camera``)."""
        return self.imagedb / "camera_mount.json"

    def stage(self, stage: Stage) -> Path:
        return getattr(self, stage)

    def has(self, stage: Stage) -> bool:
        """The stage finished (its ``.done`` marker exists)."""
        return (self.stage(stage) / DONE).is_file()


@dataclass(frozen=True)
class AlignedDirs:
    """One session after ``mapkit align`` (``WORKSPACE/align/sessions/<name>``)."""

    root: Path

    @property
    def name(self) -> str:
        return self.root.name

    @property
    def trajectory(self) -> Path:
        return self.root / "trajectory"

    @property
    def map(self) -> Path:
        return self.root / "map"

    @property
    def lidar_map(self) -> Path:
        """The session's LiDAR map under the alignment's corrections (:mod:`mapkit.multisession.align`)."""
        return self.root / "lidar_map"

    @property
    def images_csv(self) -> Path:
        return self.root / "images.csv"

    @property
    def submaps(self) -> Path:
        return self.root / "submaps.json"


class Workspace:
    """A mapkit workspace folder. Cheap to make: nothing is read until asked for."""

    def __init__(self, root: str | os.PathLike | Workspace):
        self.root: Path = Path(root.root if isinstance(root, Workspace) else root)

    def __repr__(self) -> str:
        return f"Workspace({str(self.root)!r})"

    def __fspath__(self) -> str:
        return str(self.root)

    def lock(self, command: str | None = None, wait_s: float = 0.0):
        """The workspace's write lock, a context manager (:func:`mapkit.core.lock.workspace_lock`)."""
        return workspace_lock(self.root, command, wait_s)

    def __eq__(self, other) -> bool:
        return isinstance(other, Workspace) and self.root == other.root

    def __hash__(self) -> int:
        return hash(self.root)

    # ------------------------------------------------------------------ top level
    @property
    def origin(self) -> Path:
        return self.root / ORIGIN

    @property
    def build_config(self) -> Path:
        return self.root / "build_config.yaml"

    @property
    def metrics(self) -> Path:
        return self.root / "metrics.json"

    @property
    def eval_build_json(self) -> Path:
        return self.root / "eval_build.json"

    @property
    def eval_build_md(self) -> Path:
        return self.root / "eval_build.md"

    def frame(self) -> LocalFrame | None:
        """The workspace's local frame; None while no session is georeferenced."""
        if not self.origin.is_file():
            return None
        try:
            return LocalFrame.from_dict(json.loads(self.origin.read_text()))
        except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
            raise InputError(self.origin, f"not a valid frame description ({exc})") from None

    def require_frame(self, why: str = "run mapkit build on a log with GPS first") -> LocalFrame:
        """The workspace's local frame, or one clear error naming ``origin.json``."""
        frame = self.frame()
        if frame is None:
            raise InputError(self.origin, f"no such file: the workspace is not georeferenced ({why})")
        return frame

    # ------------------------------------------------------------------ sessions
    @property
    def sessions_dir(self) -> Path:
        return self.root / "sessions"

    def session(self, name: str) -> SessionDirs:
        return SessionDirs(self.sessions_dir / name)

    def session_names(self, stage: Stage | None = None) -> list[str]:
        """Sessions in the workspace, sorted; with ``stage``, only those whose stage finished."""
        if not self.sessions_dir.is_dir():
            return []
        names = sorted(p.name for p in self.sessions_dir.iterdir() if p.is_dir())
        return names if stage is None else [n for n in names if self.session(n).has(stage)]

    def sessions_with_images(self) -> list[str]:
        """Sessions whose image database has a table (``imagedb/images.csv``)."""
        return [n for n in self.session_names() if self.session(n).images_csv.is_file()]

    # ------------------------------------------------------------------ multi-session alignment
    @property
    def align_dir(self) -> Path:
        return self.root / "align"

    @property
    def align_done(self) -> Path:
        return self.align_dir / DONE

    def aligned(self, name: str) -> AlignedDirs:
        return AlignedDirs(self.align_dir / "sessions" / name)

    @property
    def tiles_dir(self) -> Path:
        return self.align_dir / "tiles"

    @property
    def align_pairs(self) -> Path:
        """Every registered submap pair with its verdict (``mapkit align``)."""
        return self.align_dir / "pairs.json"

    @property
    def eval_align_json(self) -> Path:
        return self.align_dir / "eval_align.json"

    @property
    def eval_align_md(self) -> Path:
        return self.align_dir / "eval_align.md"

    def align_record(self) -> dict:
        """The finished alignment's ``.done`` record ({} when align has not finished)."""
        if not self.align_done.is_file():
            return {}
        try:
            record = json.loads(self.align_done.read_text())
        except json.JSONDecodeError:
            return {}
        return record if isinstance(record, dict) else {}

    def aligned_sessions(self) -> list[str]:
        """Sessions that a finished ``mapkit align`` holds (listed in ``align/.done``)."""
        return list(self.align_record().get("sessions", []))

    def session_map(
        self, name: str, prefer_aligned: bool = True, source: MapKind = "semidense"
    ) -> tuple[Path, MapSource]:
        """(map folder, where it comes from) of session ``name``'s ``source`` map (the semi-dense ``map/`` or the
        ``lidar_map/``): ``align`` (one common frame for all sessions) when a finished ``mapkit align`` holds it,
        else ``build``. A session without that map is one error naming the session, the map and the maps it has."""
        if source not in _MAP_FILE:
            raise InputError(None, f"map source {source!r}: expected one of {list(MAP_KINDS)}", field="map_source")
        file = _MAP_FILE[source]
        aligned = self._map_dir(self.aligned(name), source)
        if prefer_aligned and name in self.aligned_sessions() and (aligned / file).is_file():
            return aligned, "align"
        own = self._map_dir(self.session(name), source)
        if (own / file).is_file():
            return own, "build"
        has = [_MAP_NAME[k] for k in MAP_KINDS if k != source and self._has_map(name, k)]
        raise InputError(
            own,
            f"session {name!r} has no {_MAP_NAME[source]} (map source {source!r}); it has "
            + (" and ".join(has) if has else "no map at all")
            + (
                " (build it with `lidar_map: true` from a log with a LiDAR stream, then mapkit align)"
                if source == "lidar"
                else " (run mapkit build / align)"
            ),
            field="sessions",
        )

    @staticmethod
    def _map_dir(dirs: SessionDirs | AlignedDirs, source: MapKind) -> Path:
        return dirs.map if source == "semidense" else dirs.lidar_map

    def _has_map(self, name: str, source: MapKind) -> bool:
        file = _MAP_FILE[source]
        return any((self._map_dir(d, source) / file).is_file() for d in (self.aligned(name), self.session(name)))

    def sessions_with_maps(self, source: MapKind = "semidense") -> list[str]:
        """Sessions with a ``source`` map (semi-dense by default, or LiDAR), built or aligned, sorted."""
        folder = "map" if source == "semidense" else "lidar_map"
        names = set()
        for base in (self.align_dir / "sessions", self.sessions_dir):
            if base.is_dir():
                names |= {p.name for p in base.iterdir() if (p / folder / _MAP_FILE[source]).is_file()}
        return sorted(names)

    def map_trajectory(self, name: str, where: MapSource) -> Path:
        """The trajectory folder session ``name``'s maps from ``where`` lie on: the aligned trajectory for ``align``,
        else the one the build placed them by (the GPS-aligned or fused one; the odometry's without GPS)."""
        if where == "align":
            return self.aligned(name).trajectory
        dirs = self.session(name)
        return dirs.enu_trajectory if dirs.enu_trajectory.is_dir() else dirs.trajectory

    def session_images_csv(self, name: str, prefer_aligned: bool = True) -> Path:
        """Session ``name``'s image table: the aligned poses when align holds the session, else the built ones."""
        aligned = self.aligned(name).images_csv
        if prefer_aligned and name in self.aligned_sessions() and aligned.is_file():
            return aligned
        return self.session(name).images_csv

    # ------------------------------------------------------------------ later stages
    @property
    def triplets_dir(self) -> Path:
        return self.root / "triplets"

    def triplets_folder(self, source: MapKind = "semidense") -> Path:
        """The default folder of ``mapkit triplets``: ``triplets/`` from the semi-dense maps, ``triplets-lidar/``
        from the LiDAR maps (two datasets side by side, neither overwriting the other)."""
        return self.triplets_dir if source == "semidense" else self.root / "triplets-lidar"

    @property
    def cnn_dir(self) -> Path:
        return self.root / "cnn"

    @property
    def indexes_dir(self) -> Path:
        return self.root / "indexes"

    @property
    def vlad_index(self) -> Path:
        return self.indexes_dir / "vlad"

    def vlad_index_variant(self, name: str) -> Path:
        """A second VLAD bundle built for comparison (``indexes/vlad-<name>``)."""
        return self.indexes_dir / f"vlad-{name}"

    def structure_index(self, kind: str, source: MapKind = "semidense") -> Path:
        """``indexes/structure-<kind>`` of the semi-dense maps, ``indexes/structure-<kind>-lidar`` of the LiDAR maps."""
        return self.indexes_dir / (f"structure-{kind}" if source == "semidense" else f"structure-{kind}-{source}")

    @property
    def descriptor_cache(self) -> Path:
        """Structure descriptors of session maps (keyed by map checksum and descriptor parameters),
        shared by ``mapkit index structure`` and ``mapkit eval places``: a map is described once."""
        return self.indexes_dir / "cache"

    @property
    def localize_dir(self) -> Path:
        return self.root / "localize"

    @property
    def localize_cache(self) -> Path:
        """Retrieved hits per test session, reused by localizer runs on the same bundle."""
        return self.localize_dir / "cache"

    @property
    def recording(self) -> Path:
        """The Rerun recording ``mapkit view`` writes by default."""
        return self.root / "view.rrd"

    @property
    def eval_dir(self) -> Path:
        return self.root / "eval"

    @property
    def places_eval_dir(self) -> Path:
        return self.eval_dir / "places"

    def places_eval_folder(self, source: MapKind = "semidense") -> Path:
        """The default folder of ``mapkit eval places``: ``eval/places`` on the semi-dense maps, ``eval/places-lidar``
        on the LiDAR maps."""
        return self.places_eval_dir if source == "semidense" else self.eval_dir / "places-lidar"


__all__ = ["MAP_KINDS", "AlignedDirs", "DONE", "MapKind", "ORIGIN", "SessionDirs", "Workspace"]
