"""WGS84, UTM, ECEF and local ENU frames, through pyproj.

A map lives in a local east-north-up (ENU) tangent frame at an origin; everything georeferenced
records its CRS as an EPSG code and its origin. A whole drive (or workspace) uses one declared UTM
zone, chosen from its first fix or given explicitly, even where the drive crosses a zone boundary.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from pyproj import CRS, Transformer

from .errors import InputError

EPSG_WGS84_GEODETIC_3D = 4979  # lat, lon, ellipsoidal height
EPSG_WGS84_ECEF = 4978


def utm_epsg_for(lat_deg: float, lon_deg: float) -> int:
    """EPSG code of the WGS84 / UTM zone containing a point (incl. Norway and Svalbard exceptions)."""
    if not (-80.0 <= lat_deg <= 84.0) or not (-180.0 <= lon_deg <= 180.0):
        raise InputError(None, f"latitude {lat_deg}, longitude {lon_deg} is outside the UTM domain", field="lat/lon")
    zone = int((lon_deg + 180.0) // 6.0) % 60 + 1
    if 56.0 <= lat_deg < 64.0 and 3.0 <= lon_deg < 12.0:
        zone = 32
    elif 72.0 <= lat_deg <= 84.0 and lon_deg >= 0.0:
        for lo, hi, z in ((0.0, 9.0, 31), (9.0, 21.0, 33), (21.0, 33.0, 35), (33.0, 42.0, 37)):
            if lo <= lon_deg < hi:
                zone = z
    return (32600 if lat_deg >= 0 else 32700) + zone


@dataclass(frozen=True)
class UtmProjection:
    """Forward and inverse WGS84 <-> one UTM zone (easting, northing in metres)."""

    epsg: int

    @cached_property
    def _fwd(self) -> Transformer:
        return Transformer.from_crs(4326, self.epsg, always_xy=True)

    @cached_property
    def _inv(self) -> Transformer:
        return Transformer.from_crs(self.epsg, 4326, always_xy=True)

    @property
    def zone(self) -> int:
        return self.epsg % 100

    @property
    def name(self) -> str:
        return CRS.from_epsg(self.epsg).name

    def forward(self, lat_deg, lon_deg) -> tuple[np.ndarray, np.ndarray]:
        e, n = self._fwd.transform(np.asarray(lon_deg, np.float64), np.asarray(lat_deg, np.float64))
        return np.asarray(e), np.asarray(n)

    def inverse(self, easting_m, northing_m) -> tuple[np.ndarray, np.ndarray]:
        lon, lat = self._inv.transform(np.asarray(easting_m, np.float64), np.asarray(northing_m, np.float64))
        return np.asarray(lat), np.asarray(lon)

    @classmethod
    def for_point(cls, lat_deg: float, lon_deg: float) -> "UtmProjection":
        return cls(utm_epsg_for(lat_deg, lon_deg))


_TO_ECEF = Transformer.from_crs(EPSG_WGS84_GEODETIC_3D, EPSG_WGS84_ECEF, always_xy=True)
_FROM_ECEF = Transformer.from_crs(EPSG_WGS84_ECEF, EPSG_WGS84_GEODETIC_3D, always_xy=True)


def geodetic_to_ecef(lat_deg, lon_deg, alt_m) -> np.ndarray:
    x, y, z = _TO_ECEF.transform(np.asarray(lon_deg, np.float64), np.asarray(lat_deg, np.float64), np.asarray(alt_m, np.float64))
    return np.stack([x, y, z], axis=-1)


def ecef_to_geodetic(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    xyz = np.asarray(xyz, np.float64)
    lon, lat, alt = _FROM_ECEF.transform(xyz[..., 0], xyz[..., 1], xyz[..., 2])
    return np.asarray(lat), np.asarray(lon), np.asarray(alt)


@dataclass(frozen=True)
class LocalFrame:
    """A local ENU tangent frame at a WGS84 origin, with the UTM zone the map declares.

    ``enu`` coordinates are metric and exact (through ECEF), so map geometry is never distorted by
    the UTM scale factor; UTM coordinates are derived from them when written out.
    """

    lat0_deg: float
    lon0_deg: float
    alt0_m: float = 0.0
    utm_epsg: int | None = None

    def __post_init__(self):
        if self.utm_epsg is None:
            object.__setattr__(self, "utm_epsg", utm_epsg_for(self.lat0_deg, self.lon0_deg))

    @cached_property
    def _ecef0(self) -> np.ndarray:
        return geodetic_to_ecef(self.lat0_deg, self.lon0_deg, self.alt0_m)

    @cached_property
    def ecef_from_enu_rotation(self) -> np.ndarray:
        """Columns are the east, north and up unit vectors in ECEF."""
        la, lo = np.radians(self.lat0_deg), np.radians(self.lon0_deg)
        east = np.array([-np.sin(lo), np.cos(lo), 0.0])
        north = np.array([-np.sin(la) * np.cos(lo), -np.sin(la) * np.sin(lo), np.cos(la)])
        up = np.array([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)])
        return np.stack([east, north, up], axis=1)

    @property
    def utm(self) -> UtmProjection:
        return UtmProjection(int(self.utm_epsg))

    def geodetic_to_enu(self, lat_deg, lon_deg, alt_m) -> np.ndarray:
        d = geodetic_to_ecef(lat_deg, lon_deg, alt_m) - self._ecef0
        return d @ self.ecef_from_enu_rotation

    def enu_to_geodetic(self, enu: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        xyz = np.asarray(enu, np.float64) @ self.ecef_from_enu_rotation.T + self._ecef0
        return ecef_to_geodetic(xyz)

    def enu_to_utm(self, enu: np.ndarray) -> np.ndarray:
        """(N, 3) ENU to (N, 3) easting, northing, ellipsoidal height in this frame's UTM zone."""
        lat, lon, alt = self.enu_to_geodetic(enu)
        e, n = self.utm.forward(lat, lon)
        return np.stack([e, n, alt], axis=-1)

    def utm_to_enu(self, utm_enh: np.ndarray) -> np.ndarray:
        utm_enh = np.asarray(utm_enh, np.float64)
        lat, lon = self.utm.inverse(utm_enh[..., 0], utm_enh[..., 1])
        return self.geodetic_to_enu(lat, lon, utm_enh[..., 2])

    def to_frame(self, other: "LocalFrame") -> np.ndarray:
        """``other_from_self``: the exact rigid transform between two ENU tangent frames (via ECEF)."""
        R = other.ecef_from_enu_rotation.T @ self.ecef_from_enu_rotation
        t = other.ecef_from_enu_rotation.T @ (self._ecef0 - other._ecef0)
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, t
        return T

    def to_dict(self) -> dict:
        """What a georeferenced output records: CRS and origin."""
        return {
            "frame": "local ENU tangent plane",
            "origin_wgs84": {"lat_deg": self.lat0_deg, "lon_deg": self.lon0_deg, "alt_m": self.alt0_m},
            "origin_crs_epsg": EPSG_WGS84_GEODETIC_3D,
            "utm_crs_epsg": int(self.utm_epsg),
        }

    @classmethod
    def from_dict(cls, d: dict) -> "LocalFrame":
        o = d["origin_wgs84"]
        return cls(float(o["lat_deg"]), float(o["lon_deg"]), float(o.get("alt_m", 0.0)), int(d["utm_crs_epsg"]))


def path_length_m(enu: np.ndarray) -> float:
    """Length of a polyline of (N, 2 or 3) metric points."""
    enu = np.asarray(enu, np.float64)
    if len(enu) < 2:
        return 0.0
    return float(np.linalg.norm(np.diff(enu, axis=0), axis=1).sum())
