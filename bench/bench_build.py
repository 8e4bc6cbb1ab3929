"""Map construction speed: kiss-icp inside mapkit vs kiss-icp alone, and the build's real-time factor.

- kiss-icp overhead (goal <= 1.10x): mapkit's trajectory stage on a session's LiDAR stream,
  reading and decoding included, against kiss-icp's ``KissICP.register_frame`` over the same
  scans already in memory, plus bare ``mcap`` decoding of them measured on its own.
- real-time factor (goal >= 1): the session's duration over the wall time of ``build`` (all four
  stages) on one session of the demo preset.

    python bench/bench_build.py --town /tmp/synth-demo --session train-cloudy
    python bench/bench_build.py            # makes a one-session 640x480 town first (about a minute)
    python bench/bench_build.py --quick    # the same on a 48 m town
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.common import report  # noqa: E402 (after sys.path points at this checkout)


def _make_town(out: Path, length_m: float = 150.0) -> Path:
    from mapkit.synth import synthesize

    overrides = {
        "camera": {"width": 640, "height": 480},
        "lidar": {"beams": 64, "vertical_fov_deg": [-24.9, 2.0], "azimuth_steps": 512},
        "sessions": [
            {
                "name": "bench",
                "role": "train",
                "date": "2014-06-26",
                "time": "11:00",
                "weather": "overcast",
                "length_m": length_m,
                "speed_mps": 8.0,
                "lane_offset_m": 0.0,
            }
        ],
    }
    return synthesize(preset="tiny", out=out, overrides=overrides, progress=True)


def bare_kiss_icp(
    scans: list[tuple[np.ndarray, np.ndarray]], cfg, threads: int | None = None
) -> tuple[float, np.ndarray]:
    """Seconds of kiss-icp alone over ``scans`` and the poses it gave (``threads``: its
    registration.max_num_threads, 0 = all cores; None = mapkit's config)."""
    from kiss_icp.config import KISSConfig
    from kiss_icp.kiss_icp import KissICP

    k = KISSConfig()
    o = cfg.kiss_icp
    k.data.max_range, k.data.min_range, k.data.deskew = o.max_range_m, o.min_range_m, o.deskew
    k.mapping.voxel_size = o.voxel_size_m or o.max_range_m / 100.0
    k.registration.max_num_threads = o.max_threads if threads is None else threads
    odom = KissICP(k)
    poses = []
    t0 = time.perf_counter()
    for pts, t in scans:
        odom.register_frame(pts, t)
        poses.append(odom.last_pose.copy())
    return time.perf_counter() - t0, np.stack(poses)


def bare_mcap_decode(path: Path, topic: str) -> float:
    """Seconds of bare ``mcap`` decoding of one topic of a log (a .mcap file or a rosbag2 folder's files)."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    from mapkit.io.mcap_log import rosbag2_mcap_files

    files = rosbag2_mcap_files(path) if path.is_dir() else [path]
    t0 = time.perf_counter()
    for file in files:
        with open(file, "rb") as f:
            for _ in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages(topics=[topic]):
                pass
    return time.perf_counter() - t0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--town", type=Path, help="a synthetic town folder (default: make a one-session town)")
    ap.add_argument("--session", default=None, help="session name (default: the first)")
    ap.add_argument(
        "--quick", action="store_true", help="smoke run: a 48 m town (6 s of driving) when no --town is given"
    )
    args = ap.parse_args(argv)

    from mapkit.io.mcap_log import McapLog
    from mapkit.mapping.build import BuildConfig, build
    from mapkit.mapping.trajectory import trajectory_from_lidar
    from mapkit.synth import session_logs

    with tempfile.TemporaryDirectory(prefix="mapkit-bench-build-") as tmp:
        tmp = Path(tmp)
        town = args.town or _make_town(tmp / "town", 48.0 if args.quick else 150.0)
        logs = session_logs(town)
        log_path = next(p for p in logs if args.session is None or p.stem == args.session)
        cfg = BuildConfig()
        with McapLog(log_path) as log:
            topic = log.topics_of("lidar")[0]
            scans = [(s.points_xyz.astype(np.float64), s.point_time_s.astype(np.float64)) for s in log.records("lidar")]
            duration_s = (max(s for _, s in log.stamps()) - min(s for _, s in log.stamps())) * 1e-9
        bare = [bare_kiss_icp(scans, cfg.trajectory) for _ in range(2)]
        t_bare_icp = min(t for t, _ in bare)
        # two identical runs: kiss-icp is not bitwise repeatable (its parallel reductions sum in a
        # varying order); and one registration thread against all of them
        repeat_diff = float(np.abs(bare[0][1][:, :3, 3] - bare[1][1][:, :3, 3]).max())
        t_one_thread = min(bare_kiss_icp(scans, cfg.trajectory, threads=1)[0] for _ in range(2))
        t_all_threads = min(bare_kiss_icp(scans, cfg.trajectory, threads=0)[0] for _ in range(2))
        t_bare_read = min(bare_mcap_decode(log_path, topic) for _ in range(2))
        t_mapkit = []
        for _ in range(2):
            with McapLog(log_path) as log:
                t0 = time.perf_counter()
                trajectory_from_lidar(log, topic, cfg.trajectory)
                t_mapkit.append(time.perf_counter() - t0)
        t_mapkit = min(t_mapkit)
        t0 = time.perf_counter()
        build([log_path], tmp / "ws", progress=False)
        t_build = time.perf_counter() - t0
        import json

        stages = json.loads((tmp / "ws" / "metrics.json").read_text())["sessions"][log_path.stem]["stages"]
    rows = [
        {"what": "kiss-icp alone (scans in memory)", "seconds": t_bare_icp, "scans": len(scans), "ratio": 1.0},
        {
            "what": "bare mcap decode of the scans",
            "seconds": t_bare_read,
            "scans": len(scans),
            "ratio": t_bare_read / t_bare_icp,
        },
        {
            "what": "mapkit trajectory stage (reads + kiss-icp)",
            "seconds": t_mapkit,
            "scans": len(scans),
            "ratio": t_mapkit / t_bare_icp,
        },
        {
            "what": "mapkit vs kiss-icp + bare decode",
            "seconds": t_mapkit,
            "scans": len(scans),
            "ratio": t_mapkit / (t_bare_icp + t_bare_read),
        },
    ]
    report(
        "kiss-icp inside mapkit",
        rows,
        f"Goal: mapkit <= 1.10x kiss-icp by itself. Including reading, {t_mapkit / t_bare_icp:.3f}x of kiss-icp on "
        f"in-memory scans; {t_mapkit / (t_bare_icp + t_bare_read):.3f}x of kiss-icp plus bare mcap decoding.",
    )
    report(
        "kiss-icp threads and repeatability",
        [
            {"what": "registration threads: 1", "ms_per_sweep": 1e3 * t_one_thread / len(scans), "ratio": 1.0},
            {
                "what": "registration threads: all",
                "ms_per_sweep": 1e3 * t_all_threads / len(scans),
                "ratio": t_all_threads / t_one_thread,
            },
        ],
        f"Two identical kiss-icp runs over these {len(scans)} sweeps differ by up to {repeat_diff:.3g} m in position.",
    )
    rows2 = [{"stage": k, "seconds": v.get("wall_s_this_run", float("nan"))} for k, v in stages.items()]
    rows2.append({"stage": "build (all)", "seconds": t_build})
    report(
        "build real-time factor",
        rows2,
        f"Session {log_path.stem}: {duration_s:.1f} s of driving built in {t_build:.1f} s: real-time factor "
        f"{duration_s / t_build:.2f} (goal >= 1).",
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
