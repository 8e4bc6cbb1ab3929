"""A workspace's trajectories and maps in a chosen CRS, for GIS tools, CloudCompare and evo.

``mapkit export-crs`` (:func:`export_crs`) writes, for each chosen session, its trajectory and
map, and optionally the merged map of ``mapkit align``, in one CRS:

* ``utm`` (the workspace's declared zone, from ``origin.json``), any projected ``EPSG:<code>``
  in metres, or ``ecef`` (EPSG:4978);
* ``wgs84`` (EPSG:4979, latitude, longitude, ellipsoidal height) or any geographic EPSG code:
  trajectories only (a point cloud in degrees is of no use to a point-cloud tool).

Files under ``OUT``::

    export.json                 what was written: CRS, workspace frame, sources, counts
    <session>/trajectory.tum    metric CRS: TUM lines ``t x y z qx qy qz qw`` (evo reads them;
                                '#' header lines state the CRS and the origin, as in the PLYs)
    <session>/trajectory.csv    geographic CRS: ``stamp_s,lat_deg,lon_deg,height_m,qx,qy,qz,qw``
    <session>/map.ply           the session's map (float64 x, y, z, header comments naming the CRS)
    merged_map.ply              the merged map of ``mapkit align`` (with ``--merged``)

Orientations: in a metric CRS the quaternion turns the base frame into the CRS's axes at the
pose (for UTM: grid east, grid north, up, i.e. meridian convergence applied; for ECEF the ECEF
axes); in a geographic CRS it turns the base frame into the local east-north-up frame at the pose
(x east, y north, z up). Heights are WGS84 ellipsoidal heights throughout. Positions of a TUM
file are written with 6 decimals (1 um), latitudes and longitudes with 10 (about 10 um).

Sessions are read as aligned (``WORKSPACE/align/sessions/<name>``) when ``mapkit align`` holds
them, else as built (``sessions/<name>/georef`` and ``map``), in each session's own declared frame.
"""

from __future__ import annotations

import json
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from mapkit.core.errors import InputError, InputWarning
from mapkit.core.geodesy import (
    EPSG_WGS84_GEODETIC_3D,
    LocalFrame,
    crs_info,
    frame_from_ply_comments,
    parse_crs,
    ply_crs_comments,
)
from mapkit.core.geometry import make_pose, matrix_to_quat_wxyz, quat_wxyz_to_matrix
from mapkit.core.runio import atomic_write_ply, atomic_write_text, write_json
from mapkit.core.workspace import Workspace
from mapkit.core.writers import writes_workspace
from mapkit.io.trajectory import read_tum, seconds_to_ns
from mapkit.multisession.tiles import load_tiles

Source = Literal["auto", "aligned", "built"]
CSV_COLUMNS = ("stamp_s", "lat_deg", "lon_deg", "height_m", "qx", "qy", "qz", "qw")


# --- PLY headers ----------------------------------------------------------------------------------


@dataclass
class PlyHeader:
    """A PLY file's header: ``format`` (e.g. ``binary_little_endian``), ``comments`` (without
    ``comment ``), ``elements`` ({name: count}) and ``properties`` ({element: [(type, name)]})."""

    format: str | None = None
    comments: list[str] = field(default_factory=list)
    elements: dict[str, int] = field(default_factory=dict)
    properties: dict[str, list[tuple[str, str]]] = field(default_factory=dict)


