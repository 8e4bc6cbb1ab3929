"""An outside tool reads the synthetic logs: kiss-icp's own command line on a session's LiDAR topic.

Runs kiss-icp's command line (``kiss_icp_pipeline``) on a session's log, the rosbag2 folder
``sessions/<session>/``: its rosbag dataloader (the ``rosbags`` library) reads ``/lidar/points``, and
kiss-icp deskews each scan with the per-point ``time`` field to the time of the scan's last point.
The script reads the poses it writes and compares them with the ground truth of the LiDAR frame at
the same instants: ATE (RMSE of positions) after a rigid alignment (Umeyama, no scale) and without
one (anchored at the first scan), and the drift in percent of the distance driven.

Given a bare ``.mcap`` (a session's log as one MCAP file, not a rosbag2 folder), kiss-icp uses its MCAP
dataloader instead, and kiss-icp 1.3.0 cannot read a PointCloud2 decoded by mcap-ros2-support (0.5
and 0.6 alike): its ``get_datatype_name`` looks for the PointField constants in ``vars(field)``,
which is empty for mcap_ros2's slotted message classes ("Unknown datatype code 7"; upstream PR
PRBonn/kiss-icp#498 is open). So for a bare ``.mcap`` the command line runs with that one function
replaced by a lookup of the datatype code as the PointField message defines it (``--no-patch``
shows the unpatched failure); nothing else of kiss-icp is changed. Folders need no patch.

    python bench/kiss_icp_on_synth.py [--dir DIR] [--preset tiny] [--session NAME]
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import report
from mapkit.core.geometry import interpolate_poses, invert_pose, umeyama
from mapkit.core.types import StreamKind
from mapkit.io.mcap_log import McapLog
from mapkit.synth import gt_poses, load_world, synthesize


def lidar_times(mcap: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(stamp_ns, last point time offset ns, base_from_lidar) of every sweep in a log."""
    log = McapLog(mcap)
    stamps, last = [], []
    for scan in log.records(StreamKind.LIDAR):
        stamps.append(scan.stamp_ns)
        last.append(int(round(float(np.max(scan.point_time_s)) * 1e9)))
    tf = {t.child_frame: t.parent_from_child for t in log.transforms()}
    log.close()
    return np.array(stamps, np.int64), np.array(last, np.int64), tf["lidar"]


# sensor_msgs/PointField datatype codes (INT8=1 ... FLOAT64=8) as kiss-icp names them
_PATCH = """
import sys
import kiss_icp.tools.point_cloud2 as pc2
_NAMES = {1: "int8", 2: "uint8", 3: "int16", 4: "uint16", 5: "int32", 6: "uint32", 7: "float32", 8: "float64"}
pc2.get_datatype_name = lambda field: _NAMES[int(field.datatype)]
from kiss_icp.tools.cmd import run
sys.argv = ["kiss_icp_pipeline"] + sys.argv[1:]
run()
"""


def run_kiss_icp(mcap: Path, work: Path, patch: bool = True) -> tuple[np.ndarray, float]:
    """kiss-icp's command line on a log (a rosbag2 folder, or a bare .mcap patched unless ``patch`` is False)."""
    env = dict(os.environ, kiss_icp_out_dir=str(work))
    patch = patch and not Path(mcap).is_dir()  # its rosbag dataloader reads folders unpatched
    cmd = (
        [sys.executable, "-c", _PATCH, str(mcap)]
        if patch
        else ["kiss_icp_pipeline", "--topic", "/lidar/points", str(mcap)]
    )
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"kiss_icp_pipeline failed ({proc.returncode}):\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}")
    found = sorted(work.glob("latest/*_poses.npy")) or sorted(work.glob("**/*_poses.npy"))
    if not found:
        raise SystemExit(f"kiss_icp_pipeline wrote no poses under {work}:\n{proc.stdout[-2000:]}")
    return np.load(found[0]), wall


