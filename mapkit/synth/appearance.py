"""Appearance: per-session conditions, the sun, the sky, procedural surface textures, and the camera.

Everything works on flat arrays of hit points (one row per pixel that hit something), in float32
and without Python loops over pixels. Radiance is linear and relative (a white diffuse surface in
full sun is about 3); the camera model turns it into 8-bit sRGB with exposure, white balance,
vignetting, sensor noise and a tone curve.

Conditions (``Conditions``) come from a session's weather, date and local time: the sun's
position is computed for the town's latitude and longitude (NOAA's low-precision formulas), so
that a 9:36 am winter sun in Oxford is low in the south-east and 10:41 pm is night.
"""

from __future__ import annotations

import datetime as dt
import math
from dataclasses import dataclass, field

import numpy as np

from mapkit.synth.world import Mat

F32 = np.float32


def f32(*v) -> np.ndarray:
    return np.array(v, F32)


def dot3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot products of (n, 3) arrays (column-wise: 3x faster than einsum here)."""
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


# --- sun -----------------------------------------------------------------------------------------


def sun_position(utc: dt.datetime, lat_deg: float, lon_deg: float) -> tuple[float, float]:
    """(azimuth from north, clockwise; elevation) in degrees, to about 0.1 deg (NOAA low precision)."""
    jd = utc.timestamp() / 86400.0 + 2440587.5
    n = jd - 2451545.0
    L = math.radians((280.460 + 0.9856474 * n) % 360)
    g = math.radians((357.528 + 0.9856003 * n) % 360)
    lam = L + math.radians(1.915) * math.sin(g) + math.radians(0.020) * math.sin(2 * g)
    eps = math.radians(23.439 - 0.0000004 * n)
    ra = math.atan2(math.cos(eps) * math.sin(lam), math.cos(lam))
    dec = math.asin(math.sin(eps) * math.sin(lam))
    gmst_h = (18.697374558 + 24.06570982441908 * n) % 24
    ha = math.radians(gmst_h * 15 + lon_deg) - ra
    la = math.radians(lat_deg)
    el = math.asin(math.sin(la) * math.sin(dec) + math.cos(la) * math.cos(dec) * math.cos(ha))
    az = math.atan2(-math.sin(ha), math.tan(dec) * math.cos(la) - math.sin(la) * math.cos(ha))
    return math.degrees(az) % 360, math.degrees(el)


def season_of(date: dt.date, lat_deg: float) -> str:
    m = date.month if lat_deg >= 0 else (date.month + 5) % 12 + 1
    return {
        12: "winter",
        1: "winter",
        2: "winter",
        3: "spring",
        4: "spring",
        5: "spring",
        6: "summer",
        7: "summer",
        8: "summer",
    }.get(m, "autumn")


def kelvin_rgb(k: float) -> np.ndarray:
    """Approximate linear RGB of a black body (normalised to green = 1), 1500-12000 K."""
    t = k / 100.0
    r = 255.0 if t <= 66 else 329.698727446 * (t - 60) ** -0.1332047592
    g = 99.4708025861 * math.log(t) - 161.1195681661 if t <= 66 else 288.1221695283 * (t - 60) ** -0.0755148492
    b = 255.0 if t >= 66 else (0.0 if t <= 19 else 138.5177312231 * math.log(t - 10) - 305.0447927307)
    rgb = (np.clip([r, g, b], 1, 255) / 255.0) ** 2.2
    return (rgb / rgb[1]).astype(F32)


# --- conditions ----------------------------------------------------------------------------------

WEATHER_TABLE = {
    # sun_visibility, cloud_cover, fog_visibility_m, wetness, rain, snow_cover, snowfall, sky_grey
    "sunny": (1.0, 0.0, 8000.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    "clear": (0.85, 0.12, 2500.0, 0.0, 0.0, 0.0, 0.0, 0.1),
    "cloudy": (0.5, 0.55, 2000.0, 0.0, 0.0, 0.0, 0.0, 0.25),
    "overcast": (0.0, 1.0, 1200.0, 0.15, 0.0, 0.0, 0.0, 0.85),
    "foggy": (0.0, 1.0, 45.0, 0.35, 0.0, 0.0, 0.0, 0.95),
    "rainy": (0.0, 1.0, 500.0, 1.0, 1.0, 0.0, 0.0, 0.9),
    "snowy": (0.0, 1.0, 180.0, 0.2, 0.0, 1.0, 1.0, 0.97),
}

MAX_GAIN = 6.0  # relative to a sunny day's exposure of about 0.6

FOLIAGE = {
    "spring": ((0.28, 0.5, 0.12), (0.38, 0.55, 0.18)),
    "summer": ((0.08, 0.22, 0.05), (0.14, 0.3, 0.08)),
    "autumn": ((0.6, 0.28, 0.05), (0.5, 0.12, 0.04)),
    "winter": ((0.22, 0.18, 0.15), (0.28, 0.24, 0.2)),
}
GRASS = {
    "spring": (0.2, 0.38, 0.1),
    "summer": (0.16, 0.3, 0.07),
    "autumn": (0.3, 0.3, 0.1),
    "winter": (0.22, 0.22, 0.14),
}


@dataclass
class Conditions:
    """Everything about a session's light, weather and camera that rendering needs."""

    weather: str
    season: str
    sun_dir_enu: np.ndarray  # (3,) unit, toward the sun
    sun_elevation_deg: float
    sun_azimuth_deg: float
    sun_rgb: np.ndarray  # direct irradiance (0 when hidden)
    sky_zenith_rgb: np.ndarray
    sky_horizon_rgb: np.ndarray
    ambient_rgb: np.ndarray  # sky irradiance on an upward surface
    cloud_cover: float
    cloud_rgb: np.ndarray
    fog_visibility_m: float
    fog_rgb: np.ndarray
    wetness: float
    rain: float
    snow_cover: float
    snowfall: float
    night: float  # 0 day .. 1 night: lamps, lit windows and headlights on
    lamp_rgb: np.ndarray
    foliage_rgb: tuple
    grass_rgb: np.ndarray
    exposure_gain: float
    white_balance: np.ndarray  # (3,) camera gains
    read_noise: float
    shot_noise: float
    seed: int = 0
    label: str = ""
    extra: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {
            "weather": self.weather,
            "season": self.season,
            "label": self.label,
            "sun_elevation_deg": round(self.sun_elevation_deg, 2),
            "sun_azimuth_deg": round(self.sun_azimuth_deg, 2),
            "fog_visibility_m": self.fog_visibility_m,
            "wetness": self.wetness,
            "snow_cover": self.snow_cover,
            "night": round(self.night, 3),
            "exposure_gain": round(self.exposure_gain, 4),
            "white_balance_gains": [round(float(x), 4) for x in self.white_balance],
        }


