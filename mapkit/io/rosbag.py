"""ROS 1 bags and rosbag2 folders of any storage rosbags reads (sqlite3 here), on the ``rosbags`` library.

``rosbags.highlevel.AnyReader`` reads the bag's index (ROS 1) or metadata and storage (rosbag2) and
streams raw messages in record-time order, one chunk or one database page at a time; payloads are
deserialised one by one with the type definitions stored in the bag, topped up with a standard
typestore (ROS 1 Noetic or ROS 2 Jazzy) for types a bag does not define. The deserialised
dataclasses carry the field names of ``mapkit.io.ros2``'s conversions, so records are made exactly
as the MCAP reader makes them: header stamps, the same frames, the same arrays.

Topics of other message types are skipped with one warning per topic. A bag that rosbags cannot
open or read (truncated, corrupt, not a bag) is one ``InputError`` naming the file.
"""

from __future__ import annotations

import sqlite3
import struct
import warnings
from collections import Counter
from collections.abc import Iterator
from functools import partial
from pathlib import Path
from typing import Any

import apsw
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.rosbag1 import ReaderError as Rosbag1Error
from rosbags.rosbag2 import ReaderError as Rosbag2Error
from rosbags.serde import SerdeError
from rosbags.typesys import Stores, TypesysError, get_typestore

from mapkit.core.errors import InputError, InputWarning
from mapkit.core.types import Message, StreamInfo, StreamKind
from mapkit.io import ros2
from mapkit.io.base import DriveLog
from mapkit.io.mcap_log import ROSBAG2_METADATA, is_rosbag2

#: the first bytes of a ROS 1 bag (format 2.0, the only one rosbag has written since ROS C Turtle)
ROSBAG1_MAGIC = b"#ROSBAG V2.0\n"
#: ROS 1 types read as their ROS 2 twin (same fields): tf's message before tf2
ALIASES = {"tf/tfMessage": "tf2_msgs/TFMessage"}
# what rosbags (and the storage libraries under it) raise on a bag it cannot read
_READ_ERRORS = (
    AnyReaderError,
    Rosbag1Error,
    Rosbag2Error,
    TypesysError,
    SerdeError,
    apsw.Error,
    sqlite3.Error,
    OSError,
    EOFError,
    ValueError,
    struct.error,
    KeyError,
    IndexError,
    AssertionError,
)


def is_rosbag1(path: str | Path) -> bool:
    try:
        with open(path, "rb") as f:
            return f.read(len(ROSBAG1_MAGIC)) == ROSBAG1_MAGIC
    except OSError:
        return False


def msgtype_of(name: str | None) -> str:
    """``pkg/msg/Type`` as rosbags names it -> the ``pkg/Type`` of ``ros2.KIND_OF_MSGTYPE``."""
    short = ros2.short_type(name or "")
    return ALIASES.get(short, short)


def header_stamp_from_ros1(data: bytes | memoryview) -> int | None:
    """The ``header.stamp`` of a ROS 1 message whose first field is a std_msgs/Header, undecoded:
    little-endian uint32 seq, then uint32 sec and nsec."""
    if len(data) < 12:
        return None
    sec, nsec = struct.unpack_from("<II", data, 4)
    return sec * 1_000_000_000 + nsec


