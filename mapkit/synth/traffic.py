"""Moving cars: oncoming traffic on a session's route.

A session's ``moving_cars`` drive its route the other way, in the opposite lane (``lane_offset_m`` to the
left of the path the vehicle drove), each at its own constant speed, entering the route at its far end at
times spread over the drive so that each meets the vehicle once. They are rendered by the camera and the
LiDAR like parked cars but placed at each frame's time (a LiDAR sweep places them at its middle: at 25 m/s a
car moves 1.25 m in half a sweep, so its returns are a little smeared, as a real scanner's are).

Which LiDAR returns hit a moving car is known at render time; the session writes it beside the log
(``sessions/<name>.moving_cars.npz``: per scan, the indices of its points that hit one), the truth a
dynamic-point filter is scored on.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mapkit.core.runio import atomic_path
from mapkit.synth.world import CAR_COLOURS, CarShapes, Geometry, car_meshes

LANE_OFFSET_M = 3.2  # the opposite lane's centre, left of the vehicle's path (streets are 12 m wide)


@dataclass
class Traffic:
    """Cars moving along a polyline ``track_xy`` against its direction, ``speed`` m/s each, at arc length
    ``s0`` at ``t0_ns`` (they appear where 0 <= s <= the track's length)."""

    track_xy: np.ndarray  # (M, 2) the opposite lane's centre line, in the vehicle's direction
    track_s: np.ndarray  # (M,) arc length along it
    t0_ns: int
    s0: np.ndarray  # (n,) arc length of each car at t0
    speed: np.ndarray  # (n,) m/s, against the track's direction
    shape: CarShapes

    def __len__(self) -> int:
        return int(len(self.s0))

    def placed(self, t_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(xy (k, 2), yaw (k,), index (k,)) of the cars on the track at ``t_ns``."""
        s = self.s0 - self.speed * (t_ns - self.t0_ns) * 1e-9
        on = np.flatnonzero((s >= 0) & (s <= self.track_s[-1]))
        s = s[on]
        xy, ahead, behind = self._at(s), self._at(s + 1.0), self._at(s - 1.0)
        d = ahead - behind
        yaw = np.arctan2(d[:, 1], d[:, 0]) + np.pi  # driving against the track
        return xy, yaw, on

    def _at(self, s: np.ndarray) -> np.ndarray:
        """Points (k, 2) of the track at arc lengths ``s`` (clamped to its ends)."""
        return np.c_[np.interp(s, self.track_s, self.track_xy[:, 0]), np.interp(s, self.track_s, self.track_xy[:, 1])]

    def geometry_at(self, t_ns: int) -> Geometry | None:
        """The cars' meshes at ``t_ns``; None when none is on the track."""
        xy, yaw, on = self.placed(t_ns)
        return car_meshes(self.shape.take(on), xy, yaw) if len(on) else None


def oncoming_traffic(
    stamps_ns: np.ndarray, world_from_base: np.ndarray, n: int, rng: np.random.Generator
) -> Traffic | None:
    """``n`` cars driving the drive (``world_from_base`` at ``stamps_ns``) the other way in the opposite lane,
    at 6-12 m/s, entering at the route's end at times spread over the drive. None for ``n == 0``."""
    if n <= 0:
        return None
    xy = world_from_base[:, :2, 3]
    step = np.r_[True, np.linalg.norm(np.diff(xy, axis=0), axis=1) > 0.05]
    xy, heading = xy[step], world_from_base[step, :2, 0]
    left = np.c_[-heading[:, 1], heading[:, 0]] / np.linalg.norm(heading, axis=1)[:, None]
    lane = xy + LANE_OFFSET_M * left
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(lane, axis=0), axis=1))]
    keep = np.r_[True, np.diff(s) > 1e-6]
    lane, s = lane[keep], s[keep]
    duration_s = (stamps_ns[-1] - stamps_ns[0]) * 1e-9
    speed = rng.uniform(6.0, 12.0, n)
    enter_s = np.sort(rng.uniform(0.0, 0.8, n)) * duration_s  # when each enters the route's far end
    s0 = s[-1] + speed * enter_s  # at t0 still beyond the end, reaching it at enter_s
    length = rng.uniform(3.8, 4.8, n)
    colour = CAR_COLOURS[rng.integers(len(CAR_COLOURS), size=n)] * rng.uniform(0.85, 1.1, (n, 1))
    shape = CarShapes(
        length,
        rng.uniform(1.7, 1.9, n),
        rng.uniform(0.65, 0.8, n),
        length * rng.uniform(0.45, 0.55, n),
        rng.uniform(0.45, 0.55, n),
        colour,
    )
    return Traffic(lane, s, int(stamps_ns[0]), s0, speed, shape)


def write_dynamic_truth(path: Path, traffic: Traffic, scan_stamps_ns: list[int], hits: list[np.ndarray]) -> Path:
    """The LiDAR truth of a session with moving cars: per scan (its stamp), the indices of its points that hit a
    moving car, as one concatenated array and offsets; and the cars' track and speeds."""
    offsets = np.cumsum([0] + [len(h) for h in hits]).astype(np.int64)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez(
            f,
            scan_stamp_ns=np.asarray(scan_stamps_ns, np.int64),
            offsets=offsets,
            index=np.concatenate(hits).astype(np.int64) if hits else np.zeros(0, np.int64),
            track_xy=traffic.track_xy,
            s0=traffic.s0,
            speed=traffic.speed,
            t0_ns=traffic.t0_ns,
        )
    return path


def read_dynamic_truth(path: str | Path) -> dict[int, np.ndarray]:
    """Scan stamp -> indices of its points that hit a moving car, from :func:`write_dynamic_truth`'s file."""
    with np.load(Path(path)) as z:
        stamps, offsets, index = z["scan_stamp_ns"], z["offsets"], z["index"]
    return {int(t): index[offsets[k] : offsets[k + 1]] for k, t in enumerate(stamps)}


__all__ = ["Traffic", "oncoming_traffic", "write_dynamic_truth", "read_dynamic_truth", "LANE_OFFSET_M"]