def smoothstep(e0: float, e1: float, x):
    t = np.clip((np.asarray(x, F32) - F32(e0)) * F32(1.0 / (e1 - e0)), 0, 1)
    return t * t * (3 - 2 * t)


def make_conditions(
    weather: str,
    local_time: dt.datetime,
    lat_deg: float,
    lon_deg: float,
    *,
    exposure_ev: float = 0.0,
    white_balance_k: float = 5500.0,
    season: str | None = None,
    seed: int = 0,
) -> Conditions:
    """Conditions of a session at ``local_time`` (timezone-aware) under ``weather``."""
    az, el = sun_position(local_time.astimezone(dt.timezone.utc), lat_deg, lon_deg)
    season = season or season_of(local_time.date(), lat_deg)
    sun_vis, cloud, fog_vis, wet, rain, snow, snowfall, grey = WEATHER_TABLE[weather]
    a, e = math.radians(az), math.radians(el)
    sun_dir = f32(math.sin(a) * math.cos(e), math.cos(a) * math.cos(e), math.sin(e))
    day = float(smoothstep(-7.0, 8.0, el))  # civil twilight to low sun
    night = 1.0 - float(smoothstep(-8.0, 2.0, el))
    # sun colour through the air mass (reddens near the horizon)
    e_c = max(el, 0.0)
    airmass = 1.0 / (math.sin(math.radians(e_c)) + 0.50572 * (e_c + 6.07995) ** -1.6364)
    trans = np.exp(-airmass * f32(0.06, 0.11, 0.24))
    sun_up = float(smoothstep(-1.0, 3.0, el))
    sun_rgb = (3.2 * sun_vis * sun_up * trans * max(math.sin(math.radians(max(el, 0.5))), 0.0) ** 0.2).astype(F32)
    warm = 1.0 - float(smoothstep(2.0, 20.0, el))
    clear_zen = f32(0.16, 0.33, 0.85) * (1 - 0.3 * warm) + f32(0.2, 0.15, 0.25) * warm
    clear_hor = f32(0.62, 0.72, 0.9) * (1 - warm) + f32(1.0, 0.55, 0.3) * warm
    grey_rgb = f32(0.62, 0.64, 0.67) * (1.0 - 0.25 * rain - 0.1 * snow) + f32(0.05, 0.05, 0.06) * snow
    level = 0.015 + 0.985 * day
    zen = (clear_zen * (1 - grey) + grey_rgb * 0.8 * grey) * level
    hor = (clear_hor * (1 - grey) + grey_rgb * grey) * level
    night_zen, night_hor = f32(0.004, 0.005, 0.012), f32(0.03, 0.022, 0.016)  # city glow near the horizon
    zen = zen + night_zen * night
    hor = hor + night_hor * night
    ambient = (0.55 * zen + 0.45 * hor) * (1.2 if weather in ("sunny", "clear") else 1.0)
    cloud_rgb = (f32(0.9, 0.9, 0.92) * (0.5 + 0.5 * sun_vis) * (1 - 0.3 * rain)) * level + f32(
        0.02, 0.018, 0.016
    ) * night
    fog_rgb = (0.7 * hor + 0.1 * ambient).astype(F32)
    grass = f32(0.85, 0.86, 0.9) if snow else f32(*GRASS[season])
    key = float(np.dot(sun_rgb * 0.6 + ambient, f32(0.2126, 0.7152, 0.0722)))
    # auto exposure toward mid-grey, limited by the sensor's maximum gain (night stays dark)
    gain = min(1.6 / max(key, 1e-6), MAX_GAIN) * 2.0**exposure_ev
    wb = 1.0 / kelvin_rgb(white_balance_k) * kelvin_rgb(5500.0)
    label = ("night" if night > 0.5 else ("dusk" if day < 0.8 else "day")) + f"-{weather}"
    return Conditions(
        weather=weather,
        season=season,
        sun_dir_enu=sun_dir,
        sun_elevation_deg=el,
        sun_azimuth_deg=az,
        sun_rgb=sun_rgb,
        sky_zenith_rgb=zen.astype(F32),
        sky_horizon_rgb=hor.astype(F32),
        ambient_rgb=ambient.astype(F32),
        cloud_cover=cloud,
        cloud_rgb=cloud_rgb.astype(F32),
        fog_visibility_m=fog_vis,
        fog_rgb=fog_rgb,
        wetness=wet,
        rain=rain,
        snow_cover=snow,
        snowfall=snowfall,
        night=night,
        lamp_rgb=f32(1.0, 0.72, 0.42) * 1.0,
        foliage_rgb=FOLIAGE[season],
        grass_rgb=grass,
        exposure_gain=gain,
        white_balance=wb.astype(F32),
        read_noise=0.0025,
        shot_noise=0.0015,
        seed=seed,
        label=label,
    )


