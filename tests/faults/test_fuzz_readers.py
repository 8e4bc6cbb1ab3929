"""Bounded fuzzing of the readers for CI: only InputError and InputWarning may leave a reader.

Hypothesis writes arbitrary text into the files of small valid KITTI odometry, KITTI raw OXTS and folder
logs (calibration, stamps, poses, OXTS records, CSV rows: numbers that are not finite, huge exponents,
non-ASCII digits, stray bytes, missing and extra values) and reads the log completely. A seeded campaign
then damages whole logs (MCAP written by mapkit, a ROS 1 bag written by rosbags, PNG/JPEG images) with
the fault classes of bench/fuzz_readers.py, which runs the same campaign for longer.
"""

from __future__ import annotations

import importlib.util
import shutil
import sys
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mapkit.core.errors import InputError

BENCH = Path(__file__).resolve().parents[2] / "bench" / "fuzz_readers.py"


def _load_bench():
    """bench/fuzz_readers.py (its writers, faults and campaign), loaded once per session under one name."""
    name = "fuzz_readers_bench"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, BENCH)
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module  # before running it: its dataclasses look their module up
        spec.loader.exec_module(module)
    return sys.modules[name]


fz = _load_bench()

SETTINGS = settings(
    max_examples=60, deadline=None, derandomize=True, database=None, suppress_health_check=[HealthCheck.too_slow]
)

#: tokens of a numeric text file: real numbers in any spelling, the hard ones, and short arbitrary text
TOKEN = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(min_value=-(10**30), max_value=10**30).map(str),
    st.sampled_from(fz.BAD_NUMBERS),
    st.text(max_size=6),
)
#: a matrix row of numbers from a few distinct values, so that singular, zero and scaled matrices come often;
#: or of any tokens
MATRIX_VALUE = st.sampled_from(["0", "1", "-1", "0.5", "5", "707.0912", "1e-300", "1e300", "-0"])
MATRIX_ROW = st.one_of(st.lists(MATRIX_VALUE, min_size=12, max_size=12), st.lists(TOKEN, min_size=11, max_size=13))
LINE = st.lists(TOKEN, max_size=14).map(" ".join)


def _encoded(text: str) -> bytes:
    return text.encode("utf-8", "surrogatepass")


#: a whole text file: lines of tokens, or any bytes
TEXT = st.one_of(st.lists(LINE, max_size=8).map(lambda lines: _encoded("\n".join(lines))), st.binary(max_size=160))


def _only_input_errors(path: Path, fmt: str) -> None:
    read = fz.read_log(path, fmt)
    if read.error is not None and not isinstance(read.error, InputError):
        raise read.error


@pytest.fixture(scope="module")
def clean(tmp_path_factory) -> dict[str, Path]:
    base = tmp_path_factory.mktemp("clean")
    return {
        "odometry": fz.write_kitti_odometry(base / "seq"),
        "raw": fz.write_kitti_raw_oxts(base / "raw"),
        "folder": fz.write_folder(base / "folder"),
    }


def _copy(src: Path) -> Path:
    dst = Path(tempfile.mkdtemp()) / src.name
    shutil.copytree(src, dst)
    return dst


@SETTINGS
@given(name=st.sampled_from(["calib.txt", "times.txt", "poses.txt"]), content=TEXT)
def test_kitti_odometry_text_never_crashes(clean, name, content):
    seq = _copy(clean["odometry"])
    try:
        (seq / name).write_bytes(content)
        _only_input_errors(seq, "kitti-odometry")
    finally:
        shutil.rmtree(seq.parent)


@SETTINGS
@given(k=st.integers(0, 2), label=st.sampled_from(["P0:", "P1:", "Tr:", "P9:", ""]), row=MATRIX_ROW)
def test_kitti_calibration_entries_never_crash(clean, k, label, row):
    """One calib.txt entry of about the right length: singular, zero, scaled and non-finite matrices included."""
    seq = _copy(clean["odometry"])
    try:
        lines = (seq / "calib.txt").read_text().splitlines()
        lines[k] = f"{label} {' '.join(row)}"
        (seq / "calib.txt").write_bytes(_encoded("\n".join(lines) + "\n"))
        _only_input_errors(seq, "kitti-odometry")
    finally:
        shutil.rmtree(seq.parent)


