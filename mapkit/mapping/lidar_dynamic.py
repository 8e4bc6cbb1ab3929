"""Points of moving objects, removed from a LiDAR map where passes disagree.

The rule is free-space carving between scans (the visibility test of Removert, Kim & Kim IROS 2020, applied
point by point within a time window): a point that a later or earlier scan sees *through* was not there when
that scan looked, so it belonged to something that moved. For each scan, ``witnesses`` other scans are taken
at time offsets spread over ``min_dt_s``..``max_dt_s`` before and after it (a car has driven its own length
away by then). Each witness keeps a range image of what it measured: per pixel of azimuth and elevation
(``azimuth_resolution_deg`` x ``vertical_resolution_deg``, around the sensor's orientation at the sweep's
middle) the nearest return, then the nearest over each 3 x 3 neighbourhood. A point of the scan is projected
into the witness along the ray from the witness's sensor position when it fired that azimuth; the witness
sees through it when the neighbourhood's nearest return lies beyond the point by more than
``margin_m + margin_fraction * range``. A point seen through by at least ``min_votes`` witnesses is removed.

What stays, by construction: a point no witness can see (occluded, out of range, or with no return in its
neighbourhood: sky, a black car) gets no vote; a surface seen at a grazing angle has nearer returns in the
neighbourhood; a parked car is seen again where it was. What goes that should not: a thin object (a pole, a
branch) that every witness's rays pass beside; the measured share is in the docs. What cannot go: a car
moving with the vehicle at its speed stays in the same place relative to it, so no witness sees through it.

Streaming: a scan is decided once the scans up to ``max_dt_s`` after it have arrived; the filter holds the
scans of that window and the range images of twice it, so its memory is bounded by the window, not the log.
"""

from __future__ import annotations

import dataclasses
from collections import deque
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import cv2
import numpy as np
from pydantic import Field, model_validator

from mapkit.core.config import MapkitConfig
from mapkit.core.types import LidarScan

GROW_PASSES = 2
GROUND_CELL_M, GROUND_CELL_DEG = 2.0, 2.0
HDL64_BEAM_SPACING_DEG = 0.4  # 26.9 deg over 64 beams (Velodyne HDL-64E datasheet)


def beam_spacing(xyz: np.ndarray, ring: np.ndarray | None) -> float | None:
    """The mean spacing (rad) of a scanner's beams from one scan in its own frame: the span of the rings' median
    elevations over their count less one. None without a ring field or with fewer than two rings."""
    if ring is None or len(ring) != len(xyz):
        return None
    xyz = np.asarray(xyz, np.float64)
    el = np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1]))
    rings, index = np.unique(np.asarray(ring), return_inverse=True)
    if len(rings) < 2:
        return None
    order = np.argsort(index, kind="stable")
    starts = np.searchsorted(index[order], np.arange(len(rings)))
    medians = np.sort([np.median(part) for part in np.split(el[order], starts[1:])])
    return float((medians[-1] - medians[0]) / (len(rings) - 1))


