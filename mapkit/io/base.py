"""The small interface every drive-log reader implements.

A reader streams: ``messages()`` is a generator over records in time order, holding at most a few
messages in memory. The base class enforces the guarantees consumers rely on: on every stream,
timestamps strictly increase. A duplicate or out-of-order message is skipped with a warning that
names the file, topic and index, and counted in ``skipped``. And no exception of damaged input leaves a
reader raw: readers name the file and line or byte themselves; what one lets slip (``DATA_ERRORS``)
becomes an ``InputError`` naming the file and how far reading got, its cause chained for debugging.
"""

from __future__ import annotations

import struct
import warnings
import zlib
from abc import ABC, abstractmethod
from collections import Counter
from collections.abc import Callable, Generator, Iterable, Iterator
from pathlib import Path
from typing import Any

from mapkit.core.errors import InputError, InputWarning
from mapkit.core.types import CameraInfo, FrameTransform, Message, StreamInfo, StreamKind

MAX_WARNINGS_PER_STREAM = 5
#: what parsers and decoders raise on damaged bytes (numpy's LinAlgError and UnicodeDecodeError are ValueErrors,
#: decimal's Overflow an ArithmeticError); a programming error (TypeError, AttributeError, ...) is not among them
DATA_ERRORS = (
    ValueError,
    KeyError,
    IndexError,
    struct.error,
    ArithmeticError,
    MemoryError,
    EOFError,
    OSError,
    zlib.error,
)


