"""MCAP logs of ROS 2 messages: a streaming reader and atomic writers, on the ``mcap`` library.

A log is one ``.mcap`` file or a rosbag2 folder with MCAP storage, as ``ros2 bag record -s mcap``
writes it (``metadata.yaml`` beside ``<name>_0.mcap``, ``<name>_1.mcap``, ...); the folder's files
are read in the order ``metadata.yaml`` lists them, as one log.

Reading never trusts one damaged byte with the rest of the file. Each file's chunks are located from
its summary when that is intact (CRC and chunk index checked), otherwise by a linear scan that steps
over damage to the next well-formed chunk; each chunk is decompressed on its own, with its CRC
checked, and messages come in log-time order. A damaged chunk, a truncated end or a damaged summary
costs only the messages in the damaged part: a warning names the file and byte offset, and every
intact chunk after it is read.
"""

from __future__ import annotations

import heapq
import io
import itertools
import mmap
import os
import shutil
import struct
import warnings
import zlib
from collections import Counter
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from functools import partial
from pathlib import Path, PurePosixPath
from typing import Any

import lz4.frame
import yaml
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import Channel, ChunkIndex, Schema, Statistics
from mcap.records import Message as McapMessage
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


def _mcap_with_damaged_magic(path: Path) -> bool:
    """Whether a file whose first 8 bytes are not the MCAP magic is an MCAP all the same: it ends with the
    magic, or a header record (opcode 0x01 and a length inside the file) follows the 8 bytes."""
    try:
        with open(path, "rb") as f:
            head = f.read(len(MCAP_MAGIC) + 9)
            size = os.fstat(f.fileno()).st_size
            f.seek(max(size - len(MCAP_MAGIC), 0))
            tail = f.read()
    except OSError:
        return False
    if size < 2 * len(MCAP_MAGIC) + 9:
        return False
    op, length = struct.unpack_from("<BQ", head, len(MCAP_MAGIC))
    return tail == MCAP_MAGIC or (op == Opcode.HEADER and length < size)


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
    except (OSError, UnicodeDecodeError, yaml.YAMLError, RecursionError) as exc:
        raise InputError(meta_path, f"could not be read as YAML ({type(exc).__name__}: {str(exc)[:200]})") from None
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
    files = info.get("files")
    files_info = files if isinstance(files, list) else []
    rel = info.get("relative_file_paths") or [f["path"] for f in files_info if isinstance(f, dict) and "path" in f]
    if not rel:
        raise InputError(meta_path, "lists no storage files", field="relative_file_paths")
    if not isinstance(rel, list) or not all(isinstance(p, str) and p and "\0" not in p for p in rel):
        raise InputError(
            meta_path, f"relative_file_paths is not a list of file names: {str(rel)[:80]}", field="relative_file_paths"
        )
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
        raise InputError(
            meta_path,
            f"compressed rosbag2 ({info.get('compression_mode')} mode, "
            f"{info.get('compression_format')!r}) cannot be read; decompress it with `ros2 bag convert`",
            field="compression_mode",
        )
    # versions before 4 wrote paths relative to the bag's parent folder: the file name is what counts
    files = [folder / PurePosixPath(str(p).replace("\\", "/")).name for p in rel]
    missing = [f.name for f in files if not f.is_file()]
    if missing:
        raise InputError(
            folder, f"storage files listed in {ROSBAG2_METADATA} are missing: {missing}", field="relative_file_paths"
        )
    return files


#: largest chunk mapkit decompresses: far above what recorders write (``ros2 bag record`` closes a chunk at a
#: few MB; one message larger than that makes a chunk of its own size), and it keeps a corrupt size field from
#: asking for exabytes
MAX_CHUNK_BYTES = 1 << 30
_RECORD_HEAD = struct.Struct("<BQ")  # opcode, body length
#: a chunk's fields before its compression name: message start and end time, uncompressed size and CRC
_CHUNK_HEAD = struct.Struct("<QQQI")
#: a message's fields before its payload: channel id, sequence, log time, publish time
_MESSAGE_HEAD = struct.Struct("<HIQQ")
#: a footer record: opcode, length (20), summary start, summary offset start, summary CRC
_FOOTER = struct.Struct("<BQQQI")
_COMPRESSIONS = ("", "zstd", "lz4")
_KNOWN_OPCODES = frozenset(int(op) for op in Opcode)
_SUMMARY_RECORDS: dict[Opcode, type[Schema] | type[Channel] | type[ChunkIndex] | type[Statistics]] = {
    Opcode.SCHEMA: Schema,
    Opcode.CHANNEL: Channel,
    Opcode.CHUNK_INDEX: ChunkIndex,
    Opcode.STATISTICS: Statistics,
}
#: what damaged bytes make the record parsers and decompressors raise
_PARSE_ERRORS = (
    McapError,
    EOFError,
    ValueError,
    struct.error,
    OverflowError,
    MemoryError,
    RuntimeError,
    zstandard.ZstdError,
)


