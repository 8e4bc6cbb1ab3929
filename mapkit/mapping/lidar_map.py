"""The LiDAR map of a session: every scan deskewed, placed by the session's trajectory and the LiDAR's mount,
and accumulated into a :class:`~mapkit.mapping.voxel_map.VoxelMap`, scan by scan.

Deskewing. A spinning scanner sweeps for a tenth of a second, during which the vehicle moves (3 m at 30 m/s)
and turns; each point is placed by the trajectory's pose at its own time, ``enu_from_base(stamp + t) @
base_from_lidar @ p``, the poses interpolated (linear position, slerp rotation) at ``DESKEW_SLICES`` times
across the sweep and each point taking the nearest one (at 10 Hz a slice is 0.2 ms: 3 mm at 15 m/s). The
point times are the scan's time field (``LidarScan.point_time_s``, seconds relative to the stamp; the KITTI
readers derive them from each point's azimuth). A scan without a time field gets its times from the azimuth,
as kiss-icp does for KITTI (``kiss_icp/datasets/kitti_raw.py``: ``0.5 * (-atan2(y, x) / pi + 1)``, a clockwise
sweep from the rear), scaled by ``sweep_period_s`` and ending at the stamp (kiss-icp deskews to the sweep's
last point and gives its pose the scan's stamp). A time field that cannot be used (not one finite time per
point, or no spread) leaves that scan undeskewed, with one warning for all such scans. Without deskewing a
scan is placed by one pose, the trajectory's at its stamp.

Where a point falls outside the trajectory's time span (the first sweep of a kiss-icp trajectory, whose poses
are stamped at each sweep's end) it takes the nearest end pose; a scan whose whole sweep lies outside it is
skipped and counted.

Moving objects (``dynamic``, on by default): each placed scan passes through
:class:`~mapkit.mapping.lidar_dynamic.DynamicFilter` before it enters the map, and the points it removes go into a
second voxel map of the same size (``dynamic.ply``), so that what was removed can be looked at.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from mapkit.core.config import MapkitConfig
from mapkit.core.errors import InputWarning
from mapkit.core.geodesy import LocalFrame
from mapkit.core.geometry import interpolate_poses
from mapkit.core.runio import atomic_path, atomic_write_ply, progress_bar
from mapkit.core.types import LidarScan
from mapkit.mapping.lidar_dynamic import DynamicConfig, DynamicFilter, PlacedScan
from mapkit.mapping.trajectory import Trajectory
from mapkit.mapping.voxel_map import VoxelMap, VoxelStats

DESKEW_SLICES = 512  # poses interpolated across one sweep


class LidarMapConfig(MapkitConfig):
    """The LiDAR map (``lidar_map/`` of a session)."""

    enabled: bool | Literal["auto"] = Field(
        "auto", description="Build the LiDAR map; auto = when the log has a LiDAR stream (topics.lidar)."
    )
    voxel_size_m: float = Field(
        0.10,
        gt=0,
        allow_inf_nan=False,
        description="Edge of the map's voxels: one point (the centroid) per voxel in points.ply.",
    )
    min_range_m: float = Field(
        2.0, ge=0, allow_inf_nan=False, description="Returns nearer than this are dropped (the vehicle's body)."
    )
    max_range_m: float = Field(
        100.0,
        gt=0,
        allow_inf_nan=False,
        description="Returns farther than this are dropped: a heading error moves a point by its range times it.",
    )
    deskew: bool = Field(True, description="Place each point by the pose at its own time (motion compensation).")
    sweep_period_s: float = Field(
        0.1, gt=0, allow_inf_nan=False, description="Sweep duration for times derived from the azimuth (10 Hz)."
    )
    chunk_points: int = Field(
        1_000_000,
        ge=1,
        description="Points buffered before they are merged into the map (memory per chunk); the removed points' "
        "map merges with it.",
    )
    dynamic: DynamicConfig = Field(
        default_factory=DynamicConfig, description="Removal of moving objects' points (free space between scans)."
    )

    @model_validator(mode="after")
    def _ranges(self) -> LidarMapConfig:
        if self.min_range_m >= self.max_range_m:
            raise ValueError(f"min_range_m ({self.min_range_m}) must be below max_range_m ({self.max_range_m})")
        return self


@dataclass
class LidarMapResult:
    """The map and what went into it."""

    voxels: VoxelMap
    removed: VoxelMap | None = None  # the moving objects' points, when dynamic removal is on
    near_ground: tuple[int, int] = (0, 0)  # points near the ground the removal saw, and removed
    scans_used: int = 0
    points_seen: int = 0  # within the range limits, before dynamic removal
    skipped: dict[str, int] = field(default_factory=dict)  # reason -> scans
    times: dict[str, int] = field(default_factory=dict)  # where the deskew times came from -> scans

    def metrics(self, cfg: LidarMapConfig) -> dict:
        return {
            "points": int(self.voxels.points_added),
            "voxels": len(self.voxels),
            "voxel_size_m": cfg.voxel_size_m,
            "scans_used": self.scans_used,
            "scans_skipped": int(sum(self.skipped.values())),
            **({"skipped": dict(self.skipped)} if self.skipped else {}),
            "deskew": cfg.deskew,
            "deskew_times": dict(self.times),
            "dynamic": {"enabled": False}
            if self.removed is None
            else {
                "enabled": True,
                "points_removed": int(self.removed.points_added),
                "fraction_removed": round(self.removed.points_added / max(self.points_seen, 1), 5),
                # a road carved by pose errors shows here, where no moving object should be
                "near_ground_fraction_removed": round(self.near_ground[1] / max(self.near_ground[0], 1), 5),
                "voxels_removed": len(self.removed),
            },
        }


def scan_times(scan: LidarScan, cfg: LidarMapConfig) -> tuple[np.ndarray | None, str]:
    """Per-point times of a scan (s, relative to its stamp) and where they come from: ``field``, ``azimuth``, or
    None with ``off`` (deskew off) or ``unusable`` (a time field that cannot be used)."""
    if not cfg.deskew:
        return None, "off"
    t = scan.point_time_s
    if t is None:
        xyz = np.asarray(scan.points_xyz, np.float64)
        fraction = 0.5 * (-np.arctan2(xyz[:, 1], xyz[:, 0]) / np.pi + 1.0)  # kiss-icp's, 0 at the rear
        return (fraction - 1.0) * cfg.sweep_period_s, "azimuth"
    t = np.asarray(t, np.float64)
    if t.shape != (len(scan),) or not np.isfinite(t).all() or len(t) and np.ptp(t) <= 0:
        return None, "unusable"
    return t, "field"


def _clamped_poses(traj: Trajectory, query_ns: np.ndarray) -> np.ndarray:
    """The trajectory's poses at ``query_ns``, a query outside its span taking the nearest end pose."""
    q = np.clip(np.asarray(query_ns, np.int64), traj.stamps_ns[0], traj.stamps_ns[-1])
    poses, ok = interpolate_poses(traj.stamps_ns, traj.world_from_base, q)
    assert ok.all()  # clipped into the span
    return poses