def evaluate(out: Path, session: str, poses_kiss: np.ndarray, mcap: Path) -> dict:
    stamps, last_ns, base_from_lidar = lidar_times(mcap)
    if len(stamps) != len(poses_kiss):
        raise SystemExit(f"kiss-icp returned {len(poses_kiss)} poses for {len(stamps)} scans")
    gs, world_from_base = gt_poses(out, session)
    # kiss-icp deskews every scan to the instant of its last point: compare the poses there
    t_ref = stamps + last_ns
    wfb, mask = interpolate_poses(gs, world_from_base, t_ref)
    world_from_lidar = wfb @ base_from_lidar
    gt = world_from_lidar[:, :3, 3]
    k = np.flatnonzero(mask)
    est_anchored = (world_from_lidar[0] @ poses_kiss[k])[:, :3, 3] if mask[0] else None
    S = umeyama(poses_kiss[k, :3, 3], gt, with_scale=False)
    est = poses_kiss[k, :3, 3] @ S[:3, :3].T + S[:3, 3]
    dist = float(np.linalg.norm(np.diff(gt, axis=0), axis=1).sum())
    err = np.linalg.norm(est - gt, axis=1)
    row = {
        "session": session,
        "scans": int(len(k)),
        "distance_m": round(dist, 2),
        "ate_rmse_m": round(float(np.sqrt(np.mean(err**2))), 4),
        "ate_max_m": round(float(err.max()), 4),
    }
    if est_anchored is not None:
        e0 = np.linalg.norm(est_anchored - gt, axis=1)
        row["anchored_rmse_m"] = round(float(np.sqrt(np.mean(e0**2))), 4)
        row["final_drift_pct"] = round(100 * float(e0[-1]) / max(dist, 1e-9), 3)
    # relative pose error over 1 s (rotation in degrees)
    step = 10
    if len(k) > step:
        rel_gt = invert_pose(world_from_lidar[k[:-step]]) @ world_from_lidar[k[step:]]
        rel_est = invert_pose(poses_kiss[k[:-step]]) @ poses_kiss[k[step:]]
        d = invert_pose(rel_gt) @ rel_est
        row["rpe_1s_trans_m"] = round(float(np.sqrt(np.mean(np.sum(d[:, :3, 3] ** 2, axis=1)))), 4)
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "--dir", type=Path, help="a synthesized town (made with --preset into a temporary folder if omitted)"
    )
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--session", action="append", help="session name (repeatable; default: all)")
    ap.add_argument(
        "--no-patch",
        action="store_true",
        help=(
            "run kiss_icp_pipeline unpatched on bare .mcap logs (fails on kiss-icp 1.3.0; folders never need the patch)"
        ),
    )
    args = ap.parse_args(argv)
    if shutil.which("kiss_icp_pipeline") is None:
        raise SystemExit("kiss_icp_pipeline is not installed (pip install kiss-icp)")
    tmp = None
    out = args.dir
    if out is None or not (out / "world" / "manifest.json").is_file():
        if out is None:
            tmp = tempfile.TemporaryDirectory(prefix="mapkit-kiss-")
            out = Path(tmp.name) / "town"
        synthesize(preset=args.preset, out=out)
    world = load_world(out)
    names = args.session or [s["name"] for s in world.sessions]
    rows = []
    for name in names:
        mcap = out / world.session(name)["file"]
        with tempfile.TemporaryDirectory(prefix="kiss-out-") as work:
            poses, wall = run_kiss_icp(mcap, Path(work), patch=not args.no_patch)
        row = evaluate(out, name, poses, mcap)
        row["condition"] = world.session(name)["condition"]
        row["kiss_icp_wall_s"] = round(wall, 2)
        rows.append(row)
    report(
        "kiss-icp (its own CLI and rosbag dataloader) on synthetic LiDAR vs ground truth",
        rows,
        "ATE after a rigid (SE3) alignment; anchored = first scan at its true pose, no fit.",
    )
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
