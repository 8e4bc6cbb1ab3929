"""``mapkit view``: a Rerun recording (``.rrd``) of a workspace, to fly through in the Rerun viewer.

Everything is drawn in the workspace's local ENU frame (x east, y north, z up), under ``world/``:

    world/build/<session>/trajectory     the GPS-aligned trajectory (``mapkit build``), a line strip
    world/build/<session>/vehicle        its pose over time
    world/build/<session>/map            the session's semi-dense map, decimated
    world/build/<session>/gps/fixes      GPS fixes in ENU (as the georef stage saved them), and
    world/build/<session>/gps/rejected   those the alignment rejected
    world/align/<session>/...            the same after ``mapkit align`` (trajectory, vehicle, map)
    world/<source>/<session>/camera      thumbnails at their camera poses over time (a pinhole), from
                                         the aligned image table when align holds the session
    world/localize/<run>/filter, retrieval        a ``mapkit localize`` run's estimates over time
    world/localize/hits/<session>/retrieved       database poses a localizer retrieved per query

Time is the ``drive_time`` timeline: seconds since each session's (or run's) first pose, so that
sessions play side by side. The recording is kept to a budget whatever the workspace's size: at
most ``budget_points`` map points over all maps together (each map keeps its share, sampled
uniformly) and one thumbnail per ``image_spacing_m`` of camera travel.

The Rerun SDK (``rerun-sdk``, the ``viewer`` extra) is imported only when a recording is written
or read, so that mapkit works without it.
"""

from __future__ import annotations

import json
import logging
import os
import time
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from mapkit.core.errors import InputError, InputWarning, MapkitError
from mapkit.core.geometry import matrix_to_quat_wxyz
from mapkit.core.runio import atomic_path, progress_bar
from mapkit.core.workspace import Workspace
from mapkit.core.writers import writes_workspace
from mapkit.io.benchmark import camera_info_from_colmap

if TYPE_CHECKING:
    import rerun as rr

    from mapkit.core.geodesy import LocalFrame

log = logging.getLogger(__name__)

#: the one line that says how to get the SDK
INSTALL_HINT = "mapkit view needs the Rerun SDK: pip install 'mapkit[viewer]' (or pip install 'rerun-sdk>=0.20')"
APPLICATION_ID = "mapkit"
TIMELINE = "drive_time"
#: session colours (matplotlib's tab10), RGB
PALETTE = np.array(
    [
        [31, 119, 180],
        [255, 127, 14],
        [44, 160, 44],
        [214, 39, 40],
        [148, 103, 189],
        [140, 86, 75],
        [227, 119, 194],
        [127, 127, 127],
        [188, 189, 34],
        [23, 190, 207],
    ],
    np.uint8,
)
#: distance (m) at which a camera's image plane is drawn: visible at the scale of a street
IMAGE_PLANE_M = 3.0


def _rerun():
    """The Rerun SDK, or one clear error saying how to install it."""
    try:
        import rerun as rr
    except ImportError:
        raise MapkitError(INSTALL_HINT) from None
    return rr


@dataclass
class RecordingSummary:
    """What ``write_recording`` wrote: the file, its size, and per entity what it holds."""

    path: Path
    bytes: int
    seconds: float
    map_points: dict[str, int] = field(default_factory=dict)  # entity -> points logged
    map_points_total: dict[str, int] = field(default_factory=dict)  # entity -> points in the map file
    images: dict[str, int] = field(default_factory=dict)  # camera entity -> thumbnails
    poses: dict[str, int] = field(default_factory=dict)  # trajectory / estimate entity -> poses
    gps_fixes: dict[str, int] = field(default_factory=dict)  # gps entity -> fixes
    notes: list[str] = field(default_factory=list)  # what could not be drawn, and why

    @property
    def points(self) -> int:
        return sum(self.map_points.values())


# --------------------------------------------------------------------------- what the workspace holds


@dataclass
class _Map:
    session: str
    entity: str
    ply: Path
    colour: np.ndarray
    count: int