@SETTINGS
@given(stamps=st.lists(st.one_of(TOKEN, st.floats(0, 1e12).map(repr)), min_size=6, max_size=6))
def test_kitti_times_never_crash(clean, stamps):
    """times.txt, one stamp a line: huge exponents (a Decimal overflow), non-finite, negative and disordered values."""
    seq = _copy(clean["odometry"])
    try:
        (seq / "times.txt").write_bytes(_encoded("\n".join(stamps) + "\n"))
        _only_input_errors(seq, "kitti-odometry")
    finally:
        shutil.rmtree(seq.parent)


@SETTINGS
@given(k=st.integers(0, 5), row=MATRIX_ROW)
def test_kitti_poses_never_crash(clean, k, row):
    """One poses.txt line: zero, scaled and reflected rotations, jumps, non-finite values."""
    seq = _copy(clean["odometry"])
    try:
        lines = (seq / "poses.txt").read_text().splitlines()
        lines[k] = " ".join(row)
        (seq / "poses.txt").write_bytes(_encoded("\n".join(lines) + "\n"))
        _only_input_errors(seq, "kitti-odometry")
    finally:
        shutil.rmtree(seq.parent)


@SETTINGS
@given(
    record=st.one_of(st.lists(TOKEN, min_size=28, max_size=31).map(" ".join), LINE),
    k=st.integers(0, 5),
    stamp=st.one_of(st.none(), st.text(max_size=40)),
)
def test_kitti_raw_oxts_records_never_crash(clean, record, k, stamp):
    root = _copy(clean["raw"].parents[1])
    drive = root / clean["raw"].relative_to(clean["raw"].parents[1])
    try:
        (drive / "oxts" / "data" / f"{k:010d}.txt").write_bytes(_encoded(record + "\n"))
        if stamp is not None:
            lines = (drive / "oxts" / "timestamps.txt").read_text().splitlines()
            lines[k] = stamp
            (drive / "oxts" / "timestamps.txt").write_bytes(_encoded("\n".join(lines) + "\n"))
        _only_input_errors(drive, "kitti-raw")
    finally:
        shutil.rmtree(root.parent)


CELL = st.one_of(TOKEN, st.sampled_from(["0001.jpg", "0002.png", "", "../frames.csv", "a" * 300, '"', "1700000000.5"]))


@SETTINGS
@given(
    row=st.one_of(
        st.lists(CELL, min_size=14, max_size=18).map(lambda cells: _encoded(",".join(cells))), st.binary(max_size=120)
    ),
    k=st.integers(1, 6),
)
def test_folder_csv_rows_never_crash(clean, row, k):
    root = _copy(clean["folder"])
    try:
        lines = (root / "frames.csv").read_bytes().split(b"\n")
        lines[k] = row
        (root / "frames.csv").write_bytes(b"\n".join(lines))
        _only_input_errors(root, "folder")
    finally:
        shutil.rmtree(root.parent)


def test_seeded_campaign_over_whole_logs_never_crashes_nor_loses_intact_chunks(tmp_path):
    """15 inputs of every fault class of bench/fuzz_readers.py (MCAP flips in the summary, in chunks and elsewhere,
    bursts and truncations, ROS 1 bag damage, KITTI and folder text, impossible poses, corrupt images)."""
    tallies = fz.campaign(seconds=float("inf"), seed=23, base=tmp_path / "clean", max_inputs=15)
    assert len(tallies) == 19 and all(t.tried == 15 for t in tallies.values())
    bad = {
        name: {k: t.examples[k] for k in ("crash", "silent loss", "intact data lost") if k in t.outcomes}
        for name, t in tallies.items()
    }
    assert not any(bad.values()), bad
    # the damage is seen: every summary flip and truncation warns, and every MCAP input reads everything it can
    for compression in ("zstd", "none"):
        assert tallies[f"MCAP flip in summary ({compression})"].outcomes["warning, intact data kept"] == 15
        assert tallies[f"MCAP truncation ({compression})"].outcomes["warning, intact data kept"] == 15
        assert (
            tallies[f"MCAP end opcode at a chunk, no summary ({compression})"].outcomes["warning, intact data kept"]
            == 15
        )
    assert tallies["KITTI impossible pose"].outcomes["warning, intact data kept"] == 15