# --- noise ---------------------------------------------------------------------------------------


def hash01(*ints: np.ndarray) -> np.ndarray:
    """A float32 in [0, 1) per element from integer lattice coordinates (a murmur-style mix)."""
    h = None
    for k, x in enumerate(ints):
        x = np.asarray(x)
        xi = (x if x.dtype == np.int32 else x.astype(np.int32)).view(np.uint32)
        m = xi * np.uint32(0x85EBCA6B + 0x1000 * k)
        h = (m ^ np.uint32(0x9E3779B9)) if h is None else (h ^ m)
        h *= np.uint32(0xC2B2AE35)
        h ^= h >> np.uint32(15)
    h *= np.uint32(0x27D4EB2D)
    h ^= h >> np.uint32(13)
    return (h >> np.uint32(8)).astype(F32) * F32(1.0 / (1 << 24))


class NoiseTexture:
    """A periodic 512x512 fractal value-noise texture in [0, 1], sampled bilinearly (fast lookups)."""

    N = 512

    def __init__(self, seed: int = 7):
        n = self.N
        img = np.zeros((n, n), np.float64)
        amp, total = 1.0, 0.0
        for cells in (8, 16, 32, 64, 128):
            ix = np.arange(n) * cells / n
            i0 = np.floor(ix).astype(int)
            f = ix - i0
            f = f * f * (3 - 2 * f)
            lat = hash01(
                *np.meshgrid(np.arange(cells), np.arange(cells), indexing="ij"), np.full((cells, cells), seed + cells)
            ).astype(np.float64)
            a = lat[i0 % cells][:, i0 % cells]
            b = lat[(i0 + 1) % cells][:, i0 % cells]
            c = lat[i0 % cells][:, (i0 + 1) % cells]
            d = lat[(i0 + 1) % cells][:, (i0 + 1) % cells]
            fx, fy = f[:, None], f[None, :]
            img += amp * ((a * (1 - fx) + b * fx) * (1 - fy) + (c * (1 - fx) + d * fx) * fy)
            total += amp
            amp *= 0.55
        img /= total
        img = (img - img.min()) / (img.max() - img.min())
        self.tex = img.astype(F32)

    @property
    def _flat(self) -> np.ndarray:
        if not hasattr(self, "_padded"):
            self._padded = np.pad(self.tex, ((0, 1), (0, 1)), mode="wrap").ravel()  # (n+1)^2, no wrap at +1
        return self._padded

    def __call__(self, x: np.ndarray, y: np.ndarray, scale: float) -> np.ndarray:
        """Sample at world units (x, y); one period of the texture is 64 * ``scale`` metres."""
        n1 = self.N + 1
        k = F32(8.0 / scale)
        u = np.asarray(x, F32) * k
        v = np.asarray(y, F32) * k
        iu = np.floor(u)
        iv = np.floor(v)
        fu = u - iu
        fv = v - iv
        k00 = (iu.astype(np.int32) & (self.N - 1)) * n1 + (iv.astype(np.int32) & (self.N - 1))
        t = self._flat
        a = t[k00]
        b = t[k00 + n1]
        top = a + (b - a) * fu
        c = t[k00 + 1]
        d = t[k00 + n1 + 1]
        bot = c + (d - c) * fu
        return top + (bot - top) * fv


NOISE = NoiseTexture()


def fade(period: float | np.ndarray, footprint: np.ndarray) -> np.ndarray:
    """How much of a pattern of ``period`` metres survives at a pixel footprint (anti-aliasing)."""
    return np.clip((np.asarray(period, F32) / np.maximum(footprint, F32(1e-4)) - 2.0) / 4.0, 0, 1).astype(F32)


def line_mask(dist: np.ndarray, half_width: float, footprint: np.ndarray) -> np.ndarray:
    """Coverage of a painted line of ``half_width`` at signed distance ``dist``, footprint-aware."""
    hw = F32(half_width)
    grown = hw + 0.5 * footprint
    return np.where(np.abs(dist) < grown, (2 * hw) / (2 * hw + footprint), F32(0)).astype(F32)


def hsv_rgb(h: np.ndarray, s: float, v: float) -> np.ndarray:
    h = np.asarray(h, F32)[:, None]
    k = (f32(5, 3, 1)[None] + h * 6) % 6
    return (v - v * s * np.clip(np.minimum(k, 4 - k), 0, 1)).astype(F32)


# --- sky -----------------------------------------------------------------------------------------


