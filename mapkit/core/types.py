"""The data model of a drive (session): sensor records with integer-nanosecond timestamps.

Pure numpy. Every record carries ``stamp_ns`` (sensor time, integer nanoseconds since the Unix
epoch or since the start of the log) and the name of the sensor frame it belongs to. Names state
frames and units: ``parent_from_child`` maps points of the child frame into the parent frame,
``orientation_quat_wxyz`` is scalar-first, ``point_time_s`` is seconds relative to ``stamp_ns``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from enum import Enum

import numpy as np


class StreamKind(str, Enum):
    IMAGE = "image"
    CAMERA_INFO = "camera_info"
    GPS = "gps"
    LIDAR = "lidar"
    IMU = "imu"
    POSE = "pose"
    TF = "tf"
    OTHER = "other"


@dataclass(frozen=True)
class CameraInfo:
    """Pinhole intrinsics of one camera (ROS ``CameraInfo`` semantics)."""

    camera: str
    width: int
    height: int
    K: np.ndarray  # 3x3
    distortion_model: str = "plumb_bob"
    D: np.ndarray = field(default_factory=lambda: np.zeros(0))
    stamp_ns: int = 0

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, CameraInfo):
            return NotImplemented
        return (
            self.camera == other.camera
            and self.width == other.width
            and self.height == other.height
            and self.distortion_model == other.distortion_model
            and np.allclose(self.K, other.K)
            and np.allclose(self.D, other.D)
        )


class CameraFrame:
    """One image. Pixels are decoded lazily, so scanning a log never pays for decoding.

    ``encoding`` follows ROS: ``mono8``, ``mono16``, ``rgb8`` or ``bgr8`` once decoded; a compressed
    frame keeps ``format`` (``jpeg``/``png``) and decodes on first access of ``image``.
    """

    __slots__ = ("stamp_ns", "camera", "_image", "_loader", "encoding", "source")

    def __init__(
        self,
        stamp_ns: int,
        camera: str,
        image: np.ndarray | None = None,
        *,
        loader: Callable[[], np.ndarray] | None = None,
        encoding: str = "mono8",
        source: str | None = None,
    ):
        if image is None and loader is None:
            raise ValueError("CameraFrame needs an image or a loader")
        self.stamp_ns = int(stamp_ns)
        self.camera = camera
        self._image = image
        self._loader = loader
        self.encoding = encoding
        self.source = source  # file path or "topic#index", for messages about this frame

    @property
    def image(self) -> np.ndarray:
        if self._image is None:
            assert self._loader is not None
            self._image = self._loader()
        return self._image

    @property
    def is_loaded(self) -> bool:
        return self._image is not None

    def gray(self) -> np.ndarray:
        """The image as one channel (uint8 or uint16), converting colour by ITU-R BT.601 luma."""
        img = self.image
        if img.ndim == 2:
            return img
        weights = (0.299, 0.587, 0.114) if self.encoding == "rgb8" else (0.114, 0.587, 0.299)
        return np.clip(img[..., :3].astype(np.float32) @ np.array(weights, np.float32) + 0.5, 0, 255).astype(np.uint8)

    def __repr__(self) -> str:
        shape = self._image.shape if self._image is not None else "lazy"
        return f"CameraFrame(stamp_ns={self.stamp_ns}, camera={self.camera!r}, {self.encoding}, {shape})"


class GpsStatus(int, Enum):
    """``sensor_msgs/NavSatStatus`` values."""

    NO_FIX = -1
    FIX = 0
    SBAS_FIX = 1
    GBAS_FIX = 2


@dataclass
class GpsFix:
    """A GNSS fix in WGS84. ``covariance_enu_m2`` is 3x3 (east, north, up) or None if unknown."""

    stamp_ns: int
    lat_deg: float
    lon_deg: float
    alt_m: float
    status: int = GpsStatus.FIX
    covariance_enu_m2: np.ndarray | None = None
    frame_id: str = "gps"

    @property
    def has_fix(self) -> bool:
        return self.status >= GpsStatus.FIX and bool(np.isfinite([self.lat_deg, self.lon_deg]).all())

    @property
    def horizontal_sigma_m(self) -> float:
        """RMS of the horizontal standard deviations, NaN when the covariance is unknown."""
        if self.covariance_enu_m2 is None:
            return float("nan")
        return float(np.sqrt(0.5 * (self.covariance_enu_m2[0, 0] + self.covariance_enu_m2[1, 1])))


@dataclass
class LidarScan:
    """One LiDAR sweep in its sensor frame; invalid points are already dropped with their times."""

    stamp_ns: int
    frame_id: str
    points_xyz: np.ndarray  # (N, 3) float32 or float64, metres in frame_id
    intensity: np.ndarray | None = None  # (N,)
    point_time_s: np.ndarray | None = None  # (N,) seconds relative to stamp_ns
    ring: np.ndarray | None = None  # (N,) beam index

    def __len__(self) -> int:
        return int(self.points_xyz.shape[0])


@dataclass
class ImuSample:
    stamp_ns: int
    frame_id: str
    angular_velocity_rad_s: np.ndarray  # (3,)
    linear_acceleration_m_s2: np.ndarray  # (3,)
    orientation_quat_wxyz: np.ndarray | None = None  # (4,) or None when not estimated


@dataclass
class PoseSample:
    """A pose of ``child_frame`` in ``parent_frame`` (ground truth, INS, or odometry)."""

    stamp_ns: int
    parent_frame: str
    child_frame: str
    parent_from_child: np.ndarray  # 4x4 SE(3)
    covariance: np.ndarray | None = None  # 6x6 (x, y, z, rx, ry, rz) when known
    source: str = "pose"  # "ground_truth", "ins", "odometry", ...


@dataclass
class FrameTransform:
    """A (static) extrinsic: ``parent_from_child`` maps child-frame points into the parent frame."""

    stamp_ns: int
    parent_frame: str
    child_frame: str
    parent_from_child: np.ndarray  # 4x4
    static: bool = True


Record = CameraFrame | CameraInfo | GpsFix | LidarScan | ImuSample | PoseSample | FrameTransform


@dataclass
class Message:
    """A record as it came out of a log: which stream it is on and its index in that stream."""

    topic: str
    kind: StreamKind
    index: int
    record: Record

    @property
    def stamp_ns(self) -> int:
        return self.record.stamp_ns


@dataclass
class StreamInfo:
    """What a log holds on one stream, as far as can be known without reading it."""

    topic: str
    kind: StreamKind
    msgtype: str
    count: int | None = None