class _Damage(Exception):
    """A part of an MCAP file that cannot be read; ``offset`` is the file byte where it starts (None: nowhere in
    particular)."""

    def __init__(self, offset: int | None, what: str):
        super().__init__(what)
        self.offset = offset
        self.what = what


@dataclass(frozen=True)
class _Segment:
    """A chunk record, or a message record outside chunks, located in its file."""

    offset: int  # of the record's opcode byte
    length: int  # of the record's body
    start_ns: int  # log time of its first message
    chunk: bool
    #: channels with messages in the chunk (from its chunk index), None where unknown
    channel_ids: frozenset[int] | None = None


@dataclass(frozen=True)
class _ChunkHead:
    """The fields of a chunk record up to its compressed records."""

    start_ns: int
    uncompressed_size: int
    crc: int
    compression: str
    data_at: int  # file offset of the compressed records
    data_len: int


def _records(buf, start: int, end: int, where: Callable[[int], int]) -> Iterator[tuple[int, memoryview]]:
    """(opcode, body) of the records in ``buf[start:end]``, bodies as views (copy what is kept); ``where`` maps a
    position to a file offset for errors."""
    view = memoryview(buf)
    pos = start
    try:
        while pos < end:
            if pos + _RECORD_HEAD.size > end:
                raise _Damage(where(pos), "a record header is cut off")
            op, length = _RECORD_HEAD.unpack_from(buf, pos)
            body = pos + _RECORD_HEAD.size
            if length > end - body:
                raise _Damage(where(pos), f"a record claims {length} bytes, {end - body} are left")
            with view[body : body + length] as record:
                yield op, record
            pos = body + length
    finally:
        view.release()  # an mmap cannot close while a view of it lives


def _parse(op: int, body: bytes | memoryview, offset: int):
    """The summary-type record (schema, channel, chunk index, statistics) of one record body."""
    try:
        return _SUMMARY_RECORDS[Opcode(op)].read(ReadDataStream(io.BytesIO(body)))
    except _PARSE_ERRORS as exc:
        raise _Damage(offset, f"a {Opcode(op).name.lower()} record is damaged ({type(exc).__name__})") from None


def _message(body: bytes | memoryview, offset: int) -> McapMessage:
    """A message record's fields, its payload copied out of ``body``."""
    if len(body) < _MESSAGE_HEAD.size:
        raise _Damage(offset, f"a message record of {len(body)} bytes is shorter than its fixed fields")
    channel_id, sequence, log_time, publish_time = _MESSAGE_HEAD.unpack_from(body)
    return McapMessage(
        channel_id=channel_id,
        log_time=log_time,
        data=bytes(body[_MESSAGE_HEAD.size :]),
        publish_time=publish_time,
        sequence=sequence,
    )


def _decompress(compression: str, data: bytes, size: int, offset: int) -> bytes:
    """``data`` decompressed; stops after ``size`` + 1 bytes however the stream is damaged."""
    if compression == "":
        out = data
    elif compression == "zstd" and zstandard.frame_content_size(data) == size:
        out = zstandard.ZstdDecompressor().decompress(data)  # one allocation, of the size already checked
    elif compression == "zstd":  # a frame without its size (or a damaged one): in pieces, stopping past the size
        buf = bytearray()
        for piece in zstandard.ZstdDecompressor().read_to_iter(io.BytesIO(data), write_size=1 << 20):
            buf += piece
            if len(buf) > size:
                break
        out = bytes(buf)
    else:
        decompressor = lz4.frame.LZ4FrameDecompressor()
        buf = bytearray(decompressor.decompress(data, max_length=size + 1))
        while not decompressor.eof and not decompressor.needs_input and len(buf) <= size:
            buf += decompressor.decompress(b"", max_length=size + 1 - len(buf))
        out = bytes(buf)
    if len(out) != size:
        got = f"more than {size}" if len(out) > size else str(len(out))
        raise _Damage(offset, f"the chunk decompresses to {got} bytes, its header says {size}")
    return out


