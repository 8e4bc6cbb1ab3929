"""MCAP logs of ROS 2 messages: a streaming reader and an atomic writer, on the ``mcap`` library.

Reading uses the file's chunk index when it has one (messages come in log-time order, one chunk
decompressed at a time). A truncated or corrupt file has no usable summary: it is read linearly
up to the damage, with a warning saying at which byte it stopped and how many messages were read.
"""

from __future__ import annotations

import os
import warnings
from collections import Counter
from pathlib import Path
from typing import Any, Iterator, Optional

from mcap.exceptions import McapError
from mcap.reader import NonSeekingReader, SeekingReader
from mcap.writer import CompressionType
from mcap_ros2.decoder import DecoderFactory
from mcap_ros2.writer import Writer as Ros2Writer

from ..errors import InputError, InputWarning
from ..types import (
    CameraFrame,
    CameraInfo,
    FrameTransform,
    GpsFix,
    ImuSample,
    LidarScan,
    Message,
    PoseSample,
    StreamInfo,
    StreamKind,
)
from . import ros2
from .base import DriveLog

MCAP_MAGIC = b"\x89MCAP0\r\n"


def is_mcap(path: Path) -> bool:
    try:
        with open(path, "rb") as f:
            return f.read(8) == MCAP_MAGIC
    except OSError:
        return False


