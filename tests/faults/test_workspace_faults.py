"""Workspace faults: nothing stale, nothing half-written.

A log built while still being copied, a replaced log, a truncated ``points.ply``, a full disk, an
edited export and bad config values: each ends in one clear error or a correct rebuild, and
nothing is lost. Logs are the small image-less INS drive of ``test_build`` (300 poses, 30 fixes)
and maps the synthetic street of ``test_align``.
"""

from __future__ import annotations

import errno
import json
import os
import threading
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
from test_align import make_workspace
from test_align import street as street_points
from test_build import _imageless_log

from mapkit.core.bundle import MANIFEST, copy_file, is_finished, write_manifest
from mapkit.core.errors import ConfigError, InputError, InputWarning, MapkitError
from mapkit.core.fingerprint import log_fingerprint
from mapkit.core.runio import (
    DONE_MARKER,
    WriteError,
    atomic_write_ply,
    config_hash,
    is_done,
    mark_done,
    read_marker,
    stage_hash,
    write_json,
)
from mapkit.core.workspace import Workspace
from mapkit.mapping.build import build
from mapkit.mapping.trajectory import Trajectory
from mapkit.multisession.align import align_workspace

OLD = time.time() - 3600  # an mtime long past: a log that finished being written


def _settled(path: Path) -> Path:
    os.utime(path, (OLD, OLD))
    return path


def _build(log: Path, ws: Path, config: Path | None = None) -> Workspace:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputWarning)  # the image stages are skipped: this log has no camera
        build([log], ws, config=config, progress=False)
    return Workspace(ws)


def _poses(ws: Workspace, name: str) -> int:
    return len(Trajectory.load(ws.session(name).trajectory))


@pytest.fixture(scope="module")
def full_log(tmp_path_factory) -> bytes:
    """The drive in 2 KiB chunks (as a long log is in many): a truncated copy keeps its first chunks."""
    import functools

    import test_build

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(test_build, "McapWriter", functools.partial(test_build.McapWriter, chunk_size=2048))
        return _imageless_log(tmp_path_factory.mktemp("log") / "drive.mcap").read_bytes()


def test_a_log_still_being_copied_is_refused_then_built_once_complete(tmp_path, full_log):
    """A log still being copied: while bytes keep arriving the build refuses before writing anything;
    once the copy is complete it builds every pose."""
    log = tmp_path / "drive.mcap"
    half = len(full_log) // 2
    log.write_bytes(full_log[:half])
    chunks = np.array_split(np.frombuffer(full_log[half:], np.uint8), 40)

    def copy_rest():
        with open(log, "ab") as f:
            for c in chunks:
                time.sleep(0.03)
                f.write(c.tobytes())
                f.flush()

    copier = threading.Thread(target=copy_rest)
    copier.start()
    try:
        with pytest.raises(InputError, match="still being written") as err:
            _build(log, tmp_path / "ws")
    finally:
        copier.join()
    assert str(log) in str(err.value)
    assert not (tmp_path / "ws").exists()  # refused before any write
    assert log.read_bytes() == full_log
    ws = _build(_settled(log), tmp_path / "ws")
    assert _poses(ws, "drive") == 300