def sky_radiance(d: np.ndarray, c: Conditions) -> np.ndarray:
    """Radiance (n, 3) of the sky seen along unit directions ``d`` (n, 3) (ENU)."""
    z = np.clip(d[:, 2], -0.2, 1.0)
    t = (1.0 - np.clip(z, 0, 1)) ** 3
    sky = c.sky_zenith_rgb[None] * (1 - t)[:, None] + c.sky_horizon_rgb[None] * t[:, None]
    if c.cloud_cover > 0:
        zz = np.maximum(z, 0.04)
        x, y = d[:, 0] / zz * 400.0, d[:, 1] / zz * 400.0
        n = NOISE(x, y, 900.0) * 0.65 + NOISE(x + 37.0, y - 11.0, 260.0) * 0.35
        cover = smoothstep(1.0 - c.cloud_cover - 0.12, 1.0 - c.cloud_cover + 0.18, n)
        if c.cloud_cover >= 0.99:
            cover = np.full_like(n, 1.0)
        shade = 0.75 + 0.35 * NOISE(x * 1.7, y * 1.7, 300.0)
        sky = sky * (1 - cover)[:, None] + (c.cloud_rgb[None] * shade[:, None]) * cover[:, None]
    else:
        cover = np.zeros(len(d), F32)
    if c.sun_rgb.max() > 0:
        cosg = d @ c.sun_dir_enu
        glow = np.exp((cosg - 1.0) * 60.0) * 0.6 + np.exp((cosg - 1.0) * 8.0) * 0.15
        disk = (cosg > 0.99985).astype(F32) * 40.0
        sky = sky + ((glow + disk) * (1 - cover))[:, None] * c.sun_rgb[None]
    return sky.astype(F32)


# --- materials ------------------------------------------------------------------------------------


@dataclass
class TriangleTable:
    """Per-triangle attributes the shading looks up by triangle id."""

    frames: np.ndarray  # (T, 17) float32: origin (3), axis_u (3), axis_v (3), aux (8)
    style: np.ndarray  # (T,) int64
    object_id: np.ndarray  # (T,) int32


class Hits:
    """What the rays hit, one row per hit, sorted by material. Texture coordinates and the
    per-triangle attributes are gathered lazily, so a material that does not use them costs nothing."""

    __slots__ = ("p", "n", "d", "rng_m", "footprint", "mat", "tri", "table", "_uv", "_aux")

    def __init__(self, p, n, d, rng_m, footprint, mat, tri, table: TriangleTable):
        self.p, self.n, self.d, self.rng_m, self.footprint, self.mat, self.tri, self.table = (
            p,
            n,
            d,
            rng_m,
            footprint,
            mat,
            tri,
            table,
        )
        self._uv: np.ndarray | None = None
        self._aux: np.ndarray | None = None

    @property
    def uv(self) -> np.ndarray:
        """(n, 2) surface coordinates in metres in the triangle's texture frame."""
        if self._uv is None:
            fr = self.table.frames[self.tri, :9]
            rel = self.p - fr[:, 0:3]
            uv = np.empty((len(self.tri), 2), F32)
            uv[:, 0] = dot3(rel, fr[:, 3:6])
            uv[:, 1] = dot3(rel, fr[:, 6:9])
            self._uv = uv
        return self._uv

    @property
    def aux(self) -> np.ndarray:
        if self._aux is None:
            self._aux = self.table.frames[self.tri, 9:17]
        return self._aux

    @property
    def style(self) -> np.ndarray:
        return self.table.style[self.tri]

    @property
    def obj(self) -> np.ndarray:
        return self.table.object_id[self.tri]

    def __len__(self) -> int:
        return len(self.tri)

    def take(self, idx) -> Hits:
        """The hits at ``idx`` (a slice gives views, without copying)."""
        return Hits(
            self.p[idx],
            self.n[idx],
            self.d[idx],
            self.rng_m[idx],
            self.footprint[idx],
            self.mat[idx],
            self.tri[idx],
            self.table,
        )

    def material_slices(self) -> list[tuple[int, slice]]:
        """(material, slice) runs; hits are sorted by material (the renderer sorts them)."""
        m = self.mat
        if len(m) == 0:
            return []
        starts = np.concatenate([[0], np.flatnonzero(m[1:] != m[:-1]) + 1])
        ends = np.concatenate([starts[1:], [len(m)]])
        return [(int(m[a]), slice(int(a), int(b))) for a, b in zip(starts, ends, strict=True)]


@dataclass
class Surface:
    """Per-hit shading inputs: albedo, emitted radiance at night, mirror reflectance, LiDAR reflectivity."""

    albedo: np.ndarray
    emissive_night: np.ndarray
    mirror: np.ndarray  # (n,) reflectance of a mirror-like component (glass, wet road, paint)
    reflectivity: np.ndarray  # (n,) 0..1 for LiDAR intensity


