"""How far a drive's relative motion between consecutive images lies from the truth: the odometry noise behind the
6-DoF pose graph's defaults (``SixDofConfig.odometry_sigma_*``, docs/guide/localize.md).

For each named session of a workspace (the training drives: the accuracy page scores the test drives) the motion
between consecutive images of its image table (the build's trajectory, placed in the aligned map) is compared with
the same motion of the true camera poses. Printed per session: the images, the median step length, and the rms and
95th percentile of the step's position error (m) and rotation error (deg), for steps of 1, 2 and 4 images:

    python3 bench/odometry_noise.py runs/main/workspace --truth runs/main/town --session train-sunny \\
        --session train-overcast --session train-foggy
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's mapkit, whatever is installed

from mapkit.core.geometry import invert_pose, rotation_angle_rad  # noqa: E402 (after sys.path points at this checkout)
from mapkit.core.workspace import Workspace  # noqa: E402 (after sys.path points at this checkout)
from mapkit.evaluation.truth import truth_camera_poses_at  # noqa: E402 (after sys.path points at this checkout)
from mapkit.retrieval.vlad_bundle import read_session_images  # noqa: E402 (after sys.path points at this checkout)


def step_errors(estimated: np.ndarray, truth: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per pair of poses k images apart: (position error m, rotation error deg, true step length m) of the
    estimated relative motion against the true one."""
    m, deg, length = [], [], []
    for a, b, ta, tb in zip(estimated[:-k], estimated[k:], truth[:-k], truth[k:], strict=True):
        est, true = invert_pose(a) @ b, invert_pose(ta) @ tb
        err = invert_pose(true) @ est
        m.append(np.linalg.norm(err[:3, 3]))
        deg.append(np.degrees(rotation_angle_rad(err[:3, :3])))
        length.append(np.linalg.norm(true[:3, 3]))
    return np.array(m), np.array(deg), np.array(length)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workspace", type=Path)
    ap.add_argument("--truth", type=Path, required=True, help="the synthetic town the workspace was built from")
    ap.add_argument("--session", action="append", required=True, help="a session to measure (repeat)")
    args = ap.parse_args()
    ws = Workspace(args.workspace)
    frame = ws.require_frame()
    print("| session | images | steps of | median step m | position rms m | p95 m | rotation rms deg | p95 deg |")
    print("|---|---|---|---|---|---|---|---|")
    for name in args.session:
        imgs = read_session_images(ws.root, name)
        truth, ok = truth_camera_poses_at(args.truth, name, frame, imgs.table["stamp_ns"])
        est, truth = imgs.world_from_cam[ok], truth[ok]
        for k in (1, 2, 4):
            m, deg, length = step_errors(est, truth, k)
            print(
                f"| {name} | {len(est)} | {k} | {np.median(length):.2f} | {np.sqrt(np.mean(m**2)):.4f} | "
                f"{np.percentile(m, 95):.4f} | {np.sqrt(np.mean(deg**2)):.4f} | {np.percentile(deg, 95):.4f} |"
            )


if __name__ == "__main__":
    main()