class DynamicConfig(MapkitConfig):
    """Removal of moving objects' points from the LiDAR map (``lidar_map.dynamic``)."""

    enabled: bool = Field(True, description="Remove points that other scans see through (moving objects).")
    min_dt_s: float = Field(
        0.5,
        gt=0,
        allow_inf_nan=False,
        description="Witness scans at least this far in time: an oncoming car (20 m/s relative) has moved 10 m.",
    )
    max_dt_s: float = Field(
        3.0,
        gt=0,
        allow_inf_nan=False,
        description="Witness scans at most this far in time (a walker at 1.5 m/s has moved 3 m); also the delay "
        "before a scan is decided.",
    )
    witnesses: int = Field(8, ge=1, description="Witness scans per scan, half before and half after it.")
    min_votes: int = Field(2, ge=1, description="Witnesses that must see through a point to remove it.")
    margin_m: float = Field(
        0.3, ge=0, allow_inf_nan=False, description="A witness sees through a point beyond it by more than this..."
    )
    margin_fraction: float = Field(
        0.02, ge=0, allow_inf_nan=False, description="...plus this fraction of the point's range (pose error)."
    )
    grow_px: int = Field(
        2,
        ge=0,
        description="Then a kept point goes too when, within this many pixels of it in its own scan's range image, "
        "more points at its range (within margin_m) went than stayed: the rest of a car whose parts the witnesses "
        "could not see through. 0: off.",
    )
    margin_vertical_m: float = Field(
        0.1,
        ge=0,
        allow_inf_nan=False,
        description="...plus, for points near the ground, this height error carried along the ray (divided by the "
        "sine of its elevation): the road seen at a grazing angle, where centimetres of height move a return metres "
        "along the beam.",
    )
    ground_band_m: float = Field(
        0.15,
        ge=0,
        allow_inf_nan=False,
        description="Near the ground: within this of the lowest point around (2 m x 2 deg polar cells).",
    )
    vertical_resolution_deg: float | None = Field(
        None,
        gt=0,
        allow_inf_nan=False,
        description="Range-image rows; None: the scanner's mean beam spacing, from the scans' ring field, else "
        "0.4 deg (a Velodyne HDL-64E's, as in KITTI's ring-less files). Rows finer than the beams let a surface seen "
        "at a grazing angle look seen through: set it for a ring-less scanner with fewer beams.",
    )
    azimuth_resolution_deg: float = Field(
        0.4,
        gt=0,
        allow_inf_nan=False,
        description="Range-image columns; coarser than the scanner's own step is safe (fewer holes), finer leaves "
        "empty pixels and their points get no vote.",
    )

    @model_validator(mode="after")
    def _window(self) -> DynamicConfig:
        if self.min_dt_s > self.max_dt_s:
            raise ValueError(f"min_dt_s ({self.min_dt_s}) must not exceed max_dt_s ({self.max_dt_s})")
        if self.min_votes > self.witnesses:
            raise ValueError(f"min_votes ({self.min_votes}) must not exceed witnesses ({self.witnesses})")
        return self


@dataclass
class PlacedScan:
    """A scan's points in the map frame and where they were measured from: the sensor's positions across the
    sweep (one without deskewing) and which of them each point was measured at."""

    stamp_ns: int
    points: np.ndarray  # (N, 3) map frame
    intensity: np.ndarray | None  # (N,)
    positions: np.ndarray  # (S, 3) the sensor's positions across the sweep
    position_of: np.ndarray  # (N,) integer: each point's index into positions
    rotation: np.ndarray  # (3, 3) map_from_sensor at the sweep's middle

    @property
    def origin(self) -> np.ndarray:
        """(N, 3) the sensor's position when each point was measured."""
        return self.positions[self.position_of]


@dataclass
class RangeView:
    """What one scan saw: the nearest return per pixel and over each 3 x 3 neighbourhood (0: none)."""

    stamp_ns: int
    rotation: np.ndarray  # (3, 3) map_from_sensor at the sweep's middle
    centre: np.ndarray  # (3,) the sensor's mean position
    column_offset: np.ndarray  # (3, W) float32: the sensor's position when it fired each column, from the centre,
    # in the sensor's frame
    image: np.ndarray  # (H + 2, W) float32, an empty row (0) above and below the rows that can hold returns
    el_lo: float  # elevation of row 1's lower edge (rad)


@dataclass
class _Prepared:
    """A placed scan as the filter holds it while it waits: its points from the sensor's mean position in
    float32, one row per axis (a sweep spans metres, not kilometres: under 4 micrometres of rounding at 64 m), and
    each point's pixel and range in its own range image."""

    scan: PlacedScan  # its points dropped (an empty array): rel holds them
    centre: np.ndarray  # (3,) float64
    rel: np.ndarray  # (3, N) float32: points - centre
    row: np.ndarray  # (N,) int32, from the scan's lowest point (row 0)
    col: np.ndarray  # (N,) int32
    r: np.ndarray  # (N,) float32
    ground: np.ndarray  # indices of the points near the ground (_near_ground)


def _rotate(R: np.ndarray, p: np.ndarray, shift: np.ndarray | None = None) -> np.ndarray:
    """``(p.T @ R).T + shift`` for points ``p`` (3, N) float32, axis by axis: elementwise passes, no BLAS threads
    (a BLAS product of this shape costs far more than its arithmetic on a shared machine)."""
    R = np.asarray(R, np.float32)
    out = np.empty_like(p)
    tmp = np.empty_like(p[0])
    for j in range(3):
        np.multiply(p[0], R[0, j], out=out[j])
        out[j] += np.multiply(p[1], R[1, j], out=tmp)
        out[j] += np.multiply(p[2], R[2, j], out=tmp)
        if shift is not None:
            out[j] += np.float32(shift[j])
    return out


