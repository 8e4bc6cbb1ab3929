"""Readers on damaged input: no reader crashes; each case ends in an InputError naming the file and
line or byte, or in an InputWarning saying what was skipped, with every intact part read.

The MCAP cases damage a log written by mapkit's ``McapWriter`` at known places (the summary section, the
first chunk, a chunk's size field) and compare what is read with what the mcap library finds in the clean
file; the KITTI cases use the layout KITTI's devkit describes and the real clip and OXTS drive in
../shared/data.
"""

from __future__ import annotations

import importlib.util
import shutil
import struct
import sys
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest

from mapkit.core.errors import InputError, InputWarning
from mapkit.core.types import CameraFrame, StreamKind
from mapkit.io import open_log
from mapkit.io.folder import FolderLog
from mapkit.io.kitti import MAX_SPEED_MPS, KittiOdometry, KittiRaw
from mapkit.io.mcap_log import McapLog

REPO = Path(__file__).resolve().parents[2]
SHARED_DATA = REPO.parent / "shared" / "data"


def _bench():
    """bench/fuzz_readers.py, whose writers make the clean inputs (one copy of them for tests and campaign)."""
    name = "fuzz_readers_bench"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, REPO / "bench" / "fuzz_readers.py")
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module  # before running it: its dataclasses look their module up
        spec.loader.exec_module(module)
    return sys.modules[name]


fz = _bench()


def _read(path: Path, fmt: str | None = None):
    """(set of (topic, stamp) read, InputWarning texts); images decoded."""
    seen, texts = set(), []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with open_log(path, fmt) as log:
            for msg in log.messages():
                if isinstance(msg.record, CameraFrame):
                    _ = msg.record.image  # decodes the frame
                seen.add((msg.topic, msg.record.stamp_ns))
    texts = [str(w.message) for w in caught if issubclass(w.category, InputWarning)]
    return seen, texts


# --- MCAP -----------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def mcap_log(tmp_path_factory) -> tuple[Path, fz.McapLayout]:
    path = fz.write_mcap(tmp_path_factory.mktemp("mcap") / "drive.mcap")
    return path, fz.mcap_layout(path)


def _damaged(tmp_path: Path, data: bytes) -> Path:
    path = tmp_path / "damaged.mcap"
    path.write_bytes(data)
    return path


def test_premise_the_clean_log_has_many_chunks_and_a_summary(mcap_log):
    path, layout = mcap_log
    assert len(layout.chunks) > 20 and layout.summary_start > layout.chunks[-1][1]
    seen, texts = _read(path)
    assert seen == layout.messages and len(seen) == 91 and texts == []


def test_twenty_flips_in_the_summary_lose_nothing(mcap_log, tmp_path):
    """A one-byte flip anywhere in the summary loses no message: the summary is set aside, a linear scan reads every
    chunk, and a warning says so (20 flips spread over the summary, one at a time)."""
    path, layout = mcap_log
    data = path.read_bytes()
    footer_at = layout.size - 8 - 29
    for k in range(20):
        at = layout.summary_start + k * (footer_at - layout.summary_start) // 20
        damaged = bytearray(data)
        damaged[at] ^= 0x5A
        seen, texts = _read(_damaged(tmp_path, bytes(damaged)))
        assert seen == layout.messages, f"flip at byte {at}"
        assert any("summary" in t and "linear scan" in t for t in texts), f"flip at byte {at}: {texts}"


def test_a_damaged_first_chunk_keeps_every_chunk_after_it(mcap_log, tmp_path):
    path, layout = mcap_log
    data = bytearray(path.read_bytes())
    start, end, lost = layout.chunks[0]
    data[start + 40 : start + 104] = bytes(64)  # inside the first chunk's compressed records
    seen, texts = _read(_damaged(tmp_path, bytes(data)))
    assert seen == layout.messages - lost
    assert any(f"near byte {start} of" in t and "intact chunks after it are read" in t for t in texts), texts


def test_a_broken_chunk_length_without_summary_is_stepped_over(mcap_log, tmp_path):
    """No summary (the file is cut before it) and a chunk's length field broken: the linear scan finds the next chunk.
    (A chunk defining channels is the exception: without a summary, its channels' later messages cannot be read.)"""
    path, layout = mcap_log
    data = bytearray(path.read_bytes()[: layout.summary_start])
    start, _, lost = layout.chunks[5]
    data[start + 1 : start + 9] = struct.pack("<Q", 2**62)  # the chunk claims 4 EiB
    seen, texts = _read(_damaged(tmp_path, bytes(data)))
    assert seen == layout.messages - lost
    assert any(f"near byte {start} of" in t for t in texts), texts


