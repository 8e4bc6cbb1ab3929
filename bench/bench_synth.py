"""Synthetic town: rendering speed, and the demo preset's time and peak memory.

1. Camera frames per second rendered together with their LiDAR sweep (the target: a 640x480
   camera and a 32-beam LiDAR, here the HDL-32E layout at 1024 azimuth steps; the demo's 64 x 512
   LiDAR casts the same number of rays) on the demo town, per condition, including JPEG encoding and
   building the PointCloud2 message; best of ``--repeat`` passes over ``--frames`` poses. The
   baseline in the same run is the bare open3d ray casting of the same rays (camera, sun shadows,
   LiDAR) with no shading: the ratio says what the shading costs on top. The goal is 5 frames/s.
2. ``synthesize(preset="demo")`` end to end in a fresh process: wall time and peak resident memory
   of the main process and of the largest worker (workers are spawned processes).
3. On that demo output, the naive thumbnail-matching figure (bench/naive_thumbnail_matching.py).

    python bench/bench_synth.py [--frames 12] [--repeat 2] [--skip-demo] [--demo-dir DIR]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import best_of, report


def render_speed(frames: int, repeat: int) -> list[dict]:
    import cv2
    import open3d as o3d

    from mapkit.core.threads import single_thread_blas
    from mapkit.core.types import LidarScan
    from mapkit.io import ros2
    from mapkit.synth.appearance import F32
    from mapkit.synth.config import load_config
    from mapkit.synth.render import Renderer
    from mapkit.synth.sensors import extrinsics
    from mapkit.synth.sessions import plan_sessions, session_parked_cars
    from mapkit.synth.world import build_town

    cfg = load_config(
        "demo", overrides={"lidar": {"beams": 32, "vertical_fov_deg": [-30.67, 10.67], "azimuth_steps": 1024}}
    )
    rows = []
    with single_thread_blas():
        town = build_town(cfg)
        plans = plan_sessions(cfg, town)
        ex = extrinsics(cfg)
        picks = {}
        for p in plans:  # one session per condition kind
            picks.setdefault(p.conditions.label, p)
        for label, plan in picks.items():
            r = Renderer(town, session_parked_cars(town, plan.seed), cfg.camera, cfg.lidar)
            st = np.linspace(plan.drive.stamps_ns[0], plan.drive.stamps_ns[-1] - 2 * 10**8, frames).astype(np.int64)
            wfb = plan.drive.poses_at(st)
            col = [s + np.round(r.lidar_col_time_s * 1e9).astype(np.int64) for s in st]
            wfl = [plan.drive.poses_at(c) @ ex["lidar"] for c in col]
            wfc = wfb @ ex["camera_front"]

            def full(r=r, plan=plan, st=st, wfb=wfb, wfl=wfl, wfc=wfc):
                for i in range(frames):
                    f = r.render_camera(wfc[i], plan.conditions, np.random.default_rng(i), wfb[i])
                    cv2.imencode(".jpg", f.rgb[..., ::-1])
                    sw = r.scan_lidar(wfl[i], np.random.default_rng(i))
                    ros2.lidar_to_msg(LidarScan(int(st[i]), "lidar", sw.points_xyz, sw.intensity, sw.time_s, sw.ring))

            def bare(r=r, plan=plan, wfl=wfl, wfc=wfc):
                for i in range(frames):
                    d = r.rays_cam @ wfc[i][:3, :3].T.astype(F32)
                    o = wfc[i][:3, 3].astype(F32)
                    out = r.cast(np.broadcast_to(o, d.shape), d)
                    hit = np.isfinite(out["t_hit"])
                    if plan.conditions.sun_rgb.max() > 0.01:
                        p = o + d[hit] * out["t_hit"][hit, None]
                        rays = np.hstack([p, np.broadcast_to(plan.conditions.sun_dir_enu, p.shape)]).astype(F32)
                        r.scene.test_occlusions(o3d.core.Tensor(rays), nthreads=r.nthreads)
                    R = wfl[i][:, :3, :3]
                    dl = np.matmul(r.lidar_dirs, np.swapaxes(R, 1, 2).astype(F32)).reshape(-1, 3)
                    r.cast(np.repeat(wfl[i][:, :3, 3], r.lidar_dirs.shape[1], axis=0).astype(F32), dl)

            full()  # warm up
            t_full = best_of(full, repeat)
            t_bare = best_of(bare, repeat)
            rows.append(
                {
                    "condition": label,
                    "session": plan.name,
                    "frames": frames,
                    "fps_camera_plus_lidar": round(frames / t_full, 2),
                    "ms_per_frame": round(1000 * t_full / frames, 1),
                    "fps_bare_ray_casts": round(frames / t_bare, 2),
                    "shading_cost_ratio": round(t_full / t_bare, 2),
                }
            )
    return rows


_DEMO = """
import json, resource, sys, time
from pathlib import Path
from mapkit.synth import synthesize
t0 = time.perf_counter()
out = synthesize(preset="demo", out=Path(sys.argv[1]), overwrite=True, progress=False)
wall = time.perf_counter() - t0
print("DEMO_JSON " + json.dumps({"wall_s": wall,
      "peak_rss_main_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
      "peak_rss_largest_worker_mb": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0}))