def _ply_vertices(path: Path) -> int:
    from mapkit.deploy.crs_export import read_ply_header

    return int(read_ply_header(path).elements.get("vertex", 0))


def point_quotas(counts: list[int], budget: int) -> list[int]:
    """Points kept per map so that all together hold at most ``budget``: every map keeps the same
    share of its points (all of them when the workspace is under budget)."""
    total = sum(counts)
    if total <= budget:
        return list(counts)
    return [int(c * budget // total) for c in counts]


def _colour(i: int) -> np.ndarray:
    return PALETTE[i % len(PALETTE)]


def _xyzw(R: np.ndarray) -> np.ndarray:
    """Rerun's quaternions (x, y, z, w) of rotations (N, 3, 3)."""
    return matrix_to_quat_wxyz(R)[:, [1, 2, 3, 0]]


def _seconds(stamps_ns: np.ndarray, t0_ns: int) -> np.ndarray:
    return (np.asarray(stamps_ns, np.int64) - int(t0_ns)) * 1e-9


# --------------------------------------------------------------------------- the writer


class _Writer:
    """Logs one workspace into a recording stream, counting what it logs."""

    def __init__(self, rec: rr.RecordingStream, ws: Workspace, summary: RecordingSummary):
        self.rr = _rerun()
        self.rec, self.ws, self.summary = rec, ws, summary

    def trajectory(
        self, entity: str, stamps_ns: np.ndarray, world_from_body: np.ndarray, colour: np.ndarray, t0_ns: int
    ) -> None:
        """A line strip of the whole path (static) and the body's pose over ``drive_time``."""
        rr = self.rr
        P = np.asarray(world_from_body, np.float64)
        self.rec.log(
            f"{entity}/trajectory",
            rr.LineStrips3D([P[:, :3, 3]], colors=[colour], radii=rr.Radius.ui_points(2.0)),
            static=True,
        )
        self.rec.send_columns(
            f"{entity}/vehicle",
            indexes=[rr.TimeColumn(TIMELINE, duration=_seconds(stamps_ns, t0_ns))],
            columns=rr.Transform3D.columns(translation=P[:, :3, 3], quaternion=_xyzw(P[:, :3, :3])),
        )
        self.rec.log(f"{entity}/vehicle", rr.TransformAxes3D(2.0), static=True)
        self.summary.poses[f"{entity}/trajectory"] = len(P)

    def map(self, m: _Map, keep: int, rng: np.random.Generator) -> None:
        """``keep`` points of the map, drawn uniformly, tinted with the session's colour by intensity."""
        import open3d as o3d

        # open3d's stub says os.PathLike; its binding takes a str path as well
        cloud = o3d.io.read_point_cloud(str(m.ply), format="ply")  # type: ignore[arg-type]
        pts = np.asarray(cloud.points, np.float64)
        grey = np.asarray(cloud.colors, np.float64)[:, 0] if cloud.has_colors() else np.full(len(pts), 0.7)
        idx = np.sort(rng.choice(len(pts), size=min(keep, len(pts)), replace=False))
        colours = (m.colour[None, :] * (0.35 + 0.65 * grey[idx, None])).astype(np.uint8)
        self.rec.log(
            m.entity, self.rr.Points3D(pts[idx], colors=colours, radii=self.rr.Radius.ui_points(1.5)), static=True
        )
        self.summary.map_points[m.entity] = len(idx)
        self.summary.map_points_total[m.entity] = len(pts)

    def images(self, entity: str, name: str, spacing_m: float, width_px: int, t0_ns: int, prefer_aligned: bool) -> None:
        """Thumbnails ``width_px`` wide, one per ``spacing_m`` of camera travel, each at its camera
        pose (optical frame: x right, y down, z forward) and time."""
        import cv2

        from mapkit.mapping.imagedb import select_by_spacing
        from mapkit.retrieval.index_vlad import read_session_images

        rr = self.rr
        imgs = read_session_images(self.ws.root, name, prefer_aligned)
        if not len(imgs):
            return
        K, size_wh = _camera_intrinsics(self.ws, name)
        keep = select_by_spacing(imgs.world_from_cam[:, :3, 3], spacing_m)
        scale = width_px / size_wh[0]
        height_px = int(round(size_wh[1] * scale))
        K_thumb = K.copy()
        K_thumb[:2, :2] *= scale
        K_thumb[:2, 2] = (K[:2, 2] + 0.5) * scale - 0.5  # pixel centres
        cam = f"{entity}/camera"
        self.rec.log(
            cam,
            rr.Pinhole(image_from_camera=K_thumb, resolution=[width_px, height_px], image_plane_distance=IMAGE_PLANE_M),
            static=True,
        )
        logged = 0
        for i in keep:
            image = cv2.imread(str(imgs.image_paths[i]), cv2.IMREAD_COLOR)
            if image is None:  # a database folder copied without some images: draw the rest
                warnings.warn(
                    f"{imgs.image_paths[i]}: unreadable image; left out of the recording", InputWarning, stacklevel=2
                )
                continue
            thumb = cv2.resize(image, (width_px, height_px), interpolation=cv2.INTER_AREA)
            ok, jpg = cv2.imencode(".jpg", thumb, [cv2.IMWRITE_JPEG_QUALITY, 80])
            if not ok:
                raise InputError(imgs.image_paths[i], "could not encode its thumbnail as JPEG")
            T = imgs.world_from_cam[i]
            self.rec.set_time(TIMELINE, duration=float(_seconds(imgs.table["stamp_ns"][i : i + 1], t0_ns)[0]))
            self.rec.log(cam, rr.Transform3D(translation=T[:3, 3], quaternion=_xyzw(T[None, :3, :3])[0]))
            self.rec.log(cam, rr.EncodedImage(contents=jpg.tobytes(), media_type="image/jpeg"))
            logged += 1
        self.rec.reset_time()
        self.summary.images[cam] = logged

    def gps(self, entity: str, name: str, frame: LocalFrame) -> None:
        """The session's GPS fixes in ENU, the rejected ones apart: those the georef stage saved
        (``georef/gps_fixes.npz``, after screening), else, for a session without that file, read again
        from the session's log with the rejections of ``gps_alignment.json``."""
        saved = self.ws.session(name).gps_fixes
        if saved.is_file():
            with np.load(saved, allow_pickle=False) as f:
                enu, rejected = f["enu"], f["associated"] & ~f["inlier"]
        else:
            fixes = _gps_fixes(self.ws, name)
            if fixes is None:
                return
            stamps, lat, lon, alt = fixes
            enu = frame.geodetic_to_enu(lat, lon, alt)
            ga = json.loads(self.ws.session(name).gps_alignment.read_text())
            rejected = np.isin(stamps, [int(r["stamp_ns"]) for r in ga.get("rejected_fixes", [])])
        rr = self.rr
        self.rec.log(
            f"{entity}/gps/fixes",
            rr.Points3D(enu[~rejected], colors=[[40, 200, 80]], radii=rr.Radius.ui_points(3.0)),
            static=True,
        )
        self.rec.log(
            f"{entity}/gps/rejected",
            rr.Points3D(enu[rejected], colors=[[230, 30, 30]], radii=rr.Radius.ui_points(4.0)),
            static=True,
        )
        self.summary.gps_fixes[f"{entity}/gps/fixes"] = int((~rejected).sum())
        self.summary.gps_fixes[f"{entity}/gps/rejected"] = int(rejected.sum())

    def localize_run(self, folder: Path, entity: str) -> None:
        """A ``mapkit localize`` run: the filter's and retrieval's camera poses (TUM files) over time."""
        from mapkit.io.trajectory import read_tum

        t0 = None
        for key, colour in (("filter", [220, 0, 220]), ("retrieval", [250, 160, 0])):
            path = folder / ("poses_tum.txt" if key == "filter" else "retrieval_tum.txt")
            if not path.is_file():
                continue
            stamps, poses = read_tum(path)
            if not len(stamps):
                continue
            t0 = int(stamps[0]) if t0 is None else t0
            self.trajectory(f"{entity}/{key}", stamps, poses, np.asarray(colour, np.uint8), t0)

    def retrieved(self, hits: Path, entity: str) -> None:
        """Database positions a localizer retrieved for each query of a session (a hits cache file),
        at the query's time; queries are the session's image table, in order."""
        from mapkit.retrieval.index_vlad import read_database_csv, read_session_images
        from mapkit.retrieval.vlad_bundle import DATABASE_CSV

        with np.load(hits, allow_pickle=False) as f:
            session, ids = str(f["session"]), f["ids"].astype(np.int64)
            bundle = Path(str(f["bundle_path"])) if "bundle_path" in f.files else None
        if bundle is None or not (bundle / DATABASE_CSV).is_file():
            warnings.warn(
                f"{hits}: its bundle's database.csv is not found ({bundle}); retrieved poses left out",
                InputWarning,
                stacklevel=2,
            )
            return
        db = read_database_csv(bundle / DATABASE_CSV)
        xyz = np.stack([db["x_m"], db["y_m"], db["z_m"]], axis=1)
        try:
            stamps = read_session_images(self.ws.root, session).table["stamp_ns"]
        except InputError:
            stamps = np.zeros(0, np.int64)
        if len(stamps) != len(ids):
            warnings.warn(
                f"{hits}: {len(ids)} queries but session {session!r} has {len(stamps)} images; retrieved poses left "
                "out",
                InputWarning,
                stacklevel=2,
            )
            return
        rr = self.rr
        valid = ids >= 0
        pos = xyz[ids[valid]]
        self.rec.send_columns(
            f"{entity}/{session}/retrieved",
            indexes=[rr.TimeColumn(TIMELINE, duration=_seconds(stamps, stamps[0]))],
            columns=rr.Points3D.columns(positions=pos).partition(valid.sum(axis=1)),
        )
        self.rec.log(
            f"{entity}/{session}/retrieved",
            rr.Points3D.from_fields(colors=[[250, 120, 0]], radii=rr.Radius.ui_points(4.0)),
            static=True,
        )
        self.summary.poses[f"{entity}/{session}/retrieved"] = len(ids)


def _camera_intrinsics(ws: Workspace, name: str) -> tuple[np.ndarray, tuple[int, int]]:
    """(K, (width, height)) of the session's image database camera (a build writes one), from its COLMAP
    reconstruction, in mapkit's pixel convention (:func:`mapkit.io.benchmark.camera_info_from_colmap`)."""
    import pycolmap

    folder = ws.session(name).imagedb / "colmap"
    if not (folder / "cameras.bin").is_file():
        raise InputError(
            folder, f"session {name!r}: the image database has no COLMAP cameras (run mapkit build)", field="cameras"
        )
    cams = list(pycolmap.Reconstruction(str(folder)).cameras.values())
    if not cams:
        raise InputError(folder / "cameras.bin", "no camera", field="cameras")
    c = cams[0]
    try:
        info = camera_info_from_colmap(name, c.model_name, c.width, c.height, [float(v) for v in c.params])
    except ValueError as e:
        raise InputError(folder / "cameras.bin", str(e), field="cameras") from e
    return info.K, (info.width, info.height)


def _gps_fixes(ws: Workspace, name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """(stamps, lat, lon, alt) of the fixes in the session's log (the path its metrics.json records),
    or None, with a warning, when the log is gone or has no GPS."""
    import yaml

    from mapkit.core.config import TopicConfig, resolve_topics
    from mapkit.core.types import StreamKind
    from mapkit.io import open_log

    dirs = ws.session(name)
    log_path = json.loads(dirs.metrics.read_text()).get("log") if dirs.metrics.is_file() else None
    if not log_path or not Path(log_path).exists():
        warnings.warn(
            f"session {name!r}: its log ({log_path}) is not found, and the build saves no GPS positions; "
            "GPS fixes left out",
            InputWarning,
            stacklevel=3,
        )
        return None
    topics = TopicConfig()
    if dirs.config.is_file():
        topics = TopicConfig.model_validate((yaml.safe_load(dirs.config.read_text()) or {}).get("topics") or {})
    with open_log(log_path) as lg:
        gps = resolve_topics(lg, topics).get(StreamKind.GPS, [])
        fixes = [f for f in lg.records(StreamKind.GPS, topic=gps[0]) if f.has_fix] if gps else []
    if not fixes:
        return None
    return (
        np.array([f.stamp_ns for f in fixes], np.int64),
        np.array([f.lat_deg for f in fixes]),
        np.array([f.lon_deg for f in fixes]),
        np.array([f.alt_m for f in fixes]),
    )


def _localize_runs(folder: Path) -> Iterator[Path]:
    """``folder`` and the folders below it that hold a localizer's estimates (``poses_tum.txt``): a
    ``mapkit localize`` run, or one test session of a ``mapkit eval localize`` run (``RUN/SESSION``)."""
    if not folder.is_dir():
        return
    yield from sorted(p.parent for p in folder.rglob("poses_tum.txt"))


@writes_workspace("out", within=True, default="workspace")
def write_recording(
    workspace: str | Path | Workspace,
    out: str | Path | None = None,
    budget_points: int = 2_000_000,
    image_spacing_m: float = 10.0,
    thumbnail_width_px: int = 320,
    localize: str | Path | None = None,
    gps: bool = True,
    spawn: bool = False,
    seed: int = 0,
    progress: bool = True,
) -> RecordingSummary:
    """Write a Rerun recording of ``workspace`` to ``out`` (default ``WORKSPACE/view.rrd``, replaced atomically).

    Every session's trajectory and map (``mapkit build``; and the aligned ones under ``world/align``
    when ``mapkit align`` finished), its GPS fixes (``gps``: those the georef stage saved; for a session
    without ``georef/gps_fixes.npz``, read again from the session's log, which must still be where the
    build found it), thumbnails of its images at their poses, and, from ``localize`` (default
    ``WORKSPACE/localize``), every ``mapkit localize`` run's estimates and the database poses retrieved
    for each query of the cached hits. At most ``budget_points`` map points over all maps; one thumbnail
    per ``image_spacing_m`` of camera travel. ``spawn`` also streams the recording to a Rerun viewer it
    starts (needs a display). Returns what was written.
    """
    rr = _rerun()
    t_start = time.perf_counter()
    ws = Workspace(workspace)
    if not ws.sessions_dir.is_dir():
        raise InputError(ws.sessions_dir, "no sessions here: not a mapkit workspace (run mapkit build)")
    out = Path(out) if out is not None else ws.recording
    frame = ws.frame()
    aligned = set(ws.aligned_sessions())
    names = ws.session_names("georef")
    summary = RecordingSummary(out, 0, 0.0)
    if not names:
        raise InputError(
            ws.sessions_dir, "no session has a georeferenced trajectory (run mapkit build)", field="sessions"
        )
    maps = []
    for i, name in enumerate(names):
        for source, folder in (("build", ws.session(name).map), ("align", ws.aligned(name).map)):
            if (source == "build" or name in aligned) and (folder / "points.ply").is_file():
                ply = folder / "points.ply"
                maps.append(_Map(name, f"world/{source}/{name}/map", ply, _colour(i), _ply_vertices(ply)))
    quotas = point_quotas([m.count for m in maps], budget_points)
    loc_folder = Path(localize) if localize is not None else ws.localize_dir
    runs = list(_localize_runs(loc_folder))
    hits = sorted({*loc_folder.glob("cache/hits-*.npz"), *ws.localize_cache.glob("hits-*.npz")})
    if spawn:
        _check_display()

    rec = rr.RecordingStream(APPLICATION_ID, recording_id=f"mapkit-view-{ws.root.resolve()}")
    with atomic_path(out) as tmp:
        sinks = [rr.FileSink(str(tmp))]
        if spawn:
            rr.spawn(connect=False)
            sinks.append(rr.GrpcSink())
        rec.set_sinks(*sinks)
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)  # ENU
        w = _Writer(rec, ws, summary)
        rng = np.random.default_rng(seed)
        bar = progress_bar(len(names) + len(runs) + len(hits), progress, "mapkit view", "item")
        for i, name in enumerate(names):
            _session(w, name, i, frame, name in aligned, gps, image_spacing_m, thumbnail_width_px)
            for m, q in zip(maps, quotas, strict=True):
                if m.session == name:
                    w.map(m, q, rng)
            bar.update(1)
        for run in runs:
            w.localize_run(
                run, f"world/localize/{run.relative_to(loc_folder).as_posix() if run != loc_folder else run.name}"
            )
            bar.update(1)
        for h in hits:
            w.retrieved(h, "world/localize/hits")
            bar.update(1)
        bar.close()
        summary.notes += _missing_notes(frame, gps, runs, hits)
        rec.log(
            "notes",
            rr.TextDocument(_notes_markdown(ws, summary, budget_points, image_spacing_m), media_type="text/markdown"),
            static=True,
        )
        rec.send_blueprint(_blueprint(sorted(summary.images)))
        rec.flush()
        rec.disconnect()
    summary.bytes = out.stat().st_size
    summary.seconds = time.perf_counter() - t_start
    log.info(
        "recording written to %s (%.1f MB, %d map points, %d thumbnails)",
        out,
        summary.bytes / 1e6,
        summary.points,
        sum(summary.images.values()),
    )
    return summary


def _session(
    w: _Writer,
    name: str,
    i: int,
    frame: LocalFrame | None,
    aligned: bool,
    gps: bool,
    spacing_m: float,
    width_px: int,
) -> None:
    """One session: its built (and aligned) trajectory, GPS fixes and thumbnails."""
    from mapkit.mapping.trajectory import Trajectory

    dirs = w.ws.session(name)
    traj = Trajectory.load(dirs.enu_trajectory)
    if traj.frame != "enu":
        w.summary.notes.append(f"session {name}: not georeferenced; drawn in its own frame")
        warnings.warn(
            f"session {name!r} is not georeferenced: drawn in its own frame, not the workspace's",
            InputWarning,
            stacklevel=3,
        )
    t0 = int(traj.stamps_ns[0])
    w.trajectory(f"world/build/{name}", traj.stamps_ns, traj.world_from_base, _colour(i), t0)
    if aligned:
        at = Trajectory.load(w.ws.aligned(name).trajectory)
        w.trajectory(f"world/align/{name}", at.stamps_ns, at.world_from_base, _colour(i), t0)
    if gps and frame is not None and traj.frame == "enu":
        w.gps(f"world/build/{name}", name, frame)
    if dirs.images_csv.is_file():
        source = "align" if aligned and w.ws.aligned(name).images_csv.is_file() else "build"
        w.images(f"world/{source}/{name}", name, spacing_m, width_px, t0, prefer_aligned=source == "align")


def _missing_notes(frame: LocalFrame | None, gps: bool, runs: list[Path], hits: list[Path]) -> list[str]:
    """What the recording cannot show, and why (its notes panel and the command's output)."""
    notes = []
    if gps:
        notes.append(
            "GPS fixes: from each session's georef/gps_fixes.npz (the screened fixes the alignment used); for a "
            "session without that file, read again from the session's log"
        )
    if frame is None:
        notes.append("the workspace is not georeferenced (no origin.json): no GPS fixes")
    notes.append("particle clouds: no localizer run saves its particles; not drawn")
    if hits and not runs:
        notes.append(
            "no localizer estimates (poses_tum.txt) were found: only the retrieved database poses of the cached hits "
            "are drawn (mapkit eval localize writes each test session's estimates)"
        )
    return notes


def _notes_markdown(ws: Workspace, s: RecordingSummary, budget: int, spacing_m: float) -> str:
    """The recording's ``notes`` document: frame, timeline, what the budget kept, what is missing."""
    total = sum(s.map_points_total.values())
    lines = [
        f"# mapkit workspace `{ws.root.name}`",
        "",
        f"Local ENU frame of the workspace; timeline `{TIMELINE}`: seconds since each session's first pose.",
        "",
        f"- map points: {s.points:,} of {total:,} (budget {budget:,}, each map sampled uniformly to its share)",
        f"- thumbnails: {sum(s.images.values())} (one per {spacing_m:g} m of camera travel)",
    ]
    lines += [f"- {n}" for n in s.notes]
    return "\n".join(lines) + "\n"


def _blueprint(cameras: list[str]):
    """The viewer's layout: the workspace in 3D beside the notes and one tab per session camera."""
    import rerun.blueprint as rrb

    side: list[rrb.Container | rrb.View] = [rrb.TextDocumentView(origin="notes", name="notes")]
    if cameras:
        side.append(rrb.Tabs(*[rrb.Spatial2DView(origin=c, name=c.split("/")[2]) for c in cameras]))
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="world", name="workspace (local ENU)"), rrb.Vertical(*side), column_shares=[3, 1]
        )
    )