def test_a_log_completed_after_its_build_is_rebuilt(tmp_path, full_log):
    """A log built while incomplete (its copy stalled), then completed: the trajectory's marker records the
    log's fingerprint, so the next build makes the session again instead of keeping the partial one."""
    log = tmp_path / "drive.mcap"
    log.write_bytes(full_log[: len(full_log) // 2])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the reader salvages the intact chunks of the truncated log
        ws = _build(_settled(log), tmp_path / "ws")
    partial = _poses(ws, "drive")
    assert 0 < partial < 300
    marker = read_marker(ws.session("drive").trajectory)
    assert marker["inputs"]["log"] == log_fingerprint(log)
    log.write_bytes(full_log)
    ws = _build(_settled(log), tmp_path / "ws")
    assert _poses(ws, "drive") == 300
    georef = json.loads(ws.session("drive").gps_alignment.read_text())
    assert georef["fixes_total"] == 30  # the downstream stage was redone too, with every fix


def test_a_replaced_log_is_rebuilt_and_an_unchanged_one_is_not(tmp_path, full_log):
    log = tmp_path / "drive.mcap"
    log.write_bytes(full_log)
    ws = _build(_settled(log), tmp_path / "ws")
    traj_marker = ws.session("drive").trajectory / DONE_MARKER
    first = traj_marker.stat().st_mtime_ns
    ws = _build(log, tmp_path / "ws")
    assert traj_marker.stat().st_mtime_ns == first  # nothing changed: nothing re-run
    _imageless_log(log, yaw_deg=80.0)  # another drive under the same name
    ws = _build(_settled(log), tmp_path / "ws")
    assert traj_marker.stat().st_mtime_ns != first
    assert json.loads(ws.session("drive").gps_alignment.read_text())["alignment"]["yaw_deg"] == pytest.approx(
        80.0, abs=0.5
    )


def test_a_marker_without_inputs_is_not_trusted_and_an_older_one_is_migrated(tmp_path):
    """A marker without input records is not finished for a stage that has inputs (it runs again); a marker
    without a stage version that holds the older rule's hash of the config, and whose inputs still match, is
    migrated once, with a warning; once a marker records inputs, other inputs make it unfinished."""
    folder = tmp_path / "stage"
    folder.mkdir()
    new, old = stage_hash("stage", 1, {"a": 1}), config_hash({"a": 1})
    mark_done(folder, new)
    assert not is_done(folder, new, inputs={"log": {"bytes": 1}}, verify=True)
    mark_done(folder, old, inputs={"log": {"bytes": 1}})
    assert not is_done(folder, new, inputs={"log": {"bytes": 1}})
    with pytest.warns(InputWarning, match="finished by an older mapkit"):
        assert is_done(folder, new, inputs={"log": {"bytes": 1}}, legacy_hash=old, version=1)
    assert read_marker(folder)["stage_version"] == 1 and read_marker(folder)["config_hash"] == new
    assert is_done(folder, new, inputs={"log": {"bytes": 1}})
    assert not is_done(folder, new, inputs={"log": {"bytes": 2}})


@pytest.mark.filterwarnings("ignore:.*skipped. the log has no image stream")
def test_a_truncated_stage_output_is_remade_by_build(tmp_path, full_log):
    """A truncated artefact of a finished stage (here the aligned trajectory the later stages load)
    does not count as finished: the next build re-makes that stage, with a warning naming the file."""
    log = tmp_path / "drive.mcap"
    log.write_bytes(full_log)
    ws = _build(_settled(log), tmp_path / "ws")
    npz = ws.session("drive").georef_trajectory / "trajectory.npz"
    good = npz.read_bytes()
    npz.write_bytes(good[: len(good) // 2])
    with pytest.warns(InputWarning, match=r"trajectory\.npz has \d+ bytes where its stage wrote"):
        build([log], tmp_path / "ws", progress=False)
    assert npz.read_bytes() == good


@pytest.fixture()
def aligned_inputs(tmp_path) -> Path:
    """Two built sessions of the synthetic street whose markers record their outputs, as a build writes them."""
    from test_align import gps_error

    ws = tmp_path / "ws"
    make_workspace(
        ws, street_points(np.random.default_rng(1)), {"s0": gps_error(1.0, -1.0, 0.0), "s1": gps_error(-1.0, 1.0, 0.0)}
    )
    for name in ("s0", "s1"):
        for stage in ("georef", "map"):
            mark_done(ws / "sessions" / name / stage, "test", outputs=True)
    return ws


def test_a_truncated_points_ply_is_one_error_in_align(aligned_inputs):
    """A truncated points.ply is one error, not a map merged with its missing points as zeros: align refuses
    it, naming the file and the command to re-run, and so it does a points.ply of the right size whose
    SHA-256 differs from the one its stage recorded."""
    ply = aligned_inputs / "sessions" / "s1" / "map" / "points.ply"
    data = ply.read_bytes()
    ply.write_bytes(data[: len(data) // 3])
    with pytest.raises(
        InputError, match=r"points\.ply.*has \d+ bytes where its stage wrote \d+: re-run mapkit build \(session s1\)"
    ):
        align_workspace(aligned_inputs, progress=False)
    assert not (aligned_inputs / "align" / DONE_MARKER).exists()
    ply.write_bytes(data[:-8] + b"\x00" * 8)  # same size, other content
    with pytest.raises(InputError, match="another SHA-256"):
        align_workspace(aligned_inputs, progress=False)


def _patch_disk_full(monkeypatch, after_bytes: int) -> None:
    """Writes of files fail with ENOSPC once ``after_bytes`` have been written (a disk that fills up)."""
    import builtins

    real_open = builtins.open
    budget = [after_bytes]

    class FullDisk:
        def __init__(self, f):
            self._f = f

        def write(self, b):
            if len(b) > budget[0]:
                self._f.write(bytes(b)[: budget[0]])
                budget[0] = 0
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            budget[0] -= len(b)
            return self._f.write(b)

        def __getattr__(self, name):
            return getattr(self._f, name)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return self._f.__exit__(*exc)

    def patched(file, mode="r", *args, **kwargs):
        f = real_open(file, mode, *args, **kwargs)
        return FullDisk(f) if "w" in mode or "a" in mode else f

    monkeypatch.setattr(builtins, "open", patched)


def test_disk_full_is_one_line_and_nothing_is_renamed_into_place(tmp_path, monkeypatch, capsys):
    """ENOSPC while writing a PLY, a JSON or a stage of `mapkit build`: one WriteError line naming
    the path and the free space; no partial file left, no stage marked finished."""
    log = _settled(_imageless_log(tmp_path / "logs" / "drive.mcap"))
    _patch_disk_full(monkeypatch, after_bytes=200)
    target = tmp_path / "points.ply"
    with pytest.raises(
        WriteError, match=r"points\.ply: could not be written \(No space left on device; [\d.]+ MB free on "
    ):
        atomic_write_ply(target, np.zeros((1000, 3)))
    with pytest.raises(WriteError, match=r"m\.json: could not be written"):
        write_json(tmp_path / "m.json", {"x": list(range(1000))})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["logs"]

    from mapkit.cli import main

    monkeypatch.undo()
    _patch_disk_full(monkeypatch, after_bytes=20_000)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputWarning)
        assert main(["build", str(log), "--out", str(tmp_path / "ws")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len([line for line in err if "could not be written" in line]) == 1 and "Traceback" not in "\n".join(err)
    ws = Workspace(tmp_path / "ws")
    assert not is_done(ws.session("drive").trajectory) and not list(tmp_path.rglob("*.partial"))


def test_a_short_npz_write_is_not_renamed_into_place(tmp_path, monkeypatch):
    """A writer that reports success on a full disk (as open3d's may) leaves a file that does not
    read back: the check before the rename refuses it."""
    from mapkit.core.runio import atomic_path

    target = tmp_path / "observations.npz"
    with pytest.raises(WriteError, match="does not read back"), atomic_path(target) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, a=np.arange(100_000))
        with open(tmp, "r+b") as f:
            f.truncate(os.path.getsize(tmp) // 2)
    assert list(tmp_path.iterdir()) == []


def test_an_edited_export_is_restored_and_the_index_untouched(tmp_path):
    """Exported files are copies: editing one cannot reach the workspace's index, and a bundle edited
    in place with the same size is not taken for finished (sizes alone said it was)."""
    index = tmp_path / "ws" / "indexes" / "vlad"
    index.mkdir(parents=True)
    (index / "vectors.npy").write_bytes(np.arange(256, dtype=np.float32).tobytes())
    write_manifest(index, {"format_version": 1, "build_hash": "h"})
    export = tmp_path / "export" / "vlad"
    for f in (index / "vectors.npy", index / MANIFEST):
        copy_file(f, export / f.name)
    assert os.stat(export / "vectors.npy").st_ino != os.stat(index / "vectors.npy").st_ino
    original = (index / "vectors.npy").read_bytes()
    with open(export / "vectors.npy", "r+b") as f:
        f.write(b"\xff" * 16)
    assert (index / "vectors.npy").read_bytes() == original
    assert is_finished(index, "h", 1)
    assert not is_finished(export, "h", 1)  # same size, other content


@pytest.mark.parametrize(
    "overrides, field",
    [
        ({"trajectory": {"kiss_icp": {"voxel_size_m": 0}}}, "trajectory.kiss_icp.voxel_size_m"),
        ({"trajectory": {"kiss_icp": {"voxel_size_m": -0.5}}}, "trajectory.kiss_icp.voxel_size_m"),
        ({"trajectory": {"kiss_icp": {"max_range_m": -5}}}, "trajectory.kiss_icp.max_range_m"),
        ({"georef": {"inlier_sigmas": float("nan")}}, "georef.inlier_sigmas"),
        ({"imagedb": {"min_spacing_m": -1}}, "imagedb.min_spacing_m"),
        ({"topics": {"images": ["/no/such/camera"]}}, "images"),
    ],
)
def test_a_bad_build_config_is_named_before_anything_is_written(tmp_path, full_log, overrides, field):
    import yaml

    log = tmp_path / "drive.mcap"
    log.write_bytes(full_log)
    cfg = tmp_path / "build.yaml"
    cfg.write_text(yaml.safe_dump(overrides))
    with pytest.raises(MapkitError) as err:
        build([_settled(log)], tmp_path / "ws", config=cfg, progress=False)
    assert field in str(err.value)
    assert isinstance(err.value, (ConfigError, InputError))
    assert not (tmp_path / "ws").exists()


@pytest.mark.parametrize(
    "command, overrides, field",
    [
        ("align", {"icp": {"voxel_sizes_m": [1.0, 0.0, 0.25]}}, "icp"),
        ("triplets", {"icp_voxel_sizes_m": [-0.3]}, "icp_voxel_sizes_m"),
    ],
)
def test_a_bad_align_or_triplets_config_is_named_before_anything_is_written(tmp_path, command, overrides, field):
    ws = tmp_path / "ws"
    write_json(ws / "origin.json", {"lat_deg": 49.0, "lon_deg": 8.4, "alt_m": 110.0})
    if command == "align":
        with pytest.raises(ConfigError, match=field):
            align_workspace(ws, overrides=overrides, progress=False)
    else:
        from mapkit.places.triplets import export_triplets

        with pytest.raises(ConfigError, match=field):
            export_triplets(ws, overrides=overrides, progress=False)
    assert sorted(p.name for p in ws.iterdir() if p.name != ".lock") == ["origin.json"]  # (the lock is no output)


@pytest.fixture()
def small_disk(tmp_path):
    """A 200 KiB tmpfs (root only): a real full disk, grown to 2 MiB by ``remount``."""
    import subprocess

    disk = tmp_path / "disk"
    disk.mkdir()
    if (
        os.geteuid() != 0
        or subprocess.run(
            ["mount", "-t", "tmpfs", "-o", "size=200k", "tmpfs", str(disk)], capture_output=True
        ).returncode
        != 0
    ):
        pytest.skip("mounting a small tmpfs needs root (the patched writer above covers the non-root case)")
    yield disk, lambda: subprocess.run(["mount", "-o", "remount,size=2m", str(disk)], check=True)
    subprocess.run(["umount", str(disk)], check=True)


def test_a_real_full_disk_stops_the_build_with_one_line_and_it_resumes(tmp_path, small_disk, capsys):
    """`mapkit build` into a 200 KiB file system (the workspace needs ~340 KB): exit 2, one line
    naming the file and the free space, no partial file, the stage that filled the disk not marked
    finished; with room made, the same command finishes."""
    from mapkit.cli import main

    disk, grow = small_disk
    log = _settled(_imageless_log(tmp_path / "drive.mcap"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputWarning)
        assert main(["build", str(log), "--out", str(disk / "ws")]) == 2
    err = capsys.readouterr().err
    assert err.count("No space left on device") == 1 and "MB free on" in err and "Traceback" not in err
    assert not list(disk.rglob("*.partial"))
    ws = Workspace(disk / "ws")
    assert not (is_done(ws.session("drive").trajectory) and is_done(ws.session("drive").georef))
    grow()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputWarning)
        assert main(["build", str(log), "--out", str(disk / "ws")]) == 0
    assert is_done(ws.session("drive").georef) and _poses(ws, "drive") == 300


SHARDS_ONTO = """
import sys
from pathlib import Path
import numpy as np
from mapkit.core.errors import MapkitError
from mapkit.places.triplets import ShardWriter
rng = np.random.default_rng(0)
w = ShardWriter(Path(sys.argv[1]), 16)  # a shard of about 260 kB: more than the disk holds at first
try:
    for _ in range(4):
        w.add(rng.integers(0, 255, (16, 32, 32, 4), np.uint8), rng.integers(0, 255, (16, 3, 32, 32, 4), np.uint8))
    w.flush()
except MapkitError as exc:
    print(exc, file=sys.stderr)
    sys.exit(2)
"""


def test_a_full_disk_under_an_hdf5_shard_is_one_error_not_a_crash(small_disk):
    """Triplet shards (HDF5, incompressible grids) written onto a 200 KiB file system, in a process of its own: it
    exits 2 with one line naming the shard and the free space, no traceback and no crash at exit, nothing partial
    left; with room made, the same shards are written and read back."""
    import subprocess
    import sys

    from mapkit.places.triplets import read_shard

    disk, grow = small_disk
    r = subprocess.run([sys.executable, "-c", SHARDS_ONTO, str(disk)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, (r.returncode, r.stderr[-2000:])
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "patches-00000.h5" in lines[0] and "MB free on" in lines[0], r.stderr[-2000:]
    assert not list(disk.rglob("*.partial"))
    grow()
    r = subprocess.run([sys.executable, "-c", SHARDS_ONTO, str(disk)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    assert read_shard(disk / "patches-00003.h5")["occupancy"].shape == (16, 32, 32, 4)


def test_a_tampered_export_is_restored_by_re_export_and_the_index_is_untouched(tmp_path):
    """An export shares no file with the workspace's index (its files are copies, not hard links), so
    editing the export leaves the index intact; loading the edited export fails its checksum, re-export
    restores it, and an index edited in place (same size, other bytes) is not taken for finished but rebuilt."""
    from test_index_vlad import make_workspace as vlad_workspace
    from test_index_vlad import small_config

    from mapkit.deploy.export import export_bundles, load_bundle
    from mapkit.retrieval.index_vlad import build_vlad_index

    ws = vlad_workspace(tmp_path, names=("train-a", "train-b"))
    index = build_vlad_index(ws, config=small_config(), progress=False)
    before = {p.relative_to(index): p.read_bytes() for p in index.rglob("*") if p.is_file()}
    export = export_bundles(ws, tmp_path / "export")
    vectors = max(
        (p for p in (export / "vlad").rglob("*") if p.is_file() and p.name != MANIFEST), key=lambda p: p.stat().st_size
    )
    assert vectors.stat().st_nlink == 1
    with open(vectors, "r+b") as f:  # same size, other bytes
        f.seek(vectors.stat().st_size // 2)
        f.write(b"\x00\x01" * 8)
    with pytest.raises(InputError, match="checksum"):
        load_bundle(export)
    assert {p.relative_to(index): p.read_bytes() for p in index.rglob("*") if p.is_file()} == before
    export_bundles(ws, tmp_path / "export")
    assert load_bundle(export)["vlad"] is not None  # restored, every checksum verified
    edited = index / vectors.relative_to(export / "vlad")
    with open(edited, "r+b") as f:
        f.seek(edited.stat().st_size // 2)
        f.write(b"\x00\x01" * 8)
    build_vlad_index(ws, config=small_config(), progress=False)  # not taken for finished: rebuilt
    assert edited.read_bytes() == before[edited.relative_to(index)]


def test_a_named_camera_missing_from_the_log_is_refused_before_the_trajectory(tmp_path, full_log):
    """`camera: front` on a log without that camera is refused before any stage runs (the trajectory and georef
    stages do not need the camera, so only an early check spares their work): nothing is written."""
    log = tmp_path / "drive.mcap"
    log.write_bytes(full_log)
    _settled(log)
    cfg = tmp_path / "build.yaml"
    cfg.write_text("camera: front\n")
    with pytest.raises(InputError, match=r"\[camera\]: has no image stream, but the config asks for camera 'front'"):
        build([log], tmp_path / "ws", config=cfg, progress=False)
    assert not (tmp_path / "ws").exists()


def test_an_edited_image_table_is_refused_by_index_vlad_naming_the_stage(tmp_path):
    from test_index_vlad import make_workspace as vlad_workspace
    from test_index_vlad import small_config

    from mapkit.retrieval.index_vlad import build_vlad_index

    ws = vlad_workspace(tmp_path, names=("train-a", "train-b"))
    for name in ("train-a", "train-b"):
        mark_done(ws / "sessions" / name / "imagedb", "test", outputs=True)
    csv = ws / "sessions" / "train-b" / "imagedb" / "images.csv"
    csv.write_text(csv.read_text().replace("images/cam/003.png", "images/cam/004.png"))
    with pytest.raises(InputError, match=r"images\.csv.*re-run mapkit build \(session train-b\)"):
        build_vlad_index(ws, config=small_config(), progress=False)
    assert not (ws / "indexes").exists()
