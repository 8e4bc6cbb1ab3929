"""MCAP logs of ROS 2 messages: a streaming reader and atomic writers, on the ``mcap`` library.

A log is one ``.mcap`` file or a rosbag2 folder with MCAP storage, as ``ros2 bag record -s mcap``
writes it (``metadata.yaml`` beside ``<name>_0.mcap``, ``<name>_1.mcap``, ...); the folder's files
are read in the order ``metadata.yaml`` lists them, as one log.

Reading uses each file's chunk index when it has one (messages come in log-time order, one chunk
decompressed at a time). A truncated or corrupt file has no usable summary: it is read linearly
up to the damage, with a warning saying at which byte it stopped and how many messages were read.
"""

from __future__ import annotations

import os
import shutil
import warnings
from collections import Counter
from pathlib import Path, PurePosixPath
from typing import Any, Iterator, Optional

import yaml
from mcap.exceptions import McapError
from mcap.reader import NonSeekingReader, SeekingReader
from mcap.writer import CompressionType
from mcap_ros2.decoder import DecoderFactory
from mcap_ros2.writer import Writer as Ros2Writer

from mapkit.core.errors import InputError, InputWarning
from mapkit.core.runio import atomic_write_text
from mapkit.core.types import (
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
from mapkit.io import ros2
from mapkit.io.base import DriveLog

MCAP_MAGIC = b"\x89MCAP0\r\n"
#: the metadata file that makes a folder a rosbag2 bag
ROSBAG2_METADATA = "metadata.yaml"


def is_mcap(path: Path) -> bool:
    try:
        with open(path, "rb") as f:
            return f.read(8) == MCAP_MAGIC
    except OSError:
        return False


def is_rosbag2(path: str | Path) -> bool:
    """A folder holding a rosbag2 ``metadata.yaml`` (any storage)."""
    return (Path(path) / ROSBAG2_METADATA).is_file()


def rosbag2_metadata(folder: str | Path) -> dict:
    """The ``rosbag2_bagfile_information`` mapping of a rosbag2 folder's ``metadata.yaml``."""
    meta_path = Path(folder) / ROSBAG2_METADATA
    if not meta_path.is_file():
        raise InputError(folder, f"not a rosbag2 folder (no {ROSBAG2_METADATA})")
    try:
        doc = yaml.safe_load(meta_path.read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise InputError(meta_path, f"could not be read as YAML ({type(exc).__name__}: {exc})") from None
    info = doc.get("rosbag2_bagfile_information") if isinstance(doc, dict) else None
    if not isinstance(info, dict):
        raise InputError(meta_path, "has no rosbag2_bagfile_information mapping", field="rosbag2_bagfile_information")
    return info


def rosbag2_mcap_files(folder: str | Path) -> list[Path]:
    """The MCAP files of a rosbag2 folder, in the order its metadata lists them.

    Raises InputError for other storage (``sqlite3`` names the ``rosbag`` reader, which reads it), file-compressed
    bags and missing files.
    """
    folder = Path(folder)
    info = rosbag2_metadata(folder)
    meta_path = folder / ROSBAG2_METADATA
    rel = info.get("relative_file_paths") or [f["path"] for f in info.get("files") or [] if isinstance(f, dict) and "path" in f]
    if not rel:
        raise InputError(meta_path, "lists no storage files", field="relative_file_paths")
    storage = str(info.get("storage_identifier") or "").strip().lower()
    if not storage:  # old bags may leave it out: the file suffix tells
        suffixes = {PurePosixPath(str(p)).suffix for p in rel}
        storage = {frozenset({".mcap"}): "mcap", frozenset({".db3"}): "sqlite3"}.get(frozenset(suffixes), "unknown")
    if storage == "sqlite3":
        raise InputError(
            meta_path,
            "rosbag2 storage 'sqlite3' is read by the 'rosbag' reader, not the MCAP one: open it with "
            "mapkit.io.open_log (it picks that reader) or `--format rosbag`",
            field="storage_identifier",
        )
    if storage != "mcap":
        raise InputError(
            meta_path,
            f"rosbag2 storage {storage!r} cannot be read yet (mapkit reads rosbag2 folders with mcap storage; "
            "convert with `ros2 bag convert` or re-record with `-s mcap`)",
            field="storage_identifier",
        )
    if str(info.get("compression_mode") or "").strip().lower() not in ("", "none"):
        raise InputError(meta_path, f"compressed rosbag2 ({info.get('compression_mode')} mode, "
                         f"{info.get('compression_format')!r}) cannot be read; decompress it with `ros2 bag convert`",
                         field="compression_mode")
    # versions before 4 wrote paths relative to the bag's parent folder: the file name is what counts
    files = [folder / PurePosixPath(str(p).replace("\\", "/")).name for p in rel]
    missing = [f.name for f in files if not f.is_file()]
    if missing:
        raise InputError(folder, f"storage files listed in {ROSBAG2_METADATA} are missing: {missing}", field="relative_file_paths")
    return files


class _McapFile:
    """One MCAP file: its summary if readable, indexed or linear raw iteration."""

    def __init__(self, path: Path, validate_crcs: bool):
        self.path = path
        self.validate_crcs = validate_crcs
        self.file = open(path, "rb")
        self.summary = None
        self.indexed = False
        self.summary_error: Optional[str] = None
        self.linear_schemas: dict[int, Any] = {}
        # decoders are cached by schema id, which is only unique within one file
        self.decoders = DecoderFactory()
        try:
            self.summary = SeekingReader(self.file).get_summary()
            self.indexed = self.summary is not None and len(self.summary.chunk_indexes) > 0
        except (McapError, EOFError, ValueError, OSError, StopIteration, Exception) as exc:  # noqa: BLE001
            # a truncated file has no footer: everything below falls back to a linear read
            self.summary_error = f"{type(exc).__name__}: {exc}"

    def close(self) -> None:
        self.file.close()

    def channels(self) -> Optional[list[tuple[str, str, Optional[int]]]]:
        """(topic, schema name, count) from the summary; None without one."""
        if self.summary is None or not self.summary.channels:
            return None
        counts = self.summary.statistics.channel_message_counts if self.summary.statistics else {}
        return [
            (c.topic, self.summary.schemas[c.schema_id].name if c.schema_id else "", counts.get(c.id))
            for c in self.summary.channels.values()
        ]


class McapLog(DriveLog):
    """A drive in one MCAP file, or in a rosbag2 folder of MCAP files, of ROS 2 (CDR) messages."""

    format_name = "mcap"

    def __init__(self, path: str | Path, validate_crcs: bool = True):
        """``validate_crcs`` checks every chunk's CRC (on by default: zstd and lz4 chunks carry no
        checksum of their own, so without it a corrupt chunk could decode into wrong values)."""
        super().__init__(path)
        self.validate_crcs = validate_crcs
        if self.path.name == ROSBAG2_METADATA and self.path.is_file():
            self.path = self.path.parent  # a bag named by its metadata file, as ROS tools allow
        if self.path.is_dir():
            files = rosbag2_mcap_files(self.path)
        elif self.path.is_file():
            files = [self.path]
        else:
            raise InputError(self.path, "no such file")
        for f in files:
            if not is_mcap(f):
                raise InputError(f, "not an MCAP file (bad magic bytes)")
        #: the MCAP files read, in order (one for a bare ``.mcap``)
        self.files: list[Path] = files
        self._parts: list[_McapFile] = []
        try:
            for f in files:
                self._parts.append(_McapFile(f, validate_crcs))
        except OSError as exc:
            self.close()
            raise InputError(f, f"could not be opened ({exc})") from None
        self._streams: Optional[list[StreamInfo]] = None
        #: byte offset where reading stopped at damage (in ``truncated_file``), else None
        self.truncated_at: Optional[int] = None
        self.truncated_file: Optional[Path] = None

    def close(self) -> None:
        for part in self._parts:
            part.close()

    @property
    def is_rosbag2(self) -> bool:
        return self.path.is_dir()

    @property
    def indexed(self) -> bool:
        return all(p.indexed for p in self._parts)

    # --- streams ----------------------------------------------------------------------------------
    def streams(self) -> list[StreamInfo]:
        if self._streams is not None:
            return self._streams
        types: dict[str, str] = {}
        counts: dict[str, Optional[int]] = {}
        for part in self._parts:
            chans = part.channels()
            if chans is None:
                chans = self._scan_channels(part)
            for topic, t, n in chans:
                types.setdefault(topic, t)
                if n is None or (topic in counts and counts[topic] is None):
                    counts[topic] = None  # unknown in one file: unknown in all
                else:
                    counts[topic] = (counts.get(topic) or 0) + n
        self._streams = [
            StreamInfo(topic, ros2.KIND_OF_MSGTYPE.get(ros2.short_type(t), StreamKind.OTHER), ros2.short_type(t), counts[topic])
            for topic, t in sorted(types.items())
        ]
        return self._streams

    def _scan_channels(self, part: _McapFile) -> list[tuple[str, str, Optional[int]]]:
        """Channels and counts by a linear pass (no summary to read them from)."""
        counts: Counter[int] = Counter()
        channels: dict[int, Any] = {}
        for _, channel, message in self._linear_raw(part, None, warn=False):
            channels[channel.id] = channel
            counts[channel.id] += 1
        schemas = part.linear_schemas
        return [(c.topic, schemas[c.schema_id].name if c.schema_id in schemas else "", counts[cid]) for cid, c in channels.items()]

    # --- raw iteration ----------------------------------------------------------------------------
    def _raw(self, topics: Optional[set[str]]) -> Iterator[tuple[_McapFile, Any, Any, Any]]:
        """(file, schema, channel, message) of every message, file after file."""
        for part in self._parts:
            if part.indexed:
                part.file.seek(0)
                reader = SeekingReader(part.file, validate_crcs=self.validate_crcs)
                try:
                    for schema, channel, message in reader.iter_messages(
                        topics=None if topics is None else sorted(topics), log_time_order=True
                    ):
                        yield part, schema, channel, message
                except (McapError, EOFError, ValueError, OSError) as exc:
                    self._report_damage(part, part.file.tell(), exc)
            else:
                for schema, channel, message in self._linear_raw(part, topics):
                    yield part, schema, channel, message

    def _linear_raw(self, part: _McapFile, topics: Optional[set[str]], warn: bool = True) -> Iterator[tuple[Any, Any, Any]]:
        """Records of one file in file order, stopping (with a warning) where the file is damaged."""
        part.file.seek(0)
        part.linear_schemas = {}
        reader = NonSeekingReader(part.file, validate_crcs=self.validate_crcs)
        it = reader.iter_messages(topics=None if topics is None else sorted(topics), log_time_order=False)
        try:
            for schema, channel, message in it:
                if schema is not None:
                    part.linear_schemas[schema.id] = schema
                yield schema, channel, message
        except (McapError, EOFError, ValueError, OSError, Exception) as exc:  # noqa: BLE001
            if warn:
                self._report_damage(part, part.file.tell(), exc)
            else:
                self.truncated_at, self.truncated_file = part.file.tell(), part.path

    def _report_damage(self, part: _McapFile, offset: int, exc: BaseException) -> None:
        self.truncated_at, self.truncated_file = offset, part.path
        size = part.path.stat().st_size
        rest = self._parts[self._parts.index(part) + 1:]
        more = f"; reading goes on with the next file, {rest[0].path.name}" if rest else ""
        warnings.warn(
            f"{part.path}: log is truncated or corrupt near byte {offset} of {size} "
            f"({type(exc).__name__}: {exc}); messages after it are not read{more}",
            InputWarning,
            stacklevel=4,
        )

    def stamps(self, topics: Optional[set[str]] = None) -> Iterator[tuple[str, int]]:
        """(topic, header stamp in ns) of every message, without decoding payloads."""
        for _, schema, channel, message in self._raw(topics):
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
        for part, schema, channel, message in self._raw(topics):
            topic = channel.topic
            i = index[topic]
            index[topic] += 1
            kind = kinds.get(topic, StreamKind.OTHER)
            if kind == StreamKind.OTHER or schema is None:
                continue
            msgtype = ros2.short_type(schema.name)
            try:
                decoder = part.decoders.decoder_for(channel.message_encoding, schema)
                if decoder is None:
                    raise ValueError(f"no decoder for encoding {channel.message_encoding!r}")
                decoded = decoder(message.data)
                records = ros2.records_from_msg(decoded, msgtype, topic, i)
            except InputError as exc:
                self._skip(topic, i, "could not be decoded", exc.what)
                continue
            except Exception as exc:  # noqa: BLE001 - a corrupt payload must not end the stream
                self._skip(topic, i, "could not be decoded", f"{type(exc).__name__}: {exc}")
                continue
            for rec in records:
                yield Message(topic, kind, i, rec)


# --- writer ---------------------------------------------------------------------------------------

_COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}

#: rosbag2 metadata version written: 9, that of ROS 2 Jazzy (QoS profiles as YAML lists)
ROSBAG2_VERSION = 9
ROSBAG2_ROS_DISTRO = "jazzy"
# rmw's "infinite" duration (RMW_DURATION_INFINITE) as rosbag2 serialises it
_QOS_INFINITE = {"sec": 9223372036, "nsec": 854775807}


def offered_qos(topic: str) -> dict:
    """The QoS profile recorded as offered on a topic: ROS 2's defaults (reliable, volatile, keep
    last 10); ``/tf_static`` latched (transient local, keep last 1) as tf2's static broadcaster is,
    so that a player re-publishes it to late subscribers."""
    static = topic.rstrip("/").endswith("tf_static")
    return {
        "history": "keep_last", "depth": 1 if static else 10, "reliability": "reliable",
        "durability": "transient_local" if static else "volatile",
        "deadline": dict(_QOS_INFINITE), "lifespan": dict(_QOS_INFINITE), "liveliness": "automatic",
        "liveliness_lease_duration": dict(_QOS_INFINITE), "avoid_ros_namespace_conventions": False,
    }


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:  # e.g. Windows: folders cannot be opened
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


class McapWriter:
    """Writes mapkit records as ROS 2 messages into one MCAP file, atomically.

    The file appears under its name only when ``close()`` succeeds; until then it is written to a
    ``.partial`` sibling, which is removed if writing fails. Channels carry the offered QoS as
    ``ros2 bag record`` writes it (``offered_qos_profiles`` channel metadata).
    """

    def __init__(self, path: str | Path, *, compression: str = "zstd", chunk_size: int = 4 << 20):
        self.path = Path(path)
        self._open_file(self.path, compression, chunk_size)

    def _open_file(self, target: Path, compression: str, chunk_size: int) -> None:
        if compression not in _COMPRESSION:
            raise ValueError(f"compression must be one of {sorted(_COMPRESSION)}, not {compression!r}")
        self._target = target
        target.parent.mkdir(parents=True, exist_ok=True)
        self._tmp = target.with_name(target.name + ".partial")
        self._fh = open(self._tmp, "wb")
        self._writer = Ros2Writer(self._fh, chunk_size=chunk_size, compression=_COMPRESSION[compression])
        self._schemas: dict[str, Any] = {}
        self._sequence: Counter[str] = Counter()
        self._closed = False
        self.count = 0
        #: topic -> ROS 2 type name (``sensor_msgs/msg/Image``), in the order topics first appeared
        self.topic_types: dict[str, str] = {}
        #: topic -> messages written
        self.topic_counts: Counter[str] = Counter()
        #: smallest and largest log time written (ns), None before the first message
        self.first_log_ns: Optional[int] = None
        self.last_log_ns: Optional[int] = None

    def _schema(self, msgtype: str):
        if msgtype not in self._schemas:
            self._schemas[msgtype] = self._writer.register_msgdef(ros2.schema_name(msgtype), ros2.full_msgdef(msgtype))
        return self._schemas[msgtype]

    def _register_channel(self, topic: str, schema) -> None:
        """The topic's channel with its QoS metadata (mcap_ros2 registers channels without metadata)."""
        inner, ids = getattr(self._writer, "_writer", None), getattr(self._writer, "_channel_ids", None)
        if inner is None or not isinstance(ids, dict) or topic in ids:
            return  # another mcap_ros2 version: its own registration, without QoS, still makes a valid log
        qos = yaml.safe_dump([offered_qos(topic)], sort_keys=False).strip()
        ids[topic] = inner.register_channel(topic=topic, message_encoding="cdr", schema_id=schema.id,
                                            metadata={"offered_qos_profiles": qos})

    def _put(self, topic: str, msgtype: str, payload: dict, stamp_ns: int, log_time_ns: Optional[int]) -> None:
        log_time = int(stamp_ns if log_time_ns is None else log_time_ns)
        schema = self._schema(msgtype)
        if topic not in self.topic_types:
            self._register_channel(topic, schema)
            self.topic_types[topic] = schema.name
        self._writer.write_message(
            topic, schema, payload, log_time=log_time, publish_time=log_time, sequence=self._sequence[topic],
        )
        self._sequence[topic] += 1
        self.topic_counts[topic] += 1
        self.count += 1
        self.first_log_ns = log_time if self.first_log_ns is None else min(self.first_log_ns, log_time)
        self.last_log_ns = log_time if self.last_log_ns is None else max(self.last_log_ns, log_time)

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

    def _finish_file(self) -> None:
        self._writer.finish()
        self._fh.flush()
        os.fsync(self._fh.fileno())
        self._fh.close()
        os.replace(self._tmp, self._target)

    def close(self) -> Path:
        if not self._closed:
            self._finish_file()
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


class Rosbag2Writer(McapWriter):
    """Writes a rosbag2 folder as ``ros2 bag record -s mcap`` does, atomically.

    ``FOLDER/<name>_0.mcap`` holds the messages (as ``McapWriter`` writes them) and
    ``FOLDER/metadata.yaml`` the rosbag2 metadata (version 9, ROS 2 Jazzy's) made from the
    writer's own counts: topics with types, QoS and message counts, start time and duration.
    The folder is written as the hidden sibling ``.<name>.partial`` and renamed into place only
    when ``close()`` succeeds, so a killed run never leaves a folder that looks finished; the
    partial folder is removed if writing fails, or by the next writer of the same folder.
    """

    def __init__(self, folder: str | Path, *, compression: str = "zstd", chunk_size: int = 4 << 20,
                 ros_distro: str = ROSBAG2_ROS_DISTRO, custom_data: Optional[dict[str, str]] = None):
        self.path = Path(folder)
        if not self.path.name or self.path.name in (".", ".."):
            raise ValueError(f"a rosbag2 folder needs a name, not {str(folder)!r}")
        self.ros_distro = ros_distro
        self.custom_data = {str(k): str(v) for k, v in (custom_data or {}).items()}
        self._tmp_folder = self.path.with_name(f".{self.path.name}.partial")
        if self._tmp_folder.exists():  # left by a killed run
            shutil.rmtree(self._tmp_folder)
        #: the storage file's name inside the folder
        self.file_name = f"{self.path.name}_0.mcap"
        self._open_file(self._tmp_folder / self.file_name, compression, chunk_size)  # makes the partial folder

    def metadata(self) -> dict:
        """The ``metadata.yaml`` document for what has been written so far."""
        start = int(self.first_log_ns or 0)
        duration = int((self.last_log_ns - self.first_log_ns) if self.count else 0)
        topics = [
            {
                "topic_metadata": {
                    "name": topic, "type": msgtype, "serialization_format": "cdr",
                    "offered_qos_profiles": [offered_qos(topic)],
                    "type_description_hash": "",  # RIHS01 hashes are not computed
                },
                "message_count": int(self.topic_counts[topic]),
            }
            for topic, msgtype in self.topic_types.items()
        ]
        return {
            "rosbag2_bagfile_information": {
                "version": ROSBAG2_VERSION,
                "storage_identifier": "mcap",
                "duration": {"nanoseconds": duration},
                "starting_time": {"nanoseconds_since_epoch": start},
                "message_count": int(self.count),
                "topics_with_message_count": topics,
                "compression_format": "",
                "compression_mode": "",
                "relative_file_paths": [self.file_name],
                "files": [{
                    "path": self.file_name,
                    "starting_time": {"nanoseconds_since_epoch": start},
                    "duration": {"nanoseconds": duration},
                    "message_count": int(self.count),
                }],
                "custom_data": self.custom_data or None,
                "ros_distro": self.ros_distro,
            }
        }

    def close(self) -> Path:
        if self._closed:
            return self.path
        self._finish_file()
        atomic_write_text(self._tmp_folder / ROSBAG2_METADATA, yaml.safe_dump(self.metadata(), sort_keys=False, default_flow_style=False))
        _fsync_dir(self._tmp_folder)
        old = None
        if self.path.exists() or self.path.is_symlink():  # a folder cannot replace a non-empty one: swap
            old = self.path.with_name(f".{self.path.name}.old")
            if old.exists():
                shutil.rmtree(old)
            os.replace(self.path, old)
        os.replace(self._tmp_folder, self.path)
        _fsync_dir(self.path.parent)
        if old is not None and old.is_dir() and not old.is_symlink():
            shutil.rmtree(old, ignore_errors=True)
        elif old is not None:
            old.unlink(missing_ok=True)
        self._closed = True
        return self.path

    def abort(self) -> None:
        if not self._closed:
            self._fh.close()
            shutil.rmtree(self._tmp_folder, ignore_errors=True)
            self._closed = True

    def __enter__(self) -> "Rosbag2Writer":
        return self