@pytest.mark.parametrize("opcode", [0x0F, 0x02])
def test_an_end_opcode_left_by_damage_does_not_end_the_scan(mcap_log, tmp_path, opcode):
    """No summary, and damage leaves a chunk starting with the DATA_END (0x0F) or FOOTER (0x02) opcode: that chunk is
    lost, the scan goes on to every chunk after it, and the warning names the byte."""
    path, layout = mcap_log
    data = bytearray(path.read_bytes()[: layout.summary_start])
    start, _, lost = layout.chunks[5]  # (a chunk that defines no channel: see the test above)
    data[start] = opcode
    seen, texts = _read(_damaged(tmp_path, bytes(data)))
    assert seen == layout.messages - lost
    assert any(f"near byte {start} of" in t for t in texts), texts


def test_the_real_data_end_is_believed_and_nothing_after_it_is_read_as_data(mcap_log, tmp_path):
    """A clean log cut inside its summary: the scan ends at the real DATA_END with every message and no other
    warning than the truncation's."""
    path, layout = mcap_log
    cut = layout.summary_start + (layout.size - layout.summary_start) // 2
    seen, texts = _read(_damaged(tmp_path, path.read_bytes()[:cut]))
    assert seen == layout.messages
    assert len(texts) == 1 and "ends without a footer" in texts[0], texts


def test_a_chunk_claiming_exabytes_is_skipped_without_allocating_them(mcap_log, tmp_path):
    """A flipped uncompressed-size field (2^63 bytes) costs its chunk only: nothing is allocated for it, no MemoryError
    or OverflowError leaves the reader, and the warning names the field and the byte."""
    path, layout = mcap_log
    data = bytearray(path.read_bytes())
    start, _, lost = layout.chunks[3]
    struct.pack_into("<Q", data, start + 9 + 16, 2**63 + 5)  # message start, end, then the uncompressed size
    seen, texts = _read(_damaged(tmp_path, bytes(data)))
    assert seen == layout.messages - lost
    assert any("uncompressed" in t and f"near byte {start}" in t for t in texts), texts


def test_a_flip_in_the_leading_magic_loses_nothing(mcap_log, tmp_path):
    path, layout = mcap_log
    data = bytearray(path.read_bytes())
    data[3] ^= 0x20
    seen, texts = _read(_damaged(tmp_path, bytes(data)), "mcap")
    assert seen == layout.messages and any("magic bytes at its start are damaged" in t for t in texts)


@pytest.mark.parametrize("keep", [0.25, 0.6, 0.9])
def test_truncation_keeps_every_complete_chunk(mcap_log, tmp_path, keep):
    path, layout = mcap_log
    cut = int(layout.size * keep)
    seen, texts = _read(_damaged(tmp_path, path.read_bytes()[:cut]))
    assert layout.kept(cut, layout.size) <= seen <= layout.messages
    assert any("truncated or corrupt near byte" in t for t in texts)
    with McapLog(tmp_path / "damaged.mcap") as log, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        list(log.messages())
        assert log.truncated_at is not None and log.truncated_at <= cut


# --- ROS 1 ----------------------------------------------------------------------------------------


