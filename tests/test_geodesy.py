"""Geodesy against known coordinates and pyproj's own geodesic."""

import numpy as np
import pytest
from pyproj import Geod

from mapkit.core.errors import InputError
from mapkit.core.geodesy import LocalFrame, UtmProjection, utm_epsg_for


@pytest.mark.parametrize(
    "lat, lon, epsg",
    [
        (49.01, 8.40, 32632),  # Karlsruhe (KITTI)
        (51.75, -1.25, 32630),  # Oxford (RobotCar)
        (-33.87, 151.21, 32756),  # Sydney: southern hemisphere
        (60.39, 5.32, 32632),  # Bergen: the Norway exception widens zone 32
        (78.22, 15.65, 32633),  # Longyearbyen: Svalbard's zone 33
    ],
)
def test_utm_zone_choice(lat, lon, epsg):
    assert utm_epsg_for(lat, lon) == epsg


def test_utm_zone_outside_domain_is_a_clear_error():
    with pytest.raises(InputError, match="outside the UTM domain"):
        utm_epsg_for(85.0, 0.0)


def test_central_meridian_on_equator_is_false_easting():
    e, n = UtmProjection(32631).forward(0.0, 3.0)
    assert float(e) == pytest.approx(500000.0, abs=1e-6)
    assert float(n) == pytest.approx(0.0, abs=1e-6)


def test_utm_round_trip():
    proj = UtmProjection.for_point(49.0, 8.4)
    lat = np.array([49.0, 49.01, 48.99])
    lon = np.array([8.4, 8.41, 8.39])
    e, n = proj.forward(lat, lon)
    lat2, lon2 = proj.inverse(e, n)
    np.testing.assert_allclose(lat2, lat, atol=1e-10)
    np.testing.assert_allclose(lon2, lon, atol=1e-10)


def test_enu_is_metric_and_oriented():
    frame = LocalFrame(49.0, 8.4, 110.0)
    geod = Geod(ellps="WGS84")
    lon1, lat1, _ = geod.fwd(8.4, 49.0, 0.0, 1000.0)  # 1 km due north
    lon2, lat2, _ = geod.fwd(8.4, 49.0, 90.0, 1000.0)  # 1 km due east
    enu = frame.geodetic_to_enu([lat1, lat2], [lon1, lon2], [110.0, 110.0])
    # due north: +y; due east: +x; the tangent plane dips below the ellipsoid by d^2/2R ~ 8 cm
    np.testing.assert_allclose(enu[0, :2], [0.0, 1000.0], atol=0.05)
    np.testing.assert_allclose(enu[1, :2], [1000.0, 0.0], atol=0.05)
    assert -0.1 < enu[0, 2] < -0.05


def test_enu_geodetic_round_trip(rng):
    frame = LocalFrame(51.75, -1.25, 60.0)
    pts = rng.uniform(-2000, 2000, size=(100, 3))
    lat, lon, alt = frame.enu_to_geodetic(pts)
    np.testing.assert_allclose(frame.geodetic_to_enu(lat, lon, alt), pts, atol=1e-6)
    np.testing.assert_allclose(frame.utm_to_enu(frame.enu_to_utm(pts)), pts, atol=1e-6)


def test_drive_across_zone_boundary_stays_in_declared_zone():
    # origin just west of the 6E boundary (zone 31); points east of it are still in zone 31
    frame = LocalFrame(49.0, 5.999)
    assert frame.utm_epsg == 32631
    utm = frame.enu_to_utm(np.array([[0.0, 0, 0], [2000.0, 0, 0]]))
    assert utm[1, 0] - utm[0, 0] == pytest.approx(2000.0, rel=2e-3)  # continuous, no zone jump


def test_local_frame_dict_round_trip():
    frame = LocalFrame(49.0, 8.4, 110.0)
    again = LocalFrame.from_dict(frame.to_dict())
    assert again == frame
    assert frame.to_dict()["utm_crs_epsg"] == 32632


def test_transform_between_local_frames_is_exact(rng):
    a = LocalFrame(49.0, 8.4, 110.0)
    b = LocalFrame(49.004, 8.41, 95.0)
    pts_a = rng.uniform(-1500, 1500, size=(50, 3))
    T = a.to_frame(b)
    lat, lon, alt = a.enu_to_geodetic(pts_a)
    np.testing.assert_allclose(pts_a @ T[:3, :3].T + T[:3, 3], b.geodetic_to_enu(lat, lon, alt), atol=1e-6)
    np.testing.assert_allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-12)
