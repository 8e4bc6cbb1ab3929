"""Coordinates that say what they are: CRS conversions against pyproj, PLY headers, tiles in UTM,
and ``mapkit export-crs``."""

from __future__ import annotations

import json

import numpy as np
import open3d as o3d
import pytest
from pyproj import Proj, Transformer

from mapkit.cli import main
from mapkit.core.errors import InputError
from mapkit.core.geodesy import LocalFrame, crs_info, frame_from_ply_comments, parse_crs
from mapkit.core.geometry import make_pose, yaw_rotation
from mapkit.core.runio import atomic_write_ply, write_json
from mapkit.deploy.crs_export import export_crs, ply_georef, read_crs_trajectory, read_ply_header, write_crs_trajectory
from mapkit.io.trajectory import read_tum
from mapkit.mapping.trajectory import Trajectory
from mapkit.multisession.tiles import load_tiles, write_tiles

FRAME = LocalFrame(51.7520209, -1.2577263, 61.25)  # UTM zone 30N, EPSG:32630
UTM = 32630


@pytest.fixture(scope="module")
def geodetic():
    """Points within ~2 km and +-50 m of the origin, as WGS84 (lat, lon, h) and as ENU."""
    rng = np.random.default_rng(3)
    lat = FRAME.lat0_deg + rng.uniform(-0.02, 0.02, 200)
    lon = FRAME.lon0_deg + rng.uniform(-0.03, 0.03, 200)
    h = FRAME.alt0_m + rng.uniform(-50, 50, 200)
    return lat, lon, h, FRAME.geodetic_to_enu(lat, lon, h)


def test_enu_against_proj_topocentric(geodetic):
    lat, lon, h, enu = geodetic
    e, n, u = Transformer.from_pipeline(FRAME.enu_pipeline).transform(lon, lat, h)
    assert np.abs(np.stack([e, n, u], axis=1) - enu).max() < 1e-6


@pytest.mark.parametrize("epsg", [UTM, 4978, 4979, 25830, 3857, 32631])
def test_enu_to_crs_equals_pyproj_and_round_trips(geodetic, epsg):
    lat, lon, h, enu = geodetic
    x, y, z = Transformer.from_crs(4979, epsg, always_xy=True).transform(lon, lat, h)
    ref = np.stack([x, y, z], axis=1)
    got = FRAME.enu_to_crs(enu, epsg)
    tol = np.array([1e-9, 1e-9, 1e-4]) if epsg == 4979 else 1e-4  # degrees (1e-9 deg ~ 0.1 mm), metres
    assert np.all(np.abs(got - ref) < tol)
    assert np.abs(FRAME.crs_to_enu(got, epsg) - enu).max() < 1e-6


def test_enu_to_utm_is_the_workspace_zone(geodetic):
    _, _, _, enu = geodetic
    assert parse_crs("utm", FRAME) == UTM and parse_crs("EPSG:4978") == 4978 and parse_crs("wgs84") == 4979
    assert np.array_equal(FRAME.enu_to_crs(enu, UTM), FRAME.enu_to_utm(enu))
    assert (
        crs_info(UTM)["kind"] == "utm" and crs_info(4978)["kind"] == "ecef" and crs_info(4979)["kind"] == "geographic"
    )
    for bad in ("EPSG:999999", "lambert", "EPSG:2249"):  # unknown, not a CRS, US survey feet
        with pytest.raises(InputError):
            parse_crs(bad, FRAME)


def test_orientation_in_utm_turns_by_the_meridian_convergence():
    R = FRAME.crs_from_enu_rotations(np.zeros((1, 3)), UTM)[0]
    gamma = np.radians(Proj(f"EPSG:{UTM}").get_factors(FRAME.lon0_deg, FRAME.lat0_deg).meridian_convergence)
    # true north in grid coordinates, from pyproj along the meridian, and its angle from grid north
    # is the meridian convergence (PROJ's sign: grid north is gamma clockwise of true north)
    t = Transformer.from_crs(4979, UTM, always_xy=True)
    a, b = (np.array(t.transform(FRAME.lon0_deg, FRAME.lat0_deg + d, FRAME.alt0_m)) for d in (-1e-5, 1e-5))
    north = (b - a) / np.linalg.norm(b - a)
    assert np.allclose(R @ [0.0, 1.0, 0.0], north, atol=1e-9)
    assert abs(gamma) > np.radians(1) and np.allclose(north, [-np.sin(gamma), np.cos(gamma), 0.0], atol=1e-9)
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(R), 1.0)
    # ECEF: the exact constant rotation
    assert np.allclose(FRAME.crs_from_enu_rotations(np.ones((2, 3)), 4978), FRAME.ecef_from_enu_rotation, atol=0)


