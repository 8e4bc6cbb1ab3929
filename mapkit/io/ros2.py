"""ROS 2 message definitions and conversions between decoded messages and mapkit records.

The definitions are the standard ``.msg`` texts (field lists of ROS 2 Humble and later), joined
the way ``ros2 bag record`` stores them in MCAP schemas, so that any ROS 2 tool reads the logs
mapkit writes. Encoding and decoding themselves are done by ``mcap_ros2``; this module only maps
fields. PointCloud2 is decoded vectorised from its ``PointField`` layout. The same functions take the
dataclasses ``rosbags`` deserialises from ROS 1 bags and rosbag2 folders (``mapkit.io.rosbag``): ROS 1
names its fields alike except CameraInfo's ``D``/``K``, and its header's extra ``seq`` is not read.
"""

from __future__ import annotations

import struct
from typing import Any

import cv2
import numpy as np

from mapkit.core.errors import InputError
from mapkit.core.geometry import make_pose, matrix_to_quat_wxyz, quat_wxyz_to_matrix
from mapkit.core.types import (
    CameraFrame,
    CameraInfo,
    FrameTransform,
    GpsFix,
    ImuSample,
    LidarScan,
    PoseSample,
    StreamKind,
)

_DEFS: dict[str, str] = {
    "builtin_interfaces/Time": "int32 sec\nuint32 nanosec\n",
    "std_msgs/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "geometry_msgs/Vector3": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/Point": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/Quaternion": "float64 x\nfloat64 y\nfloat64 z\nfloat64 w\n",
    "geometry_msgs/Pose": "geometry_msgs/Point position\ngeometry_msgs/Quaternion orientation\n",
    "geometry_msgs/PoseStamped": "std_msgs/Header header\ngeometry_msgs/Pose pose\n",
    "geometry_msgs/PoseWithCovariance": "geometry_msgs/Pose pose\nfloat64[36] covariance\n",
    "geometry_msgs/Twist": "geometry_msgs/Vector3 linear\ngeometry_msgs/Vector3 angular\n",
    "geometry_msgs/TwistWithCovariance": "geometry_msgs/Twist twist\nfloat64[36] covariance\n",
    "geometry_msgs/Transform": "geometry_msgs/Vector3 translation\ngeometry_msgs/Quaternion rotation\n",
    "geometry_msgs/TransformStamped": (
        "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/Transform transform\n"
    ),
    "tf2_msgs/TFMessage": "geometry_msgs/TransformStamped[] transforms\n",
    "nav_msgs/Odometry": (
        "std_msgs/Header header\nstring child_frame_id\n"
        "geometry_msgs/PoseWithCovariance pose\ngeometry_msgs/TwistWithCovariance twist\n"
    ),
    "sensor_msgs/Image": (
        "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\n"
        "uint8 is_bigendian\nuint32 step\nuint8[] data\n"
    ),
    "sensor_msgs/CompressedImage": "std_msgs/Header header\nstring format\nuint8[] data\n",
    "sensor_msgs/RegionOfInterest": (
        "uint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\nbool do_rectify\n"
    ),
    "sensor_msgs/CameraInfo": (
        "std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\n"
        "float64[] d\nfloat64[9] k\nfloat64[9] r\nfloat64[12] p\nuint32 binning_x\nuint32 binning_y\n"
        "sensor_msgs/RegionOfInterest roi\n"
    ),
    "sensor_msgs/NavSatStatus": (
        "int8 STATUS_NO_FIX=-1\nint8 STATUS_FIX=0\nint8 STATUS_SBAS_FIX=1\nint8 STATUS_GBAS_FIX=2\n"
        "int8 status\n"
        "uint16 SERVICE_GPS=1\nuint16 SERVICE_GLONASS=2\nuint16 SERVICE_COMPASS=4\nuint16 SERVICE_GALILEO=8\n"
        "uint16 service\n"
    ),
    "sensor_msgs/NavSatFix": (
        "std_msgs/Header header\nsensor_msgs/NavSatStatus status\nfloat64 latitude\nfloat64 longitude\n"
        "float64 altitude\nfloat64[9] position_covariance\n"
        "uint8 COVARIANCE_TYPE_UNKNOWN=0\nuint8 COVARIANCE_TYPE_APPROXIMATED=1\n"
        "uint8 COVARIANCE_TYPE_DIAGONAL_KNOWN=2\nuint8 COVARIANCE_TYPE_KNOWN=3\n"
        "uint8 position_covariance_type\n"
    ),
    "sensor_msgs/PointField": (
        "uint8 INT8=1\nuint8 UINT8=2\nuint8 INT16=3\nuint8 UINT16=4\nuint8 INT32=5\nuint8 UINT32=6\n"
        "uint8 FLOAT32=7\nuint8 FLOAT64=8\n"
        "string name\nuint32 offset\nuint8 datatype\nuint32 count\n"
    ),
    "sensor_msgs/PointCloud2": (
        "std_msgs/Header header\nuint32 height\nuint32 width\nsensor_msgs/PointField[] fields\n"
        "bool is_bigendian\nuint32 point_step\nuint32 row_step\nuint8[] data\nbool is_dense\n"
    ),
    "sensor_msgs/Imu": (
        "std_msgs/Header header\ngeometry_msgs/Quaternion orientation\nfloat64[9] orientation_covariance\n"
        "geometry_msgs/Vector3 angular_velocity\nfloat64[9] angular_velocity_covariance\n"
        "geometry_msgs/Vector3 linear_acceleration\nfloat64[9] linear_acceleration_covariance\n"
    ),
}