def _polar(local: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Azimuth, elevation and range of points ``local`` (3, N) float32."""
    x, y, z = local
    horizontal2 = x * x + y * y
    return np.arctan2(y, x), np.arctan2(z, np.sqrt(horizontal2)), np.sqrt(horizontal2 + z * z)


def _nearest_around(grid: np.ndarray) -> np.ndarray:
    """The minimum over each cell's 3 x 3 neighbourhood of ``grid`` (rows x columns of azimuth), the columns
    wrapping around the circle, the rows not (inf beyond them)."""
    padded = np.concatenate([grid[:, -1:], grid, grid[:, :1]], axis=1)
    eroded = cv2.erode(padded, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=np.inf)
    return np.ascontiguousarray(eroded[:, 1:-1])


class DynamicFilter:
    """Scans in (time order) with :meth:`push`, decided scans out with their keep masks, ``max_dt_s`` later;
    :meth:`finish` decides the rest. :meth:`run` does both over a stream, its rows from the first scan's rings."""

    def __init__(self, cfg: DynamicConfig):
        self.cfg = cfg
        self.az_res = np.radians(cfg.azimuth_resolution_deg)
        self.el_res = float(np.radians(cfg.vertical_resolution_deg or HDL64_BEAM_SPACING_DEG))
        self.columns = int(np.ceil(2 * np.pi / self.az_res))
        self.max_dt_ns = int(round(cfg.max_dt_s * 1e9))
        self.min_dt_ns = int(round(cfg.min_dt_s * 1e9))
        self._pending: deque[_Prepared] = deque()
        self._views: deque[RangeView] = deque()
        self.ground_seen = 0  # points near the ground (_near_ground), and those of them removed: the road carved
        self.ground_removed = 0

    def _column(self, az: np.ndarray) -> np.ndarray:
        col = np.floor((az + np.float32(np.pi)) * np.float32(1.0 / self.az_res)).astype(np.intp)
        col[col >= self.columns] -= self.columns  # az = pi exactly (and float32 rounding at the seam)
        return col

    def prepare(self, scan: PlacedScan) -> tuple[_Prepared, RangeView]:
        """The scan's points relative to the sensor, each point's row and column in its own range image (row 0 at
        the scan's lowest point: a beam at a row's middle), its range and whether it lies near the ground; and the
        scan's range image."""
        positions = np.asarray(scan.positions, np.float64)
        weight = np.bincount(scan.position_of, minlength=len(positions))  # points per position
        centre = weight @ positions / weight.sum() if len(scan.points) else positions.mean(axis=0)
        rel = (scan.points - centre).T.astype(np.float32)
        sensor = (positions - centre).astype(np.float32)  # (S, 3)
        from_origin = rel - sensor[scan.position_of].T
        az, el, r = _polar(_rotate(scan.rotation, from_origin))
        el_min = float(el.min()) if len(el) else 0.0
        row = np.floor((el - np.float32(el_min)) * np.float32(1.0 / self.el_res) + np.float32(0.5)).astype(np.intp)
        col = self._column(az)
        ground = np.flatnonzero(self._near_ground(from_origin, rel[2]))
        view = self._view(scan, centre, row, col, r, el_min, sensor)
        light = dataclasses.replace(scan, points=np.empty((0, 3)))
        return _Prepared(light, centre, rel, row.astype(np.int32), col.astype(np.int32), r, ground), view

    def _view(
        self,
        scan: PlacedScan,
        centre: np.ndarray,
        row: np.ndarray,
        col: np.ndarray,
        r: np.ndarray,
        el_min: float,
        sensor: np.ndarray,
    ) -> RangeView:
        """The range image of a scan (its points' ``row``, ``col`` and range ``r`` in it), with an empty row below
        its lowest beam (the neighbourhoods of the lowest beam reach into it) and, beyond those, the empty rows that
        points outside fall on; and the sensor's position per column (``sensor``: its positions across the sweep
        from ``centre``)."""
        W = self.columns
        row = row + 2  # the outer empty row, then the one below the lowest beam
        H = int(row.max()) + 2 if len(row) else 3
        flat = np.full(H * W, np.inf, np.float32)
        np.minimum.at(flat, row * W + col, r)
        image = flat.reshape(H, W)
        image[1:-1] = _nearest_around(image[1:-1])
        image[~np.isfinite(image)] = 0.0  # no return: sees through nothing
        counts = np.bincount(col, minlength=W)
        offset = np.zeros((3, W), np.float32)  # the sensor's position per column, from the centre, map axes
        filled = np.flatnonzero(counts)
        if len(filled):
            at = sensor[scan.position_of]
            for k in range(3):
                sums = np.bincount(col, at[:, k], minlength=W)
                offset[k] = np.interp(np.arange(W), filled, sums[filled] / counts[filled], period=W)
        offset = _rotate(scan.rotation, offset)
        return RangeView(scan.stamp_ns, scan.rotation, centre, offset, image, el_min - 1.5 * self.el_res)

    def see_through(self, p: _Prepared, view: RangeView) -> np.ndarray:
        """Which points of a prepared scan ``view`` sees through; for the points near the ground, ``margin_vertical_m``
        of height error is carried along each ray into the margin."""
        local = _rotate(view.rotation, p.rel, (p.centre - view.centre) @ view.rotation)
        col0 = self._column(np.arctan2(local[1], local[0]))
        for k in range(3):  # from the sensor's position when it fired that column
            local[k] -= view.column_offset[k][col0]
        az, el, r = _polar(local)
        rows = view.image.shape[0]
        row = np.floor((el - np.float32(view.el_lo)) * np.float32(1.0 / self.el_res)).astype(np.intp) + 1
        np.clip(row, 0, rows - 1, out=row)  # beyond the image: its empty outer rows
        seen = view.image.reshape(-1)[row * self.columns + self._column(az)]
        margin = np.float32(self.cfg.margin_fraction) * r
        margin += np.float32(self.cfg.margin_m) + r
        if self.cfg.margin_vertical_m:
            at = p.ground
            sin_el = np.abs(local[2][at]) / np.maximum(r[at], np.float32(1e-6))
            margin[at] += np.float32(self.cfg.margin_vertical_m) / np.maximum(sin_el, np.float32(0.01))
        return seen > margin

    def _witnesses(self, stamp_ns: int) -> list[RangeView]:
        """Up to ``witnesses`` views, each nearest to one of the target offsets spread over the window."""
        half = max(1, self.cfg.witnesses // 2)
        offsets = np.linspace(self.min_dt_ns, self.max_dt_ns, half)
        targets = np.r_[-offsets[::-1], offsets][: self.cfg.witnesses] if self.cfg.witnesses > 1 else offsets[:1]
        dt = np.array([v.stamp_ns - stamp_ns for v in self._views], np.int64)
        eligible = np.flatnonzero((np.abs(dt) >= self.min_dt_ns) & (np.abs(dt) <= self.max_dt_ns))
        chosen: list[int] = []
        for target in targets:
            side = eligible[np.sign(dt[eligible]) == np.sign(target)]
            free = side[~np.isin(side, chosen)]
            if len(free):
                chosen.append(int(free[np.argmin(np.abs(dt[free] - target))]))
        return [self._views[i] for i in chosen]

    def _decide(self, p: _Prepared) -> tuple[PlacedScan, np.ndarray]:
        votes = np.zeros(len(p.r), np.uint8)
        for view in self._witnesses(p.scan.stamp_ns):
            votes += self.see_through(p, view)
        keep = votes < self.cfg.min_votes
        if self.cfg.grow_px and not keep.all():
            row, col = p.row.astype(np.intp), p.col.astype(np.intp)
            for _ in range(GROW_PASSES):
                keep &= ~self._grow(row, col, p.r, ~keep)
        self.ground_seen += len(p.ground)
        self.ground_removed += int(np.count_nonzero(~keep[p.ground]))
        return dataclasses.replace(p.scan, points=p.rel.T + p.centre), keep  # float64 again, for the map

    def _near_ground(self, from_origin: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Points (``from_origin``: (3, N) from the sensor, map axes; ``z``: their heights) within ``ground_band_m``
        of the lowest point around them (polar cells of 2 m by 2 deg around the sensor, the lowest over each 3 x 3
        cells): the road, and the bottom of whatever stands on it."""
        x, y, _ = from_origin
        ring = np.floor(np.sqrt(x * x + y * y) * np.float32(1.0 / GROUND_CELL_M)).astype(np.intp)
        n_sector = int(np.ceil(360 / GROUND_CELL_DEG))
        sector = np.floor((np.arctan2(y, x) + np.float32(np.pi)) * np.float32(1.0 / np.radians(GROUND_CELL_DEG)))
        cell = ring * n_sector + sector.astype(np.intp) % n_sector
        n_ring = int(ring.max()) + 1 if len(ring) else 1
        lowest = np.full(n_ring * n_sector, np.inf, np.float32)
        np.minimum.at(lowest, cell, z)
        ground = _nearest_around(lowest.reshape(n_ring, n_sector)).reshape(-1)
        return z - ground[cell] < self.cfg.ground_band_m

    def _grow(self, row: np.ndarray, col: np.ndarray, r: np.ndarray, gone: np.ndarray) -> np.ndarray:
        """Kept points whose neighbours at their range in their scan's own range image (each point's ``row``,
        ``col`` and range ``r`` there) mostly went."""
        W = self.columns
        H = int(row.max()) + 1
        pixel = row * W + col
        nearest = np.full(H * W, np.inf, np.float32)
        np.minimum.at(nearest, pixel, r)
        went = np.zeros(H * W, bool)
        went[pixel[gone]] = True
        went &= np.isfinite(nearest)
        # a pixel's status is its nearest point's: a pixel where a kept point is the nearest one stays kept
        kept_nearest = ~gone & (r <= nearest[pixel])
        went[pixel[kept_nearest]] = False
        k = self.cfg.grow_px
        Wp = W + 2 * k  # padded by k on every side, then flat: a neighbour is one offset away
        nearest = np.pad(nearest.reshape(H, W), ((k, k), (k, k)), constant_values=np.inf, mode="constant")
        went = np.pad(went.reshape(H, W), ((k, k), (k, k)))
        # only kept points within k pixels of one that went can change
        reach = cv2.dilate(went.astype(np.uint8), np.ones((2 * k + 1, 2 * k + 1), np.uint8))
        nearest, went, reach = nearest.reshape(-1), went.reshape(-1), reach.reshape(-1)
        at = (row + k) * Wp + (col + k)
        cand = np.flatnonzero(~gone & (reach[at] > 0))
        at, rr = at[cand], r[cand]
        n_went = np.zeros(len(cand), np.int32)
        n_stay = np.zeros(len(cand), np.int32)
        below = np.zeros(len(cand), bool)  # a kept point right below one that went, at its range: a wheel on the road
        for dr in range(-k, k + 1):
            for dc in range(-k, k + 1):
                if dr == 0 and dc == 0:
                    continue
                there = at + (dr * Wp + dc)
                near = np.abs(nearest[there] - rr) < self.cfg.margin_m
                w = went[there]
                n_went += near & w
                n_stay += near & ~w
                if dc == 0 and dr > 0:
                    below |= near & w
        out = np.zeros(len(gone), bool)
        out[cand[(n_went > n_stay) | below]] = True
        return out

    def push(self, scan: PlacedScan) -> list[tuple[PlacedScan, np.ndarray]]:
        """Add ``scan``; returns the scans now decided, each with its keep mask."""
        p, view = self.prepare(scan)
        self._pending.append(p)
        self._views.append(view)
        out = []
        while self._pending and self._pending[0].scan.stamp_ns + self.max_dt_ns <= scan.stamp_ns:
            out.append(self._decide(self._pending.popleft()))
        oldest = self._pending[0].scan.stamp_ns if self._pending else scan.stamp_ns
        while self._views and self._views[0].stamp_ns < oldest - self.max_dt_ns:
            self._views.popleft()
        return out

    def run(self, scans: Iterable[tuple[LidarScan, PlacedScan]]) -> Iterator[tuple[PlacedScan, np.ndarray]]:
        """Each placed scan of ``scans`` (with the scan it was placed from) and its keep mask, in order; the range
        images' rows at the beam spacing of the first scan's rings unless ``vertical_resolution_deg`` is set."""
        first = True
        for scan, placed in scans:
            if first and self.cfg.vertical_resolution_deg is None:
                self.el_res = beam_spacing(scan.points_xyz, scan.ring) or self.el_res
            first = False
            yield from self.push(placed)
        yield from self.finish()

    def finish(self) -> Iterator[tuple[PlacedScan, np.ndarray]]:
        """Decide the scans still waiting (the log's last ``max_dt_s``, with the witnesses there are), one at a
        time: each is let go once decided."""
        while self._pending:
            yield self._decide(self._pending.popleft())
        self._views.clear()


__all__ = ["DynamicConfig", "DynamicFilter", "PlacedScan", "RangeView", "beam_spacing"]
