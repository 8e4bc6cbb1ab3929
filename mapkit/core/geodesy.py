"""WGS84, UTM, ECEF and local ENU frames, through pyproj.

A map lives in a local east-north-up (ENU) tangent frame at an origin; everything georeferenced
records its CRS as an EPSG code and its origin. A whole drive (or workspace) uses one declared UTM
zone, chosen from its first fix or given explicitly, even where the drive crosses a zone boundary.

Coordinates in any other CRS (an EPSG code) are derived from the local ENU ones through WGS84
geodetic coordinates (:meth:`LocalFrame.enu_to_crs`, :meth:`LocalFrame.crs_to_enu`). Arrays of
CRS coordinates are always in "x, y, z" order: easting, northing (projected), longitude, latitude
(geographic) or X, Y, Z (ECEF); the third coordinate of a 2D CRS (UTM, 4326) is the WGS84
ellipsoidal height in metres.

**PLY header comments.** Every PLY mapkit writes states its frame in ``comment`` lines of the
header, one ``key value`` pair per line (:func:`ply_crs_comments`, read back with
:func:`frame_from_ply_comments`); readers that ignore comments (open3d) are unaffected::

    comment mapkit_crs 1                  version of this convention
    comment frame local_enu               local_enu | utm | ecef | projected | geographic | unspecified
    comment crs EPSG:32630                the CRS of x, y, z (absent for local_enu and unspecified)
    comment crs_name WGS 84 / UTM zone 30N
    comment z wgs84_ellipsoidal_height_m  only for a 2D CRS: what z is
    comment units m                       of x, y, z (deg, deg, m for a geographic CRS)
    comment origin_lat_deg 51.7520209     the workspace's local ENU origin (WGS84, EPSG:4979)
    comment origin_lon_deg -1.2577263
    comment origin_alt_m 60.0
    comment utm_crs EPSG:32630            the UTM zone the workspace declares
    comment enu_pipeline +proj=pipeline ...  PROJ pipeline from WGS84 (lon, lat, h) to the local ENU

No coordinate offset is ever written: x, y, z are float64 and hold the coordinates themselves
(UTM northings are exact to 1e-9 m), so a reader that ignores the comments still gets them right.
A local ENU frame is *not* UTM shifted by an offset (grid convergence and the UTM scale factor
rotate and scale it), so no offset could honestly describe one; ``enu_pipeline`` does, and
``cct``/``cs2cs`` or pyproj's ``Transformer.from_pipeline`` run it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property, lru_cache

import numpy as np
from pyproj import CRS, Transformer

from mapkit.core.errors import InputError

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
    def for_point(cls, lat_deg: float, lon_deg: float) -> UtmProjection:
        return cls(utm_epsg_for(lat_deg, lon_deg))


_TO_ECEF = Transformer.from_crs(EPSG_WGS84_GEODETIC_3D, EPSG_WGS84_ECEF, always_xy=True)
_FROM_ECEF = Transformer.from_crs(EPSG_WGS84_ECEF, EPSG_WGS84_GEODETIC_3D, always_xy=True)


@lru_cache(maxsize=64)
def _transformer(src: int, dst: int) -> Transformer:
    return Transformer.from_crs(src, dst, always_xy=True)


@lru_cache(maxsize=64)
def crs_info(epsg: int) -> dict:
    """What a CRS is: ``kind`` (utm, ecef, projected, geographic), its name, whether it is 3D and
    the units of x, y, z. Raises InputError for an unknown code or a kind mapkit cannot write."""
    try:
        crs = CRS.from_epsg(int(epsg))
    except Exception as exc:  # pyproj.exceptions.CRSError
        raise InputError(None, f"EPSG:{epsg} is not a CRS that PROJ knows ({exc})", field="crs") from None
    if crs.is_geocentric:
        kind = "ecef"
    elif crs.is_geographic:
        kind = "geographic"
    elif crs.is_projected:
        kind = "utm" if 32601 <= int(epsg) <= 32660 or 32701 <= int(epsg) <= 32760 else "projected"
    else:
        raise InputError(None, f"EPSG:{epsg} ({crs.name}) is neither geographic, projected nor geocentric", field="crs")
    units = [a.unit_name for a in crs.axis_info]
    if kind != "geographic" and any(u not in ("metre", "meter") for u in units):
        raise InputError(
            None, f"EPSG:{epsg} ({crs.name}) has axes in {units}; mapkit writes metric CRSs only", field="crs"
        )
    return {
        "epsg": int(epsg),
        "kind": kind,
        "name": crs.name,
        "is_3d": len(crs.axis_info) == 3,
        "units": ("deg", "deg", "m") if kind == "geographic" else ("m", "m", "m"),
    }


def parse_crs(spec: str | int, frame: LocalFrame | None = None) -> int:
    """An EPSG code from ``utm`` (the frame's declared zone), ``ecef`` (4978), ``wgs84`` (4979),
    ``EPSG:n`` or ``n``."""
    text = str(spec).strip().lower()
    if text == "utm":
        if frame is None:
            raise InputError(
                None, "'utm' needs a georeferenced workspace (its origin.json names the zone)", field="crs"
            )
        epsg = int(frame.utm_epsg)
    elif text == "ecef":
        epsg = EPSG_WGS84_ECEF
    elif text in ("wgs84", "lla", "geodetic"):
        epsg = EPSG_WGS84_GEODETIC_3D
    else:
        code = text[5:] if text.startswith("epsg:") else text
        if not code.isdigit():
            raise InputError(None, f"CRS {spec!r}: expected utm, ecef, wgs84 or EPSG:<code>", field="crs")
        epsg = int(code)
    crs_info(epsg)  # validates
    return epsg


def ecef_from_enu_rotations(lat_deg, lon_deg) -> np.ndarray:
    """(..., 3, 3) rotations whose columns are the east, north and up unit vectors (in ECEF) of the
    ENU tangent frame at each (lat, lon)."""
    la, lo = np.radians(np.asarray(lat_deg, np.float64)), np.radians(np.asarray(lon_deg, np.float64))
    z = np.zeros_like(la)
    east = np.stack([-np.sin(lo), np.cos(lo), z], axis=-1)
    north = np.stack([-np.sin(la) * np.cos(lo), -np.sin(la) * np.sin(lo), np.cos(la)], axis=-1)
    up = np.stack([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)], axis=-1)
    return np.stack([east, north, up], axis=-1)


def geodetic_to_ecef(lat_deg, lon_deg, alt_m) -> np.ndarray:
    x, y, z = _TO_ECEF.transform(
        np.asarray(lon_deg, np.float64), np.asarray(lat_deg, np.float64), np.asarray(alt_m, np.float64)
    )
    return np.stack([x, y, z], axis=-1)


def ecef_to_geodetic(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    xyz = np.asarray(xyz, np.float64)
    lon, lat, alt = _FROM_ECEF.transform(xyz[..., 0], xyz[..., 1], xyz[..., 2])
    return np.asarray(lat), np.asarray(lon), np.asarray(alt)


@dataclass(frozen=True, init=False)
class LocalFrame:
    """A local ENU tangent frame at a WGS84 origin, with the UTM zone the map declares.

    ``enu`` coordinates are metric and exact (through ECEF), so map geometry is never distorted by
    the UTM scale factor; UTM coordinates are derived from them when written out.
    """

    lat0_deg: float
    lon0_deg: float
    alt0_m: float
    utm_epsg: int

    def __init__(self, lat0_deg: float, lon0_deg: float, alt0_m: float = 0.0, utm_epsg: int | None = None):
        """``utm_epsg``: the zone the map declares; by default the one of the origin."""
        object.__setattr__(self, "lat0_deg", lat0_deg)
        object.__setattr__(self, "lon0_deg", lon0_deg)
        object.__setattr__(self, "alt0_m", alt0_m)
        object.__setattr__(self, "utm_epsg", utm_epsg_for(lat0_deg, lon0_deg) if utm_epsg is None else utm_epsg)

    @cached_property
    def _ecef0(self) -> np.ndarray:
        return geodetic_to_ecef(self.lat0_deg, self.lon0_deg, self.alt0_m)

    @cached_property
    def ecef_from_enu_rotation(self) -> np.ndarray:
        """Columns are the east, north and up unit vectors in ECEF."""
        return ecef_from_enu_rotations(self.lat0_deg, self.lon0_deg)

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

    def enu_to_crs(self, enu: np.ndarray, epsg: int) -> np.ndarray:
        """(N, 3) ENU to (N, 3) coordinates in EPSG ``epsg`` (x, y, z order; see the module doc)."""
        enu = np.asarray(enu, np.float64)
        epsg = int(epsg)
        if epsg == EPSG_WGS84_ECEF:
            return enu @ self.ecef_from_enu_rotation.T + self._ecef0
        lat, lon, alt = self.enu_to_geodetic(enu)
        if epsg == int(self.utm_epsg):
            e, n = self.utm.forward(lat, lon)
            return np.stack([e, n, alt], axis=-1)
        crs_info(epsg)
        x, y, z = _transformer(EPSG_WGS84_GEODETIC_3D, epsg).transform(lon, lat, alt)
        return np.stack([np.asarray(x), np.asarray(y), np.asarray(z)], axis=-1)

    def crs_to_enu(self, xyz: np.ndarray, epsg: int) -> np.ndarray:
        """Inverse of :meth:`enu_to_crs`."""
        xyz = np.asarray(xyz, np.float64)
        epsg = int(epsg)
        if epsg == EPSG_WGS84_ECEF:
            return (xyz - self._ecef0) @ self.ecef_from_enu_rotation
        if epsg == int(self.utm_epsg):
            return self.utm_to_enu(xyz)
        crs_info(epsg)
        lon, lat, alt = _transformer(epsg, EPSG_WGS84_GEODETIC_3D).transform(xyz[..., 0], xyz[..., 1], xyz[..., 2])
        return self.geodetic_to_enu(lat, lon, alt)

    def crs_from_enu_rotations(self, enu: np.ndarray, epsg: int, step_m: float = 1.0) -> np.ndarray:
        """(N, 3, 3) rotations taking directions in this ENU frame to the axes of EPSG ``epsg`` at
        each point: for ECEF the exact constant rotation; for a geographic CRS the local ENU
        (east, north, up) tangent frame at the point; for a projected CRS grid east, grid north and
        up there (the orthonormal part of the projection's Jacobian: its scale factor removed,
        meridian convergence and the tilt of the local vertical kept)."""
        enu = np.atleast_2d(np.asarray(enu, np.float64))
        epsg = int(epsg)
        kind = crs_info(epsg)["kind"]
        if kind == "ecef":
            return np.broadcast_to(self.ecef_from_enu_rotation, (len(enu), 3, 3)).copy()
        if kind == "geographic":
            lat, lon, _ = self.enu_to_geodetic(enu)
            return np.swapaxes(ecef_from_enu_rotations(lat, lon), -1, -2) @ self.ecef_from_enu_rotation
        # central differences along each ENU axis (1 m steps: truncation error ~1e-13 rad)
        J = np.empty((len(enu), 3, 3))
        for k in range(3):
            d = np.zeros(3)
            d[k] = step_m
            J[:, :, k] = (self.enu_to_crs(enu + d, epsg) - self.enu_to_crs(enu - d, epsg)) / (2.0 * step_m)
        U, _, Vt = np.linalg.svd(J)
        R = U @ Vt
        flip = np.linalg.det(R) < 0
        if flip.any():  # a left-handed CRS (none in practice): keep a proper rotation's best fit
            U[flip, :, -1] *= -1
            R[flip] = U[flip] @ Vt[flip]
        return R

    @property
    def enu_pipeline(self) -> str:
        """A PROJ pipeline from WGS84 (lon, lat, ellipsoidal height) to this local ENU frame."""
        return (
            "+proj=pipeline +step +proj=cart +ellps=WGS84 +step +proj=topocentric +ellps=WGS84 "
            f"+lat_0={self.lat0_deg!r} +lon_0={self.lon0_deg!r} +h_0={self.alt0_m!r}"
        )

    def to_frame(self, other: LocalFrame) -> np.ndarray:
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
    def from_dict(cls, d: dict) -> LocalFrame:
        o = d["origin_wgs84"]
        return cls(float(o["lat_deg"]), float(o["lon_deg"]), float(o.get("alt_m", 0.0)), int(d["utm_crs_epsg"]))


PLY_CRS_CONVENTION = 1


def ply_crs_comments(frame: LocalFrame | None, crs_epsg: int | None = None) -> list[str]:
    """The header comments (without ``comment ``) stating the frame of a PLY's x, y, z: the local
    ENU frame of ``frame`` when ``crs_epsg`` is None, else EPSG ``crs_epsg``; ``frame`` (the
    workspace origin) is recorded either way when known. See the module doc."""
    out = [f"mapkit_crs {PLY_CRS_CONVENTION}"]
    if crs_epsg is None:
        out.append("frame " + ("unspecified" if frame is None else "local_enu"))
        units = ("m", "m", "m")
    else:
        info = crs_info(int(crs_epsg))
        out += [f"frame {info['kind']}", f"crs EPSG:{info['epsg']}", f"crs_name {info['name']}"]
        if not info["is_3d"]:
            out.append("z wgs84_ellipsoidal_height_m")
        units = info["units"]
    out.append("units " + (units[0] if len(set(units)) == 1 else " ".join(units)))
    if frame is not None:
        out += [
            f"origin_lat_deg {float(frame.lat0_deg)!r}",
            f"origin_lon_deg {float(frame.lon0_deg)!r}",
            f"origin_alt_m {float(frame.alt0_m)!r}",
            f"origin_crs EPSG:{EPSG_WGS84_GEODETIC_3D}",
            f"utm_crs EPSG:{int(frame.utm_epsg)}",
            f"enu_pipeline {frame.enu_pipeline}",
        ]
    return out


def frame_from_ply_comments(comments: Sequence[str]) -> tuple[LocalFrame | None, int | None, dict[str, str]]:
    """(workspace frame or None, EPSG of x, y, z or None for local ENU / unspecified, all key-value
    pairs) from a PLY header's comments (with or without the leading ``comment ``)."""
    kv: dict[str, str] = {}
    for c in comments:
        c = c.strip()
        if c.startswith("comment "):
            c = c[len("comment ") :]
        key, _, value = c.partition(" ")
        if key and key not in kv:
            kv[key] = value.strip()
    frame = None
    if all(k in kv for k in ("origin_lat_deg", "origin_lon_deg", "origin_alt_m")):
        utm = kv.get("utm_crs", "")
        frame = LocalFrame(
            float(kv["origin_lat_deg"]),
            float(kv["origin_lon_deg"]),
            float(kv["origin_alt_m"]),
            int(utm.split(":")[1]) if utm.upper().startswith("EPSG:") else None,
        )
    crs = kv.get("crs", "")
    epsg = int(crs.split(":")[1]) if crs.upper().startswith("EPSG:") else None
    return frame, epsg, kv


def path_length_m(enu: np.ndarray) -> float:
    """Length of a polyline of (N, 2 or 3) metric points."""
    enu = np.asarray(enu, np.float64)
    if len(enu) < 2:
        return 0.0
    return float(np.linalg.norm(np.diff(enu, axis=0), axis=1).sum())