def read_ply_header(path: str | Path) -> PlyHeader:
    """The header of a PLY file (:class:`PlyHeader`)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "no such file")
    out = PlyHeader()
    current = None
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            raise InputError(path, "is not a PLY file (no 'ply' magic line)")
        for raw in f:
            line = raw.decode("ascii", errors="replace").rstrip("\r\n")
            if line == "end_header":
                return out
            key, _, rest = line.partition(" ")
            if key == "format":
                out.format = rest.split()[0]
            elif key == "comment":
                out.comments.append(rest)
            elif key == "element":
                name, count = rest.split()
                out.elements[name] = int(count)
                out.properties[name] = []
                current = name
            elif key == "property" and current is not None:
                parts = rest.split()
                out.properties[current].append((" ".join(parts[:-1]), parts[-1]))
    raise InputError(path, "PLY header has no end_header line")


def ply_georef(path: str | Path) -> tuple[LocalFrame | None, int | None, dict[str, str]]:
    """(workspace frame, EPSG code of x, y, z or None for local ENU, all header key-values)."""
    return frame_from_ply_comments(read_ply_header(path).comments)


# --- trajectories ---------------------------------------------------------------------------------


def poses_to_crs(frame: LocalFrame, enu_from_base: np.ndarray, epsg: int) -> tuple[np.ndarray, np.ndarray]:
    """(positions (N, 3) in the CRS, rotations (N, 3, 3) CRS-axes-from-base) of ENU poses."""
    P = np.asarray(enu_from_base, np.float64)
    xyz = frame.enu_to_crs(P[:, :3, 3], epsg)
    R = frame.crs_from_enu_rotations(P[:, :3, 3], epsg) @ P[:, :3, :3]
    return xyz, R


def poses_from_crs(frame: LocalFrame, xyz: np.ndarray, R_crs: np.ndarray, epsg: int) -> np.ndarray:
    """Inverse of :func:`poses_to_crs`: (N, 4, 4) ``enu_from_base``."""
    enu = frame.crs_to_enu(np.asarray(xyz, np.float64), epsg)
    Q = frame.crs_from_enu_rotations(enu, epsg)
    return make_pose(np.swapaxes(Q, -1, -2) @ np.asarray(R_crs, np.float64), enu)


def _header_lines(frame: LocalFrame, epsg: int) -> list[str]:
    return [f"# {c}" for c in ["generator mapkit", *ply_crs_comments(frame, epsg)]]


def write_crs_trajectory(
    path: str | Path, stamps_ns: np.ndarray, enu_from_base: np.ndarray, frame: LocalFrame, epsg: int
) -> Path:
    """A trajectory in EPSG ``epsg``: TUM for a metric CRS, CSV for a geographic one (module doc)."""
    epsg = int(epsg)
    xyz, R = poses_to_crs(frame, enu_from_base, epsg)
    q = matrix_to_quat_wxyz(R)
    stamps = [f"{s // 1_000_000_000}.{s % 1_000_000_000:09d}" for s in np.asarray(stamps_ns, np.int64)]
    if crs_info(epsg)["kind"] == "geographic":
        lines = [",".join(CSV_COLUMNS)]
        for st, (lon, lat, h), qi in zip(stamps, xyz, q, strict=True):
            lines.append(f"{st},{lat:.10f},{lon:.10f},{h:.6f},{qi[1]:.9f},{qi[2]:.9f},{qi[3]:.9f},{qi[0]:.9f}")
    else:
        lines = _header_lines(frame, epsg) + ["# timestamp tx ty tz qx qy qz qw"]
        for st, t, qi in zip(stamps, xyz, q, strict=True):
            lines.append(f"{st} {t[0]:.6f} {t[1]:.6f} {t[2]:.6f} {qi[1]:.9f} {qi[2]:.9f} {qi[3]:.9f} {qi[0]:.9f}")
    return atomic_write_text(path, "\n".join(lines) + "\n")


def read_crs_trajectory(
    path: str | Path, frame: LocalFrame | None = None, epsg: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(stamps_ns, enu_from_base) of a file from :func:`write_crs_trajectory`, in ``frame`` (by
    default the one its header names; a CSV carries no header, so give ``frame``; ``epsg``
    defaults to the header's, or 4979 for a CSV)."""
    path = Path(path)
    if path.suffix == ".csv":
        if frame is None:
            raise InputError(path, "a CSV trajectory names no frame: pass the workspace frame", field="frame")
        text = path.read_text().splitlines()
        if not text or tuple(text[0].split(",")) != CSV_COLUMNS:
            raise InputError(path, f"expected the header {','.join(CSV_COLUMNS)}", field="line 1")
        rows = [line.split(",") for line in text[1:] if line.strip()]
        stamps = np.array([seconds_to_ns(r[0]) for r in rows], np.int64)
        a = np.array([[float(v) for v in r[1:]] for r in rows], np.float64).reshape(-1, 7)
        xyz = a[:, [1, 0, 2]]  # lon, lat, h: x, y, z order
        q = a[:, [6, 3, 4, 5]]
        R = quat_wxyz_to_matrix(q / np.linalg.norm(q, axis=1, keepdims=True))
        return stamps, poses_from_crs(frame, xyz, R, EPSG_WGS84_GEODETIC_3D if epsg is None else epsg)
    comments = [line[1:].strip() for line in path.read_text().splitlines() if line.startswith("#")]
    f_header, e_header, _ = frame_from_ply_comments(comments)
    frame = frame or f_header
    epsg = epsg if epsg is not None else e_header
    if frame is None or epsg is None:
        raise InputError(path, "names no CRS or workspace frame in its '#' header", field="header")
    stamps, P = read_tum(path)
    return stamps, poses_from_crs(frame, P[:, :3, 3], P[:, :3, :3], epsg)


