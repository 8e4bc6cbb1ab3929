"""Fault campaign over mapkit's log readers: damaged bytes in whole logs, damaged lines and images in folders.

Each input is made from a small valid log, damaged by one seeded fault, and read completely as a build
reads it: every message of every stream, every image decoded, a frame whose decode raises ``InputError``
skipped as the build's frame loop skips it. Its outcome is one of:

- ``read in full``: every message read, no warning (the damage hit bytes nothing depends on, such as
  MCAP message-index records, which the reader does not use);
- ``warning, intact data kept``: InputWarnings say what was skipped and where; for MCAP every message
  of a chunk the damage did not touch was read;
- ``clean error``: one ``InputError`` naming the file (a log that cannot be opened at all);
- ``silent loss``: MCAP messages missing and no warning;
- ``intact data lost``: MCAP messages of an undamaged chunk missing;
- ``crash``: any other exception escaped the reader (its type is listed).

Fault classes: MCAP (written by mapkit's ``McapWriter``, zstd and uncompressed chunks) one-byte flips
in the summary, in a chunk and elsewhere, 64-byte bursts, truncations, a chunk whose opcode reads as the
data end or the footer in a log without its summary; ROS 1 bags (written with
``rosbags``) flips and truncations; KITTI odometry text (calib.txt, times.txt, poses.txt) and KITTI
raw OXTS records with a damaged token, byte or line, or a physically impossible pose; a folder log's
frames.csv; corrupt PNG and JPEG images. The text and image classes have no notion of "intact data":
their outcomes say only whether the reader ended cleanly.

Run from the repository root::

    python bench/fuzz_readers.py                 # 300 s, seed 0
    python bench/fuzz_readers.py --seconds 30 --seed 1
"""

from __future__ import annotations

import argparse
import io
import os
import random
import shutil
import struct
import sys
import tempfile
import time
import traceback
import warnings
from collections import Counter, defaultdict
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from mcap.reader import SeekingReader
from mcap.stream_reader import StreamReader, breakup_chunk

from mapkit.core.errors import InputError, InputWarning
from mapkit.core.geometry import make_pose
from mapkit.core.types import CameraFrame, FrameTransform, GpsFix, ImuSample
from mapkit.io import open_log
from mapkit.io.mcap_log import McapWriter

T0 = 1_700_000_000_000_000_000
OUTCOMES = ("read in full", "warning, intact data kept", "clean error", "silent loss", "intact data lost", "crash")


# --- reading and classing ---------------------------------------------------------------------------


@dataclass
class Outcome:
    kind: str
    detail: str = ""


@dataclass
class Read:
    """What reading one input gave."""

    messages: set = field(default_factory=set)  # (topic, stamp_ns) of every message read
    warnings: list[str] = field(default_factory=list)
    error: BaseException | None = None


def read_log(path: Path, fmt: str) -> Read:
    """Every message of the log at ``path``, images decoded; decode failures of a frame skipped as a build skips
    them."""
    out = Read()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            with open_log(path, fmt) as log:
                for msg in log.messages():
                    record = msg.record
                    if isinstance(record, CameraFrame):
                        try:
                            _ = record.image  # decodes the frame
                        except InputError as exc:
                            warnings.warn(f"frame skipped: {exc}", InputWarning, stacklevel=2)
                            continue
                    out.messages.add((msg.topic, int(getattr(record, "stamp_ns", 0))))
        except Exception as exc:  # noqa: BLE001 - the campaign classes whatever escapes
            out.error = exc
    out.warnings = [str(w.message) for w in caught if issubclass(w.category, InputWarning)]
    return out


def classify(read: Read, everything: set | None = None, kept: set | None = None) -> Outcome:
    """The outcome of one read; ``everything`` and ``kept``: all messages of the log, and those a damage spared."""
    if read.error is not None:
        if isinstance(read.error, InputError):
            return Outcome("clean error", str(read.error)[:160])
        where = traceback.extract_tb(read.error.__traceback__)[-1]
        return Outcome(
            "crash",
            f"{type(read.error).__name__} at {Path(where.filename).name}:{where.lineno}: {str(read.error)[:120]}",
        )
    if kept is not None and not kept <= read.messages:
        return Outcome("intact data lost", f"{len(kept - read.messages)} messages of undamaged chunks missing")
    complete = everything is None or everything <= read.messages
    if not read.warnings:
        return (
            Outcome("read in full")
            if complete
            else Outcome("silent loss", f"{len(everything - read.messages)} messages missing")
        )
    return Outcome("warning, intact data kept", read.warnings[0][:160])