def test_a_truncated_ros1_bag_is_one_clean_error(tmp_path):
    bag = fz.write_rosbag1(tmp_path / "drive.bag")
    bag.write_bytes(bag.read_bytes()[: bag.stat().st_size // 2])
    with pytest.raises(InputError, match="could not be read as a ROS 1 bag") as exc:
        _read(bag)
    assert exc.value.path == bag


# --- KITTI ----------------------------------------------------------------------------------------


def _odometry(tmp_path: Path) -> Path:
    return fz.write_kitti_odometry(tmp_path / "seq")


def _replace_line(path: Path, prefix: str, values: np.ndarray) -> int:
    """Replaces the line starting with ``prefix``; returns its line number."""
    lines = path.read_text().splitlines()
    k = next(i for i, line in enumerate(lines) if line.startswith(prefix))
    lines[k] = (prefix + " " if prefix else "") + " ".join(f"{v:.6e}" for v in values.ravel())
    path.write_text("\n".join(lines) + "\n")
    return k + 1


def test_singular_projection_names_calib_line(tmp_path):
    seq = _odometry(tmp_path)
    P = fz.P0.copy()
    P[1] = P[0]  # two equal rows: no inverse (np.linalg.solve raised LinAlgError)
    line = _replace_line(seq / "calib.txt", "P0:", P)
    with pytest.raises(InputError, match=f"line {line} \\(P0\\).*singular") as exc:
        KittiOdometry(seq)
    assert exc.value.path == seq / "calib.txt"


def test_zero_rotation_in_calibration_names_its_line(tmp_path):
    seq = _odometry(tmp_path)
    line = _replace_line(seq / "calib.txt", "Tr:", np.hstack([np.zeros((3, 3)), [[0.1], [0.2], [0.3]]]))
    with pytest.raises(InputError, match=f"line {line} \\(Tr\\) is not a rotation") as exc:
        list(KittiOdometry(seq).messages())
    assert exc.value.path == seq / "calib.txt"


def test_impossible_poses_are_rejected_with_counts(tmp_path):
    """A 1 km jump within 0.1 s, a rotation scaled x5 and a zero rotation are skipped; the rest is read."""
    seq = _odometry(tmp_path)
    poses = np.loadtxt(seq / "poses.txt").reshape(-1, 3, 4)
    jumped, scaled, zeroed = poses[2].copy(), poses[3].copy(), poses[4].copy()
    jumped[:, 3] += [1000.0, 0.0, 0.0]
    scaled[:, :3] *= 5.0
    zeroed[:, :3] = 0.0
    path = seq / "poses.txt"
    lines = path.read_text().splitlines()
    for k, P in ((2, jumped), (3, scaled), (4, zeroed)):
        lines[k] = " ".join(f"{v:.6e}" for v in P.ravel())
    path.write_text("\n".join(lines) + "\n")
    with pytest.warns(InputWarning, match=r"poses.txt: 3 of 6 poses rejected as physically impossible") as rec:
        log = KittiOdometry(seq)
    text = str(rec[0].message)
    assert f"line 3: moves 1000 m in 0.104 s, faster than {MAX_SPEED_MPS:g} m/s" in text
    assert "line 4: R^T R departs from the identity by 24" in text
    assert "line 5: R^T R departs from the identity by 1 " in text
    gt = list(log.records(StreamKind.POSE))
    assert [p.stamp_ns for p in gt] == [log.stamps_ns[i] for i in (0, 1, 5)]
    np.testing.assert_allclose(gt[2].parent_from_child[:3, :], poses[5], atol=1e-9)
    assert log.skipped[("/kitti/ground_truth", "physically impossible pose")] == 3


def test_real_clip_poses_are_all_accepted(kitti_clip):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        log = KittiOdometry(kitti_clip)
    assert not [w for w in caught if "rejected" in str(w.message)]
    assert len(list(log.records(StreamKind.POSE))) == 51


def _raw_oxts(tmp_path: Path) -> Path:
    return fz.write_kitti_raw_oxts(tmp_path / "raw")


def test_impossible_oxts_records_are_rejected_with_counts(tmp_path):
    drive = _raw_oxts(tmp_path)
    files = sorted((drive / "oxts" / "data").iterdir())
    for path, lat_shift in (
        (files[2], 0.01),
        (files[4], 1000.0),
    ):  # 0.01 deg: 1.1 km within 0.1 s; then no latitude at all
        v = path.read_text().split()
        v[0] = repr(float(v[0]) + lat_shift)
        path.write_text(" ".join(v) + "\n")
    log = KittiRaw(drive)
    with pytest.warns(InputWarning, match=r"2 of 6 OXTS records rejected as physically impossible") as rec:
        fixes = list(log.records(StreamKind.GPS))
    text = str(rec[0].message)
    assert "0000000002.txt line 1: moves 1114 m in 0.1 s" in text and "0000000004.txt line 1: latitude" in text
    assert len(fixes) == 4 and all(abs(f.lat_deg - 49.011) < 1e-3 for f in fixes)
    assert log.skipped[("/kitti/oxts/gps", "physically impossible OXTS record")] == 2


def test_real_oxts_records_are_all_accepted():
    drive = SHARED_DATA / "kitti-raw-0001-oxts" / "2011_09_26" / "2011_09_26_drive_0001_sync"
    if not (drive / "oxts" / "timestamps.txt").is_file():
        pytest.skip(f"real data not found at {drive}")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        poses = list(KittiRaw(drive).records(StreamKind.POSE))
    assert len(poses) == 108 and not [w for w in caught if "rejected" in str(w.message)]


def test_stamp_beyond_int64_nanoseconds_names_its_line(tmp_path):
    seq = _odometry(tmp_path)
    lines = (seq / "times.txt").read_text().splitlines()
    lines[2] = "1e999999999"  # beyond int64 ns; parsed exactly it would be a billion-digit integer
    (seq / "times.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match="line 3") as exc:
        KittiOdometry(seq)
    assert exc.value.path == seq / "times.txt"


# --- images and folder tables ---------------------------------------------------------------------


def _corrupt(path: Path) -> None:
    data = bytearray(path.read_bytes())
    data[len(data) // 2 :] = bytes(len(data) - len(data) // 2)
    path.write_bytes(bytes(data))


def test_a_corrupt_image_fails_alone_naming_its_file(tmp_path):
    """The reader side of "one corrupt PNG aborts a whole build": only that frame's decode raises."""
    root = fz.write_folder(tmp_path / "f")
    bad = root / "images" / "0002.png"
    _corrupt(bad)
    frames = list(FolderLog(root).records(StreamKind.IMAGE))
    decoded, failed = [], []
    for frame in frames:
        try:
            decoded.append(frame.image.shape)
        except InputError as exc:
            failed.append(exc.path)
    assert failed == [bad] and decoded == [(24, 32, 3)] * 5


def test_a_corrupt_first_image_takes_the_layout_from_the_next(tmp_path):
    root = fz.write_folder(tmp_path / "f")
    _corrupt(root / "images" / "0000.png")
    with pytest.warns(InputWarning, match=r"0000.png.*layout of its camera is taken from the next image"):
        log = FolderLog(root)
    assert (log.layout.width, log.layout.height, log.layout.encoding) == (32, 24, "bgr8")


def test_non_utf8_csv_and_nul_image_name_name_their_line(tmp_path):
    root = fz.write_folder(tmp_path / "f")
    table = root / "frames.csv"
    lines = table.read_bytes().split(b"\n")
    lines[3] = lines[3].replace(b"0002.png", b"00\xff2.png")
    table.write_bytes(b"\n".join(lines))
    with pytest.raises(InputError, match="line 4: byte 0xff"):
        list(FolderLog(root).messages())
    lines[3] = lines[3].replace(b"00\xff2.png", b"00\x002.png")
    table.write_bytes(b"\n".join(lines))
    with pytest.raises(InputError) as exc:
        list(FolderLog(root).messages())
    assert exc.value.path == table and exc.value.field == "line 4, column image"


def test_kitti_image_folder_with_a_corrupt_frame_reads_the_others(tmp_path):
    seq = _odometry(tmp_path)
    _corrupt(seq / "image_0" / "000003.png")
    shutil.copy(seq / "image_0" / "000003.png", tmp_path / "keep.png")
    frames = list(KittiOdometry(seq).records(StreamKind.IMAGE))
    ok = []
    for frame in frames:
        try:
            ok.append(int(frame.image[0, 0]))
        except InputError as exc:
            assert exc.path == seq / "image_0" / "000003.png"
    assert ok == [0, 10, 20, 40, 50]
    assert cv2.imread(str(tmp_path / "keep.png")) is None  # premise: OpenCV cannot decode it


# --- the net under every reader -------------------------------------------------------------------


def test_a_data_error_that_slips_out_of_a_reader_becomes_an_input_error(tmp_path):
    """What a reader fails to name itself still reaches the user as one InputError naming the file, cause kept."""
    from mapkit.core.types import GpsFix, Message, StreamInfo
    from mapkit.io.base import DriveLog

    class Broken(DriveLog):
        def streams(self):
            return [StreamInfo("/gps", StreamKind.GPS, "sensor_msgs/NavSatFix", 2)]

        def _iter_messages(self, topics):
            yield Message("/gps", StreamKind.GPS, 0, GpsFix(1, 49.0, 8.4, 100.0))
            np.linalg.solve(np.zeros((3, 3)), np.ones(3))  # LinAlgError, a ValueError

    log = Broken(tmp_path / "drive.log")
    with pytest.raises(
        InputError, match=r"could not be read after message 0 of /gps \(LinAlgError: Singular matrix\)"
    ) as exc:
        list(log.messages())
    assert exc.value.path == tmp_path / "drive.log" and isinstance(exc.value.__cause__, np.linalg.LinAlgError)