def _road(h: Hits, c: Conditions | None):
    """Asphalt with markings from road coordinates (s along, lat across; aux: see world.AUX):
    dashed centre line (streets), double yellow and dashed lane lines (avenues), parking edge
    lines and bay ticks, zebra crossings and stop lines at junctions. Markings are evaluated only
    on the few pixels near one (a cheap test first), with footprint-aware coverage."""
    u, lat = h.uv[:, 0], h.uv[:, 1]
    a = h.aux
    s = a[:, 0] + u
    w, kind, s0, s1 = a[:, 2], a[:, 3], a[:, 4], a[:, 5]
    fp = h.footprint
    grain = NOISE(h.p[:, 0], h.p[:, 1], 1.5)
    patch = NOISE(h.p[:, 1] * 0.05, h.p[:, 0] * 0.05, 1.5)
    grey = 0.075 + 0.05 * grain * fade(0.2, fp) + 0.035 * patch
    alat = np.abs(lat)
    park_edge = w - 2.3
    near_end = (s < s0 + 5.2) | (s > s1 - 5.2)
    cand = (
        (alat < 0.3)
        | (np.abs(alat - park_edge) < 0.3)
        | (alat > park_edge)
        | near_end
        | ((kind == 2) & (np.abs(alat - 3.6) < 0.3))
    )
    ci = np.flatnonzero(cand)
    paint = np.zeros(len(u), F32)
    yellow = np.zeros(len(u), F32)
    if len(ci):
        sl, la, al, f, k, ww = s[ci], lat[ci], alat[ci], fp[ci], kind[ci], w[ci]
        pe = park_edge[ci]
        c0, c1 = s0[ci], s1[ci]
        xa, xb = a[ci, 6], a[ci, 7]
        m = line_mask(la, 0.06, f) * ((sl % 9.0) < 3.0) * (k == 1)
        m = np.maximum(m, line_mask(al - 3.6, 0.06, f) * ((sl % 12.0) < 3.0) * (k == 2))
        m = np.maximum(m, line_mask(al - pe, 0.06, f) * (k >= 1))
        ticks = (al > pe) & (al < ww - 0.2) & (k >= 1)
        m = np.maximum(m, ticks * line_mask(((sl - c0 + 3.0) % 6.0) - 3.0, 0.06, f))
        zebra_zone = (
            ((xa > 0) & (sl > c0 + 0.5) & (sl < c0 + 3.5)) | ((xb > 0) & (sl < c1 - 0.5) & (sl > c1 - 3.5))
        ) & (al < ww - 0.4)
        fz = fade(1.0, f)
        stripes = (((la + 50.0) % 1.0) < 0.5) * fz + 0.5 * (1 - fz)
        m = np.maximum(m, zebra_zone * stripes)
        stop = (
            ((xb > 0) & (la < 0) & (sl > c1 - 5.1) & (sl < c1 - 4.6))
            | ((xa > 0) & (la > 0) & (sl > c0 + 4.6) & (sl < c0 + 5.1))
        ) & (al < pe)
        m = np.maximum(m, stop.astype(F32))
        paint[ci] = m * (0.7 + 0.6 * grain[ci] * patch[ci])
        yellow[ci] = np.maximum(line_mask(la - 0.13, 0.06, f), line_mask(la + 0.13, 0.06, f)) * (k == 2)
    col = np.empty((len(u), 3), F32)
    rest = 1 - paint - yellow
    col[:, 0] = grey * rest + 0.75 * paint + 0.7 * yellow
    col[:, 1] = grey * rest + 0.75 * paint + 0.52 * yellow
    col[:, 2] = grey * 1.02 * rest + 0.72 * paint + 0.08 * yellow
    refl = 0.08 + 0.6 * np.maximum(paint, yellow)
    return col, refl, lat, paint


def _asphalt(h: Hits):
    grain = NOISE(h.p[:, 0], h.p[:, 1], 1.5)
    v = 0.075 + 0.05 * grain * fade(0.2, h.footprint) + 0.035 * NOISE(h.p[:, 1] * 0.05, h.p[:, 0] * 0.05, 1.5)
    return (v[:, None] * f32(1, 1, 1.02)[None]).astype(F32)


def _sidewalk(h: Hits):
    s = h.aux[:, 0] + h.uv[:, 0]
    lat = h.uv[:, 1]
    tile = 1.2
    i, j = np.floor(s / tile), np.floor(lat / tile)
    var = 0.9 + 0.2 * hash01(i, j, np.full_like(i, 3)) * fade(tile, h.footprint)
    grout = np.maximum(
        line_mask(((s + 0.6) % tile) - 0.6, 0.02, h.footprint),
        line_mask(((lat + 60.6) % tile) - 0.6, 0.02, h.footprint),
    )
    v = 0.42 * var * (1 - 0.4 * grout) * (0.9 + 0.2 * NOISE(h.p[:, 0], h.p[:, 1], 6.0))
    return (v[:, None] * f32(1.0, 0.98, 0.95)[None]).astype(F32)


def _ground(h: Hits, c: Conditions | None):
    grass = f32(0.16, 0.3, 0.07) if c is None else c.grass_rgb
    n1 = NOISE(h.p[:, 0], h.p[:, 1], 4.0)
    n2 = NOISE(h.p[:, 0] + 91.0, h.p[:, 1], 60.0)
    dirt = smoothstep(0.62, 0.8, n2)
    col = grass[None] * (0.7 + 0.6 * n1 * fade(0.5, h.footprint))[:, None]
    col = col * (1 - dirt)[:, None] + f32(0.3, 0.24, 0.17)[None] * dirt[:, None]
    return col.astype(F32)