class McapLog(DriveLog):
    """A drive in one MCAP file of ROS 2 (CDR) messages."""

    format_name = "mcap"

    def __init__(self, path: str | Path, validate_crcs: bool = True):
        """``validate_crcs`` checks every chunk's CRC (on by default: zstd and lz4 chunks carry no
        checksum of their own, so without it a corrupt chunk could decode into wrong values)."""
        super().__init__(path)
        self.validate_crcs = validate_crcs
        if not self.path.is_file():
            raise InputError(self.path, "no such file")
        if not is_mcap(self.path):
            raise InputError(self.path, "not an MCAP file (bad magic bytes)")
        self._file = open(self.path, "rb")
        self._decoders = DecoderFactory()
        self._summary = None
        self._indexed = False
        try:
            self._summary = SeekingReader(self._file).get_summary()
            self._indexed = self._summary is not None and len(self._summary.chunk_indexes) > 0
        except (McapError, EOFError, ValueError, OSError, StopIteration, Exception) as exc:  # noqa: BLE001
            # a truncated file has no footer: everything below falls back to a linear read
            self._summary_error = f"{type(exc).__name__}: {exc}"
        self._streams: Optional[list[StreamInfo]] = None
        self.truncated_at: Optional[int] = None

    def close(self) -> None:
        self._file.close()

    @property
    def indexed(self) -> bool:
        return self._indexed

    # --- streams ----------------------------------------------------------------------------------
    def streams(self) -> list[StreamInfo]:
        if self._streams is not None:
            return self._streams
        if self._summary is not None and self._summary.channels:
            counts = self._summary.statistics.channel_message_counts if self._summary.statistics else {}
            chans = [
                (c.topic, self._summary.schemas[c.schema_id].name if c.schema_id else "", counts.get(c.id))
                for c in self._summary.channels.values()
            ]
        else:
            chans = self._scan_channels()
        self._streams = [
            StreamInfo(topic, ros2.KIND_OF_MSGTYPE.get(ros2.short_type(t), StreamKind.OTHER), ros2.short_type(t), n)
            for topic, t, n in sorted(chans)
        ]
        return self._streams

    def _scan_channels(self) -> list[tuple[str, str, Optional[int]]]:
        """Channels and counts by a linear pass (no summary to read them from)."""
        counts: Counter[int] = Counter()
        channels: dict[int, Any] = {}
        schemas: dict[int, Any] = {}
        for _, channel, message in self._linear_raw(None, warn=False):
            channels[channel.id] = channel
            counts[channel.id] += 1
        for schema_id, schema in self._linear_schemas.items():
            schemas[schema_id] = schema
        return [(c.topic, schemas[c.schema_id].name if c.schema_id in schemas else "", counts[cid]) for cid, c in channels.items()]

    # --- raw iteration ----------------------------------------------------------------------------
    def _raw(self, topics: Optional[set[str]]) -> Iterator[tuple[Any, Any, Any]]:
        if self._indexed:
            self._file.seek(0)
            reader = SeekingReader(self._file, validate_crcs=self.validate_crcs)
            try:
                yield from reader.iter_messages(topics=None if topics is None else sorted(topics), log_time_order=True)
            except (McapError, EOFError, ValueError, OSError) as exc:
                self._report_damage(self._file.tell(), exc)
        else:
            yield from self._linear_raw(topics)

    def _linear_raw(self, topics: Optional[set[str]], warn: bool = True) -> Iterator[tuple[Any, Any, Any]]:
        """Records in file order, stopping (with a warning) where the file is damaged."""
        self._file.seek(0)
        self._linear_schemas: dict[int, Any] = {}
        reader = NonSeekingReader(self._file, validate_crcs=self.validate_crcs)
        it = reader.iter_messages(topics=None if topics is None else sorted(topics), log_time_order=False)
        try:
            for schema, channel, message in it:
                if schema is not None:
                    self._linear_schemas[schema.id] = schema
                yield schema, channel, message
        except (McapError, EOFError, ValueError, OSError, Exception) as exc:  # noqa: BLE001
            if warn:
                self._report_damage(self._file.tell(), exc)
            else:
                self.truncated_at = self._file.tell()

    def _report_damage(self, offset: int, exc: BaseException) -> None:
        self.truncated_at = offset
        size = self.path.stat().st_size
        warnings.warn(
            f"{self.path}: log is truncated or corrupt near byte {offset} of {size} "
            f"({type(exc).__name__}: {exc}); messages after it are not read",
            InputWarning,
            stacklevel=4,
        )

    def stamps(self, topics: Optional[set[str]] = None) -> Iterator[tuple[str, int]]:
        """(topic, header stamp in ns) of every message, without decoding payloads."""
        for schema, channel, message in self._raw(topics):
            header_first = (
                schema is not None and channel.message_encoding == "cdr"
                and ros2.short_type(schema.name) in ros2.HEADER_FIRST
            )
            stamp = ros2.header_stamp_from_cdr(message.data) if header_first else None
            yield channel.topic, message.log_time if stamp is None else stamp

    # --- decoded iteration ------------------------------------------------------------------------
    def _iter_messages(self, topics: Optional[set[str]]) -> Iterator[Message]:
        kinds = {s.topic: s.kind for s in self.streams()}
        index: Counter[str] = Counter()
        for schema, channel, message in self._raw(topics):
            topic = channel.topic
            i = index[topic]
            index[topic] += 1
            kind = kinds.get(topic, StreamKind.OTHER)
            if kind == StreamKind.OTHER or schema is None:
                continue
            msgtype = ros2.short_type(schema.name)
            try:
                decoder = self._decoders.decoder_for(channel.message_encoding, schema)
                if decoder is None:
                    raise ValueError(f"no decoder for encoding {channel.message_encoding!r}")
                decoded = decoder(message.data)
                records = _to_records(decoded, msgtype, topic, i)
            except InputError as exc:
                self._skip(topic, i, "could not be decoded", exc.what)
                continue
            except Exception as exc:  # noqa: BLE001 - a corrupt payload must not end the stream
                self._skip(topic, i, "could not be decoded", f"{type(exc).__name__}: {exc}")
                continue
            for rec in records:
                yield Message(topic, kind, i, rec)


def _to_records(msg: Any, msgtype: str, topic: str, index: int) -> list:
    source = f"{topic}#{index}"
    if msgtype in ("sensor_msgs/Image", "sensor_msgs/CompressedImage"):
        return [ros2.image_from_msg(msg, msgtype, source)]
    if msgtype == "sensor_msgs/CameraInfo":
        return [ros2.camera_info_from_msg(msg, source)]
    if msgtype == "sensor_msgs/NavSatFix":
        return [ros2.gps_from_msg(msg)]
    if msgtype == "sensor_msgs/PointCloud2":
        return [ros2.lidar_from_msg(msg, source)]
    if msgtype == "sensor_msgs/Imu":
        return [ros2.imu_from_msg(msg)]
    if msgtype in ("geometry_msgs/PoseStamped", "nav_msgs/Odometry"):
        return [ros2.pose_from_msg(msg, msgtype, topic)]
    if msgtype == "tf2_msgs/TFMessage":
        return ros2.transforms_from_msg(msg, static=topic.rstrip("/").endswith("tf_static"))
    return []