def _check_display() -> None:
    """``--spawn`` starts a native viewer: refuse clearly where there is no display to show it on."""
    import sys

    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise MapkitError(
            "--spawn: no display here (DISPLAY / WAYLAND_DISPLAY unset); write the .rrd and open it with "
            "`rerun FILE.rrd` on a machine with one"
        )


# --------------------------------------------------------------------------- reading a recording back


def read_recording(path: str | Path) -> dict[str, dict[str, list]]:
    """Every component column of a ``.rrd``: ``{entity: {"Archetype:component": [row, ...]}}``, rows of
    the static and the temporal chunks together (static first), and the ``drive_time`` of the temporal
    rows (seconds). A row of vectors (positions, translations, a strip) is an (n, k) float array, a
    row of numbers an (n,) array, anything else a Python value. For tests and pictures."""
    _rerun()
    from rerun.chunk import RrdReader

    out: dict[str, dict[str, list]] = {}
    for chunk in sorted(RrdReader(str(path)).stream(), key=lambda c: not c.is_static):
        batch = chunk.to_record_batch()
        cols = out.setdefault(chunk.entity_path.lstrip("/"), {})
        for name in batch.schema.names:
            if name == TIMELINE or (":" in name and not name.startswith("rerun.")):
                cols.setdefault(name, []).extend(_rows(batch.column(name)))
    return out