class RosbagLog(DriveLog):
    """A ROS 1 ``.bag`` file or a rosbag2 folder (sqlite3 storage; mcap too), read through rosbags."""

    format_name = "rosbag"

    def __init__(self, path: str | Path):
        super().__init__(path)
        if self.path.name == ROSBAG2_METADATA and self.path.is_file():
            self.path = self.path.parent  # a bag named by its metadata file, as ROS tools allow
        if self.path.is_dir():
            if not is_rosbag2(self.path):
                raise InputError(self.path, f"not a rosbag2 folder (no {ROSBAG2_METADATA})")
            default = Stores.ROS2_JAZZY
        elif self.path.is_file():
            if not is_rosbag1(self.path):
                raise InputError(self.path, f"not a ROS 1 bag (it does not start with {ROSBAG1_MAGIC!r})")
            if self.path.suffix != ".bag":  # rosbags tells ROS 1 from rosbag2 by this suffix
                raise InputError(self.path, "is a ROS 1 bag without the .bag suffix; rename it to end in .bag")
            default = Stores.ROS1_NOETIC
        else:
            raise InputError(self.path, "no such file or folder")
        #: True for a ROS 1 bag, False for a rosbag2 folder
        self.is_ros1 = default == Stores.ROS1_NOETIC
        standard = get_typestore(default)
        try:
            reader = AnyReader([self.path], default_typestore=standard)
        except _READ_ERRORS as exc:
            raise self._error(exc) from None
        self._reader: AnyReader = reader
        try:
            self._reader.open()
            self._top_up_types(standard)
            self._streams = self._read_streams()
        except _READ_ERRORS as exc:
            self.close()
            raise self._error(exc) from None
        self._warned_unknown: set[str] = set()

    def _error(self, exc: BaseException) -> InputError:
        what = "ROS 1 bag" if self.is_ros1 else "rosbag2 folder"
        return InputError(
            self.path, f"could not be read as a {what} (truncated or corrupt?): {type(exc).__name__}: {exc}"
        )

    def _top_up_types(self, default: Any) -> None:
        """Standard types the bag does not define itself (a rosbag2 bag may store no definitions)."""
        have = self._reader.typestore.fielddefs
        if all(c.msgtype in have for c in self._reader.connections):
            return
        self._reader.typestore.register(
            {name: fields for name, fields in default.fielddefs.items() if name not in have}
        )

    def _read_streams(self) -> list[StreamInfo]:
        out = []
        for topic, info in sorted(self._reader.topics.items()):
            msgtype = msgtype_of(info.msgtype)  # None when connections of one topic disagree: not read
            kind = ros2.KIND_OF_MSGTYPE.get(msgtype, StreamKind.OTHER) if info.msgtype else StreamKind.OTHER
            out.append(StreamInfo(topic, kind, msgtype, int(info.msgcount)))
        return out

    def close(self) -> None:
        if self._reader is not None and self._reader.stack is not None:
            self._reader.close()

    def streams(self) -> list[StreamInfo]:
        """Streams and counts from the bag's index (ROS 1) or its storage's tables (rosbag2)."""
        return self._streams

    # --- raw iteration ----------------------------------------------------------------------------
    def _raw(self, topics: set[str] | None, known_only: bool) -> Iterator[tuple[Any, str, int, bytes]]:
        """(connection, pkg/Type, record time ns, raw bytes) of the messages of ``topics`` (all if None),
        in record-time order; with ``known_only``, topics of other types are left out with a warning."""
        kinds = {s.topic: s.kind for s in self._streams}
        wanted = set(kinds) if topics is None else set(topics)
        if known_only:
            unknown = {t for t in wanted if kinds.get(t) == StreamKind.OTHER}
            for topic in sorted(unknown - self._warned_unknown):
                mtype = next(s.msgtype for s in self._streams if s.topic == topic) or "several types"
                warnings.warn(
                    f"{self.path}: topic {topic} ({mtype}) is not a message type mapkit reads; skipped",
                    InputWarning,
                    stacklevel=4,
                )
            self._warned_unknown |= unknown
            wanted -= unknown
        conns = [c for c in self._reader.connections if c.topic in wanted]
        if not conns:
            return  # AnyReader reads every connection when given none
        it = self._reader.messages(connections=conns)
        while True:
            try:
                conn, t, raw = next(it)
            except StopIteration:
                return
            except _READ_ERRORS as exc:
                raise self._error(exc) from None
            yield conn, msgtype_of(conn.msgtype), t, raw

    def stamps(self, topics: set[str] | None = None) -> Iterator[tuple[str, int]]:
        """(topic, header stamp in ns) of every message, other types included, without deserialising
        payloads; the record time where a message has no header first (tf), as the MCAP reader does
        with its log time."""
        header_at = header_stamp_from_ros1 if self.is_ros1 else ros2.header_stamp_from_cdr
        for conn, msgtype, t, raw in self._raw(topics, known_only=False):
            stamp = header_at(raw) if msgtype in ros2.HEADER_FIRST else None
            yield conn.topic, t if stamp is None else stamp

    # --- decoded iteration ------------------------------------------------------------------------
    def _iter_messages(self, topics: set[str] | None) -> Iterator[Message]:
        kinds = {s.topic: s.kind for s in self._streams}
        index: Counter[str] = Counter()
        for conn, msgtype, _, raw in self._raw(topics, known_only=True):
            topic = conn.topic
            i = index[topic]
            index[topic] += 1
            records = self._records_or_skip(topic, i, partial(self._decode, raw, conn, msgtype, topic, i))
            for rec in records:
                yield Message(topic, kinds[topic], i, rec)

    def _decode(self, raw: bytes, conn: Any, msgtype: str, topic: str, index: int) -> list:
        """The records of one message (raises on a payload that cannot be deserialised)."""
        return ros2.records_from_msg(self._reader.deserialize(raw, conn.msgtype), msgtype, topic, index)