# --- writer ---------------------------------------------------------------------------------------

_COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}


class McapWriter:
    """Writes mapkit records as ROS 2 messages into one MCAP file, atomically.

    The file appears under its name only when ``close()`` succeeds; until then it is written to a
    ``.partial`` sibling, which is removed if writing fails.
    """

    def __init__(self, path: str | Path, *, compression: str = "zstd", chunk_size: int = 4 << 20):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._tmp = self.path.with_name(self.path.name + ".partial")
        if compression not in _COMPRESSION:
            raise ValueError(f"compression must be one of {sorted(_COMPRESSION)}, not {compression!r}")
        self._fh = open(self._tmp, "wb")
        self._writer = Ros2Writer(self._fh, chunk_size=chunk_size, compression=_COMPRESSION[compression])
        self._schemas: dict[str, Any] = {}
        self._sequence: Counter[str] = Counter()
        self._closed = False
        self.count = 0

    def _schema(self, msgtype: str):
        if msgtype not in self._schemas:
            self._schemas[msgtype] = self._writer.register_msgdef(ros2.schema_name(msgtype), ros2.full_msgdef(msgtype))
        return self._schemas[msgtype]

    def _put(self, topic: str, msgtype: str, payload: dict, stamp_ns: int, log_time_ns: Optional[int]) -> None:
        log_time = stamp_ns if log_time_ns is None else log_time_ns
        self._writer.write_message(
            topic, self._schema(msgtype), payload, log_time=int(log_time), publish_time=int(log_time),
            sequence=self._sequence[topic],
        )
        self._sequence[topic] += 1
        self.count += 1

    def write(
        self,
        topic: str,
        record: Any,
        *,
        log_time_ns: Optional[int] = None,
        compress: Optional[str] = None,
        pose_msgtype: str = "nav_msgs/Odometry",
    ) -> None:
        """Write one record; its message type follows from the record type."""
        if isinstance(record, CameraFrame):
            msgtype, payload = ros2.image_to_msg(record, compress=compress)
        elif isinstance(record, CameraInfo):
            msgtype, payload = "sensor_msgs/CameraInfo", ros2.camera_info_to_msg(record)
        elif isinstance(record, GpsFix):
            msgtype, payload = "sensor_msgs/NavSatFix", ros2.gps_to_msg(record)
        elif isinstance(record, LidarScan):
            msgtype, payload = "sensor_msgs/PointCloud2", ros2.lidar_to_msg(record)
        elif isinstance(record, ImuSample):
            msgtype, payload = "sensor_msgs/Imu", ros2.imu_to_msg(record)
        elif isinstance(record, PoseSample):
            msgtype, payload = pose_msgtype, ros2.pose_to_msg(record, pose_msgtype)
        elif isinstance(record, FrameTransform):
            self.write_transforms(topic, [record], log_time_ns=log_time_ns)
            return
        else:
            raise TypeError(f"cannot write {type(record).__name__} to MCAP")
        self._put(topic, msgtype, payload, record.stamp_ns, log_time_ns)

    def write_transforms(self, topic: str, transforms: list[FrameTransform], *, log_time_ns: Optional[int] = None) -> None:
        """One ``tf2_msgs/TFMessage`` holding several transforms (``/tf_static`` for extrinsics)."""
        if not transforms:
            raise ValueError("write_transforms needs at least one transform")
        stamp = min(t.stamp_ns for t in transforms)
        self._put(topic, "tf2_msgs/TFMessage", ros2.transforms_to_msg(transforms), stamp, log_time_ns)

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        self._writer.add_metadata(name, {str(k): str(v) for k, v in data.items()})

    def close(self) -> Path:
        if not self._closed:
            self._writer.finish()
            self._fh.flush()
            os.fsync(self._fh.fileno())
            self._fh.close()
            os.replace(self._tmp, self.path)
            self._closed = True
        return self.path

    def abort(self) -> None:
        if not self._closed:
            self._fh.close()
            self._tmp.unlink(missing_ok=True)
            self._closed = True

    def __enter__(self) -> "McapWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()
