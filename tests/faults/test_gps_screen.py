"""GNSS screening: fixes no drive could produce are removed and counted by reason, the good ones
all kept, whatever position in the stream the bad ones take (first fix included)."""

from __future__ import annotations

import numpy as np
import pytest

from mapkit.core.geodesy import LocalFrame
from mapkit.core.types import GpsFix, GpsStatus
from mapkit.mapping.gps_screen import ALTITUDE, JUMP, NO_FIX, NULL_ISLAND, OUT_OF_BOUNDS, screen_fixes

FRAME = LocalFrame(48.7758, 9.1829, 250.0)
T0 = 1_700_000_000_000_000_000


def _drive(n: int = 120, speed: float = 15.0, noise: float = 2.0, seed: int = 0) -> list[GpsFix]:
    """1 Hz fixes of a car turning through a quarter circle at ``speed`` m/s, with ``noise`` m per axis."""
    rng = np.random.default_rng(seed)
    s = speed * np.arange(n)
    theta = s / 400.0
    enu = np.c_[400 * np.sin(theta), 400 * (1 - np.cos(theta)), np.zeros(n)] + rng.normal(0, noise, (n, 3))
    lat, lon, alt = FRAME.enu_to_geodetic(enu)
    cov = np.eye(3) * noise**2
    return [
        GpsFix(T0 + i * 1_000_000_000, float(lat[i]), float(lon[i]), float(alt[i]), GpsStatus.FIX, cov)
        for i in range(n)
    ]


def _moved(f: GpsFix, east_m: float, north_m: float = 0.0, up_m: float = 0.0) -> GpsFix:
    enu = FRAME.geodetic_to_enu([f.lat_deg], [f.lon_deg], [f.alt_m])[0] + [east_m, north_m, up_m]
    lat, lon, alt = FRAME.enu_to_geodetic(enu[None])
    return GpsFix(f.stamp_ns, float(lat[0]), float(lon[0]), float(alt[0]), f.status, f.covariance_enu_m2)


def _replace(fix: GpsFix, **kw) -> GpsFix:
    d = dict(
        stamp_ns=fix.stamp_ns,
        lat_deg=fix.lat_deg,
        lon_deg=fix.lon_deg,
        alt_m=fix.alt_m,
        status=fix.status,
        covariance_enu_m2=fix.covariance_enu_m2,
    )
    d.update(kw)
    return GpsFix(**d)


def test_clean_drive_keeps_every_fix():
    fixes = _drive()
    out = screen_fixes(fixes)
    assert len(out.kept) == len(fixes) and not out.rejected


def test_stationary_receiver_noise_is_not_a_jump():
    fixes = _drive(n=300, speed=0.0, noise=4.0)
    assert len(screen_fixes(fixes).kept) == 300


@pytest.mark.parametrize("bad_first", [False, True])
def test_each_fault_removed_and_counted(bad_first):
    fixes = _drive()
    bad = {
        3: _replace(fixes[3], lat_deg=0.0, lon_deg=0.0, alt_m=0.0),  # null island, status FIX
        10: _replace(fixes[10], lat_deg=95.0),
        20: _replace(fixes[20], lat_deg=float("nan")),
        21: _replace(fixes[21], status=GpsStatus.NO_FIX),
        30: _replace(fixes[30], alt_m=fixes[30].alt_m + 1500.0),
        50: _moved(fixes[50], 1000.0),  # one fix 1 km off, 1 s after a good one
        # three fixes in a row 2 km off (a multipath burst): consistent with each other, not with the drive
        70: _moved(fixes[70], -2000.0),
        71: _moved(fixes[71], -2000.0),
        72: _moved(fixes[72], -2000.0),
    }
    if bad_first:
        bad[0] = _moved(fixes[0], 0.0, 5000.0)
    stream = [bad.get(i, f) for i, f in enumerate(fixes)]
    out = screen_fixes(stream[::-1])  # input order does not matter: output is in time order
    good = [i for i in range(len(fixes)) if i not in bad]
    assert [f.stamp_ns for f in out.kept] == [fixes[i].stamp_ns for i in good]
    assert out.rejected[NULL_ISLAND] == 1 and out.rejected[OUT_OF_BOUNDS] == 1 and out.rejected[NO_FIX] == 2
    assert out.rejected[ALTITUDE] == 1
    assert out.rejected[JUMP] == 4 + int(bad_first)
    assert out.total == len(fixes)
    assert out.examples[NULL_ISLAND] == [fixes[3].stamp_ns]


def test_a_long_gap_allows_the_distance_driven_in_it():
    fixes = _drive(n=200, speed=20.0)
    gap = fixes[:50] + fixes[150:]  # 100 s without fixes, 2 km driven
    assert len(screen_fixes(gap).kept) == 100


def test_warning_states_the_counts():
    fixes = _drive()
    fixes[5] = _replace(fixes[5], lat_deg=0.0, lon_deg=0.0)
    out = screen_fixes(fixes)
    with pytest.warns(UserWarning, match=r"log\.mcap: 1 of 120 GPS fixes rejected .*null island"):
        out.warn("log.mcap")
