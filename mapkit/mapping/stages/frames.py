"""The mapping camera of a session and its frames with poses, which the map (stage 3) and the image
database (stage 4) read."""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mapkit.core.config import TopicConfig, resolve_topics
from mapkit.core.errors import InputError, InputWarning
from mapkit.core.geometry import interpolate_poses
from mapkit.core.types import CameraFrame, CameraInfo, StreamKind
from mapkit.io.base import DriveLog
from mapkit.mapping.trajectory import Trajectory


@dataclass(frozen=True)
class MappingCamera:
    """The camera a session is mapped with."""

    name: str
    image_topics: list[str]  # the topics its frames are read from
    info: CameraInfo


def choose_camera(log: DriveLog, camera: str | None, topics: TopicConfig, log_path: Path) -> MappingCamera:
    """The mapping camera and the topics its frames are read from (``topics.images``, every image stream
    if unset). The camera is ``camera``, else the first one (by name) with intrinsics; with
    ``topics.images`` set, the first of those that the named topics carry, so that naming a topic is
    enough to map from it. An :class:`InputError` (naming ``log_path``) when there is none."""
    image_topics = resolve_topics(log, topics).get(StreamKind.IMAGE, [])
    infos = log.camera_infos()
    if not image_topics:
        raise InputError(log_path, "has no image stream to map from", field="topics.images")
    if not infos:
        raise InputError(
            log_path,
            "has no camera intrinsics (CameraInfo / calibration); a map cannot be built",
            field="camera_info",
        )
    name = camera
    if name is None:
        on_topics = _cameras_on(log, image_topics) if topics.images is not None else set(infos)
        name = next((c for c in sorted(infos) if c in on_topics), sorted(infos)[0])
    if name not in infos:
        raise InputError(
            log_path,
            f"camera {name!r} has no intrinsics; cameras with intrinsics: {sorted(infos)}",
            field="camera",
        )
    return MappingCamera(name, image_topics, infos[name])


def _cameras_on(log: DriveLog, image_topics: list[str]) -> set[str]:
    """The cameras of the first frame of each topic (a frame's pixels are not decoded to read it)."""
    cameras = set()
    for topic in image_topics:
        frames = log.records(StreamKind.IMAGE, topic=topic)
        try:
            first = next(frames, None)
        finally:
            frames.close()
        if first is not None:
            cameras.add(first.camera)
    return cameras


class PosedFrames:
    """(frame index, CameraFrame, enu_from_camera) of the mapping camera on its image topics, inside
    ``trajectory``, its pose interpolated there and mounted by ``base_from_camera``; with ``decode``,
    decoded first.

    A frame whose image cannot be decoded (a corrupt PNG or JPEG: the reader's ``InputError`` names the
    file) is skipped with a warning: it costs that frame, not the build. Without ``decode`` the caller
    decodes the frames it keeps through :meth:`decodes`. Each iteration reads the log again."""

    def __init__(
        self,
        log: DriveLog,
        camera: MappingCamera,
        trajectory: Trajectory,
        base_from_camera: np.ndarray,
        decode: bool = True,
    ):
        self.log = log
        self.camera = camera
        self.trajectory = trajectory
        self.base_from_camera = base_from_camera
        self.decode = decode
        self.undecodable = 0  # frames whose image did not decode, in the current pass over the log

    def __iter__(self) -> Iterator[tuple[int, CameraFrame, np.ndarray]]:
        name = self.camera.name
        traj = self.trajectory
        index = 0
        self.undecodable = 0
        for msg in self.log.messages(topics=self.camera.image_topics):
            frame = msg.record
            assert isinstance(frame, CameraFrame)  # the records of image topics
            if frame.camera != name:
                continue
            poses, ok = interpolate_poses(traj.stamps_ns, traj.world_from_base, np.array([frame.stamp_ns], np.int64))
            if ok[0] and (not self.decode or self.decodes(frame, index)):
                yield index, frame, poses[0] @ self.base_from_camera
            index += 1
        if self.undecodable > 5:
            warnings.warn(
                f"{self.log.path}: {self.undecodable} frames of {name} could not be decoded and were skipped "
                "(the first 5 are named above)",
                InputWarning,
                stacklevel=2,
            )

    def decodes(self, frame: CameraFrame, index: int) -> bool:
        """Whether the frame's image decodes (it is then cached on the frame); a warning names the
        first five that do not."""
        try:
            _ = frame.image  # decodes the image and caches it on the frame
        except InputError as exc:
            self.undecodable += 1
            if self.undecodable <= 5:
                warnings.warn(f"{exc}; frame {index} of {frame.camera} skipped", InputWarning, stacklevel=3)
            return False
        return True