# --- a workspace ----------------------------------------------------------------------------------


def _session_sources(
    ws: Workspace, ws_frame: LocalFrame, name: str, source: Source, aligned: set[str]
) -> tuple[str, LocalFrame, Path, Path]:
    """(which, session frame, trajectory folder, map PLY) of one session."""
    al = ws.aligned(name)
    use_aligned = source == "aligned" or (source == "auto" and name in aligned)
    if use_aligned:
        if name not in aligned or not al.trajectory.is_dir():
            raise InputError(
                al.root, f"session {name!r} is not in a finished `mapkit align` of this workspace", field="session"
            )
        return "aligned", ws_frame, al.trajectory, al.map / "points.ply"
    sdir = ws.session(name)
    ga_path = sdir.gps_alignment
    if not ga_path.is_file():
        raise InputError(sdir.root, f"session {name!r} has no georef stage (run mapkit build)", field="session")
    ga = json.loads(ga_path.read_text())
    if not ga.get("georeferenced"):
        raise InputError(
            ga_path,
            f"session {name!r} is not georeferenced ({ga.get('reason', 'no reason given')}): it has no CRS",
            field="session",
        )
    return "built", LocalFrame.from_dict(ga), sdir.enu_trajectory, sdir.map / "points.ply"


def _read_points(path: Path) -> np.ndarray:
    import open3d as o3d

    # open3d's stub says os.PathLike; its binding takes a str path as well
    cloud = o3d.io.read_point_cloud(str(path), format="ply")  # type: ignore[arg-type]
    return np.asarray(cloud.points, np.float64)