class _McapFile:
    """One MCAP file, located record by record so that damage costs only the damaged part.

    With an intact summary (its CRC matches; in a file written without CRCs, every chunk index points at a
    chunk record of the length it gives) the chunks come from the chunk index. Otherwise a linear scan of the data
    section finds them; it steps over a damaged record by searching for the next well-formed chunk record (opcode,
    length and fields that add up). Each chunk is then read on its own with its CRC checked, so a damaged chunk is
    skipped and every intact chunk after it is kept. Messages come in log-time order: chunks are opened
    in order of their first message and merged, so only overlapping chunks are held at once.
    """

    def __init__(self, path: Path, validate_crcs: bool):
        self.path = path
        self.validate_crcs = validate_crcs
        with open(path, "rb") as f:
            self.size = os.fstat(f.fileno()).st_size
            self._map = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.statistics: Statistics | None = None
        self.segments: list[_Segment] = []
        #: the summary was read and checked (its channels and counts are trusted)
        self.summary_ok = False
        #: why the summary was not used, when the file has one that is damaged
        self.summary_problem: str | None = None
        #: damage found while locating records (each costs the messages in it)
        self.damage: list[_Damage] = []
        # definitions from a damaged summary, used only for ids no chunk defines
        self._fallback_schemas: dict[int, Schema] = {}
        self._fallback_channels: dict[int, Channel] = {}
        # decoders are cached by schema id, which is only unique within one file
        self.decoders = DecoderFactory()
        self._read_summary()
        if not self.indexed:
            self._scan()

    @property
    def indexed(self) -> bool:
        return self.summary_ok and any(s.chunk for s in self.segments)

    def close(self) -> None:
        self._map.close()

    # --- locating ---------------------------------------------------------------------------------
    def _read_summary(self) -> None:
        """Reads the summary; it is used when its CRC matches (or, written without a CRC, when every chunk
        index points at a chunk record of the length it gives). A damaged summary still lends its schemas
        and channels to messages whose own definitions are lost with a damaged chunk."""
        footer_at = self.size - len(MCAP_MAGIC) - _FOOTER.size
        if footer_at < len(MCAP_MAGIC) or self._map[self.size - len(MCAP_MAGIC) :] != MCAP_MAGIC:
            self.damage.append(_Damage(self.size, "the file ends without a footer (truncated)"))
            return
        op, length, summary_start, _, crc = _FOOTER.unpack_from(self._map, footer_at)
        if op != Opcode.FOOTER or length != _FOOTER.size - _RECORD_HEAD.size:
            self.summary_problem = f"the footer record at byte {footer_at} is damaged"
            return
        if summary_start == 0:
            return  # written without a summary
        if not len(MCAP_MAGIC) <= summary_start <= footer_at:
            self.summary_problem = f"the footer puts the summary at byte {summary_start}, outside the file"
            return
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        statistics, indexes, problem = None, [], None
        try:
            for op, body in _records(self._map, summary_start, footer_at, lambda pos: pos):
                if op in _SUMMARY_RECORDS:
                    rec = _parse(op, body, summary_start)
                    if isinstance(rec, Schema):
                        schemas[rec.id] = rec
                    elif isinstance(rec, Channel):
                        channels[rec.id] = rec
                    elif isinstance(rec, Statistics):
                        statistics = rec
                    else:
                        indexes.append(rec)
        except _Damage as exc:
            problem = f"the summary is damaged ({exc.what})"
        segments = [
            _Segment(
                ci.chunk_start_offset,
                ci.chunk_length - _RECORD_HEAD.size,
                ci.message_start_time,
                True,
                frozenset(ci.message_index_offsets) or None,
            )
            for ci in indexes
        ]
        if problem is None and crc and zlib.crc32(self._map[summary_start : footer_at + _FOOTER.size - 4]) != crc:
            problem = f"the summary section (bytes {summary_start} to {self.size}) fails its CRC"
        if problem is None and not crc:  # nothing vouches for the chunk index: check where it points
            try:
                for seg in segments:
                    self._chunk_at(seg.offset, seg.length)
            except _Damage as exc:
                problem = f"the summary does not match the data ({exc.what} at byte {exc.offset})"
        if problem is not None:
            self.summary_problem = problem
            self._fallback_schemas, self._fallback_channels = schemas, channels
            return
        self.schemas, self.channels, self.statistics, self.segments = schemas, channels, statistics, segments
        self.summary_ok = True

    def _chunk_at(self, offset: int, length: int | None = None) -> _ChunkHead:
        """The fields of the chunk record at ``offset`` (checked for shape, not content); ``_Damage`` if none is
        there."""
        m = self._map
        if not len(MCAP_MAGIC) <= offset <= self.size - _RECORD_HEAD.size:
            raise _Damage(offset, "no chunk record there (outside the file)")
        op, body_len = _RECORD_HEAD.unpack_from(m, offset)
        if op != Opcode.CHUNK:
            raise _Damage(offset, f"expected a chunk record, found opcode 0x{op:02x}")
        if length is not None and body_len != length:
            raise _Damage(offset, f"the chunk record is {body_len} bytes long, its index says {length}")
        body = offset + _RECORD_HEAD.size
        if body_len > self.size - body:
            raise _Damage(offset, f"a chunk record of {body_len} bytes runs past the end of the file")
        fixed = _CHUNK_HEAD.size + 4
        if body_len < fixed + 8:
            raise _Damage(offset, f"a chunk record of {body_len} bytes is shorter than its fixed fields")
        start, _, size, crc = _CHUNK_HEAD.unpack_from(m, body)
        (name_len,) = struct.unpack_from("<I", m, body + _CHUNK_HEAD.size)
        if name_len > max(map(len, _COMPRESSIONS)) or body_len < fixed + name_len + 8:
            raise _Damage(offset, "the chunk's compression field is damaged")
        name = bytes(m[body + fixed : body + fixed + name_len])
        (data_len,) = struct.unpack_from("<Q", m, body + fixed + name_len)
        if fixed + name_len + 8 + data_len != body_len:
            raise _Damage(offset, f"the chunk's fields do not add up to its length of {body_len} bytes")
        if name.decode("ascii", "replace") not in _COMPRESSIONS:
            raise _Damage(offset, f"unknown chunk compression {name!r}")
        return _ChunkHead(start, size, crc, name.decode(), body + fixed + name_len + 8, data_len)

    def _next_chunk(self, start: int) -> int | None:
        """The offset of the next well-formed chunk record at or after ``start``, if any."""
        pos = start
        while True:
            pos = self._map.find(bytes([Opcode.CHUNK]), pos)
            if pos < 0:
                return None
            try:
                self._chunk_at(pos)
                return pos
            except _Damage:
                pos += 1

    def _scan(self) -> None:
        """Locates chunks (and messages outside chunks) from the start of the file, up to the data end."""
        pos = len(MCAP_MAGIC)
        while pos + _RECORD_HEAD.size <= self.size:
            op, length = _RECORD_HEAD.unpack_from(self._map, pos)
            body, end = pos + _RECORD_HEAD.size, pos + _RECORD_HEAD.size + length
            try:
                if op in (Opcode.DATA_END, Opcode.FOOTER):
                    # the summary after a real data end holds no chunk: one that follows says this opcode is damage
                    if self._next_chunk(pos + 1) is None:
                        return
                    raise _Damage(pos, f"an end-of-data opcode (0x{op:02x}) with chunks after it")
                if op not in _KNOWN_OPCODES:
                    raise _Damage(pos, f"no record starts here (opcode 0x{op:02x})")
                if end > self.size:
                    raise _Damage(pos, f"a record of {length} bytes runs past the end of the file")
                if op == Opcode.CHUNK:
                    head = self._chunk_at(pos)
                    self.segments.append(_Segment(pos, length, head.start_ns, True))
                elif op == Opcode.MESSAGE:
                    log_time = _message(bytes(self._map[body : body + min(length, _MESSAGE_HEAD.size)]), pos).log_time
                    self.segments.append(_Segment(pos, length, log_time, False))
                elif op in (Opcode.SCHEMA, Opcode.CHANNEL):
                    self._define(_parse(op, bytes(self._map[body:end]), pos))
            except _Damage as exc:
                resume = self._next_chunk(pos + 1)
                after = f"bytes {pos} to {resume} are skipped" if resume is not None else "nothing after it can be read"
                self.damage.append(_Damage(exc.offset, f"{exc.what}; {after}"))
                if resume is None:
                    return
                pos = resume
                continue
            pos = end
        if pos < self.size:
            self.damage.append(_Damage(pos, "a record header is cut off (truncated)"))

    def _define(self, rec) -> None:
        """A schema or channel seen in the data: the first definition of an id counts."""
        if isinstance(rec, Schema):
            self.schemas.setdefault(rec.id, rec)
        else:
            self.channels.setdefault(rec.id, rec)

    # --- reading ----------------------------------------------------------------------------------
    def _load(self, seg: _Segment) -> tuple[list[McapMessage], _Damage | None]:
        """The messages of one segment, defining the schemas and channels in it; on damage part-way, the
        messages before it and the damage."""
        body = seg.offset + _RECORD_HEAD.size
        if not seg.chunk:
            return [_message(bytes(self._map[body : body + seg.length]), seg.offset)], None
        head = self._chunk_at(seg.offset, seg.length)
        if head.uncompressed_size > MAX_CHUNK_BYTES:
            raise _Damage(
                seg.offset,
                f"the chunk claims {head.uncompressed_size} bytes uncompressed (more than {MAX_CHUNK_BYTES})",
            )
        compressed = bytes(self._map[head.data_at : head.data_at + head.data_len])
        self._release(head.data_at, head.data_at + head.data_len)
        try:
            data = _decompress(head.compression, compressed, head.uncompressed_size, seg.offset)
        except _PARSE_ERRORS as exc:
            raise _Damage(seg.offset, f"the chunk does not decompress ({type(exc).__name__}: {exc})") from None
        if self.validate_crcs and head.crc and zlib.crc32(data) != head.crc:
            raise _Damage(seg.offset, "the chunk fails its CRC")
        messages: list[McapMessage] = []
        try:
            for op, rec in _records(data, 0, len(data), lambda _: seg.offset):
                if op == Opcode.MESSAGE:
                    messages.append(_message(rec, seg.offset))
                elif op in (Opcode.SCHEMA, Opcode.CHANNEL):
                    self._define(_parse(op, rec, seg.offset))
        except _Damage as exc:
            return messages, exc
        return messages, None

    def _release(self, start: int, end: int) -> None:
        """Hand the mapped pages of ``[start, end)`` back to the kernel once their bytes are copied out: the
        pages of a mapped file stay in the process's memory once touched, which would make a reader's
        peak memory grow with the log's length. (They stay in the page cache; reading them again is exact.)"""
        if hasattr(mmap, "MADV_DONTNEED"):
            first = start - start % mmap.PAGESIZE
            if end > first:
                self._map.madvise(mmap.MADV_DONTNEED, first, end - first)

    def raw(
        self, topics: set[str] | None, on_damage: Callable[[_Damage], None]
    ) -> Iterator[tuple[Any, Any, McapMessage]]:
        """(schema, channel, message) in log-time order; damaged segments go to ``on_damage`` and are skipped."""
        segments = sorted(self.segments, key=lambda s: (s.start_ns, s.offset))
        wanted_ids = None
        if topics is not None and self.summary_ok:
            wanted_ids = {cid for cid, c in self.channels.items() if c.topic in topics}
        heap: list[tuple[int, int, McapMessage]] = []
        order = itertools.count()
        unknown: Counter[int] = Counter()
        i = 0
        while i < len(segments) or heap:
            # open every segment that may hold a message earlier than the earliest one held
            while i < len(segments) and (not heap or segments[i].start_ns <= heap[0][0]):
                seg = segments[i]
                i += 1
                if wanted_ids is not None and seg.channel_ids is not None and not seg.channel_ids & wanted_ids:
                    continue
                try:
                    messages, damage = self._load(seg)
                except _Damage as exc:
                    messages, damage = [], exc
                if damage is not None:
                    on_damage(damage)
                for m in messages:
                    heapq.heappush(heap, (m.log_time, next(order), m))
            if not heap:
                continue
            message = heapq.heappop(heap)[2]
            channel = self.channels.get(message.channel_id) or self._fallback_channels.get(message.channel_id)
            if channel is None:
                unknown[message.channel_id] += 1
                continue
            if topics is None or channel.topic in topics:
                yield (
                    self.schemas.get(channel.schema_id) or self._fallback_schemas.get(channel.schema_id),
                    channel,
                    message,
                )
        for cid, n in unknown.items():
            on_damage(_Damage(None, f"{n} messages of channel {cid} skipped: its channel record is lost"))

    def count_messages(self) -> Counter[int]:
        """Messages per channel id by reading every segment (no summary to count them); damage is left
        for the reading passes to report."""
        counts: Counter[int] = Counter()
        for seg in self.segments:
            try:
                messages, _ = self._load(seg)
            except _Damage:
                continue
            counts.update(m.channel_id for m in messages)
        return counts

    def channel_list(self) -> list[tuple[str, str, int | None]]:
        """(topic, schema name, count) of every channel."""
        if self.summary_ok and self.channels:
            counts = self.statistics.channel_message_counts if self.statistics else {}
            channels, schemas = self.channels, self.schemas
        else:
            counts = self.count_messages()
            lent = {cid: c for cid, c in self._fallback_channels.items() if counts.get(cid)}
            channels, schemas = {**lent, **self.channels}, {**self._fallback_schemas, **self.schemas}
        return [
            (c.topic, schemas[c.schema_id].name if c.schema_id in schemas else "", counts.get(cid))
            for cid, c in channels.items()
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
                if not _mcap_with_damaged_magic(f):
                    raise InputError(f, "not an MCAP file (bad magic bytes)")
                warnings.warn(
                    f"{f}: the MCAP magic bytes at its start are damaged; read as MCAP all the same (its header "
                    "record or closing magic says it is one)",
                    InputWarning,
                    stacklevel=2,
                )
        #: the MCAP files read, in order (one for a bare ``.mcap``)
        self.files: list[Path] = files
        self._parts: list[_McapFile] = []
        try:
            for f in files:
                self._parts.append(_McapFile(f, validate_crcs))
        except (OSError, ValueError) as exc:
            self.close()
            raise InputError(f, f"could not be opened ({exc})") from None
        self._streams: list[StreamInfo] | None = None
        #: byte offset of the first damage met (in ``truncated_file``, the earliest there), else None;
        #: reading goes on after it
        self.truncated_at: int | None = None
        self.truncated_file: Path | None = None
        #: (file, byte offset or None, what) of every damaged part met, once each
        self.damage: list[tuple[Path, int | None, str]] = []
        self._reported: set[tuple[Path, int | None, str]] = set()

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
        counts: dict[str, int | None] = {}
        for part in self._parts:
            for topic, t, n in part.channel_list():
                types.setdefault(topic, t)
                if n is None or (topic in counts and counts[topic] is None):
                    counts[topic] = None  # unknown in one file: unknown in all
                else:
                    counts[topic] = (counts.get(topic) or 0) + n
        self._streams = [
            StreamInfo(
                topic, ros2.KIND_OF_MSGTYPE.get(ros2.short_type(t), StreamKind.OTHER), ros2.short_type(t), counts[topic]
            )
            for topic, t in sorted(types.items())
        ]
        return self._streams

    # --- raw iteration ----------------------------------------------------------------------------
    def _raw(self, topics: set[str] | None) -> Iterator[tuple[_McapFile, Any, Any, Any]]:
        """(file, schema, channel, message) of every message, file after file."""
        for part in self._parts:
            if part.summary_problem is not None:
                self._warn_once(part, None, f"{part.summary_problem}; its chunks are found by a linear scan instead")
            for damage in part.damage:
                self._report_damage(part, damage)
            for schema, channel, message in part.raw(topics, partial(self._report_damage, part)):
                yield part, schema, channel, message

    def _report_damage(self, part: _McapFile, damage: _Damage) -> None:
        if damage.offset is None:
            self._warn_once(part, None, damage.what)
            return
        if self.truncated_at is None or (part.path == self.truncated_file and damage.offset < self.truncated_at):
            self.truncated_at, self.truncated_file = damage.offset, part.path
        self._warn_once(
            part,
            damage.offset,
            f"log is truncated or corrupt near byte {damage.offset} of {part.size} ({damage.what}); "
            "the messages there are skipped, intact chunks after it are read",
        )

    def _warn_once(self, part: _McapFile, offset: int | None, what: str) -> None:
        key = (part.path, offset, what)
        if key in self._reported:
            return
        self._reported.add(key)
        self.damage.append(key)
        warnings.warn(f"{part.path}: {what}", InputWarning, stacklevel=4)

    def stamps(self, topics: set[str] | None = None) -> Iterator[tuple[str, int]]:
        """(topic, header stamp in ns) of every message, without decoding payloads."""
        for _, schema, channel, message in self._raw(topics):
            header_first = (
                schema is not None
                and channel.message_encoding == "cdr"
                and ros2.short_type(schema.name) in ros2.HEADER_FIRST
            )
            stamp = ros2.header_stamp_from_cdr(message.data) if header_first else None
            yield channel.topic, message.log_time if stamp is None else stamp

    # --- decoded iteration ------------------------------------------------------------------------
    def _iter_messages(self, topics: set[str] | None) -> Iterator[Message]:
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
            decode = partial(self._decode, part, schema, channel, message, msgtype, topic, i)
            records = self._records_or_skip(topic, i, decode)
            for rec in records:
                yield Message(topic, kind, i, rec)

    @staticmethod
    def _decode(part: _McapFile, schema: Any, channel: Any, message: Any, msgtype: str, topic: str, index: int) -> list:
        """The records of one message (raises on a payload that cannot be decoded)."""
        decoder = part.decoders.decoder_for(channel.message_encoding, schema)
        if decoder is None:
            raise ValueError(f"no decoder for encoding {channel.message_encoding!r}")
        return ros2.records_from_msg(decoder(message.data), msgtype, topic, index)


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
        "history": "keep_last",
        "depth": 1 if static else 10,
        "reliability": "reliable",
        "durability": "transient_local" if static else "volatile",
        "deadline": dict(_QOS_INFINITE),
        "lifespan": dict(_QOS_INFINITE),
        "liveliness": "automatic",
        "liveliness_lease_duration": dict(_QOS_INFINITE),
        "avoid_ros_namespace_conventions": False,
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
        self._fh = open(self._tmp, "wb")  # noqa: SIM115 - open for the writer's lifetime; close() and abort() close it
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
        self.first_log_ns: int | None = None
        self.last_log_ns: int | None = None

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
        ids[topic] = inner.register_channel(
            topic=topic, message_encoding="cdr", schema_id=schema.id, metadata={"offered_qos_profiles": qos}
        )

    def _put(self, topic: str, msgtype: str, payload: dict, stamp_ns: int, log_time_ns: int | None) -> None:
        log_time = int(stamp_ns if log_time_ns is None else log_time_ns)
        schema = self._schema(msgtype)
        if topic not in self.topic_types:
            self._register_channel(topic, schema)
            self.topic_types[topic] = schema.name
        self._writer.write_message(
            topic,
            schema,
            payload,
            log_time=log_time,
            publish_time=log_time,
            sequence=self._sequence[topic],
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
        log_time_ns: int | None = None,
        compress: str | None = None,
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

    def write_transforms(self, topic: str, transforms: list[FrameTransform], *, log_time_ns: int | None = None) -> None:
        """One ``tf2_msgs/TFMessage`` holding several transforms (``/tf_static`` for extrinsics)."""
        if not transforms:
            raise ValueError("write_transforms needs at least one transform")
        stamp = min(t.stamp_ns for t in transforms)
        self._put(topic, "tf2_msgs/TFMessage", ros2.transforms_to_msg(transforms), stamp, log_time_ns)

    def add_metadata(self, name: str, data: Mapping[str, object]) -> None:
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

    def __enter__(self) -> McapWriter:
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

    def __init__(
        self,
        folder: str | Path,
        *,
        compression: str = "zstd",
        chunk_size: int = 4 << 20,
        ros_distro: str = ROSBAG2_ROS_DISTRO,
        custom_data: dict[str, str] | None = None,
    ):
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
        first, last = self.first_log_ns, self.last_log_ns  # both set by the first message
        duration = int((last - first) if first is not None and last is not None else 0)
        topics = [
            {
                "topic_metadata": {
                    "name": topic,
                    "type": msgtype,
                    "serialization_format": "cdr",
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
                "files": [
                    {
                        "path": self.file_name,
                        "starting_time": {"nanoseconds_since_epoch": start},
                        "duration": {"nanoseconds": duration},
                        "message_count": int(self.count),
                    }
                ],
                "custom_data": self.custom_data or None,
                "ros_distro": self.ros_distro,
            }
        }

    def close(self) -> Path:
        if self._closed:
            return self.path
        self._finish_file()
        atomic_write_text(
            self._tmp_folder / ROSBAG2_METADATA,
            yaml.safe_dump(self.metadata(), sort_keys=False, default_flow_style=False),
        )
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

    def __enter__(self) -> Rosbag2Writer:
        return self