# --- inputs -------------------------------------------------------------------------------------------


def write_mcap(path: Path, compression: str = "zstd", n: int = 30) -> Path:
    """A small MCAP of images, GPS, IMU and a static transform in many chunks (1 kB chunk size)."""
    rng = np.random.default_rng(0)
    with McapWriter(path, compression=compression, chunk_size=1024) as w:
        w.write("/tf_static", FrameTransform(T0, "base_link", "cam", make_pose(np.eye(3), [1.0, 0.0, 1.5])))
        for i in range(n):
            t = T0 + i * 100_000_000
            w.write("/cam/image", CameraFrame(t, "cam", rng.integers(0, 255, (12, 16), dtype=np.uint8)))
            w.write("/gps/fix", GpsFix(t, 49.0 + i * 1e-5, 8.4, 110.0))
            w.write("/imu/data", ImuSample(t, "imu", rng.normal(size=3), rng.normal(size=3), np.array([1.0, 0, 0, 0])))
    return path


@dataclass(frozen=True)
class McapLayout:
    """Where a clean MCAP keeps its chunks (byte range, messages in it) and its summary."""

    size: int
    summary_start: int
    chunks: list[tuple[int, int, frozenset]]

    @property
    def messages(self) -> set:
        return set().union(*(m for _, _, m in self.chunks))

    def kept(self, start: int, end: int) -> set:
        """Messages of the chunks that bytes ``start`` to ``end`` do not touch."""
        return set().union(*(m for a, b, m in self.chunks if b <= start or a >= end))


def mcap_layout(path: Path) -> McapLayout:
    """Chunk ranges and contents of a clean MCAP, read with the mcap library alone."""
    data = path.read_bytes()
    summary = SeekingReader(io.BytesIO(data)).get_summary()
    topics = {c.id: c.topic for c in summary.channels.values()}
    chunks = []
    for ci in summary.chunk_indexes:
        stream = io.BytesIO(data[ci.chunk_start_offset : ci.chunk_start_offset + ci.chunk_length])
        chunk = next(iter(StreamReader(stream, skip_magic=True, emit_chunks=True).records))
        msgs = frozenset((topics[m.channel_id], m.log_time) for m in breakup_chunk(chunk) if hasattr(m, "log_time"))
        chunks.append((ci.chunk_start_offset, ci.chunk_start_offset + ci.chunk_length, msgs))
    footer_at = len(data) - 8 - 29
    summary_start = struct.unpack_from("<Q", data, footer_at + 9)[0]
    return McapLayout(len(data), summary_start, chunks)