class DriveLog(ABC):
    """One drive (session) as a set of time-ordered sensor streams."""

    #: short name in the reader registry, e.g. ``mcap`` or ``kitti-odometry``
    format_name: str = ""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        #: (topic, reason) -> number of messages skipped on that stream
        self.skipped: Counter[tuple[str, str]] = Counter()
        self._warned: Counter[str] = Counter()

    # --- to implement ---------------------------------------------------------------------------
    @abstractmethod
    def streams(self) -> list[StreamInfo]:
        """The streams in the log (counts where known without a full read)."""

    @abstractmethod
    def _iter_messages(self, topics: set[str] | None) -> Iterator[Message]:
        """Messages of the given topics (all if None), in (approximately) increasing time."""

    # --- provided ---------------------------------------------------------------------------------
    @classmethod
    def detect(cls, path: Path) -> bool:
        """Whether ``path`` has this reader's folder layout (``guess_format`` asks the readers that recognise
        folders by layout, and they override this)."""
        return False

    def messages(
        self,
        kinds: Iterable[StreamKind | str] | None = None,
        topics: Iterable[str] | None = None,
    ) -> Iterator[Message]:
        """Stream messages of the chosen kinds/topics; per stream, stamps strictly increase."""
        wanted = self._select_topics(kinds, topics)
        last: dict[tuple[str, str], int] = {}
        for msg in self._guarded(self._iter_messages(wanted)):
            # transforms of several child frames share one TF message and stamp: key by child too
            key = (msg.topic, getattr(msg.record, "child_frame", "") if msg.kind == StreamKind.TF else "")
            prev = last.get(key)
            if prev is not None and msg.stamp_ns <= prev:
                reason = "duplicate timestamp" if msg.stamp_ns == prev else "timestamp earlier than the previous"
                self._skip(msg.topic, msg.index, reason, f"{msg.stamp_ns} after {prev}")
                continue
            last[key] = msg.stamp_ns
            yield msg
        self._warn_suppressed()

    def stamps(self, topics: set[str] | None = None) -> Iterator[tuple[str, int]]:
        """(topic, stamp_ns) of every message, in read order, duplicates and disorder included.

        Readers that can read stamps without decoding payloads override this; ``mapkit info``
        uses it to count and time streams.
        """
        for msg in self._guarded(self._iter_messages(topics)):
            yield msg.topic, msg.stamp_ns

    def records(self, kind: StreamKind | str, topic: str | None = None) -> Generator[Any, None, None]:
        """The records of one kind (optionally of one topic of that kind), in time order."""
        kind = StreamKind(kind)
        if topic is not None:
            stream = next((s for s in self.streams() if s.topic == topic), None)
            if stream is not None and stream.kind != kind:
                from mapkit.core.errors import InputError

                raise InputError(
                    self.path, f"topic {topic!r} carries {stream.kind.value}, not {kind.value}", field="topic"
                )
        for msg in self.messages(
            kinds=None if topic is not None else [kind], topics=None if topic is None else [topic]
        ):
            yield msg.record

    def camera_infos(self) -> dict[str, CameraInfo]:
        """The first intrinsics seen for each camera, by camera name."""
        out: dict[str, CameraInfo] = {}
        for info in self.records(StreamKind.CAMERA_INFO):
            out.setdefault(info.camera, info)
            if len(out) == self._count_of(StreamKind.CAMERA_INFO):
                break
        return out

    def transforms(self) -> list[FrameTransform]:
        """Static extrinsics (the first value of each parent/child pair)."""
        seen: dict[tuple[str, str], FrameTransform] = {}
        for t in self.records(StreamKind.TF):
            if t.static:
                seen.setdefault((t.parent_frame, t.child_frame), t)
        return list(seen.values())

    def topics_of(self, kind: StreamKind | str) -> list[str]:
        kind = StreamKind(kind)
        return [s.topic for s in self.streams() if s.kind == kind]

    def close(self) -> None:  # noqa: B027 - a no-op by design: readers that hold no files keep it
        """Release open files (readers that hold none need not override)."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __repr__(self) -> str:
        return f"{type(self).__name__}({str(self.path)!r})"

    # --- internals --------------------------------------------------------------------------------
    def _guarded(self, messages: Iterator[Message]) -> Iterator[Message]:
        """``messages``, with a ``DATA_ERRORS`` exception turned into an ``InputError`` naming the file and the
        last message read (readers name line or byte themselves; this is the net under them)."""
        last: Message | None = None
        while True:
            try:
                msg = next(messages)
            except StopIteration:
                return
            except DATA_ERRORS as exc:
                where = "before the first message" if last is None else f"after message {last.index} of {last.topic}"
                raise InputError(
                    self.path, f"could not be read {where} ({type(exc).__name__}: {str(exc)[:200]})"
                ) from exc
            last = msg
            yield msg

    def _count_of(self, kind: StreamKind) -> int:
        return sum(1 for s in self.streams() if s.kind == kind)

    def _select_topics(self, kinds, topics) -> set[str] | None:
        if kinds is None and topics is None:
            return None
        wanted: set[str] = set()
        streams = self.streams()
        if kinds is not None:
            ks = {StreamKind(k) for k in kinds}
            wanted |= {s.topic for s in streams if s.kind in ks}
        if topics is not None:
            known = {s.topic for s in streams}
            for t in topics:
                if t not in known:
                    from mapkit.core.errors import InputError

                    raise InputError(self.path, f"no topic {t!r} in this log (topics: {sorted(known)})", field="topic")
                wanted.add(t)
        return wanted

    def _records_or_skip(self, topic: str, index: int, decode: Callable[[], list]) -> list:
        """The records ``decode()`` makes of one message; a payload that cannot be decoded is skipped
        with a warning and gives none (one corrupt message must not end the stream)."""
        try:
            return decode()
        except InputError as exc:
            self._skip(topic, index, "could not be decoded", exc.what)
        except Exception as exc:  # noqa: BLE001 - whatever a decoder raises on a corrupt payload
            self._skip(topic, index, "could not be decoded", f"{type(exc).__name__}: {exc}")
        return []

    def _skip(self, topic: str, index: int, reason: str, detail: str = "") -> None:
        self.skipped[(topic, reason)] += 1
        self._warned[topic] += 1
        if self._warned[topic] <= MAX_WARNINGS_PER_STREAM:
            extra = f" ({detail})" if detail else ""
            warnings.warn(
                f"{self.path}: topic {topic} message {index}: {reason}{extra}; skipped", InputWarning, stacklevel=3
            )

    def _warn_suppressed(self) -> None:
        for topic, n in self._warned.items():
            if n > MAX_WARNINGS_PER_STREAM:
                total = sum(c for (t, _), c in self.skipped.items() if t == topic)
                warnings.warn(
                    f"{self.path}: topic {topic}: {total} messages skipped in all "
                    f"({n - MAX_WARNINGS_PER_STREAM} warnings not shown)",
                    InputWarning,
                    stacklevel=3,
                )
        self._warned.clear()
