"""Cost of the LiDAR map stage against the trajectory stage, and its memory on a 4x longer log.

Both on a log with a LiDAR, by default the real KITTI clip beside the project (30 HDL-64 scans, about 120 000
points each); ``--log`` takes any other (a synthetic drive: ``--log runs/main/town/sessions/test-clear``):

1. time: the trajectory stage's kiss-icp (``trajectory_from_lidar``, mapkit's defaults but the warm start: kiss-icp's
   own forward run) against the LiDAR map
   stage (``write_lidar_map``: deskew, voxel map, statistics, PLY, voxels.npz, top view) on that trajectory,
   best of ``--repeat`` in wall and CPU time (the first call of each is a warm-up: imports, caches).
   Goal: the map at most 25 % of the trajectory's time. The stage with its moving-object removal off is timed
   too: what the voxel map, deskewing and files cost alone.
2. memory: peak resident memory of a fresh process that maps the clip's scans once (1x), and 2, 4 and 8 times
   over (the scans repeated with later stamps along a trajectory that drives the clip's street again, so the log is
   longer but the map covers the same ground). Goal: 4x within 1.2x of 1x. The clip (3 s) is no longer than the
   moving-object filter's window (3 s of scans waiting, 6 s of range images), so at 1x the window never holds its
   scans beside a whole map; 8x against 4x shows whether memory still grows with the log once it does.
   For comparison, the 4x log along four parallel streets 200 m apart (four times the ground, so four times the
   voxels): the map itself, not the log, is what the memory follows.

Run from the repository root (keep other load low; the machine has 2 cores)::

    python bench/bench_lidar_map.py [--log LOG]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.common import best_wall_and_cpu, peak_rss_mb_of, report  # noqa: E402 (after sys.path points at this checkout)

DEFAULT_CLIP = ROOT.parent / "shared" / "data" / "kitti-raw-velodyne-clip"
GOAL_TIME_RATIO = 0.25
GOAL_MEMORY_RATIO = 1.2

# run in a fresh process: map the clip's scans `repeats` times, the trajectory repeated with them
MEMORY_RUN = """
import warnings
import numpy as np
warnings.simplefilter("ignore")
from mapkit.core.types import StreamKind
from mapkit.io import open_log
from mapkit.mapping.lidar_map import LidarMapConfig, build_lidar_map
from mapkit.mapping.trajectory import Trajectory

clip, traj_dir, repeats, shift_y = {clip!r}, {traj!r}, {repeats}, {shift_y}
one = Trajectory.load(traj_dir)
period = int(one.stamps_ns[-1] - one.stamps_ns[0]) + 100_000_000
stamps = np.concatenate([one.stamps_ns + k * period for k in range(repeats)])
poses = np.concatenate([one.world_from_base for _ in range(repeats)])
for k in range(repeats):
    poses[k * len(one) : (k + 1) * len(one), 1, 3] += k * shift_y
traj = Trajectory(stamps, poses, one.source, one.frame, one.body_frame)

def scans():
    for k in range(repeats):
        log = open_log(clip)
        for scan in log.records(StreamKind.LIDAR):
            scan.stamp_ns += k * period
            yield scan
        log.close()