def write_rosbag1(path: Path, n: int = 30) -> Path:
    """A small ROS 1 bag (NavSatFix and Imu, 10 Hz), written with rosbags in several chunks."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    Header, Time = ts.types["std_msgs/msg/Header"], ts.types["builtin_interfaces/msg/Time"]
    Fix, Status = ts.types["sensor_msgs/msg/NavSatFix"], ts.types["sensor_msgs/msg/NavSatStatus"]
    Imu, Quat, Vec = (
        ts.types["sensor_msgs/msg/Imu"],
        ts.types["geometry_msgs/msg/Quaternion"],
        ts.types["geometry_msgs/msg/Vector3"],
    )
    writer = Writer(path)
    writer.chunk_threshold = 1024
    with writer:
        fix_c = writer.add_connection("/gps/fix", Fix.__msgtype__, typestore=ts)
        imu_c = writer.add_connection("/imu/data", Imu.__msgtype__, typestore=ts)
        for i in range(n):
            t = T0 + i * 100_000_000
            header = Header(seq=i, stamp=Time(sec=t // 1_000_000_000, nanosec=t % 1_000_000_000), frame_id="imu")
            fix = Fix(
                header=header,
                status=Status(status=0, service=1),
                latitude=49.0 + i * 1e-5,
                longitude=8.4,
                altitude=110.0,
                position_covariance=np.eye(3).ravel(),
                position_covariance_type=2,
            )
            imu = Imu(
                header=header,
                orientation=Quat(x=0.0, y=0.0, z=0.0, w=1.0),
                orientation_covariance=np.zeros(9),
                angular_velocity=Vec(x=0.0, y=0.0, z=0.1),
                angular_velocity_covariance=np.zeros(9),
                linear_acceleration=Vec(x=0.0, y=0.0, z=9.81),
                linear_acceleration_covariance=np.zeros(9),
            )
            writer.write(fix_c, t, ts.serialize_ros1(fix, Fix.__msgtype__))
            writer.write(imu_c, t, ts.serialize_ros1(imu, Imu.__msgtype__))
    return path


def _line(values) -> str:
    return " ".join(f"{v:.12e}" for v in np.asarray(values, float).ravel())


#: KITTI's P0 of the odometry sequences recorded 2011-09-30 (fx = fy = 707.0912, as in ../shared/data)
P0 = np.array([[707.0912, 0.0, 601.8873, 0.0], [0.0, 707.0912, 183.1104, 0.0], [0.0, 0.0, 1.0, 0.0]])


def write_kitti_odometry(root: Path, n: int = 6) -> Path:
    """An odometry sequence: n 16x8 PNGs, calib.txt (P0, P1, Tr), times.txt, poses.txt (1 m per frame forward)."""
    (root / "image_0").mkdir(parents=True)
    for i in range(n):
        cv2.imwrite(str(root / "image_0" / f"{i:06d}.png"), np.full((8, 16), 10 * i, np.uint8))
    P1 = P0.copy()
    P1[0, 3] = -386.1448  # KITTI's baseline times fx
    Tr = np.hstack([[[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]], [[0.0], [-0.08], [-0.27]]])
    (root / "calib.txt").write_text(f"P0: {_line(P0)}\nP1: {_line(P1)}\nTr: {_line(Tr)}\n")
    (root / "times.txt").write_text("".join(f"{0.1036 * i:.6e}\n" for i in range(n)))
    poses = [np.hstack([np.eye(3), [[0.0], [0.0], [1.0 * i]]]) for i in range(n)]
    (root / "poses.txt").write_text("".join(_line(P) + "\n" for P in poses))
    return root


def write_kitti_raw_oxts(root: Path, n: int = 6) -> Path:
    """A KITTI raw drive with OXTS records only (about 1 m per record north-east), returning the drive folder."""
    drive = root / "2011_09_26" / "2011_09_26_drive_0001_sync"
    (drive / "oxts" / "data").mkdir(parents=True)
    stamps = [f"2011-09-26 13:02:{25 + i // 10:02d}.{(i % 10) * 100_000_000 + 3_000_000:09d}" for i in range(n)]
    (drive / "oxts" / "timestamps.txt").write_text("\n".join(stamps) + "\n")
    for i in range(n):
        values = (
            [49.011 + i * 6e-6, 8.422 + i * 9e-6, 112.8, 0.02, -0.01, 0.7] + [0.5] * 17 + [0.1, 0.05, 4, 11, 5, 5, 5]
        )
        (drive / "oxts" / "data" / f"{i:010d}.txt").write_text(" ".join(repr(float(v)) for v in values) + "\n")
    return drive


def write_folder(root: Path, n: int = 6) -> Path:
    """A generic folder log: frames.csv with stamps, GPS and poses, and n PNG/JPEG images."""
    (root / "images").mkdir(parents=True)
    rows = ["image,timestamp,lat,lon,alt,x,y,z,qw,qx,qy,qz,fx,fy,cx,cy"]
    rng = np.random.default_rng(1)
    for i in range(n):
        name = f"{i:04d}.{'png' if i % 2 == 0 else 'jpg'}"
        cv2.imwrite(str(root / "images" / name), rng.integers(0, 255, (24, 32, 3), dtype=np.uint8))
        rows.append(
            f"{name},{1.7e9 + 0.1 * i:.3f},{49.0 + i * 1e-5},8.4,110.0,{i}.0,"
            "0.0,0.0,1.0,0.0,0.0,0.0,30.0,30.0,16.0,12.0"
        )
    (root / "frames.csv").write_text("\n".join(rows) + "\n")
    return root


# --- faults -------------------------------------------------------------------------------------------

#: number tokens that parsers get wrong: non-finite, huge exponents, non-ASCII digits, hex floats, empties
BAD_NUMBERS = (
    "nan",
    "inf",
    "-inf",
    "1e308",
    "1e999999999",
    "-1e999999999",
    "0",
    "-0",
    "1e-320",
    "0x1p3",
    "١٢",
    "²",
    "1_0",
    "--1",
    "+",
    ".",
    "e5",
    "9" * 5000,
    "\x00",
    "1,5",
)


def flip(data: bytes, at: int, rnd: random.Random) -> bytes:
    b = bytearray(data)
    b[at] ^= rnd.randrange(1, 256)
    return bytes(b)


def _is_number(token: bytes) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def mutate_text(text: bytes, rnd: random.Random) -> bytes:
    """One damage to a text file: a byte, a token, a line, or a number replaced by a hard one."""
    lines = text.split(b"\n")
    k = rnd.randrange(len(lines))
    line = lines[k]
    tokens = line.split(b" ")
    choice = rnd.randrange(7)
    if choice == 0 and line:  # one byte replaced by any byte
        at = rnd.randrange(len(line))
        lines[k] = line[:at] + bytes([rnd.randrange(256)]) + line[at + 1 :]
    elif choice == 1:  # a hard number
        tokens[rnd.randrange(len(tokens))] = rnd.choice(BAD_NUMBERS).encode()
        lines[k] = b" ".join(tokens)
    elif choice == 2 and len(tokens) > 1:  # a token lost
        del tokens[rnd.randrange(len(tokens))]
        lines[k] = b" ".join(tokens)
    elif choice == 3:  # a token repeated
        at = rnd.randrange(len(tokens))
        tokens.insert(at, tokens[at])
        lines[k] = b" ".join(tokens)
    elif choice == 4:  # a line lost or repeated
        if rnd.random() < 0.5:
            del lines[k]
        else:
            lines.insert(k, line)
    elif choice == 5:  # a number scaled by a big factor
        nums = [i for i, t in enumerate(tokens) if _is_number(t)]
        if nums:
            i = rnd.choice(nums)
            tokens[i] = repr(float(tokens[i]) * rnd.choice((5.0, -1.0, 1e3, 1e6, 0.0))).encode()
            lines[k] = b" ".join(tokens)
    else:  # the line cut short
        lines[k] = line[: rnd.randrange(len(line) + 1)]
    return b"\n".join(lines)


def mutate_csv(text: bytes, rnd: random.Random) -> bytes:
    """``mutate_text`` on the cells of a CSV (commas as separators)."""
    return mutate_text(text.replace(b",", b" "), rnd).replace(b" ", b",")


def impossible_pose(text: bytes, rnd: random.Random) -> bytes:
    """poses.txt with one pose made physically impossible: a 1 km jump, a rotation scaled x5 or a zero rotation."""
    lines = text.decode().splitlines()
    k = rnd.randrange(1, len(lines))
    v = np.array(lines[k].split(), float).reshape(3, 4)
    kind = rnd.randrange(3)
    if kind == 0:
        v[:, 3] += [1000.0, 0.0, 0.0]
    else:
        v[:, :3] *= 5.0 if kind == 1 else 0.0
    lines[k] = _line(v)
    return ("\n".join(lines) + "\n").encode()


def impossible_oxts(text: bytes, rnd: random.Random) -> bytes:
    """An OXTS record moved 1 km (0.01 deg of latitude) or given a latitude out of range."""
    v = text.split()
    v[0] = repr(float(v[0]) + (0.01 if rnd.random() < 0.5 else 1000.0)).encode()
    return b" ".join(v) + b"\n"


@dataclass
class FaultClass:
    """One kind of fault: ``run(rnd, tmp)`` makes one damaged input, reads it and returns its outcome."""

    name: str
    run: Callable[[random.Random, Path], Outcome]


#: the opcodes that end an MCAP's data section: DATA_END and FOOTER
END_OPCODES = {"data end": 0x0F, "footer": 0x02}


def _mcap_class(
    name: str, pick: Callable[[McapLayout, random.Random], tuple[int, int, str]], compression: str, base: Path
) -> FaultClass:
    clean = write_mcap(base / f"clean-{compression}.mcap", compression)
    layout, data = mcap_layout(clean), clean.read_bytes()

    def run(rnd: random.Random, tmp: Path) -> Outcome:
        start, end, how = pick(layout, rnd)
        if how == "truncate":
            damaged = data[:start]
        elif how in END_OPCODES:  # the summary cut off (so the reader must scan) and a chunk's opcode made an end's
            damaged = data[: layout.summary_start]
            damaged = damaged[:start] + bytes([END_OPCODES[how]]) + damaged[start + 1 :]
        elif how == "burst":
            damaged = data[:start] + rnd.randbytes(end - start) + data[end:]
        else:
            damaged = flip(data, start, rnd)
        path = tmp / "damaged.mcap"
        path.write_bytes(damaged)
        return classify(read_log(path, "mcap"), layout.messages, layout.kept(start, end))

    return FaultClass(f"{name} ({compression})", run)


def _file_class(
    name: str,
    clean_dir: Path,
    fmt: str,
    files: Callable[[Path], list[Path]],
    damage: Callable[[bytes, random.Random], bytes],
    open_path: Callable[[Path], Path] = lambda p: p,
) -> FaultClass:
    """Damage one of ``files(copy)`` of a copy of ``clean_dir`` and read the copy with reader ``fmt``."""

    def run(rnd: random.Random, tmp: Path) -> Outcome:
        copy = tmp / "log"
        shutil.copytree(clean_dir, copy)
        target = rnd.choice(files(copy))
        target.write_bytes(damage(target.read_bytes(), rnd))
        return classify(read_log(open_path(copy), fmt))

    return FaultClass(name, run)


def _damage_bytes(data: bytes, rnd: random.Random) -> bytes:
    """A binary file (an image, a bag) flipped at one byte, hit by a 64-byte burst, or truncated."""
    kind = rnd.randrange(3)
    at = rnd.randrange(len(data))
    if kind == 0:
        return flip(data, at, rnd)
    if kind == 1:
        return data[:at] + rnd.randbytes(min(64, len(data) - at)) + data[at + 64 :]
    return data[:at]


def fault_classes(base: Path) -> list[FaultClass]:
    """Every fault class, its clean inputs written under ``base``."""

    def in_summary(lay: McapLayout, rnd: random.Random):
        at = rnd.randrange(lay.summary_start, lay.size - 8 - 29)
        return at, at + 1, "flip"

    def in_chunk(lay: McapLayout, rnd: random.Random):
        a, b, _ = rnd.choice(lay.chunks)
        at = rnd.randrange(a, b)
        return at, at + 1, "flip"

    def elsewhere(lay: McapLayout, rnd: random.Random):
        while True:  # header, message indexes, data end, footer: any byte outside chunks and summary
            at = rnd.randrange(lay.size)
            if not lay.summary_start <= at < lay.size - 8 - 29 and not any(a <= at < b for a, b, _ in lay.chunks):
                return at, at + 1, "flip"

    def burst(lay: McapLayout, rnd: random.Random):
        at = rnd.randrange(8, lay.size - 64)
        return at, at + 64, "burst"

    def truncation(lay: McapLayout, rnd: random.Random):
        at = rnd.randrange(8, lay.size)
        return at, lay.size, "truncate"

    def end_opcode(lay: McapLayout, rnd: random.Random):
        # a chunk that defines no channel: without a summary, the chunk that defines one takes its later messages
        seen: set = set()
        candidates = []
        for a, b, msgs in lay.chunks:
            topics = {topic for topic, _ in msgs}
            if topics <= seen:
                candidates.append((a, b))
            seen |= topics
        a, b = rnd.choice(candidates)
        return a, b, rnd.choice(sorted(END_OPCODES))

    classes = []
    for compression in ("zstd", "none"):
        classes += [
            _mcap_class("MCAP flip in summary", in_summary, compression, base),
            _mcap_class("MCAP flip in a chunk", in_chunk, compression, base),
            _mcap_class("MCAP flip elsewhere", elsewhere, compression, base),
            _mcap_class("MCAP 64-byte burst", burst, compression, base),
            _mcap_class("MCAP truncation", truncation, compression, base),
            _mcap_class("MCAP end opcode at a chunk, no summary", end_opcode, compression, base),
        ]
    bag_dir = base / "bag"
    bag_dir.mkdir()
    write_rosbag1(bag_dir / "drive.bag")
    classes.append(
        _file_class(
            "ROS 1 bag flip/burst/truncation",
            bag_dir,
            "rosbag",
            lambda d: [d / "drive.bag"],
            _damage_bytes,
            lambda d: d / "drive.bag",
        )
    )
    odo = write_kitti_odometry(base / "kitti-odometry")
    classes.append(
        _file_class(
            "KITTI odometry text",
            odo,
            "kitti-odometry",
            lambda d: [d / "calib.txt", d / "times.txt", d / "poses.txt"],
            mutate_text,
        )
    )
    classes.append(
        _file_class("KITTI impossible pose", odo, "kitti-odometry", lambda d: [d / "poses.txt"], impossible_pose)
    )
    raw = write_kitti_raw_oxts(base / "kitti-raw")
    raw_root = base / "kitti-raw"

    def oxts_files(d: Path) -> list[Path]:
        drive = d / raw.relative_to(raw_root)
        return sorted((drive / "oxts" / "data").iterdir()) + [drive / "oxts" / "timestamps.txt"]

    def drive_of(d: Path) -> Path:
        return d / raw.relative_to(raw_root)

    classes.append(_file_class("KITTI raw OXTS text", raw_root, "kitti-raw", oxts_files, mutate_text, drive_of))
    classes.append(
        _file_class(
            "KITTI raw impossible OXTS", raw_root, "kitti-raw", lambda d: oxts_files(d)[1:-1], impossible_oxts, drive_of
        )
    )
    folder = write_folder(base / "folder")
    classes.append(_file_class("folder frames.csv", folder, "folder", lambda d: [d / "frames.csv"], mutate_csv))
    classes.append(
        _file_class("corrupt PNG/JPEG", folder, "folder", lambda d: sorted((d / "images").iterdir()), _damage_bytes)
    )
    return classes


# --- the campaign ------------------------------------------------------------------------------------


@dataclass
class Tally:
    tried: int = 0
    outcomes: Counter = field(default_factory=Counter)
    examples: dict = field(default_factory=dict)  # outcome kind -> one detail


def campaign(
    seconds: float,
    seed: int,
    classes: list[FaultClass] | None = None,
    base: Path | None = None,
    max_inputs: int | None = None,
) -> dict[str, Tally]:
    """Inputs of every class in turn until ``seconds`` have passed (or ``max_inputs`` per class)."""
    rnd = random.Random(seed)
    tallies: dict[str, Tally] = defaultdict(Tally)
    with tempfile.TemporaryDirectory() as tmp_root:
        base = base or Path(tmp_root) / "clean"
        base.mkdir(parents=True, exist_ok=True)
        classes = classes or fault_classes(base)
        t_end = time.monotonic() + seconds
        n = 0
        while time.monotonic() < t_end and (max_inputs is None or n < max_inputs):
            for fc in classes:
                work = Path(tempfile.mkdtemp(dir=tmp_root))
                outcome = fc.run(random.Random(rnd.getrandbits(64)), work)
                shutil.rmtree(work, ignore_errors=True)
                tally = tallies[fc.name]
                tally.tried += 1
                tally.outcomes[outcome.kind] += 1
                tally.examples.setdefault(outcome.kind, outcome.detail)
            n += 1
    return tallies


def table(tallies: dict[str, Tally]) -> str:
    """A Markdown table: fault class, inputs tried, outcome counts."""
    head = "| fault class | inputs | " + " | ".join(OUTCOMES) + " |"
    rows = [head, "|" + "---|" * (2 + len(OUTCOMES))]
    for name, t in tallies.items():
        rows.append(f"| {name} | {t.tried} | " + " | ".join(str(t.outcomes.get(o, 0)) for o in OUTCOMES) + " |")
    total = Counter()
    for t in tallies.values():
        total.update(t.outcomes)
    rows.append(
        f"| all | {sum(t.tried for t in tallies.values())} | "
        + " | ".join(str(total.get(o, 0)) for o in OUTCOMES)
        + " |"
    )
    return "\n".join(rows)


@contextmanager
def quiet_stderr():
    """Silences what the C image decoders print to file descriptor 2 (libpng, libjpeg) while inputs are read."""
    sys.stderr.flush()
    saved = os.dup(2)
    with open(os.devnull, "w") as null:
        os.dup2(null.fileno(), 2)
        try:
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=300.0, help="length of the campaign (default 300)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--out",
        type=Path,
        help="also write the counts per fault class as JSON here (docs/figures.py collect robustness)",
    )
    args = ap.parse_args()
    t0 = time.monotonic()
    with quiet_stderr():
        tallies = campaign(args.seconds, args.seed)
    print(f"fault campaign: seed {args.seed}, {time.monotonic() - t0:.0f} s\n")
    print(table(tallies))
    if args.out:
        import json

        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(
            json.dumps(
                {
                    "command": f"python3 bench/fuzz_readers.py --seconds {args.seconds:g} --seed {args.seed}",
                    "outcomes": list(OUTCOMES),
                    "classes": {
                        name: {"tried": t.tried, **{o: t.outcomes.get(o, 0) for o in OUTCOMES}}
                        for name, t in tallies.items()
                    },
                },
                indent=1,
            )
            + "\n"
        )
    bad = [
        (name, kind, t.examples[kind])
        for name, t in tallies.items()
        for kind in ("crash", "silent loss", "intact data lost")
        if kind in t.examples
    ]
    for name, kind, detail in bad:
        print(f"\n{name}: {kind}, e.g. {detail}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