def test_ply_is_written_by_numpy_and_read_by_open3d(tmp_path):
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(500, 3)) * 100
    cols = rng.uniform(size=(500, 3))
    p = atomic_write_ply(tmp_path / "a.ply", pts, cols, frame=FRAME)
    pc = o3d.io.read_point_cloud(str(p))
    assert np.array_equal(np.asarray(pc.points), pts)
    assert np.abs(np.asarray(pc.colors) - cols).max() <= 0.5 / 255 + 1e-12
    h = read_ply_header(p)
    assert h.format == "binary_little_endian" and h.elements == {"vertex": 500}
    assert [n for _, n in h.properties["vertex"]] == ["x", "y", "z", "red", "green", "blue"]
    assert p.stat().st_size == len(p.read_bytes().split(b"end_header\n")[0]) + len("end_header\n") + 500 * 27
    frame, epsg, kv = ply_georef(p)
    assert frame == FRAME and epsg is None and kv["frame"] == "local_enu" and kv["utm_crs"] == "EPSG:32630"
    # no frame: says so; no leftovers beside the file
    atomic_write_ply(tmp_path / "b.ply", pts)
    assert ply_georef(tmp_path / "b.ply")[2]["frame"] == "unspecified"
    assert np.array_equal(np.asarray(o3d.io.read_point_cloud(str(tmp_path / "b.ply")).points), pts)
    assert sorted(f.name for f in tmp_path.iterdir()) == ["a.ply", "b.ply"]


def test_ply_write_with_a_short_file_is_not_renamed_into_place(tmp_path, monkeypatch):
    import mapkit.core.runio as runio

    real = runio.os.fstat

    class Short:
        def __init__(self, st):
            self.st_size = st.st_size - 1

    monkeypatch.setattr(runio.os, "fstat", lambda fd: Short(real(fd)))
    with pytest.raises(OSError, match="expected"):
        atomic_write_ply(tmp_path / "c.ply", np.zeros((3, 3)))
    assert list(tmp_path.iterdir()) == []


def test_utm_ply_gives_back_the_workspace_origin(tmp_path, geodetic):
    _, _, _, enu = geodetic
    utm = FRAME.enu_to_utm(enu)
    p = atomic_write_ply(tmp_path / "u.ply", utm, frame=FRAME, crs_epsg=UTM)
    frame, epsg, kv = ply_georef(p)
    assert frame == FRAME and epsg == UTM and kv["frame"] == "utm" and kv["z"] == "wgs84_ellipsoidal_height_m"
    back = np.asarray(o3d.io.read_point_cloud(str(p)).points)
    assert np.array_equal(back, utm)  # float64: UTM northings exactly
    assert np.abs(frame.crs_to_enu(back, epsg) - enu).max() < 1e-6
    assert Transformer.from_pipeline(kv["enu_pipeline"]).transform(
        FRAME.lon0_deg, FRAME.lat0_deg, FRAME.alt0_m
    ) == pytest.approx((0, 0, 0), abs=1e-6)
    assert frame_from_ply_comments([f"comment {c}" for c in read_ply_header(p).comments])[0] == FRAME


def test_tiles_hold_utm_and_load_back_as_enu(tmp_path):
    rng = np.random.default_rng(1)
    enu = rng.uniform([-150, -120, -5], [150, 120, 5], size=(4000, 3))
    sid = rng.integers(0, 2, 4000).astype(np.int16)
    idx = np.arange(4000, dtype=np.int64)
    qa = write_tiles(tmp_path / "tiles", enu, sid, idx, ["a", "b"], FRAME, 100.0)
    m = json.loads((tmp_path / "tiles" / "tiles.json").read_text())
    assert qa["tiles"] == len(m["tiles"]) > 4 and m["points_crs_epsg"] == m["utm_crs_epsg"] == UTM
    for t in m["tiles"]:
        f = tmp_path / "tiles" / f"{t['name']}.ply"
        frame, epsg, _ = ply_georef(f)
        assert frame == FRAME and epsg == m["points_crs_epsg"]
        xyz = np.asarray(o3d.io.read_point_cloud(str(f)).points)
        assert np.all(xyz[:, :2] >= t["utm_min"]) and np.all(xyz[:, :2] < t["utm_max"])
        assert t["name"] == f"E{int(t['utm_min'][0])}_N{int(t['utm_min'][1])}"
    pts, s2, i2, names = load_tiles(tmp_path / "tiles")
    assert names == ["a", "b"] and len(pts) == 4000
    assert np.abs(pts[np.argsort(i2)] - enu).max() < 1e-6 and np.array_equal(s2[np.argsort(i2)], sid)
    # a merged map written before tiles held UTM (ENU points, no points_crs_epsg) still loads
    old = tmp_path / "old"
    old.mkdir()
    atomic_write_ply(old / "E0_N0.ply", enu[:10])
    np.savez(old / "E0_N0.npz", session_id=sid[:10], point_index=idx[:10])
    write_json(
        old / "tiles.json",
        {
            "format_version": 1,
            "tile_size_m": 100.0,
            "utm_crs_epsg": UTM,
            "frame": FRAME.to_dict(),
            "points_frame": "workspace ENU",
            "sessions": ["a", "b"],
            "tiles": [{"name": "E0_N0", "utm_min": [0, 0], "utm_max": [1e7, 1e7], "points": 10}],
        },
    )
    assert np.array_equal(load_tiles(old)[0], enu[:10])
    # an empty merged map has a readable manifest too
    write_tiles(tmp_path / "empty", np.zeros((0, 3)), sid[:0], idx[:0], ["a"], FRAME, 100.0)
    assert len(load_tiles(tmp_path / "empty")[0]) == 0