def _wall(h: Hits, styles: np.ndarray, c: Conditions | None):
    """Facades: brick, panel, plaster, stone, glass or siding; windows per floor; at street level
    shop windows under a sign band, and a door."""
    u, v = h.uv[:, 0], h.uv[:, 1]
    a = h.aux
    L, eave, floor_h, front = a[:, 0], a[:, 1], a[:, 2], a[:, 3]
    base = a[:, 4:7]
    bh = (a[:, 7] * 1e6).astype(np.int32)
    sid = h.style
    pattern = styles[sid, 0].astype(np.int32)
    spacing, win_w, win_h = styles[sid, 5], styles[sid, 6], styles[sid, 7]
    shop = (styles[sid, 11] > 0.5) & (front > 0.5)
    fp = h.footprint
    n = len(u)
    tone = np.ones(n, F32)
    # wall pattern
    for k in np.unique(pattern):
        sel = np.nonzero(pattern == k)[0]
        uu, vv, f = u[sel], v[sel], fp[sel]
        if k == 0:  # brick
            row = np.floor(vv / 0.09)
            off = (row % 2) * 0.125
            col = np.floor((uu + off) / 0.25)
            mortar = (((vv % 0.09) < 0.012) | (((uu + off) % 0.25) < 0.012)).astype(F32)
            b = (0.82 + 0.36 * hash01(row, col, bh[sel])) * (1 - mortar) + 1.5 * mortar
            tone[sel] = 1 + (b - 1) * fade(0.09, f)
        elif k == 1:  # panels
            pu, pv = spacing[sel], floor_h[sel] / 2
            col, row = np.floor(uu / pu), np.floor(vv / pv)
            joint = (((uu % pu) < 0.04) | ((vv % pv) < 0.04)).astype(F32) * fade(0.3, f)
            tone[sel] = (0.92 + 0.16 * hash01(col, row, bh[sel]) * fade(pu, f)) * (1 - 0.5 * joint)
        elif k == 2:  # plaster with cornices
            stain = NOISE(uu + bh[sel] % 97, vv, 8.0)
            cornice = line_mask((vv % floor_h[sel]) - 0.05, 0.06, f)
            tone[sel] = (0.85 + 0.25 * stain) * (1 + 0.25 * cornice)
        elif k == 3:  # ashlar stone
            row = np.floor(vv / 0.4)
            off = (row % 2) * 0.3
            col = np.floor((uu + off) / 0.6)
            joint = ((vv % 0.4) < 0.02) | (((uu + off) % 0.6) < 0.02)
            tone[sel] = 1 + ((0.85 + 0.3 * hash01(row, col, bh[sel])) * (1 - 0.35 * joint) - 1) * fade(0.4, f)
        elif k == 5:  # horizontal siding
            board = (vv % 0.2) / 0.2
            tone[sel] = 1 + (0.8 + 0.25 * board - 1) * fade(0.2, f)
    albedo = (base * tone[:, None]).astype(F32)
    # windows
    n_cols = np.maximum(np.floor((L - 0.6) / spacing), 0)
    u0 = (L - n_cols * spacing) / 2
    colw = np.floor((u - u0) / spacing)
    fu = (u - u0) - colw * spacing - spacing / 2
    floor = np.floor(v / floor_h)
    fv = v - floor * floor_h
    sill = (floor_h - win_h) * 0.55
    in_cols = (colw >= 0) & (colw < n_cols)
    upper = (floor >= 1) | ~shop
    below_eave = v < eave - 0.4
    win = in_cols & upper & below_eave & (np.abs(fu) < win_w / 2) & (fv > sill) & (fv < sill + win_h)
    frame = win & ((np.abs(fu) > win_w / 2 - 0.08) | (fv < sill + 0.08) | (fv > sill + win_h - 0.08))
    # street level of shops: glazing, a sign band with letters, a door
    g0 = shop & (floor == 0)
    shop_win = g0 & in_cols & (np.abs(fu) < spacing * 0.42) & (v > 0.45) & (v < floor_h - 1.05)
    band = g0 & (v > floor_h - 0.95) & (v < floor_h - 0.2) & (u > 0.3) & (u < L - 0.3)
    band_rgb = np.zeros((n, 3), F32)
    if band.any():
        band_rgb[band] = hsv_rgb((styles[sid[band], 15] + 0.13 * (bh[band] % 7)) % 1.0, 0.75, 0.75)
    lc = np.floor((u - 0.3) / 0.42)
    letter = band & (np.abs(((u - 0.3) % 0.42) - 0.21) < 0.14) & (np.abs(v - (floor_h - 0.575)) < 0.22)
    if letter.any():
        letter[letter] = hash01(lc[letter], bh[letter], np.full(int(letter.sum()), 11)) < 0.7
    door = (front > 0.5) & (v < 2.3) & (np.abs(fu) < 0.6) & in_cols
    if door.any():
        di = np.flatnonzero(door)
        door[di] = colw[di] == np.floor(hash01(bh[di], np.full(len(di), 5)) * np.maximum(n_cols[di], 1))
    glass = (win & ~frame) | (shop_win & ~door)
    albedo[frame] = styles[sid[frame], 8:11]
    gi = np.flatnonzero(glass | win)
    hcell = hash01(colw[gi], floor[gi], bh[gi])  # one value per window: interior, lit or not, brightness
    on_glass = glass[gi]
    albedo[gi[on_glass]] = (0.03 + 0.1 * hcell[on_glass])[:, None] * f32(1.0, 0.95, 0.9)[None]
    albedo[band] = band_rgb[band]
    albedo[letter] = f32(0.92, 0.92, 0.9)
    albedo[door] = f32(0.2, 0.12, 0.07)
    # grime near the ground (cheap ambient occlusion)
    low = np.flatnonzero(v < 2.0)
    albedo[low] *= (0.72 + 0.14 * v[low])[:, None]
    # night: some windows lit, shops and signs lit
    emis = np.zeros((n, 3), F32)
    if c is not None and c.night > 0.01:
        lit_w = (win[gi] & ~frame[gi] & (((hcell * 7.31) % 1.0) < styles[sid[gi], 16])) | (shop_win[gi] & ~door[gi])
        emis[gi[lit_w]] = f32(1.0, 0.78, 0.45)[None] * (0.5 + 0.5 * ((hcell[lit_w] * 13.7) % 1.0))[:, None]
        emis[band] += band_rgb[band] * 0.8
        emis[letter] += f32(1.2, 1.2, 1.1)
    mirror = np.zeros(n, F32)
    refl = (0.35 + 0.1 * tone).astype(F32)
    g = np.flatnonzero(glass)
    if len(g):
        mirror[g] = 0.35 + 0.45 * (1 - np.abs(dot3(h.d[g], h.n[g]))) ** 3
        refl[g] = 0.05
    return albedo, emis, mirror, refl