_SEPARATOR = "=" * 80


def _deps(name: str, seen: list[str]) -> list[str]:
    for line in _DEFS[name].splitlines():
        ftype = line.split()[0].split("[")[0]
        if "/" in ftype and ftype not in seen:
            seen.append(ftype)
            _deps(ftype, seen)
    return seen


def full_msgdef(name: str) -> str:
    """The schema text of ``pkg/Type`` with every nested definition appended (ros2 bag layout)."""
    parts = [_DEFS[name]]
    for dep in _deps(name, []):
        parts.append(f"{_SEPARATOR}\nMSG: {dep}\n{_DEFS[dep]}")
    return "".join(parts)


def schema_name(name: str) -> str:
    """``sensor_msgs/Image`` -> ``sensor_msgs/msg/Image`` (the name ROS 2 writes in schemas)."""
    pkg, typ = name.split("/")
    return f"{pkg}/msg/{typ}"


def short_type(msgtype: str) -> str:
    """Normalise ``pkg/msg/Type`` and ``pkg/Type`` to ``pkg/Type``."""
    parts = msgtype.split("/")
    return f"{parts[0]}/{parts[-1]}" if len(parts) >= 2 else msgtype


KIND_OF_MSGTYPE: dict[str, StreamKind] = {
    "sensor_msgs/Image": StreamKind.IMAGE,
    "sensor_msgs/CompressedImage": StreamKind.IMAGE,
    "sensor_msgs/CameraInfo": StreamKind.CAMERA_INFO,
    "sensor_msgs/NavSatFix": StreamKind.GPS,
    "sensor_msgs/PointCloud2": StreamKind.LIDAR,
    "sensor_msgs/Imu": StreamKind.IMU,
    "geometry_msgs/PoseStamped": StreamKind.POSE,
    "nav_msgs/Odometry": StreamKind.POSE,
    "tf2_msgs/TFMessage": StreamKind.TF,
}

#: message types whose first field is a std_msgs/Header (their stamp can be read without decoding)
HEADER_FIRST = frozenset(t for t in KIND_OF_MSGTYPE if t != "tf2_msgs/TFMessage")


# --- helpers --------------------------------------------------------------------------------------