result = build_lidar_map(scans(), traj, np.eye(4), LidarMapConfig())
print("VOXELS", len(result.voxels.stats()))
"""


def trajectory_stage(clip: Path):
    from mapkit.core.types import StreamKind
    from mapkit.io import open_log
    from mapkit.mapping.trajectory import TrajectoryConfig, trajectory_from_lidar

    log = open_log(clip)
    try:
        topic = next(s.topic for s in log.streams() if s.kind == StreamKind.LIDAR)
        # kiss-icp's own forward run: the warm start (a backward run over the first seconds) is left out of the baseline
        return trajectory_from_lidar(log, topic, TrajectoryConfig(kiss_icp={"warm_start_s": 0}))
    finally:
        log.close()


def lidar_map_stage(clip: Path, traj, out: Path, removal: bool = True) -> Path:
    from mapkit.core.types import StreamKind
    from mapkit.core.workspace import SessionDirs
    from mapkit.io import open_log
    from mapkit.mapping.lidar_map import LidarMapConfig
    from mapkit.mapping.stages.lidar_map import write_lidar_map
    from mapkit.mapping.trajectory import SensorMounts

    log = open_log(clip)
    try:
        topic = next(s.topic for s in log.streams() if s.kind == StreamKind.LIDAR)
        return write_lidar_map(
            SessionDirs(out),
            log,
            topic,
            traj,
            SensorMounts.of(log),
            LidarMapConfig(dynamic={"enabled": removal}),
            None,
            progress=False,
        )
    finally:
        log.close()


def _name(log: Path) -> str:
    return "KITTI clip, 30 scans" if log == DEFAULT_CLIP else log.name


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--log", "--clip", dest="clip", type=Path, default=DEFAULT_CLIP, help="a log with a LiDAR")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    if not args.clip.exists():
        print(f"no log at {args.clip}", file=sys.stderr)
        return 2
    warnings.simplefilter("ignore")
    with tempfile.TemporaryDirectory(prefix="bench-lidar-map-") as tmp_name:
        tmp = Path(tmp_name)
        traj = trajectory_stage(args.clip)  # the warm-up, and the trajectory the map is placed by
        traj.save(tmp / "trajectory")
        lidar_map_stage(args.clip, traj, tmp / "warm-up")
        traj_wall, traj_cpu = best_wall_and_cpu(lambda: trajectory_stage(args.clip), args.repeat)
        map_wall, map_cpu = best_wall_and_cpu(lambda: lidar_map_stage(args.clip, traj, tmp / "s"), args.repeat)
        bare_wall, bare_cpu = best_wall_and_cpu(
            lambda: lidar_map_stage(args.clip, traj, tmp / "bare", removal=False), args.repeat
        )
        peaks = {}
        for label, repeats, shift_y in (
            ("1x", 1, 0.0),
            ("2x same street", 2, 0.0),
            ("4x same street", 4, 0.0),
            ("8x same street", 8, 0.0),
            ("4x four streets", 4, 200.0),
        ):
            code = MEMORY_RUN.format(
                clip=str(args.clip), traj=str(tmp / "trajectory"), repeats=repeats, shift_y=shift_y
            )
            peaks[label] = peak_rss_mb_of(code)
    rows = [
        {"what": "trajectory stage (kiss-icp)", "wall s": traj_wall, "cpu s": traj_cpu, "ratio (cpu)": 1.0},
        {"what": "LiDAR map stage", "wall s": map_wall, "cpu s": map_cpu, "ratio (cpu)": map_cpu / traj_cpu},
        {
            "what": "LiDAR map stage, moving-object removal off",
            "wall s": bare_wall,
            "cpu s": bare_cpu,
            "ratio (cpu)": bare_cpu / traj_cpu,
        },
    ]
    report(
        f"LiDAR map stage time against the trajectory stage ({_name(args.clip)})",
        rows,
        f"goal: LiDAR map <= {GOAL_TIME_RATIO:.0%} of the trajectory stage; measured {map_cpu / traj_cpu:.2f} (cpu), "
        f"{map_wall / traj_wall:.2f} (wall)",
    )
    base = peaks["1x"]
    mem_rows = [{"log": k, "peak RSS MiB": v, "ratio to 1x": v / base} for k, v in peaks.items()]
    report(
        "LiDAR map peak memory, 4x longer log against 1x",
        mem_rows,
        f"goal: 4x same street <= {GOAL_MEMORY_RATIO}x of 1x; measured {peaks['4x same street'] / base:.2f}x; "
        f"8x against 4x (the filter's window full in both): {peaks['8x same street'] / peaks['4x same street']:.2f}x "
        f"(four streets, four times the map: {peaks['4x four streets'] / base:.2f}x of 1x)",
        headline={
            "mapkit": f"{map_cpu:.2f} s cpu",
            "baseline": f"{traj_cpu:.2f} s cpu (kiss-icp trajectory)",
            "ratio": f"{map_cpu / traj_cpu:.2f}",
        },
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