def _roof(h: Hits):
    pitched = h.aux[:, 0] > 0.5
    col = h.aux[:, 4:7]
    v = h.uv[:, 1]
    tiles = 0.82 + 0.25 * ((v % 0.3) / 0.3) * fade(0.3, h.footprint)
    gravel = 0.85 + 0.3 * NOISE(h.p[:, 0], h.p[:, 1], 3.0)
    return (col * np.where(pitched, tiles, gravel)[:, None]).astype(F32)


def _foliage(h: Hits, c: Conditions | None):
    f1, f2 = FOLIAGE["summer"] if c is None else c.foliage_rgb
    th = h.aux[:, 0]
    mixw = th[:, None]
    col = f32(*f1)[None] * (1 - mixw) + f32(*f2)[None] * mixw
    leaf = NOISE(h.p[:, 0] + h.p[:, 2] * 0.7, h.p[:, 1] - h.p[:, 2] * 0.7, 2.5)
    col = col * (0.6 + 0.8 * leaf * fade(0.3, h.footprint) + 0.4 * (1 - fade(0.3, h.footprint)))[:, None]
    if c is not None and c.season == "autumn":
        yellow = (hash01((th * 1e6).astype(np.int64), np.full(len(th), 4)) < 0.35)[:, None]
        col = np.where(yellow, f32(0.7, 0.55, 0.08)[None] * (0.6 + 0.8 * leaf)[:, None], col)
    return col.astype(F32)


def _sign(h: Hits):
    x = h.uv[:, 0] - 0.35
    y = h.uv[:, 1] - 0.35
    r = np.sqrt(x * x + y * y)
    t = h.aux[:, 0].astype(int)
    col = np.tile(f32(0.45, 0.45, 0.45), (len(x), 1))
    red, white, blue, yellow, black = (
        f32(0.7, 0.05, 0.04),
        f32(0.85, 0.85, 0.85),
        f32(0.04, 0.15, 0.6),
        f32(0.85, 0.65, 0.05),
        f32(0.03, 0.03, 0.03),
    )
    disc = r < 0.33
    s0 = (t == 0) & disc
    col[s0] = red
    col[s0 & (np.abs(y) < 0.06) & (np.abs(x) < 0.22)] = white
    s1 = (t == 1) & disc
    col[s1] = white
    col[s1 & (r > 0.25)] = red
    s2 = (t == 2) & disc
    col[s2] = blue
    col[
        s2 & (((np.abs(x) < 0.05) & (y < 0.12) & (y > -0.2)) | ((y > 0.05) & (y < 0.22) & (np.abs(x) < (0.22 - y))))
    ] = white
    dia = np.abs(x) + np.abs(y)
    s3 = (t == 3) & (dia < 0.34)
    col[s3] = yellow
    col[s3 & (dia > 0.29)] = black
    return col


def _fence(h: Hits):
    kind = h.aux[:, 0]
    u = h.uv[:, 0]
    f = fade(0.15, h.footprint)
    slat = ((u % 0.15) < 0.12).astype(F32)
    wood = f32(0.42, 0.29, 0.18)[None] * (0.55 + 0.45 * (slat * f + 0.8 * (1 - f)))[:, None]
    bar = ((u % 0.12) < 0.03).astype(F32)
    metal = f32(0.08, 0.18, 0.1)[None] * (0.5 + 0.5 * (bar * f + 0.25 * (1 - f)))[:, None]
    return np.where((kind > 0.5)[:, None], metal, wood).astype(F32)


FLAT = {
    Mat.CURB: (0.5, 0.5, 0.48),
    Mat.TRUNK: (0.22, 0.16, 0.1),
    Mat.POLE: (0.3, 0.31, 0.32),
    Mat.LAMP: (0.35, 0.35, 0.33),
    Mat.CAR_GLASS: (0.03, 0.035, 0.04),
    Mat.CAR_WHEEL: (0.03, 0.03, 0.03),
    Mat.HILL: (0.12, 0.2, 0.1),
}
REFLECTIVITY = {
    Mat.GROUND: 0.25,
    Mat.JUNCTION: 0.08,
    Mat.SIDEWALK: 0.3,
    Mat.CURB: 0.35,
    Mat.ROOF: 0.2,
    Mat.TRUNK: 0.3,
    Mat.FOLIAGE: 0.4,
    Mat.POLE: 0.45,
    Mat.LAMP: 0.5,
    Mat.SIGN: 0.95,
    Mat.FENCE: 0.3,
    Mat.CAR_BODY: 0.35,
    Mat.CAR_GLASS: 0.05,
    Mat.CAR_WHEEL: 0.05,
    Mat.HILL: 0.2,
}