def _header(stamp_ns: int, frame_id: str) -> dict:
    if stamp_ns < 0:
        raise ValueError(f"negative timestamp {stamp_ns} cannot be written as builtin_interfaces/Time")
    return {
        "stamp": {"sec": int(stamp_ns // 1_000_000_000), "nanosec": int(stamp_ns % 1_000_000_000)},
        "frame_id": frame_id,
    }


def stamp_ns_of(header: Any) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def header_stamp_from_cdr(data: bytes) -> int | None:
    """The ``header.stamp`` of a CDR message whose first field is a std_msgs/Header, undecoded."""
    if len(data) < 12:
        return None
    endian = "<" if data[1] & 1 else ">"  # encapsulation kind: CDR_LE = 0x01, CDR_BE = 0x00
    sec, nsec = struct.unpack_from(endian + "iI", data, 4)
    return sec * 1_000_000_000 + nsec


def _quat(q_wxyz: np.ndarray) -> dict:
    return {"x": float(q_wxyz[1]), "y": float(q_wxyz[2]), "z": float(q_wxyz[3]), "w": float(q_wxyz[0])}


def _vec(v: np.ndarray) -> dict:
    return {"x": float(v[0]), "y": float(v[1]), "z": float(v[2])}


def _quat_of(msg_q: Any) -> np.ndarray:
    return np.array([msg_q.w, msg_q.x, msg_q.y, msg_q.z], dtype=np.float64)


def _vec_of(msg_v: Any) -> np.ndarray:
    return np.array([msg_v.x, msg_v.y, msg_v.z], dtype=np.float64)


def _pose_of(msg_pose: Any) -> np.ndarray:
    return make_pose(quat_wxyz_to_matrix(_quat_of(msg_pose.orientation)), _vec_of(msg_pose.position))


def _pose_msg(T: np.ndarray) -> dict:
    return {"position": _vec(T[:3, 3]), "orientation": _quat(matrix_to_quat_wxyz(T[:3, :3]))}


# --- images ---------------------------------------------------------------------------------------

_IMAGE_DTYPES = {
    "mono8": (np.uint8, 1),
    "8UC1": (np.uint8, 1),
    "mono16": (np.uint16, 1),
    "16UC1": (np.uint16, 1),
    "rgb8": (np.uint8, 3),
    "bgr8": (np.uint8, 3),
    "rgba8": (np.uint8, 4),
    "bgra8": (np.uint8, 4),
    "8UC3": (np.uint8, 3),
}


def image_to_msg(frame: CameraFrame, *, compress: str | None = None, frame_id: str | None = None) -> tuple[str, dict]:
    """(msgtype, message dict) of a frame: raw ``Image`` or, with ``compress``, ``CompressedImage``."""
    img = np.ascontiguousarray(frame.image)
    header = _header(frame.stamp_ns, frame_id or frame.camera)
    if compress:
        fmt = compress.lower()
        ext = {"jpeg": ".jpg", "jpg": ".jpg", "png": ".png"}[fmt]
        to_encode = img
        if img.ndim == 3 and frame.encoding.startswith("rgb"):
            to_encode = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
        ok, buf = cv2.imencode(ext, to_encode)
        if not ok:
            raise ValueError(f"OpenCV could not encode frame {frame.stamp_ns} as {fmt}")
        return "sensor_msgs/CompressedImage", {"header": header, "format": fmt, "data": buf.tobytes()}
    if frame.encoding not in _IMAGE_DTYPES:
        raise ValueError(f"unsupported image encoding {frame.encoding!r}")
    height, width = img.shape[:2]
    return "sensor_msgs/Image", {
        "header": header,
        "height": height,
        "width": width,
        "encoding": frame.encoding,
        "is_bigendian": 0,
        "step": int(img.strides[0]),
        "data": img.tobytes(),
    }


def image_from_msg(msg: Any, msgtype: str, source: str, camera: str | None = None) -> CameraFrame:
    stamp = stamp_ns_of(msg.header)
    cam = camera or msg.header.frame_id or source.split("#")[0]
    if msgtype == "sensor_msgs/CompressedImage":
        data = msg.data

        def load() -> np.ndarray:
            img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
            if img is None:
                raise InputError(None, f"compressed image {source} ({msg.format}) could not be decoded", field="data")
            return img

        # OpenCV decodes colour as BGR: the encoding says so
        enc = "mono8" if "mono" in (msg.format or "") else "bgr8"
        frame = CameraFrame(stamp, cam, loader=load, encoding=enc, source=source)
        return frame
    enc = msg.encoding
    if enc not in _IMAGE_DTYPES:
        raise InputError(None, f"image {source} has unsupported encoding {enc!r}", field="encoding")
    dtype, channels = _IMAGE_DTYPES[enc]
    dt = np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    itemsize = dt.itemsize * channels
    if len(msg.data) < step * h or step < w * itemsize:
        raise InputError(
            None, f"image {source}: {len(msg.data)} bytes for {h}x{w} {enc} with step {step}", field="data"
        )
    rows = np.frombuffer(msg.data, np.uint8, count=step * h).reshape(h, step)[:, : w * itemsize]
    img = np.ascontiguousarray(rows).view(dt).reshape((h, w) if channels == 1 else (h, w, channels))
    if dt.byteorder == ">":
        img = img.astype(dt.newbyteorder("="))
    return CameraFrame(
        stamp, cam, img, encoding="mono8" if enc == "8UC1" else ("mono16" if enc == "16UC1" else enc), source=source
    )


def camera_info_to_msg(info: CameraInfo, frame_id: str | None = None) -> dict:
    K = np.asarray(info.K, np.float64)
    P = np.zeros((3, 4))
    P[:3, :3] = K
    return {
        "header": _header(info.stamp_ns, frame_id or info.camera),
        "height": info.height,
        "width": info.width,
        "distortion_model": info.distortion_model,
        "d": [float(x) for x in np.asarray(info.D).ravel()],
        "k": [float(x) for x in K.ravel()],
        "r": [float(x) for x in np.eye(3).ravel()],
        "p": [float(x) for x in P.ravel()],
        "binning_x": 0,
        "binning_y": 0,
        "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False},
    }


def camera_info_from_msg(msg: Any, source: str) -> CameraInfo:
    """From a ROS 2 ``CameraInfo`` (``d``, ``k``) or a ROS 1 one (``D``, ``K``); the rest is named alike."""
    k = msg.k if hasattr(msg, "k") else msg.K
    d = msg.d if hasattr(msg, "d") else msg.D
    K = np.asarray(k, np.float64).reshape(3, 3)
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(None, f"camera info {source} has no focal length (k = {list(k)})", field="k")
    return CameraInfo(
        camera=msg.header.frame_id or source.split("#")[0],
        width=int(msg.width),
        height=int(msg.height),
        K=K,
        distortion_model=msg.distortion_model or "plumb_bob",
        D=np.asarray(d, np.float64),
        stamp_ns=stamp_ns_of(msg.header),
    )


# --- GPS ------------------------------------------------------------------------------------------


def gps_to_msg(fix: GpsFix) -> dict:
    if fix.covariance_enu_m2 is None:
        cov, cov_type = [0.0] * 9, 0
    else:
        cov, cov_type = [float(x) for x in np.asarray(fix.covariance_enu_m2).ravel()], 3
    return {
        "header": _header(fix.stamp_ns, fix.frame_id),
        "status": {"status": int(fix.status), "service": 1},
        "latitude": float(fix.lat_deg),
        "longitude": float(fix.lon_deg),
        "altitude": float(fix.alt_m),
        "position_covariance": cov,
        "position_covariance_type": cov_type,
    }


def gps_from_msg(msg: Any) -> GpsFix:
    cov = None
    if int(msg.position_covariance_type) != 0:
        cov = np.asarray(msg.position_covariance, np.float64).reshape(3, 3)
    return GpsFix(
        stamp_ns=stamp_ns_of(msg.header),
        lat_deg=float(msg.latitude),
        lon_deg=float(msg.longitude),
        alt_m=float(msg.altitude),
        status=int(msg.status.status),
        covariance_enu_m2=cov,
        frame_id=msg.header.frame_id,
    )


# --- point clouds ---------------------------------------------------------------------------------

_POINTFIELD_DTYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
_DTYPE_POINTFIELD = {np.dtype(v).str[1:]: k for k, v in _POINTFIELD_DTYPES.items()}
# per-point time fields seen in the wild: (name, scale to seconds, absolute?)
_TIME_FIELDS = ("time", "t", "timestamp", "time_stamp", "offset_time")


def lidar_to_msg(scan: LidarScan) -> dict:
    """PointCloud2 with float32 ``x, y, z[, intensity][, time (s since stamp)][, ring (uint16)]``."""
    n = len(scan)
    cols = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if scan.intensity is not None:
        cols.append(("intensity", "<f4"))
    if scan.point_time_s is not None:
        cols.append(("time", "<f4"))
    if scan.ring is not None:
        cols.append(("ring", "<u2"))
    dt = np.dtype(cols)
    layout = dt.fields
    assert layout is not None  # a structured dtype has fields
    arr = np.empty(n, dtype=dt)
    xyz = np.asarray(scan.points_xyz)
    arr["x"], arr["y"], arr["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    if scan.intensity is not None:
        arr["intensity"] = scan.intensity
    if scan.point_time_s is not None:
        arr["time"] = scan.point_time_s
    if scan.ring is not None:
        arr["ring"] = scan.ring
    fields = [
        {
            "name": name,
            "offset": int(layout[name][1]),
            "datatype": _DTYPE_POINTFIELD[np.dtype(t).str[1:]],
            "count": 1,
        }
        for name, t in cols
    ]
    return {
        "header": _header(scan.stamp_ns, scan.frame_id),
        "height": 1,
        "width": n,
        "fields": fields,
        "is_bigendian": False,
        "point_step": dt.itemsize,
        "row_step": dt.itemsize * n,
        "data": arr.tobytes(),
        "is_dense": True,
    }


def lidar_from_msg(msg: Any, source: str) -> LidarScan:
    """Decode a PointCloud2 with one structured-array view; non-finite points drop with their times."""
    stamp = stamp_ns_of(msg.header)
    n = int(msg.width) * int(msg.height)
    names = [f.name for f in msg.fields]
    for required in ("x", "y", "z"):
        if required not in names:
            raise InputError(None, f"point cloud {source} has no {required!r} field (fields: {names})", field="fields")
    order = ">" if msg.is_bigendian else "<"
    formats, offsets, fnames = [], [], []
    for f in msg.fields:
        if f.datatype not in _POINTFIELD_DTYPES:
            raise InputError(
                None, f"point cloud {source}: field {f.name!r} has unknown datatype {f.datatype}", field="fields"
            )
        code = order + _POINTFIELD_DTYPES[f.datatype]
        formats.append(code if f.count <= 1 else (code, (int(f.count),)))
        offsets.append(int(f.offset))
        fnames.append(f.name)
    dt = np.dtype({"names": fnames, "formats": formats, "offsets": offsets, "itemsize": int(msg.point_step)})
    need = n * int(msg.point_step)
    if len(msg.data) < need:
        raise InputError(
            None, f"point cloud {source}: {len(msg.data)} bytes for {n} points of {msg.point_step}", field="data"
        )
    if int(msg.height) > 1 and int(msg.row_step) != int(msg.width) * int(msg.point_step):
        rows = np.frombuffer(msg.data, np.uint8, count=int(msg.row_step) * int(msg.height)).reshape(int(msg.height), -1)
        buf = np.ascontiguousarray(rows[:, : int(msg.width) * int(msg.point_step)]).tobytes()
    else:
        buf = msg.data
    arr = np.frombuffer(buf, dtype=dt, count=n)
    xyz = _xyz_of(arr, dt, buf, n)
    # isfinite(xyz).all(axis=1) reduces over a length-3 axis (~1.4 ms per 100k points); the
    # whole-array all() is ~50x faster and settles dense clouds, the usual case
    finite = np.isfinite(xyz)
    all_valid = bool(finite.all())
    valid = None if all_valid else finite[:, 0] & finite[:, 1] & finite[:, 2]

    def take(a: np.ndarray) -> np.ndarray:
        return a if all_valid else a[valid]

    intensity = take(np.asarray(arr["intensity"], np.float32)) if "intensity" in names else None
    ring = take(np.asarray(arr["ring"])) if "ring" in names else None
    point_time_s = None
    for tname in _TIME_FIELDS:
        if tname in names:
            point_time_s = take(_relative_time_s(np.asarray(arr[tname]), tname, stamp))
            break
    return LidarScan(stamp, msg.header.frame_id, take(xyz), intensity=intensity, point_time_s=point_time_s, ring=ring)


def _xyz_of(arr: np.ndarray, dt: np.dtype, buf, n: int) -> np.ndarray:
    """(N, 3) float32 copy of x, y, z: one block copy per point when they are adjacent (the usual layout)."""
    layout = dt.fields
    assert layout is not None  # the dtype of a PointCloud2 is structured
    (tx, ox), (ty, oy), (tz, oz) = (layout[c][:2] for c in "xyz")
    if tx == ty == tz and tx.shape == () and oy == ox + tx.itemsize and oz == oy + tx.itemsize:
        # an opaque 3*itemsize block per point copies 2x faster than numpy's strided (N, 3) loop
        block = np.dtype(
            {"names": ["xyz"], "formats": [f"V{3 * tx.itemsize}"], "offsets": [ox], "itemsize": dt.itemsize}
        )
        xyz = np.frombuffer(buf, dtype=block, count=n)["xyz"].copy().view(tx).reshape(n, 3)
        return xyz.astype(np.float32, copy=False)
    return np.stack([arr["x"], arr["y"], arr["z"]], axis=-1).astype(np.float32, copy=False)


def _relative_time_s(t: np.ndarray, name: str, stamp_ns: int) -> np.ndarray:
    """Per-point times in seconds relative to the header stamp, whatever the driver's convention."""
    if t.dtype.kind in "ui" and t.dtype.itemsize >= 4:
        # integer nanoseconds (Ouster ``t``, Livox ``offset_time``); absolute if as large as the stamp
        t64 = t.astype(np.int64)
        if t64.size and t64.max() > 10**15:
            t64 = t64 - stamp_ns
        return (t64 * 1e-9).astype(np.float32)
    if t.size and np.nanmax(np.abs(t)) > 1e6:  # absolute seconds since the epoch: subtract in float64
        return (t.astype(np.float64) - stamp_ns * 1e-9).astype(np.float32)
    return t.astype(np.float32)  # relative seconds already (Velodyne ``time``): one native copy


# --- IMU, poses, transforms -----------------------------------------------------------------------


def imu_to_msg(s: ImuSample) -> dict:
    unknown = s.orientation_quat_wxyz is None
    cov_o = [-1.0] + [0.0] * 8 if unknown else [0.0] * 9  # ROS: covariance[0] = -1 means no orientation
    return {
        "header": _header(s.stamp_ns, s.frame_id),
        "orientation": _quat(np.array([1.0, 0, 0, 0]) if s.orientation_quat_wxyz is None else s.orientation_quat_wxyz),
        "orientation_covariance": cov_o,
        "angular_velocity": _vec(s.angular_velocity_rad_s),
        "angular_velocity_covariance": [0.0] * 9,
        "linear_acceleration": _vec(s.linear_acceleration_m_s2),
        "linear_acceleration_covariance": [0.0] * 9,
    }


def imu_from_msg(msg: Any) -> ImuSample:
    has_orientation = float(msg.orientation_covariance[0]) != -1.0
    return ImuSample(
        stamp_ns=stamp_ns_of(msg.header),
        frame_id=msg.header.frame_id,
        angular_velocity_rad_s=_vec_of(msg.angular_velocity),
        linear_acceleration_m_s2=_vec_of(msg.linear_acceleration),
        orientation_quat_wxyz=_quat_of(msg.orientation) if has_orientation else None,
    )


def pose_to_msg(p: PoseSample, msgtype: str = "nav_msgs/Odometry") -> dict:
    if msgtype == "geometry_msgs/PoseStamped":
        return {"header": _header(p.stamp_ns, p.parent_frame), "pose": _pose_msg(p.parent_from_child)}
    cov = [0.0] * 36 if p.covariance is None else [float(x) for x in np.asarray(p.covariance).ravel()]
    return {
        "header": _header(p.stamp_ns, p.parent_frame),
        "child_frame_id": p.child_frame,
        "pose": {"pose": _pose_msg(p.parent_from_child), "covariance": cov},
        "twist": {"twist": {"linear": _vec(np.zeros(3)), "angular": _vec(np.zeros(3))}, "covariance": [0.0] * 36},
    }


def pose_from_msg(msg: Any, msgtype: str, topic: str, default_child: str = "base_link") -> PoseSample:
    if msgtype == "nav_msgs/Odometry":
        cov = np.asarray(msg.pose.covariance, np.float64).reshape(6, 6)
        return PoseSample(
            stamp_ns_of(msg.header),
            msg.header.frame_id,
            msg.child_frame_id or default_child,
            _pose_of(msg.pose.pose),
            covariance=None if not cov.any() else cov,
            source=topic,
        )
    return PoseSample(stamp_ns_of(msg.header), msg.header.frame_id, default_child, _pose_of(msg.pose), source=topic)


def transforms_to_msg(transforms: list[FrameTransform]) -> dict:
    return {
        "transforms": [
            {
                "header": _header(t.stamp_ns, t.parent_frame),
                "child_frame_id": t.child_frame,
                "transform": {
                    "translation": _vec(t.parent_from_child[:3, 3]),
                    "rotation": _quat(matrix_to_quat_wxyz(t.parent_from_child[:3, :3])),
                },
            }
            for t in transforms
        ]
    }


def transforms_from_msg(msg: Any, static: bool) -> list[FrameTransform]:
    out = []
    for ts in msg.transforms:
        T = make_pose(quat_wxyz_to_matrix(_quat_of(ts.transform.rotation)), _vec_of(ts.transform.translation))
        out.append(FrameTransform(stamp_ns_of(ts.header), ts.header.frame_id, ts.child_frame_id, T, static=static))
    return out


def records_from_msg(msg: Any, msgtype: str, topic: str, index: int) -> list:
    """The mapkit records of one decoded message (a TF message gives several; an unknown type none).

    Shared by the MCAP reader (``mcap_ros2`` objects) and the rosbags reader (its dataclasses): both
    name fields as ROS 2 does, bar the ROS 1 differences the converters above accept."""
    source = f"{topic}#{index}"
    if msgtype in ("sensor_msgs/Image", "sensor_msgs/CompressedImage"):
        return [image_from_msg(msg, msgtype, source)]
    if msgtype == "sensor_msgs/CameraInfo":
        return [camera_info_from_msg(msg, source)]
    if msgtype == "sensor_msgs/NavSatFix":
        return [gps_from_msg(msg)]
    if msgtype == "sensor_msgs/PointCloud2":
        return [lidar_from_msg(msg, source)]
    if msgtype == "sensor_msgs/Imu":
        return [imu_from_msg(msg)]
    if msgtype in ("geometry_msgs/PoseStamped", "nav_msgs/Odometry"):
        return [pose_from_msg(msg, msgtype, topic)]
    if msgtype == "tf2_msgs/TFMessage":
        return transforms_from_msg(msg, static=topic.rstrip("/").endswith("tf_static"))
    return []
