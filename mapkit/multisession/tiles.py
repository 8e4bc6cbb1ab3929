"""The merged map of ``mapkit align`` as UTM tiles (:func:`write_tiles`, :func:`load_tiles`)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from mapkit.core.errors import InputError
from mapkit.core.geodesy import LocalFrame
from mapkit.core.runio import atomic_path, atomic_write_ply, sha256_file, write_json

#: format of the files mapkit align writes (tiles.json, pairs.json, registrations.json)
ALIGN_FORMAT_VERSION = 1


def write_tiles(
    folder: Path,
    points_enu: np.ndarray,
    session_id: np.ndarray,
    point_index: np.ndarray,
    names: list[str],
    frame: LocalFrame,
    tile_m: float,
) -> dict:
    """The merged map as UTM tiles: ``E{easting}_N{northing}.ply`` holding UTM coordinates of the
    workspace's zone (float64 easting, northing, WGS84 ellipsoidal height; the EPSG code and the
    workspace origin in the PLY header), ``.npz`` (session and point index of every point, so
    observations stay reachable), and ``tiles.json`` with each tile's UTM bounds, count and
    checksums, and ``points_crs_epsg``: the CRS of the tiles' points."""
    folder.mkdir(parents=True, exist_ok=True)
    for old in folder.glob("E*_N*.*"):
        old.unlink()
    manifest = {
        "format_version": ALIGN_FORMAT_VERSION,
        "tile_size_m": tile_m,
        "utm_crs_epsg": frame.utm_epsg,
        "frame": frame.to_dict(),
        "points_frame": "utm",
        "points_crs_epsg": int(frame.utm_epsg),
        "points_z": "WGS84 ellipsoidal height (m)",
        "sessions": names,
        "tiles": [],
    }
    if len(points_enu) == 0:
        write_json(folder / "tiles.json", manifest)
        return {"tiles": 0, "points": 0}
    utm = frame.enu_to_utm(points_enu)
    key = np.floor(utm[:, :2] / tile_m).astype(np.int64)
    order = np.lexsort((key[:, 1], key[:, 0]))
    key_sorted = key[order]
    starts = np.flatnonzero(np.r_[True, np.any(np.diff(key_sorted, axis=0) != 0, axis=1)])
    ends = np.r_[starts[1:], len(order)]
    tiles = []
    for s0, s1 in zip(starts, ends, strict=True):
        sel = order[s0:s1]
        e, n = (int(v) for v in key_sorted[s0])
        stem = f"E{e * int(tile_m)}_N{n * int(tile_m)}"
        atomic_write_ply(folder / f"{stem}.ply", utm[sel], frame=frame, crs_epsg=int(frame.utm_epsg))
        with atomic_path(folder / f"{stem}.npz") as tmp, open(tmp, "wb") as f:
            np.savez_compressed(f, session_id=session_id[sel], point_index=point_index[sel])
        tiles.append(
            {
                "name": stem,
                "utm_min": [e * tile_m, n * tile_m],
                "utm_max": [(e + 1) * tile_m, (n + 1) * tile_m],
                "points": int(len(sel)),
                "ply_sha256": sha256_file(folder / f"{stem}.ply"),
                "npz_sha256": sha256_file(folder / f"{stem}.npz"),
            }
        )
    manifest["tiles"] = tiles
    write_json(folder / "tiles.json", manifest)
    return {"tiles": len(tiles), "points": int(len(points_enu))}


def load_tiles(
    folder: str | Path, bounds_utm: tuple[float, float, float, float] | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """Points (workspace ENU), session ids, point indices and session names of the merged map,
    optionally only of the tiles meeting ``bounds_utm`` = (e_min, n_min, e_max, n_max). Tiles in
    UTM (``points_crs_epsg`` in tiles.json) are converted back to ENU; tiles written before mapkit
    stored UTM in them (``points_frame`` "workspace ENU") are read as they are."""
    import open3d as o3d

    folder = Path(folder)
    manifest_path = folder / "tiles.json"
    if not manifest_path.is_file():
        raise InputError(manifest_path, "no such file (not a merged map folder?)")
    m = json.loads(manifest_path.read_text())
    if m.get("format_version") != ALIGN_FORMAT_VERSION:
        raise InputError(
            manifest_path,
            f"format version {m.get('format_version')!r}; this mapkit reads {ALIGN_FORMAT_VERSION}",
            field="format_version",
        )
    crs = m.get("points_crs_epsg")
    if crs is not None and "frame" not in m:
        raise InputError(
            manifest_path, f"tiles in EPSG:{crs} but no workspace frame to bring them back to ENU", field="frame"
        )
    pts, sid, idx = [], [], []
    for t in m["tiles"]:
        if bounds_utm is not None:
            e0, n0, e1, n1 = bounds_utm
            if t["utm_max"][0] < e0 or t["utm_min"][0] > e1 or t["utm_max"][1] < n0 or t["utm_min"][1] > n1:
                continue
        # open3d's stub says os.PathLike; its binding takes a str path as well
        cloud = o3d.io.read_point_cloud(str(folder / f"{t['name']}.ply"), format="ply")  # type: ignore[arg-type]
        pts.append(np.asarray(cloud.points))
        with np.load(folder / f"{t['name']}.npz") as z:
            sid.append(z["session_id"])
            idx.append(z["point_index"])
    if not pts:
        return np.zeros((0, 3)), np.zeros(0, np.int16), np.zeros(0, np.int64), m.get("sessions", [])
    xyz = np.concatenate(pts)
    if crs is not None:
        xyz = LocalFrame.from_dict(m["frame"]).crs_to_enu(xyz, int(crs))
    return xyz, np.concatenate(sid), np.concatenate(idx), m["sessions"]