"""


def run_demo(out: Path) -> dict:
    proc = subprocess.run([sys.executable, "-c", _DEMO, str(out)], capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"the demo preset failed:\n{proc.stderr[-3000:]}")
    line = next(ln for ln in proc.stdout.splitlines() if ln.startswith("DEMO_JSON "))
    info = json.loads(line.split(" ", 1)[1])
    metrics = json.loads((out / "metrics.json").read_text())
    info["camera_frames"] = metrics["rendered"]["camera_frames"]
    info["lidar_scans"] = metrics["rendered"]["lidar_scans"]
    info["sessions"] = metrics["rendered"]["sessions"]
    info["workers"] = json.loads(json.dumps(metrics)).get("workers", None)
    return info


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--skip-demo", action="store_true", help="only the rendering speed")
    ap.add_argument("--demo-dir", type=Path, help="where to write the demo (default: a temporary folder)")
    args = ap.parse_args(argv)

    rows = render_speed(args.frames, args.repeat)
    mean_fps = float(np.mean([r["fps_camera_plus_lidar"] for r in rows]))
    report(
        "Synthetic town: camera frames rendered per second with their LiDAR sweep (640x480, 32 x 1024 rays)",
        rows,
        f"mean over conditions: {mean_fps:.2f} frames/s (goal: 5); ratio = full pipeline / bare ray casts",
    )
    if args.skip_demo:
        return 0
    tmp = None
    out = args.demo_dir
    if out is None:
        tmp = tempfile.TemporaryDirectory(prefix="mapkit-demo-")
        out = Path(tmp.name) / "demo"
    t0 = time.perf_counter()
    info = run_demo(out)
    info["wall_s"] = round(info["wall_s"], 1)
    info["peak_rss_main_mb"] = round(info["peak_rss_main_mb"], 1)
    info["peak_rss_largest_worker_mb"] = round(info["peak_rss_largest_worker_mb"], 1)
    info.pop("workers", None)
    info["throughput_frames_per_s"] = round(info["camera_frames"] / info["wall_s"], 2)
    report(
        "Synthetic town: the demo preset end to end (fresh process)",
        [info],
        f"{time.perf_counter() - t0:.0f} s including interpreter start; workers are spawned, so memory is per process",
    )
    from bench.naive_thumbnail_matching import evaluate

    rows, overall = evaluate(out)
    report(
        "Naive thumbnail matching on the demo (32x24 grayscale, within 25 m)",
        rows,
        f"overall: {overall:.3f} of the queries found; the goal is under 0.5",
    )
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