def _poses(n=40):
    t = np.linspace(0, 60, n)
    yaw = np.radians(20 + 3 * t)
    pos = np.stack([300 * np.cos(yaw / 4), 200 * np.sin(yaw / 3), 0.1 * t - 2], axis=1)
    return (1_600_000_000_000_000_000 + (t * 1e9).astype(np.int64)), make_pose(yaw_rotation(yaw), pos)


@pytest.mark.parametrize("epsg,suffix", [(UTM, "tum"), (4978, "tum"), (4979, "csv")])
def test_trajectory_round_trips(tmp_path, epsg, suffix):
    stamps, P = _poses()
    path = write_crs_trajectory(tmp_path / f"t.{suffix}", stamps, P, FRAME, epsg)
    s2, P2 = read_crs_trajectory(path, frame=FRAME if suffix == "csv" else None)
    assert np.array_equal(s2, stamps)
    assert np.abs(P2[:, :3, 3] - P[:, :3, 3]).max() < 2e-5  # 1 um (TUM) / 1e-10 deg (CSV) rounding
    assert np.abs(P2[:, :3, :3] - P[:, :3, :3]).max() < 1e-7
    lat, lon, h = FRAME.enu_to_geodetic(P[:, :3, 3])
    if suffix == "tum":
        # plain TUM readers (mapkit's, evo's) skip the '#' header and get pyproj's coordinates
        _, T = read_tum(path)
        x, y, z = Transformer.from_crs(4979, epsg, always_xy=True).transform(lon, lat, h)
        assert np.abs(T[:, :3, 3] - np.stack([x, y, z], axis=1)).max() < 1e-5
    else:
        head, first = path.read_text().splitlines()[:2]
        assert head == "stamp_s,lat_deg,lon_deg,height_m,qx,qy,qz,qw"
        assert np.allclose([float(v) for v in first.split(",")[1:4]], [lat[0], lon[0], h[0]], atol=1e-9)


@pytest.fixture
def workspace(tmp_path):
    ws = tmp_path / "ws"
    write_json(ws / "origin.json", FRAME.to_dict())
    stamps, P = _poses()
    for name, georef in (("s0", True), ("s1", True), ("nogps", False)):
        sdir = ws / "sessions" / name
        write_json(
            sdir / "georef" / "gps_alignment.json",
            {"georeferenced": georef, **(FRAME.to_dict() if georef else {"reason": "no GPS"})},
        )
        Trajectory(stamps, P, "test", frame="enu").save(sdir / "georef" / "trajectory_enu")
        atomic_write_ply(sdir / "map" / "points.ply", P[:, :3, 3] + [0, 0, -1.5], frame=FRAME if georef else None)
    return ws


def test_export_crs_of_a_workspace(workspace, tmp_path):
    out = tmp_path / "out"
    m = export_crs(workspace, out, "utm")
    assert m["crs_epsg"] == UTM and sorted(m["sessions"]) == ["s0", "s1"]
    assert json.loads((out / "export.json").read_text())["sessions"]["s0"]["source"] == "built"
    _, P = _poses()
    frame, epsg, _ = ply_georef(out / "s0" / "map.ply")
    assert frame == FRAME and epsg == UTM
    pts = np.asarray(o3d.io.read_point_cloud(str(out / "s0" / "map.ply")).points)
    assert np.abs(FRAME.crs_to_enu(pts, UTM) - (P[:, :3, 3] + [0, 0, -1.5])).max() < 1e-6
    _, P2 = read_crs_trajectory(out / "s1" / "trajectory.tum")
    assert np.abs(P2[:, :3, 3] - P[:, :3, 3]).max() < 1e-5
    # WGS84: trajectories only, as CSV; maps noted as skipped
    m = export_crs(workspace, tmp_path / "geo", "wgs84", sessions=["s0"])
    assert "maps_skipped" in m and (tmp_path / "geo" / "s0" / "trajectory.csv").is_file()
    assert not (tmp_path / "geo" / "s0" / "map.ply").exists()
    with pytest.raises(InputError):
        export_crs(workspace, tmp_path / "x", "wgs84", trajectory=False)
    with pytest.raises(InputError, match="not georeferenced"):
        export_crs(workspace, tmp_path / "x", "utm", sessions=["nogps"])


def test_cli_export_crs(workspace, tmp_path, capsys):
    assert (
        main(
            ["export-crs", str(workspace), "-o", str(tmp_path / "c"), "--crs", "EPSG:4978", "-s", "s0", "--what", "map"]
        )
        == 0
    )
    assert "EPSG:4978" in capsys.readouterr().out
    assert sorted(p.name for p in (tmp_path / "c" / "s0").iterdir()) == ["map.ply"]
    assert ply_georef(tmp_path / "c" / "s0" / "map.ply")[1] == 4978
    assert main(["export-crs", str(workspace), "-o", str(tmp_path / "d"), "--crs", "bogus"]) == 2