@writes_workspace("workspace")
def export_crs(
    workspace: str | Path,
    out: str | Path,
    crs: str | int = "utm",
    sessions: Sequence[str] | None = None,
    trajectory: bool = True,
    map: bool = True,
    merged: bool = False,
    source: Source = "auto",
) -> dict:
    """Write sessions' trajectories and maps (and the merged map) of ``workspace`` in ``crs``
    (``utm``, ``ecef``, ``wgs84``, ``EPSG:<code>``) under ``out``; returns the manifest, also
    written to ``out/export.json``. ``sessions``: default all georeferenced ones; ``source``:
    ``aligned`` / ``built`` / ``auto`` (aligned where ``mapkit align`` holds the session)."""

    ws, out = Workspace(workspace), Path(out)
    ws_frame = ws.require_frame("run mapkit build with GPS first")
    epsg = parse_crs(crs, ws_frame)
    info = crs_info(epsg)
    geographic = info["kind"] == "geographic"
    maps_skipped = None
    if geographic and (map or merged):
        if not trajectory:
            raise InputError(
                None,
                f"EPSG:{epsg} ({info['name']}) is geographic: maps are written in a metric CRS only "
                "(utm, ecef or a projected EPSG code)",
                field="crs",
            )
        maps_skipped = f"EPSG:{epsg} is geographic: maps are written in a metric CRS only"
        map = merged = False
    aligned = set(ws.aligned_sessions())
    chosen = _chosen_sessions(ws, sessions, source, aligned) if (trajectory or map) else []
    manifest: dict = {
        "crs_epsg": epsg,
        "crs_name": info["name"],
        "crs_kind": info["kind"],
        "workspace_frame": ws_frame.to_dict(),
        "z": "WGS84 ellipsoidal height (m)",
        "sessions": {},
    }
    if maps_skipped:
        manifest["maps_skipped"] = maps_skipped
    for name in chosen:
        which, frame, traj_dir, map_ply = _session_sources(ws, ws_frame, name, source, aligned)
        entry: dict = {"source": which, "frame": frame.to_dict()}
        if trajectory:
            path = out / name / ("trajectory.csv" if geographic else "trajectory.tum")
            entry["trajectory"] = _export_trajectory(ws, traj_dir, path, out, frame, epsg)
        if map:
            entry["map"] = _export_map(ws, name, map_ply, out, frame, epsg)
        manifest["sessions"][name] = entry
    if merged:
        tiles = ws.tiles_dir
        pts, _, _, _ = load_tiles(tiles)
        atomic_write_ply(out / "merged_map.ply", ws_frame.enu_to_crs(pts, epsg), frame=ws_frame, crs_epsg=epsg)
        manifest["merged_map"] = {
            "file": "merged_map.ply",
            "from": tiles.relative_to(ws.root).as_posix(),
            "points": len(pts),
        }
    if not manifest["sessions"] and "merged_map" not in manifest:
        raise InputError(ws.root, "nothing to export: no georeferenced session chosen", field="sessions")
    write_json(out / "export.json", manifest)
    return manifest


def _chosen_sessions(ws: Workspace, sessions: Sequence[str] | None, source: Source, aligned: set[str]) -> list[str]:
    """``sessions`` as given, or by default the workspace's sessions that ``source`` can export:
    those in ``mapkit align`` (``aligned``), the georeferenced built ones (``built``), or either (``auto``)."""
    if sessions is not None:
        return list(sessions)

    def georeferenced(n: str) -> bool:
        ga = ws.session(n).gps_alignment
        return ga.is_file() and bool(json.loads(ga.read_text()).get("georeferenced"))

    names = ws.session_names()
    if source == "aligned":
        return [n for n in names if n in aligned]
    if source == "built":
        return [n for n in names if georeferenced(n)]
    return [n for n in names if n in aligned or georeferenced(n)]


def _export_trajectory(ws: Workspace, traj_dir: Path, path: Path, out: Path, frame: LocalFrame, epsg: int) -> dict:
    """A session's trajectory (folder ``traj_dir``) written to ``path`` in EPSG ``epsg``; returns its manifest entry."""
    from mapkit.mapping.trajectory import Trajectory

    traj = Trajectory.load(traj_dir)
    write_crs_trajectory(path, traj.stamps_ns, traj.world_from_base, frame, epsg)
    return {
        "file": path.relative_to(out).as_posix(),
        "from": traj_dir.relative_to(ws.root).as_posix(),
        "poses": len(traj),
    }


def _export_map(ws: Workspace, name: str, map_ply: Path, out: Path, frame: LocalFrame, epsg: int) -> dict | None:
    """Session ``name``'s map ``map_ply`` written to ``out/<name>/map.ply`` in EPSG ``epsg``;
    returns its manifest entry, or None (with an InputWarning) when the session has no map."""
    if not map_ply.is_file():
        warnings.warn(
            f"{map_ply}: no such file (session {name!r} built without a map?); its map is not exported",
            InputWarning,
            stacklevel=3,  # export_crs's caller
        )
        return None
    pts = _read_points(map_ply)
    path = out / name / "map.ply"
    atomic_write_ply(path, frame.enu_to_crs(pts, epsg), frame=frame, crs_epsg=epsg)
    return {
        "file": path.relative_to(out).as_posix(),
        "from": map_ply.relative_to(ws.root).as_posix(),
        "points": len(pts),
    }
