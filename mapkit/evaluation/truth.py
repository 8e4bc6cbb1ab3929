"""Ground truth for evaluations: the synthetic town's, or a trajectory from a file or a log.

The town's truth lives in the town's ENU frame (``TOWN/world/origin.json``); every transform to a
workspace goes exactly through ECEF. Any other truth (:func:`read_truth`: a TUM or KITTI file, a
pose topic of a log) is a :class:`TruthTrajectory` in a frame of its own, which evaluations align
to the estimate before measuring; :func:`associate_truth` pairs it with the estimate's stamps.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mapkit.core.errors import InputError, MapkitError
from mapkit.core.geodesy import LocalFrame
from mapkit.core.geometry import associate, interpolate_poses
from mapkit.core.types import StreamKind
from mapkit.io import guess_format, open_log
from mapkit.io.folder import read_stamp_lines
from mapkit.io.trajectory import read_kitti_poses, read_tum, seconds_to_ns
from mapkit.mapping.trajectory import trajectory_from_poses
from mapkit.synth import camera_poses, gt_poses, parked_cars_path, town_frame

#: what ``--truth`` may be, for the error that names anything else
TRUTH_KINDS = (
    "a TUM trajectory file (8 numbers a line: stamp tx ty tz qx qy qz qw, stamp in seconds), "
    "a KITTI poses file (12 numbers a line, with times.txt beside it or --truth-times), "
    "a log with a pose topic (LOG::/topic or --truth-topic), or a synthetic town folder"
)


@dataclass
class TruthTrajectory:
    """A true trajectory in a frame of its own: ``world_from_body[i]`` at ``stamps_ns[i]``.

    ``kind`` is ``tum``, ``kitti`` or ``topic``; ``stamps`` says where the stamps came from, for
    the report.
    """

    stamps_ns: np.ndarray
    world_from_body: np.ndarray
    kind: str
    source: str
    frame: str
    body_frame: str
    stamps: str

    def __len__(self) -> int:
        return len(self.stamps_ns)


def is_town(truth: str | Path) -> bool:
    """``truth`` is a synthesized town folder (it has the town's ENU frame)."""
    try:
        town_frame(truth)
    except MapkitError:
        return False
    return True


def split_log_topic(truth: str | Path, topic: str | None) -> tuple[Path, str | None]:
    """``LOG::/topic`` to (LOG, /topic); a path without ``::`` keeps ``topic`` (both given is an error)."""
    text = str(truth)
    if "::" not in text or Path(text).exists():
        return Path(text), topic
    log, _, inline = text.rpartition("::")
    if topic is not None and topic != inline:
        raise InputError(
            log, f"two truth topics given: {inline!r} (in --truth) and {topic!r} (--truth-topic)", field="topic"
        )
    return Path(log), inline


def read_truth(
    truth: str | Path,
    *,
    topic: str | None = None,
    times: Path | None = None,
    time_offset_s: float = 0.0,
    body_frame: str = "base_link",
) -> TruthTrajectory:
    """A true trajectory from a TUM file, a KITTI poses file, or a pose topic of a log.

    A pose topic's poses are moved to ``body_frame`` (the estimate's) through the log's extrinsics
    when it has them. ``time_offset_s`` is added to every truth stamp (a truth on another clock, or
    KITTI ``times.txt`` relative to the drive's start). Anything else is one ``InputError`` naming
    the path and what was expected.
    """
    path, topic = split_log_topic(truth, topic)
    if not path.exists():
        raise InputError(path, f"no such file or folder; --truth takes {TRUTH_KINDS}")
    if topic is not None or path.is_dir() or _is_log(path):
        if times is not None:
            raise InputError(times, "--truth-times is for a KITTI poses file, and the truth is a log")
        t = _read_topic(path, topic, body_frame)
    else:
        ncols = _columns(path)
        if ncols == 8:
            if times is not None:
                raise InputError(
                    times, f"--truth-times is for a KITTI poses file, and {path} is a TUM file (it has its own stamps)"
                )
            stamps, poses = read_tum(path)
            t = TruthTrajectory(
                stamps,
                poses,
                "tum",
                str(path),
                "its own (TUM file)",
                "not stated by the file",
                "the TUM file's first column (s)",
            )
        elif ncols == 12:
            t = _read_kitti(path, times)
        else:
            raise InputError(path, f"the first pose line has {ncols} values; expected {TRUTH_KINDS}", field="line 1")
    if time_offset_s:
        t.stamps_ns = t.stamps_ns + int(round(time_offset_s * 1e9))
        t.stamps += f", shifted by {time_offset_s:+.6f} s (--truth-time-offset)"
    return t


def _is_log(path: Path) -> bool:
    """A file that a log reader takes (an MCAP file, or any other format ``guess_format`` knows)."""
    try:
        guess_format(path)
    except InputError:
        return False
    return True


def _columns(path: Path) -> int:
    """Values on the first line of a text file that is not blank or a comment."""
    try:
        with open(path, encoding="utf-8") as f:
            for line in f:
                s = line.strip()
                if s and not s.startswith("#"):
                    return len(s.replace(",", " ").split())
    except UnicodeDecodeError:
        raise InputError(path, f"is not a text file; --truth takes {TRUTH_KINDS}") from None
    raise InputError(path, "holds no poses")


def _read_kitti(path: Path, times: Path | None) -> TruthTrajectory:
    """KITTI poses with the stamps of ``times`` or of ``times.txt`` beside them, line by line."""
    poses = read_kitti_poses(path)
    times = times if times is not None else path.with_name("times.txt")
    if not times.is_file():
        raise InputError(
            path,
            f"KITTI poses carry no stamps: expected {times.name} beside them (one time in seconds a line, "
            "as KITTI odometry's) or --truth-times FILE",
        )
    stamps = read_stamp_lines(times, seconds_to_ns, "times")
    if len(stamps) != len(poses):
        raise InputError(times, f"has {len(stamps)} times for the {len(poses)} poses of {path}")
    if np.any(np.diff(stamps) <= 0):
        i = int(np.nonzero(np.diff(stamps) <= 0)[0][0]) + 2
        raise InputError(times, f"times do not increase at line {i}", field=f"line {i}")
    return TruthTrajectory(
        stamps,
        poses,
        "kitti",
        str(path),
        "its own (KITTI poses: the first pose's body frame)",
        "not stated by the file",
        f"{times} (line i is pose i)",
    )


def _read_topic(path: Path, topic: str | None, body_frame: str) -> TruthTrajectory:
    try:
        guess_format(path)
    except InputError as exc:
        raise InputError(path, f"is not a log mapkit reads ({exc.what}); --truth takes {TRUTH_KINDS}") from None
    with open_log(path) as log:
        pose_topics = log.topics_of(StreamKind.POSE)
        if topic is None:
            if len(pose_topics) != 1:
                raise InputError(
                    path,
                    f"has {len(pose_topics)} pose topics ({', '.join(pose_topics) or 'none'}); name the true one "
                    "with LOG::/topic or --truth-topic",
                    field="topic",
                )
            topic = pose_topics[0]
        if topic not in pose_topics:
            raise InputError(
                path, f"has no pose topic {topic!r}; its pose topics: {', '.join(pose_topics) or 'none'}", field="topic"
            )
        frame = next((p.parent_frame for p in log.records(StreamKind.POSE, topic=topic)), "")
        traj = trajectory_from_poses(log, topic, body_frame)
    return TruthTrajectory(
        traj.stamps_ns,
        traj.world_from_base,
        "topic",
        f"{path}::{topic}",
        f"its own ({frame or 'unnamed'}, the pose messages' parent frame)",
        traj.body_frame,
        "the pose messages' header stamps",
    )


@dataclass
class Association:
    """Estimated poses paired with truth: ``est_index`` into the estimate, ``truth_poses`` at them."""

    est_index: np.ndarray
    truth_poses: np.ndarray
    interpolated: int
    nearest: int
    nearest_dt_s: np.ndarray  # |t_est - t_truth| of the nearest-stamp pairs


def associate_truth(
    est_stamps_ns: np.ndarray, truth_stamps_ns: np.ndarray, truth_poses: np.ndarray, max_dt_ns: int
) -> Association:
    """Truth at the estimate's stamps: interpolated (linear position, slerp rotation) where truth
    poses lie within ``max_dt_ns`` on both sides of the stamp (the truth is dense there), else the
    nearest truth pose within ``max_dt_ns`` (an equal stamp included), one-to-one; estimated poses
    with neither are left out.

    Interpolation only between close neighbours keeps a sparse truth from being bridged over gaps;
    the nearest pose, not an interpolated one, keeps a constant clock offset between two streams
    of the same rate from blending neighbouring poses.
    """
    est = np.asarray(est_stamps_ns, np.int64)
    ts = np.asarray(truth_stamps_ns, np.int64)
    right = np.clip(np.searchsorted(ts, est, side="left"), 0, len(ts) - 1)
    left = np.clip(np.searchsorted(ts, est, side="right") - 1, 0, len(ts) - 1)
    # an equal stamp is a nearest pair (dt 0), not an interpolation
    dense = (ts[left] < est) & (ts[right] > est) & (est - ts[left] <= max_dt_ns) & (ts[right] - est <= max_dt_ns)
    i_interp = np.nonzero(dense)[0]
    g_interp = interpolate_poses(ts, truth_poses, est[i_interp])[0] if len(i_interp) else np.zeros((0, 4, 4))
    rest = np.nonzero(~dense)[0]
    ia, ib = associate(est[rest], ts, max_dt_ns)
    i_near = rest[ia]
    index = np.concatenate([i_interp, i_near])
    poses = np.concatenate([g_interp, np.asarray(truth_poses)[ib]])
    order = np.argsort(index, kind="stable")
    dt = np.abs(est[i_near] - ts[ib]) * 1e-9
    return Association(index[order], poses[order], len(i_interp), len(i_near), dt)


def ws_from_town(truth: Path, ws_frame: LocalFrame) -> np.ndarray:
    """The exact rigid transform from a synthetic town's ENU frame to a workspace's (via ECEF)."""

    return town_frame(truth).to_frame(ws_frame)


def town_sessions(truth: Path | None) -> dict[str, dict]:
    """The town manifest's entry of every session (role, condition, ...), by name; {} without one."""
    if truth is None:
        return {}
    p = Path(truth) / "world" / "manifest.json"
    if not p.is_file():
        return {}
    return {s["name"]: s for s in json.loads(p.read_text()).get("sessions", [])}


def truth_camera_poses(truth: Path, name: str, ws_frame: LocalFrame | None) -> tuple[np.ndarray, np.ndarray]:
    """(stamps_ns, world_from_camera) of a town session's true camera, in the workspace's frame
    (the town's own when ``ws_frame`` is None)."""

    stamps, world_from_cam = camera_poses(truth, name)
    if ws_frame is not None:
        world_from_cam = ws_from_town(truth, ws_frame) @ world_from_cam
    return np.asarray(stamps, np.int64), world_from_cam


def session_truth(truth: Path, name: str):
    return gt_poses(truth, name)


def session_truth_mesh(town_mesh, truth: Path, name: str, town_to_ws: np.ndarray):
    """The surfaces session ``name`` saw: a copy of the town's mesh (already in the workspace frame)
    with the cars parked during that session, if the town has them."""
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh(town_mesh)

    cars = parked_cars_path(truth, name)
    if cars.is_file():
        # open3d's stub says os.PathLike; its binding takes a str path as well
        car_mesh = o3d.io.read_triangle_mesh(str(cars))  # type: ignore[arg-type]
        car_mesh.transform(town_to_ws)
        mesh += car_mesh
    return mesh


def error_transforms(est_stamps, est_poses, gt_stamps, gt_ws) -> tuple[np.ndarray, np.ndarray]:
    """Per estimated pose (inside the truth's time span): position and E = T_est T_gt^-1, the
    transform that takes a true point to where this session's map puts it."""
    gt, ok = interpolate_poses(gt_stamps, gt_ws, est_stamps)
    est = est_poses[ok]
    E = est @ np.linalg.inv(gt)
    return est[:, :3, 3], E


def truth_camera_poses_at(truth: Path, name: str, ws_frame: LocalFrame | None, stamps_ns: np.ndarray):
    """True camera poses (world_from_camera, workspace ENU) at ``stamps_ns`` and their validity mask."""
    return interpolate_poses(*truth_camera_poses(truth, name, ws_frame), stamps_ns)