def surface(h: Hits, styles: np.ndarray, c: Conditions | None) -> Surface:
    """Albedo and the rest of the surface model at every hit (``c`` None: neutral, for LiDAR).

    The hits must be sorted by material (each material is then a slice: views, not copies).
    """
    n = len(h.mat)
    albedo = np.zeros((n, 3), F32)
    emis = np.zeros((n, 3), F32)
    mirror = np.zeros(n, F32)
    refl = np.zeros(n, F32)
    snow_w = np.ones(n, F32)  # how much a snow layer may cover (wheel tracks stay darker)
    for m, sel in h.material_slices():
        m = Mat(m)
        if c is None and m not in (Mat.ROAD, Mat.WALL):
            refl[sel] = REFLECTIVITY.get(m, 0.3)  # LiDAR: a reflectivity per material is enough
            continue
        hs = h.take(sel)
        if m == Mat.ROAD:
            col, r, lat, paint = _road(hs, c)
            albedo[sel], refl[sel] = col, r
            track = np.minimum(np.abs(np.abs(lat) - 0.9), np.abs(np.abs(lat) - 2.6))
            # wheel tracks in the driving lanes: grey slush with ragged edges
            slush = 0.55 + 0.3 * NOISE(hs.p[:, 0] * 2.0, hs.p[:, 1] * 2.0, 3.0)
            edge = smoothstep(0.5, 0.25, track + 0.2 * (slush - 0.7))
            snow_w[sel] = 0.95 - (0.95 - slush) * edge
        elif m == Mat.JUNCTION:
            albedo[sel] = _asphalt(hs)
            snow_w[sel] = 0.6
        elif m == Mat.SIDEWALK:
            albedo[sel] = _sidewalk(hs)
        elif m == Mat.GROUND:
            albedo[sel] = _ground(hs, c)
        elif m == Mat.WALL:
            a, e, mi, r = _wall(hs, styles, c)
            albedo[sel], emis[sel], mirror[sel], refl[sel] = a, e, mi, r
        elif m == Mat.ROOF:
            albedo[sel] = _roof(hs)
        elif m == Mat.FOLIAGE:
            albedo[sel] = _foliage(hs, c)
        elif m == Mat.SIGN:
            albedo[sel] = _sign(hs)
        elif m == Mat.FENCE:
            albedo[sel] = _fence(hs)
        elif m == Mat.CAR_BODY:
            albedo[sel] = hs.aux[:, 0:3]
            mirror[sel] = 0.06 + 0.3 * (1 - np.abs(dot3(hs.d, hs.n))) ** 4
        elif m == Mat.CAR_GLASS:
            albedo[sel] = f32(*FLAT[m])
            mirror[sel] = 0.3
        elif m == Mat.LAMP:
            albedo[sel] = f32(*FLAT[m])
            emis[sel] = f32(1.0, 0.8, 0.55) * 12.0
        else:
            albedo[sel] = f32(*FLAT.get(m, (0.5, 0.5, 0.5)))
        if m != Mat.ROAD and m != Mat.WALL:
            refl[sel] = REFLECTIVITY.get(m, 0.3)
    if c is not None and c.snow_cover > 0:
        k = np.flatnonzero((h.n[:, 2] > 0.45) & (h.mat != Mat.CAR_GLASS))  # snow lies on upward faces
        if len(k):
            p = h.p[k]
            up = smoothstep(0.45, 0.85, h.n[k, 2])
            patch = 0.75 + 0.25 * NOISE(p[:, 0] * 1.3, p[:, 1] * 1.3, 5.0)
            cover = np.clip(F32(c.snow_cover) * up * patch * snow_w[k], 0, 1)
            albedo[k] += (f32(0.86, 0.88, 0.92)[None] - albedo[k]) * cover[:, None]
            mirror[k] *= 1 - cover
    if c is not None and c.wetness > 0:
        k = np.flatnonzero(np.isin(h.mat, (Mat.ROAD, Mat.JUNCTION, Mat.SIDEWALK, Mat.GROUND, Mat.ROOF, Mat.CURB)))
        if len(k):
            wet = F32(c.wetness * (1.0 if c.snow_cover == 0 else 0.3))
            albedo[k] *= 1 - 0.5 * wet
            road = np.isin(h.mat[k], (Mat.ROAD, Mat.JUNCTION))
            p = h.p[k]
            puddle = smoothstep(0.58, 0.7, NOISE(p[:, 0] + 13.0, p[:, 1], 12.0)) * road
            cos_i = np.abs(dot3(h.d[k], h.n[k]))
            fres = 0.03 + 0.6 * (1 - cos_i) ** 5
            mirror[k] = np.maximum(mirror[k], wet * (fres + 0.45 * puddle))
    return Surface(albedo, emis, mirror.astype(F32), refl.astype(F32))


# --- camera response -------------------------------------------------------------------------------


def tone_lut(size: int = 4096, max_in: float = 4.0) -> np.ndarray:
    """8-bit sRGB of linear values 0..max_in: a soft-shoulder curve, then the sRGB transfer."""
    x = np.linspace(0, max_in, size, dtype=np.float64)
    y = 1.0 - np.exp(-1.35 * x)
    y = np.where(y <= 0.0031308, 12.92 * y, 1.055 * np.power(y, 1 / 2.4) - 0.055)
    return np.clip(np.round(y * 255), 0, 255).astype(np.uint8)


TONE_LUT = tone_lut()
LUT_SCALE = F32((len(TONE_LUT) - 1) / 4.0)


def to_srgb8(linear: np.ndarray) -> np.ndarray:
    """8-bit sRGB through the tone LUT (``linear`` is used as scratch space)."""
    linear *= LUT_SCALE
    np.clip(linear, 0, len(TONE_LUT) - 1, out=linear)
    return TONE_LUT[linear.astype(np.int32)]
