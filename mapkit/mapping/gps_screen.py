"""Screening of GNSS fixes before any of them can place a map.

A receiver reporting FIX can still put out a fix that no vehicle could have produced: (0, 0) from a
firmware that has not converged ("null island"), numbers outside WGS84, an altitude hundreds of
metres off, or a jump that would need a car faster than an aircraft. The robust alignment rejects a
few such fixes, but one of them must never become the workspace's origin, so they are removed here,
before georeferencing, and counted by reason.

Jumps are judged by speed along the drive: starting from the fix nearest the robust centre of the
rest (the median of positions, which a minority of wild fixes cannot move far), each next fix in time
is kept when the distance from the last kept one is within ``max_speed_mps`` times the time between
them plus a slack for the fixes' own noise; the same walk goes backwards from the anchor.
"""

from __future__ import annotations

import warnings
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from mapkit.core.errors import InputWarning
from mapkit.core.geodesy import LocalFrame
from mapkit.core.types import GpsFix

#: reasons, in the order they are tested
NO_FIX = "no fix (status or non-finite position)"
OUT_OF_BOUNDS = "latitude or longitude outside WGS84 bounds"
NULL_ISLAND = "at latitude 0, longitude 0 (null island: an unconverged receiver)"
ALTITUDE = "altitude far from the other fixes"
JUMP = "jump faster than the vehicle can move"


@dataclass
class GpsScreen:
    """The fixes kept, in time order, and how many were rejected for each reason."""

    kept: list[GpsFix]
    rejected: Counter = field(default_factory=Counter)
    #: the stamps of the first few rejected fixes of each reason, for the report
    examples: dict[str, list[int]] = field(default_factory=dict)
    #: kept fixes whose unknown altitude the georef stage filled in
    altitude_filled: int = 0

    @property
    def total(self) -> int:
        return len(self.kept) + sum(self.rejected.values())

    def summary(self) -> dict:
        return {
            "fixes": self.total,
            "kept": len(self.kept),
            "rejected": dict(self.rejected),
            "rejected_examples_stamp_ns": self.examples,
            "altitude_filled": self.altitude_filled,
        }

    def warn(self, source: str) -> None:
        """One warning naming the counts of each reason (nothing when every fix was kept)."""
        if self.rejected:
            what = "; ".join(f"{n} {reason}" for reason, n in self.rejected.items())
            warnings.warn(
                f"{source}: {sum(self.rejected.values())} of {self.total} GPS fixes rejected before "
                f"georeferencing: {what}",
                InputWarning,
                stacklevel=2,
            )


def screen_fixes(
    fixes: list[GpsFix],
    max_speed_mps: float = 70.0,
    max_altitude_dev_m: float = 300.0,
    null_island_deg: float = 1e-3,
    slack_m: float = 10.0,
) -> GpsScreen:
    """Remove fixes no drive could have produced (see the module docstring); keeps time order.

    ``max_speed_mps`` (70 m/s, 250 km/h) bounds the vehicle's speed; ``slack_m`` plus three times a
    fix's stated horizontal sigma is added to the distance allowed between two fixes, so that a
    receiver's own noise at a standstill is not taken for a jump. An altitude is rejected when it
    is more than ``max_altitude_dev_m`` (or ten median absolute deviations, if larger) from the
    median altitude of the fixes that passed the other checks; a NaN altitude (unknown) is kept.
    """
    out = GpsScreen([])
    order = sorted(range(len(fixes)), key=lambda i: fixes[i].stamp_ns)
    cand: list[GpsFix] = []
    for i in order:
        f = fixes[i]
        reason = None
        if not f.has_fix:
            reason = NO_FIX
        elif abs(f.lat_deg) > 90 or abs(f.lon_deg) > 180:
            reason = OUT_OF_BOUNDS
        elif abs(f.lat_deg) < null_island_deg and abs(f.lon_deg) < null_island_deg:
            reason = NULL_ISLAND
        if reason:
            _reject(out, reason, f)
        else:
            cand.append(f)
    if not cand:
        return out

    alt = np.array([f.alt_m for f in cand], np.float64)
    finite = np.isfinite(alt)
    if finite.sum() >= 3:
        med = float(np.median(alt[finite]))
        mad = float(np.median(np.abs(alt[finite] - med)))
        bad_alt = finite & (np.abs(alt - med) > max(max_altitude_dev_m, 10.0 * 1.4826 * mad))
        for f in (f for f, b in zip(cand, bad_alt, strict=True) if b):
            _reject(out, ALTITUDE, f)
        cand = [f for f, b in zip(cand, bad_alt, strict=True) if not b]

    lat = np.array([f.lat_deg for f in cand])
    lon = np.array([f.lon_deg for f in cand])
    frame = LocalFrame(float(np.median(lat)), float(np.median(lon)), 0.0)
    xy = frame.geodetic_to_enu(lat, lon, np.zeros(len(cand)))[:, :2]
    t = np.array([f.stamp_ns for f in cand], np.float64) * 1e-9
    sig = np.array([f.horizontal_sigma_m for f in cand])
    sig = np.where(np.isfinite(sig), sig, 0.0)
    anchor = int(np.argmin(np.linalg.norm(xy - np.median(xy, axis=0), axis=1)))
    keep = np.zeros(len(cand), bool)
    keep[anchor] = True
    for step in (1, -1):
        last = anchor
        for j in range(anchor + step, len(cand) if step > 0 else -1, step):
            allowed = max_speed_mps * abs(t[j] - t[last]) + slack_m + 3.0 * (sig[j] + sig[last])
            if np.linalg.norm(xy[j] - xy[last]) <= allowed:
                keep[j] = True
                last = j
    for f, k in zip(cand, keep, strict=True):
        if k:
            out.kept.append(f)
        else:
            _reject(out, JUMP, f)
    return out


def _reject(out: GpsScreen, reason: str, f: GpsFix) -> None:
    out.rejected[reason] += 1
    ex = out.examples.setdefault(reason, [])
    if len(ex) < 5:
        ex.append(int(f.stamp_ns))