def within_range(xyz: np.ndarray, cfg: LidarMapConfig) -> np.ndarray:
    """Which of a scan's points (N, 3, its own frame) lie within the range limits (NaN compares false: dropped)."""
    r2 = np.einsum("ij,ij->i", xyz, xyz)
    return (r2 >= cfg.min_range_m**2) & (r2 <= cfg.max_range_m**2)


def keep_masks(
    placed: Iterable[tuple[LidarScan, PlacedScan]], cfg: LidarMapConfig, moving: DynamicFilter | None = None
) -> Iterator[tuple[PlacedScan, np.ndarray]]:
    """Each placed scan with the mask of the points the map keeps: those ``moving`` (a filter of ``cfg.dynamic``,
    made here when not given) does not remove, all of them with the removal off."""
    if not cfg.dynamic.enabled:
        return ((p, np.ones(len(p.points), bool)) for _, p in placed)
    return (moving or DynamicFilter(cfg.dynamic)).run(placed)


def place_scan(
    scan: LidarScan, traj: Trajectory, base_from_lidar: np.ndarray, cfg: LidarMapConfig, times: np.ndarray | None
) -> PlacedScan | None:
    """The scan's points within the range limits in the trajectory's world frame, with their intensities and the
    sensor's position when each was measured; deskewed when ``times`` (per point, s relative to the stamp) are
    given. None when the sweep lies outside the trajectory's time span."""
    xyz = np.asarray(scan.points_xyz, np.float64)
    keep = within_range(xyz, cfg)
    xyz = xyz[keep]
    intensity = None if scan.intensity is None else np.asarray(scan.intensity)[keep]
    t = None if times is None else times[keep]
    lo_s, hi_s = (0.0, 0.0) if t is None or not len(t) else (float(t.min()), float(t.max()))
    slack_ns = 1_000_000  # 1 ms: the trajectory's stamps are rounded from the same float times
    if (
        scan.stamp_ns + hi_s * 1e9 + slack_ns < traj.stamps_ns[0]
        or scan.stamp_ns + lo_s * 1e9 - slack_ns > traj.stamps_ns[-1]
    ):
        return None
    if t is None or hi_s <= lo_s:
        T = _clamped_poses(traj, np.array([scan.stamp_ns]))[0] @ base_from_lidar
        at = np.zeros(len(xyz), np.int16)
        return PlacedScan(scan.stamp_ns, xyz @ T[:3, :3].T + T[:3, 3], intensity, T[None, :3, 3], at, T[:3, :3])
    grid_s = np.linspace(lo_s, hi_s, DESKEW_SLICES)
    T = _clamped_poses(traj, scan.stamp_ns + np.round(grid_s * 1e9).astype(np.int64)) @ base_from_lidar
    slice_of = np.rint((t - lo_s) / (hi_s - lo_s) * (DESKEW_SLICES - 1)).astype(np.intp)
    world = np.empty_like(xyz)
    x, y, z = xyz.T
    for i in range(3):  # row by row: gathers of one entry per point, not of a 3x3 matrix per point
        world[:, i] = T[:, i, 0][slice_of] * x + T[:, i, 1][slice_of] * y + T[:, i, 2][slice_of] * z
        world[:, i] += T[:, i, 3][slice_of]
    return PlacedScan(
        scan.stamp_ns,
        world,
        intensity,
        T[:, :3, 3].copy(),
        slice_of.astype(np.int16),
        T[DESKEW_SLICES // 2, :3, :3].copy(),
    )


def build_lidar_map(
    scans: Iterator[LidarScan],
    traj: Trajectory,
    base_from_lidar: np.ndarray,
    cfg: LidarMapConfig,
    source: str | Path | None = None,
    total: int | None = None,
    progress: bool = False,
) -> LidarMapResult:
    """The voxel map of ``scans`` placed by ``traj`` (world_from_base) and the LiDAR's mount, scan by scan;
    ``source`` names the log in the warning about scans whose times cannot be used."""
    out = LidarMapResult(VoxelMap(cfg.voxel_size_m, cfg.chunk_points))
    moving = DynamicFilter(cfg.dynamic) if cfg.dynamic.enabled else None
    if moving is not None:
        out.removed = VoxelMap(cfg.voxel_size_m, cfg.chunk_points)
    bar = progress_bar(total, progress, desc="lidar map", unit="scan", leave=False)

    def placed_scans() -> Iterator[tuple[LidarScan, PlacedScan]]:
        for scan in scans:
            bar.update(1)
            times, origin = scan_times(scan, cfg)
            placed = place_scan(scan, traj, base_from_lidar, cfg, times)
            if placed is None or not len(placed.points):
                why = "outside the trajectory's time span" if placed is None else "no point within the range limits"
                out.skipped[why] = out.skipped.get(why, 0) + 1
                continue
            out.points_seen += len(placed.points)
            out.scans_used += 1
            out.times[origin] = out.times.get(origin, 0) + 1
            yield scan, placed

    for placed, keep in keep_masks(placed_scans(), cfg, moving):
        intensity = placed.intensity
        merges = out.voxels.merges
        out.voxels.add(placed.points[keep], None if intensity is None else intensity[keep], placed.stamp_ns)
        if out.removed is not None and not keep.all():
            gone = ~keep
            out.removed.add(placed.points[gone], None if intensity is None else intensity[gone], placed.stamp_ns)
        if out.removed is not None and out.voxels.merges != merges:
            out.removed.flush()  # one chunk for both: the few removed points a scan are not held for longer
    if moving is not None:
        out.near_ground = (moving.ground_seen, moving.ground_removed)
    bar.close()
    out.voxels.flush()
    if out.times.get("unusable"):
        warnings.warn(
            f"{source}: {out.times['unusable']} LiDAR scans have a time field that cannot be used (not one finite time "
            "per point, or all equal): deskew is off for them",
            InputWarning,
            stacklevel=2,
        )
    return out


def save_voxel_map(folder: Path, stats: VoxelStats, frame: LocalFrame | None) -> Path:
    """``points.ply`` (the voxels' centroids, grey by mean intensity, the frame stated in the header as for every
    mapkit PLY) and ``voxels.npz`` (every statistic of :class:`VoxelStats`) into ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    inten = np.nan_to_num(stats.intensity, nan=0.0)
    top = float(np.percentile(inten, 99)) if len(inten) else 0.0
    grey = np.repeat(np.clip(inten / top if top > 0 else inten * 0.0, 0.0, 1.0)[:, None], 3, axis=1)
    atomic_write_ply(folder / "points.ply", stats.centroid, grey, frame=frame)
    with atomic_path(folder / "voxels.npz") as tmp, open(tmp, "wb") as f:
        np.savez(
            f,
            voxel_size_m=stats.voxel_size_m,
            centroid=stats.centroid,
            count=stats.count,
            intensity=stats.intensity,
            normal=stats.normal,
            planarity=stats.planarity,
            first_ns=stats.first_ns,
            last_ns=stats.last_ns,
        )
    return folder


def load_voxel_stats(folder: str | Path) -> VoxelStats:
    """The voxel statistics a LiDAR map folder holds (``voxels.npz``)."""
    with np.load(Path(folder) / "voxels.npz") as z:
        d = {k: z[k] for k in z.files}
    return VoxelStats(
        float(d["voxel_size_m"]),
        d["centroid"],
        d["count"],
        d["intensity"],
        d["normal"],
        d["planarity"],
        d["first_ns"],
        d["last_ns"],
    )