def _rows(col) -> list:
    """The rows of one Arrow column: numeric lists as NumPy arrays (fast for millions of points)."""
    import pyarrow as pa

    if pa.types.is_duration(col.type):  # the drive_time timeline, in seconds
        return list(col.cast(pa.int64()).to_numpy(zero_copy_only=False) * 1e-9)
    if not pa.types.is_list(col.type):
        return col.to_pylist()
    values, offsets = col.values, col.offsets.to_numpy()
    if pa.types.is_fixed_size_list(values.type) and pa.types.is_floating(values.type.value_type):
        arr = values.flatten().to_numpy(zero_copy_only=False).reshape(-1, values.type.list_size)
    elif pa.types.is_integer(values.type) or pa.types.is_floating(values.type):
        arr = values.to_numpy(zero_copy_only=False)
    else:
        return col.to_pylist()
    return [None if not col[k].is_valid else arr[offsets[k] : offsets[k + 1]] for k in range(len(col))]


def _xy(rows: list) -> np.ndarray:
    """(n, 3) positions of all non-empty rows together."""
    rows = [np.asarray(r, np.float64).reshape(-1, 3) for r in rows if r is not None and len(r)]
    return np.concatenate(rows) if rows else np.zeros((0, 3))


def render_top_view(recording: str | Path, png: str | Path, max_points: int = 400_000) -> Path:
    """A top view (east, north) of a recording drawn with matplotlib, for where no viewer can run:
    map points, trajectories, GPS fixes, thumbnail poses, localizer estimates and retrieved database
    poses, as the recording holds them."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    data = read_recording(recording)
    fig, ax = plt.subplots(figsize=(10, 10), dpi=120)
    pts, cols = [], []
    for entity, c in sorted(data.items()):  # by name: the recording's chunk order varies from run to run
        if entity.endswith("/map") and "Points3D:positions" in c:
            pts.append(_xy(c["Points3D:positions"]))
            cols.append(_rgba(c.get("Points3D:colors", [None])[0], len(pts[-1])))
    if pts:
        P, C = np.concatenate(pts), np.concatenate(cols)
        sel = np.random.default_rng(0).choice(len(P), size=min(max_points, len(P)), replace=False)
        ax.scatter(P[sel, 0], P[sel, 1], s=0.2, c=C[sel], linewidths=0, rasterized=True, zorder=0)
    for entity, c in sorted(data.items()):
        if entity.endswith("/trajectory") and "LineStrips3D:strips" in c:
            xyz = np.asarray(c["LineStrips3D:strips"][0][0], np.float64)
            colour = _rgba(c.get("LineStrips3D:colors", [None])[0], 1)[0]
            built = "/build/" in entity
            ax.plot(
                xyz[:, 0],
                xyz[:, 1],
                "--" if built else "-",
                color=colour,
                lw=0.8 if built else 1.4,
                zorder=3,
                label=entity.removeprefix("world/").removesuffix("/trajectory"),
            )
        elif entity.endswith("/camera") and "Transform3D:translation" in c:
            xyz = _xy(c["Transform3D:translation"])
            ax.plot(xyz[:, 0], xyz[:, 1], "^", ms=2.5, color="k", alpha=0.35, zorder=2.5)
        elif entity.endswith("/retrieved") and "Points3D:positions" in c:
            xyz = _xy(c["Points3D:positions"])
            ax.plot(xyz[:, 0], xyz[:, 1], "o", ms=2, color="darkorange", alpha=0.05, zorder=1)
        elif "/gps/" in entity and "Points3D:positions" in c:
            xyz = _xy(c["Points3D:positions"])
            rejected = entity.endswith("rejected")
            ax.plot(
                xyz[:, 0],
                xyz[:, 1],
                "x" if rejected else ".",
                ms=3,
                color="red" if rejected else "green",
                alpha=0.7,
                zorder=2,
            )
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    if pts:  # the maps' extent, without the empty margins an equal-aspect square would add
        lo, hi = P[:, :2].min(axis=0), P[:, :2].max(axis=0)
        pad = 0.03 * float(max(hi - lo))
        ax.set_xlim(lo[0] - pad, hi[0] + pad)
        ax.set_ylim(lo[1] - pad, hi[1] + pad)
    ax.set_aspect("equal", adjustable="box")
    ax.set_title(
        f"{Path(recording).name}: maps, trajectories (dashed: built, solid: aligned), GPS fixes "
        "(rejected: x), thumbnails (^), retrieved database poses (orange)",
        fontsize=9,
    )
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=6, loc="best", markerscale=2)
    with atomic_path(png) as tmp:
        fig.savefig(tmp, format="png", bbox_inches="tight")
    plt.close(fig)
    return Path(png)


def _rgba(packed, n: int) -> np.ndarray:
    """(n, 4) colours in [0, 1] of Rerun's packed 0xRRGGBBAA values (one, or one per point)."""
    if packed is None:
        return np.tile([0.5, 0.5, 0.5, 1.0], (n, 1))
    v = np.atleast_1d(np.asarray(packed, np.uint64))
    rgba = np.stack([(v >> 24) & 255, (v >> 16) & 255, (v >> 8) & 255, v & 255], axis=1) / 255.0
    return np.broadcast_to(rgba, (n, 4)) if len(rgba) == 1 else rgba


__all__ = ["INSTALL_HINT", "RecordingSummary", "point_quotas", "read_recording", "render_top_view", "write_recording"]
