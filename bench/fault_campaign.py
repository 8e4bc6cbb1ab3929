"""Fault campaign through the command line: each fault as a user meets it, run with ``mapkit`` as a subprocess.

mapkit promises that bad input ends in one clear error naming the file and field (exit 2, one ``error:`` line, no
Python traceback) or in a warning saying what was skipped; that nothing already written is lost; and that nothing
stale or half-written is taken for a result. ``bench/fuzz_readers.py`` checks the readers byte by byte inside one
process; this campaign runs the installed CLI (``.venv/bin/mapkit``) over prepared faults, as a user would:

- ``damaged logs``: MCAP/ROS 2 and ROS 1 bags of a one-drive synthetic town, KITTI odometry (12 frames of the real
  clip), KITTI raw OXTS (the real drive), a generic folder and a geotagged photo walk, each truncated, hit by flipped
  bytes, missing a file or with camera stamps reversed -> ``mapkit build``;
- ``GPS faults``: null island, 1 km jumps, no fix at all, GPS an hour away from the drive -> ``mapkit build``;
- ``SIGKILL``: ``kill -9`` while each stage runs (build's trajectory, georef, map and image database; align;
  triplets; index vlad; index structure), then the same command again: it must finish with the outputs of a clean
  run (the SHA-256 every stage marker records);
- ``two writers``: every writing entry point started while another process holds the workspace -> exit 2 naming it;
- ``full disk``: build, triplets and index vlad into a small tmpfs -> one line, exit 2; with room made, the same
  command finishes (skipped with the reason when mounting is not permitted);
- ``stale inputs``: a log replaced after its build, a truncated points.ply, an edited images.csv or index;
- ``damaged bundles``: an export with a changed file, a missing file, a manifest listing fewer indexes, an unknown
  format version -> ``mapkit localize`` and ``mapkit eval retrieval``;
- ``bad configs``: a wrong type, an unknown field, a bad value for build, align, triplets, index vlad and index
  structure -> one line naming the field, nothing written.

Each case's outcome is one of ``clear error`` (exit 2, exactly one stderr line starting ``error:`` that names the
file or field, no traceback), ``recovered`` (exit 0, warnings allowed, outputs right), ``traceback`` (a Python
traceback on stderr, or a signal we did not send), ``silent-wrong`` (exit 0, outputs wrong or empty without a
word), ``lost`` (something written and valid before is gone or corrupted, or a killed command cannot be resumed to
a clean run's outputs) and ``other`` (anything else against the promise: an error line that names nothing, a
refused command that wrote, a full disk that did not stop the command; the detail says which).

Clean inputs are made once under ``--work`` (kept there: a second run reuses them) from the tiny synthetic town
(``mapkit synth --preset tiny``, then build, align, triplets, index vlad, index structure and index export, as
``pipelines/main.py --preset tiny`` does) and from the small logs the tests make (``tests/``, imported).

Run from the repository root (as root for the full-disk class)::

    python3 bench/fault_campaign.py --out /tmp/fault-campaign.json          # every case, about 20 min on 2 cores
    python3 bench/fault_campaign.py --quick --out /tmp/fault-campaign.json  # two cases per class
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import time
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
for _p in (REPO, REPO / "tests", REPO / "tests" / "faults", REPO / "bench"):
    if str(_p) not in sys.path:
        sys.path.insert(0, str(_p))

MAPKIT = REPO / ".venv" / "bin" / "mapkit"
SHARED_DATA = Path(os.environ.get("MAPKIT_SHARED_DATA", REPO.parent / "shared" / "data"))
OUTCOMES = ("clear error", "recovered", "traceback", "silent-wrong", "lost", "other")
CLASSES = (
    "damaged logs",
    "GPS faults",
    "SIGKILL",
    "two writers",
    "full disk",
    "stale inputs",
    "damaged bundles",
    "bad configs",
)
OLD = time.time() - 7200  # an mtime long past: a log that finished being copied (a build refuses a log still growing)

#: the tiny town's stage settings, kept small so that each stage runs in seconds (every run, clean or faulted,
#: uses the same ones, so outputs compare)
VLAD_YAML = (
    "train_sessions: [tiny-sunny_0, tiny-rainy_0]\ndatabase_sessions: [tiny-sunny_0, tiny-rainy_0]\n"
    "vlad: {dsift: {half_resolution: true}}\n"
)
TRIPLETS_YAML = "n_triplets: 200\n"
N_PHOTOS = 24
STRUCTURE_SESSIONS = ("-s", "tiny-sunny_0", "-s", "tiny-rainy_0")


# --- running mapkit -----------------------------------------------------------------------------------


@dataclass
class Run:
    args: list[str]
    rc: int
    out: str
    err: str
    seconds: float

    @property
    def errors(self) -> list[str]:
        return [line for line in self.err.splitlines() if line.startswith("error:")]

    @property
    def warnings(self) -> list[str]:
        return [line for line in self.err.splitlines() if line.startswith("warning:")]

    @property
    def traceback(self) -> bool:
        return "Traceback (most recent call last)" in self.err or self.rc < 0


def mapkit(*args, timeout: float = 1200) -> Run:
    """``mapkit ARGS`` as a user runs it (stdin closed, not a terminal)."""
    argv = [str(MAPKIT), *map(str, args)]
    t0 = time.monotonic()
    p = subprocess.run(argv, capture_output=True, text=True, timeout=timeout, stdin=subprocess.DEVNULL)
    return Run([Path(argv[0]).name, *argv[1:]], p.returncode, p.stdout, p.stderr, time.monotonic() - t0)


def killed_at(
    args: list, ws: Path, trigger: str, delay_s: float, deadline_s: float | None = None, timeout: float = 1200
) -> tuple[bool, float]:
    """Starts ``mapkit ARGS``, waits for a path matching the glob ``trigger`` to appear under ``ws`` (a stage's
    folder, or the hidden folder it is written in before its rename), then ``delay_s`` more, and kills it with
    SIGKILL; or at ``deadline_s`` after the start, whichever comes first (a stage that writes nothing until its
    end). Returns (whether it was killed before it ended, seconds it ran)."""
    t0 = time.monotonic()
    proc = subprocess.Popen(
        [str(MAPKIT), *map(str, args)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, stdin=subprocess.DEVNULL
    )
    try:
        while not next(ws.glob(trigger), None):
            if proc.poll() is not None or time.monotonic() - t0 > timeout:
                return False, time.monotonic() - t0
            if deadline_s is not None and time.monotonic() - t0 > deadline_s:
                break
            time.sleep(0.02)
        else:
            time.sleep(delay_s)
        if proc.poll() is not None:
            return False, time.monotonic() - t0
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        return True, time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


@contextlib.contextmanager
def holding(ws: Path) -> Iterator[int]:
    """Another process holding ``ws``'s write lock (as a running ``mapkit build`` does); yields its pid."""
    code = (
        "import sys, time\nfrom pathlib import Path\nfrom mapkit.core.lock import workspace_lock\n"
        "with workspace_lock(sys.argv[1], command='mapkit build (campaign holder)'):\n"
        "    Path(sys.argv[2]).write_text('held')\n    time.sleep(600)\n"
    )
    flag = ws.parent / f".held-{time.monotonic_ns()}"
    proc = subprocess.Popen([sys.executable, "-c", code, str(ws), str(flag)])
    try:
        t0 = time.monotonic()
        while not flag.exists():
            if proc.poll() is not None or time.monotonic() - t0 > 60:
                raise RuntimeError(f"the lock holder did not take {ws}")
            time.sleep(0.05)
        yield proc.pid
    finally:
        proc.kill()
        proc.wait()
        flag.unlink(missing_ok=True)


# --- outcomes -----------------------------------------------------------------------------------------


@dataclass
class Case:
    klass: str
    name: str
    command: str = ""
    outcome: str = ""
    detail: str = ""
    seconds: float = 0.0
    stderr_tail: str = ""


def _tail(run: Run, n: int = 1200) -> str:
    return run.err[-n:]


def error_outcome(run: Run, names: tuple[str, ...]) -> tuple[str, str] | None:
    """The outcome of a run that ended in an error: a traceback, a clear error (one ``error:`` line naming one of
    ``names``), or other; None when it did not end in an error (exit 0)."""
    if run.traceback:
        return "traceback", (run.err.strip().splitlines() or ["(signal)"])[-1][:300] + f" (exit {run.rc})"
    if run.rc == 0:
        return None
    errs = run.errors
    if run.rc != 2:
        return "other", f"exit {run.rc}: {(errs or run.err.strip().splitlines() or [''])[-1][:300]}"
    if len(errs) != 1:
        return "other", f"{len(errs)} error lines: {' | '.join(errs)[:300]}"
    if not any(n in errs[0] for n in names):
        return "other", f"the error names none of {list(names)}: {errs[0][:300]}"
    return "clear error", errs[0][:300]


def listing(root: Path) -> dict[str, str]:
    """Every file under ``root`` (the lock file aside) with its SHA-256."""
    if not root.exists():
        return {}
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file() and p.name != ".lock"
    }


def changed(before: dict[str, str], after: dict[str, str]) -> tuple[list[str], list[str], list[str]]:
    """(files gone or altered, files added)."""
    gone = sorted(k for k in before if k not in after)
    altered = sorted(k for k in before if k in after and before[k] != after[k])
    added = sorted(k for k in after if k not in before)
    return gone, altered, added


def stage_outputs(folder: Path) -> dict:
    """What a finished stage's ``.done`` marker records of its outputs (timings aside), {} when unfinished."""
    try:
        rec = json.loads((folder / ".done").read_text())
    except (OSError, ValueError):
        return {}
    return {k: v for k, v in (rec.get("outputs") or {}).items() if not k.endswith("timings.json")}


# --- clean inputs -------------------------------------------------------------------------------------


def settle(root: Path) -> Path:
    """Every file under ``root`` made old, as a log copied long ago (a build refuses a log whose mtime is recent)."""
    for p in [root, *root.rglob("*")] if root.is_dir() else [root]:
        os.utime(p, (OLD, OLD), follow_symlinks=False)
    return root


def _copy(src: Path, dst: Path) -> Path:
    if dst.exists():
        shutil.rmtree(dst) if dst.is_dir() else dst.unlink()
    dst.parent.mkdir(parents=True, exist_ok=True)
    if src.is_dir():
        shutil.copytree(src, dst, symlinks=True)
    else:
        shutil.copy2(src, dst)
    return dst


@dataclass
class Inputs:
    """Where the clean inputs are (made once, under the work folder)."""

    work: Path
    logs: dict[str, Path] = field(default_factory=dict)  # reader kind -> clean log path
    configs: dict[str, Path] = field(default_factory=dict)  # reader kind -> build config (or absent)
    town: Path | None = None
    tiny_ws: Path | None = None  # the tiny town's workspace: built, aligned, triplets, indexes
    bundle: Path | None = None  # its export
    imageless: Path | None = None  # the tests' image-less INS drive (GPS at 1 Hz, 37 deg yaw)
    baselines: dict[str, Path] = field(default_factory=dict)  # reader kind -> workspace of a clean build

    def config_args(self, kind: str) -> list:
        return ["-c", self.configs[kind]] if kind in self.configs else []


def prepare(work: Path, log: Callable[[str], None]) -> Inputs:
    """Every clean input, under ``work`` (kept: a later run reuses what is there)."""
    import fuzz_readers as fz
    from test_build import _imageless_log
    from test_build_camera_only import CONFIG as CAMERA_ONLY
    from test_build_camera_only import _photo_walk
    from test_rosbag1 import ONE_DRIVE, _twins

    from mapkit.synth import session_log, synthesize

    inp = Inputs(work)
    clean = work / "clean"
    clean.mkdir(parents=True, exist_ok=True)
    clip = SHARED_DATA / "kitti-odometry-clip"
    raw = SHARED_DATA / "kitti-raw-0001-oxts"
    if not (clip / "poses.txt").is_file() or not raw.is_dir():
        raise SystemExit(f"the real KITTI data is not at {SHARED_DATA} (expected ../shared/data beside the project)")

    # one drive of the tiny town (camera, LiDAR, GPS) as ROS 2 MCAP and as a ROS 1 bag
    one = clean / "one-drive"
    if not (one / ".ready").exists():
        log("clean inputs: a one-drive town (MCAP and ROS 1 bag)")
        shutil.rmtree(one, ignore_errors=True)
        town = synthesize(preset="tiny", out=one / "town", overrides=ONE_DRIVE, progress=False)
        _twins(session_log(town, "drive"), one)
        (one / ".ready").write_text("")
    inp.logs["mcap"] = settle(next((one / "town" / "sessions" / "drive").glob("*.mcap")))
    inp.logs["rosbag"] = settle(one / "drive.bag")

    # 12 frames of the real KITTI odometry clip (map off: the image stages read every frame all the same)
    kodo = clean / "kitti-odometry"
    if not (kodo / "times.txt").exists():
        shutil.rmtree(kodo, ignore_errors=True)
        (kodo / "image_l").mkdir(parents=True)
        for i in range(12):
            shutil.copy(clip / "image_l" / f"{i:06d}.png", kodo / "image_l")
        shutil.copy(clip / "calib.txt", kodo)
        (kodo / "poses.txt").write_text("".join((clip / "poses.txt").read_text().splitlines(keepends=True)[:12]))
        (kodo / "times.txt").write_text("".join(f"{0.1 * i:.6e}\n" for i in range(12)))
    inp.logs["kitti-odometry"] = settle(kodo)
    (clean / "map-off.yaml").write_text("map: false\n")
    inp.configs["kitti-odometry"] = clean / "map-off.yaml"

    inp.logs["kitti-raw"] = settle(_copy(raw, clean / "kitti-raw")) / "2011_09_26" / "2011_09_26_drive_0001_sync"

    folder = clean / "folder"
    if not (folder / "frames.csv").exists():
        shutil.rmtree(folder, ignore_errors=True)
        fz.write_folder(folder)
    inp.logs["folder"] = settle(folder)

    photos = clean / "photos"
    if not (photos / f"{N_PHOTOS - 1:06d}.jpg").exists():  # (a walk of about 28 m: GPS fixes its heading)
        shutil.rmtree(photos, ignore_errors=True)
        shutil.rmtree(work / "baselines" / "photos", ignore_errors=True)
        _photo_walk(clip, photos, N_PHOTOS)
    inp.logs["photos"] = settle(photos)
    (clean / "camera-only.yaml").write_text(CAMERA_ONLY)
    inp.configs["photos"] = clean / "camera-only.yaml"

    inp.imageless = clean / "imageless.mcap"
    if not inp.imageless.exists():
        _imageless_log(inp.imageless)
    settle(inp.imageless)
    inp.logs["imageless"] = inp.imageless

    # the tiny town through every stage, as pipelines/main.py --preset tiny runs it
    inp.town = work / "town"
    if not (inp.town / ".done").exists():
        log("clean inputs: mapkit synth --preset tiny")
        _must(mapkit("synth", "--preset", "tiny", "--out", inp.town))
    for p in (inp.town / "sessions").rglob("*.mcap"):
        settle(p)
    ws = inp.tiny_ws = work / "tiny-ws"
    (clean / "vlad.yaml").write_text(VLAD_YAML)
    (clean / "triplets.yaml").write_text(TRIPLETS_YAML)
    steps = [
        ("sessions/tiny-night_0/imagedb/.done", ["build", *tiny_logs(inp), "--out", ws]),
        ("align/.done", ["align", ws]),
        ("triplets/.done", ["triplets", ws, "-c", clean / "triplets.yaml"]),
        ("indexes/vlad/manifest.json", ["index", "vlad", ws, "-c", clean / "vlad.yaml"]),
        ("indexes/structure-nbld/manifest.json", ["index", "structure", ws, *STRUCTURE_SESSIONS]),
    ]
    for done, args in steps:
        if not (ws / done).exists():
            log(f"clean inputs: mapkit {' '.join(map(str, args[:2]))}")
            _must(mapkit(*args))
    inp.bundle = work / "bundle"
    if not (inp.bundle / "manifest.json").exists():
        _must(mapkit("index", "export", ws, "--out", inp.bundle))
    return inp


def tiny_logs(inp: Inputs) -> list[Path]:
    assert inp.town is not None
    return [next((inp.town / "sessions" / n).glob("*.mcap")) for n in ("tiny-sunny", "tiny-rainy", "tiny-night")]


def _must(run: Run) -> Run:
    if run.rc != 0:
        raise RuntimeError(f"{' '.join(run.args)} failed (exit {run.rc}):\n{run.err[-3000:]}")
    return run


# --- checks on a built session ------------------------------------------------------------------------


def session_summary(ws: Path) -> dict:
    """What a build made, per session: poses, georeferenced or not, and the image positions of its database
    (UTM when georeferenced, else the local frame), for comparing a faulted build with a clean one."""
    out = {}
    for s in sorted((ws / "sessions").iterdir()) if (ws / "sessions").is_dir() else []:
        rec: dict = {"trajectory": bool(stage_outputs(s / "trajectory"))}
        npz = s / "trajectory" / "trajectory.npz"
        if npz.is_file():
            with np.load(npz) as d:
                rec["poses"] = int(len(d["stamps_ns"]))
        ga = s / "georef" / "gps_alignment.json"
        if ga.is_file():
            g = json.loads(ga.read_text())
            rec["georeferenced"] = bool(g.get("georeferenced", g.get("alignment") is not None))
            rmse = (g.get("alignment") or g).get("residual_rmse_m")
            if rmse is not None:
                rec["gps_rmse_m"] = float(rmse)
        csv = s / "imagedb" / "images.csv"
        if csv.is_file():
            rows = [r.split(",") for r in csv.read_text().splitlines()[1:]]
            utm = np.array([[float(r[7]), float(r[8]), float(r[6])] for r in rows]).reshape(-1, 3)
            local = np.array([[float(c) for c in r[10:13]] for r in rows]).reshape(-1, 3)
            # UTM easting, northing and altitude where georeferenced: the workspace's local frame starts at its first
            # fix, which a fault may move (stamps reversed: the walk's other end)
            rec["images"] = utm if len(utm) and np.isfinite(utm).all() else local
        out[s.name] = rec
    return out


#: how far an image of a faulted build may lie from the nearest image of the clean build and still count as the
#: same output: half the clean build's GPS residual (RMSE) where it is georeferenced (a fault that moves images by
#: less is within what GPS can tell), else 0.1 m
SAME_IMAGE_M = 0.1


def differences(got: dict, want: dict) -> dict:
    """What differs between two builds' session summaries (images: counts, then the largest distance from an image
    to the nearest image of the other build)."""
    diff = {}
    for (_, a), (_, b) in zip(sorted(got.items()), sorted(want.items()), strict=False):
        tol = 0.5 * b.get("gps_rmse_m", 2 * SAME_IMAGE_M) if b.get("georeferenced") else SAME_IMAGE_M
        for k in sorted(set(a) | set(b)):
            x, y = a.get(k), b.get(k)
            if k == "images" and x is not None and y is not None:
                if len(x) != len(y):
                    diff[k] = f"{len(x)} images where the clean build has {len(y)}"
                elif len(x):
                    far = float(np.linalg.norm(x[:, None] - y[None], axis=2).min(axis=1).max())
                    if far > tol:
                        diff[k] = f"an image {far:.2f} m from the nearest of the clean build (more than {tol:.2f} m)"
                    else:
                        b.setdefault("_within", []).append(f"images within {far:.2f} m of the clean build's")
            elif k == "gps_rmse_m" or k == "_within":
                continue
            elif k == "images" or x != y:
                diff[k] = f"{x} where the clean build has {y}"
    if len(got) != len(want):
        diff["sessions"] = f"{sorted(got)} where the clean build has {sorted(want)}"
    return diff


def _normal(text: str, *paths: Path) -> str:
    for p in paths:
        text = text.replace(str(p), "LOG")
    return text


def build_outcome(run: Run, ws: Path, clean_ws: Path | None, log: Path, clean_log: Path, names: tuple) -> tuple:
    """A build of a faulted log: an error (clear or not), or exit 0 judged against a clean build: the same
    outputs (the fault touched nothing used), or a warning that says what was skipped; else silent-wrong."""
    e = error_outcome(run, names)
    if e is not None:
        return e
    got = session_summary(ws)
    if not got or not all(r["trajectory"] for r in got.values()):
        return "silent-wrong", f"exit 0 without a finished trajectory: {got}"
    if clean_ws is None:
        return "recovered", "exit 0"
    want = session_summary(clean_ws)
    clean_warnings = {_normal(w, clean_log) for w in mapkit_warnings(clean_ws)}
    new = [w for w in run.warnings if _normal(w, log) not in clean_warnings]
    diff = differences(got, want)
    if not diff:
        within = next((w for r in want.values() for w in r.get("_within", [])), "")
        tol = next(iter(want.values())).get("gps_rmse_m", 2 * SAME_IMAGE_M)
        said = f"outputs equal to a clean build's ({within}; GPS residual {tol:.2f} m)" if within else "outputs equal"
        return "recovered", said + (f"; {new[0][:200]}" if new else "")
    if new:
        return "recovered", f"{new[0][:300]}"
    return "silent-wrong", f"outputs differ from a clean build's without a new warning: {str(diff)[:300]}"


def mapkit_warnings(ws: Path) -> list[str]:
    """The warnings of the clean build that made ``ws`` (kept beside it by ``Inputs.baseline``)."""
    path = ws.parent / f"{ws.name}.warnings"
    if not path.is_file():
        return []
    return path.read_text().splitlines()


# --- fault classes --------------------------------------------------------------------------------------


def flip_bytes(path: Path, rnd: random.Random, n: int = 64, start: float = 0.3, end: float = 0.7) -> str:
    data = bytearray(path.read_bytes())
    at = rnd.randrange(int(len(data) * start), max(int(len(data) * end) - n, int(len(data) * start) + 1))
    for i in range(at, min(at + n, len(data))):
        data[i] ^= rnd.randrange(1, 256)
    path.write_bytes(bytes(data))
    return f"{n} bytes flipped at byte {at} of {path.name}"


def truncate(path: Path, fraction: float) -> str:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * fraction)])
    return f"{path.name} cut to {fraction:.0%}"


def reverse_column(path: Path, column: int, sep: str = ",", header: bool = True) -> str:
    lines = path.read_text().splitlines()
    head, rows = (lines[:1], lines[1:]) if header else ([], lines)
    cells = [r.split(sep) for r in rows]
    values = [c[column] for c in cells][::-1]
    for c, v in zip(cells, values, strict=True):
        c[column] = v
    path.write_text("\n".join(head + [sep.join(c) for c in cells]) + "\n")
    return f"column {column} of {path.name} reversed"


def rewrite_exif_times_reversed(folder: Path) -> str:
    """The photos' DateTimeOriginal and sub-seconds given in reverse file order (the pixels and GPS untouched)."""
    from PIL import Image

    photos = sorted(folder.glob("*.jpg"))
    exifs = []
    for p in photos:
        with Image.open(p) as im:
            exifs.append(im.getexif())
    times = [(e.get_ifd(0x8769).get(36867), e.get_ifd(0x8769).get(37521)) for e in exifs][::-1]
    for p, e, (dt, sub) in zip(photos, exifs, times, strict=True):
        with Image.open(p) as im:
            im.load()
            ifd = e.get_ifd(0x8769)
            ifd[36867], ifd[37521] = dt, sub
            im.save(p, exif=e, quality=95)
    return f"EXIF times of {len(photos)} photos reversed"


@dataclass
class LogFault:
    kind: str  # reader kind (Inputs.logs key)
    name: str
    damage: Callable[[Path, random.Random], str]  # damages the copied log (its root), says what it did
    names: tuple[str, ...] = ()  # what a clear error may name (besides the log's own path)


def log_faults() -> list[LogFault]:
    def one(kind, name, target, damage, names=()):
        return LogFault(kind, name, lambda root, rnd: damage(target(root), rnd), names)

    def odo_frame(root):
        return root / "image_l" / "000005.png"

    def oxts(root, i=40):
        return root / "oxts" / "data" / f"{i:010d}.txt"

    return [
        one("mcap", "MCAP truncated at 60%", lambda r: r, lambda p, rnd: truncate(p, 0.6)),
        one("mcap", "MCAP 64 flipped bytes in a chunk", lambda r: r, flip_bytes),
        LogFault("mcap", "MCAP missing", lambda r, rnd: (r.unlink(), "log deleted")[1]),
        one("rosbag", "ROS 1 bag truncated at 60%", lambda r: r, lambda p, rnd: truncate(p, 0.6)),
        one("rosbag", "ROS 1 bag 64 flipped bytes", lambda r: r, flip_bytes),
        LogFault("rosbag", "ROS 1 bag missing", lambda r, rnd: (r.unlink(), "log deleted")[1]),
        one("kitti-odometry", "KITTI odometry frame PNG truncated", odo_frame, lambda p, rnd: truncate(p, 0.5)),
        one("kitti-odometry", "KITTI odometry poses.txt flipped bytes", lambda r: r / "poses.txt", _flip_text),
        LogFault(
            "kitti-odometry",
            "KITTI odometry calib.txt missing",
            lambda r, rnd: ((r / "calib.txt").unlink(), "calib.txt deleted")[1],
            ("calib.txt",),
        ),
        one(
            "kitti-odometry",
            "KITTI odometry camera stamps reversed",
            lambda r: r / "times.txt",
            lambda p, rnd: reverse_column(p, 0, " ", header=False),
            ("times.txt",),
        ),
        one("kitti-raw", "KITTI raw OXTS record truncated", oxts, lambda p, rnd: truncate(p, 0.4)),
        one("kitti-raw", "KITTI raw OXTS record flipped bytes", oxts, _flip_text),
        LogFault(
            "kitti-raw",
            "KITTI raw timestamps.txt missing",
            lambda r, rnd: ((r / "oxts" / "timestamps.txt").unlink(), "timestamps.txt deleted")[1],
            ("timestamps.txt",),
        ),
        one(
            "kitti-raw",
            "KITTI raw stamps reversed",
            lambda r: r / "oxts" / "timestamps.txt",
            lambda p, rnd: _reverse_lines(p),
            ("timestamps.txt",),
        ),
        one("folder", "folder image truncated", lambda r: r / "images" / "0002.png", lambda p, rnd: truncate(p, 0.5)),
        one("folder", "folder frames.csv flipped bytes", lambda r: r / "frames.csv", _flip_text, ("frames.csv",)),
        LogFault(
            "folder",
            "folder image missing",
            lambda r, rnd: ((r / "images" / "0003.jpg").unlink(), "images/0003.jpg deleted")[1],
            ("0003.jpg",),
        ),
        one(
            "folder",
            "folder camera stamps reversed",
            lambda r: r / "frames.csv",
            lambda p, rnd: reverse_column(p, 1),
            ("frames.csv",),
        ),
        one("photos", "photo JPEG truncated", lambda r: r / "000004.jpg", lambda p, rnd: truncate(p, 0.5)),
        one("photos", "photo JPEG flipped bytes", lambda r: r / "000006.jpg", flip_bytes),
        LogFault("photos", "photo EXIF times reversed", lambda r, rnd: rewrite_exif_times_reversed(r)),
    ]


#: readers whose format has no checksum over message payloads: flipped payload bytes are data no reader can tell
#: from good data (a case there that ends silent-wrong is the format's limit; the record says so beside it)
NO_PAYLOAD_CHECKSUM = {
    "rosbag": "ROS 1 bags carry no checksum: flipped payload bytes cannot be told from data",
    "photos": "JPEG carries no checksum: flipped entropy-coded bytes decode to other pixels",
}


def _flip_text(path: Path, rnd: random.Random) -> str:
    """Three seeded bytes of a text file replaced by random ones."""
    data = bytearray(path.read_bytes())
    ats = sorted(rnd.sample(range(len(data)), 3))
    for at in ats:
        data[at] = rnd.randrange(256)
    path.write_bytes(bytes(data))
    return f"bytes {ats} of {path.name} replaced"


def _reverse_lines(path: Path) -> str:
    lines = path.read_text().splitlines()
    path.write_text("\n".join(lines[::-1]) + "\n")
    return f"lines of {path.name} reversed"


def run_log_fault(inp: Inputs, f: LogFault, rnd: random.Random) -> Case:
    case = Case("damaged logs", f.name)
    src = inp.logs[f.kind]
    base = inp.work / "cases" / re.sub(r"\W+", "-", f.name)
    shutil.rmtree(base, ignore_errors=True)
    # the log's root: the file itself, or the folder a reader reads (KITTI raw: the drive folder)
    top = src.parents[1] if f.kind == "kitti-raw" else src  # KITTI raw: the date folder holding the drive
    root = _copy(top, base / "log" / top.name)
    log = root / src.relative_to(top) if f.kind == "kitti-raw" else root
    case.detail = f.damage(log, rnd)
    if log.exists():
        settle(root)
    ws = base / "ws"
    run = mapkit("build", log, "--out", ws, *inp.config_args(f.kind))
    case.command = " ".join(map(str, run.args))
    clean_ws = _baseline_with_warnings(inp, f.kind) if run.rc == 0 else None
    names = (str(log), log.name, *f.names)
    case.outcome, why = build_outcome(run, ws, clean_ws, log, src, names)
    case.detail += f" -> {why}"
    if case.outcome == "silent-wrong" and f.kind in NO_PAYLOAD_CHECKSUM:
        case.detail += f" ({NO_PAYLOAD_CHECKSUM[f.kind]})"
    case.seconds, case.stderr_tail = run.seconds, _tail(run)
    return case


def rewrite_gps(src: Path, dst: Path, fn: Callable[[int, object], object | None]) -> Path:
    """``src`` (an MCAP of poses and fixes) written again with each fix passed through ``fn(i, fix)`` (None drops
    it); every other record as it was."""
    from mapkit.core.types import GpsFix
    from mapkit.io import open_log
    from mapkit.io.mcap_log import McapWriter

    i = 0
    with open_log(src) as log, McapWriter(dst) as w:
        for msg in log.messages():
            rec = msg.record
            if isinstance(rec, GpsFix):
                rec = fn(i, rec)
                i += 1
                if rec is None:
                    continue
            w.write(msg.topic, rec)
    return settle(dst)


def gps_faults() -> list[tuple[str, Callable[[int, object], object | None]]]:
    from mapkit.core.types import GpsStatus

    return [
        (
            "null island (every third fix at 0, 0)",
            lambda i, f: replace(f, lat_deg=0.0, lon_deg=0.0) if i % 3 == 1 else f,
        ),
        (
            "1 km jumps (fixes 5, 6 and 20)",
            lambda i, f: replace(f, lat_deg=f.lat_deg + 0.009) if i in (5, 6, 20) else f,
        ),
        ("no fix at all (status NO_FIX)", lambda i, f: replace(f, status=GpsStatus.NO_FIX)),
        ("GPS an hour after the drive", lambda i, f: replace(f, stamp_ns=f.stamp_ns + 3600 * 10**9)),
    ]


def run_gps_fault(inp: Inputs, name: str, fn) -> Case:
    assert inp.imageless is not None
    case = Case("GPS faults", name)
    base = inp.work / "cases" / ("gps-" + re.sub(r"\W+", "-", name))
    shutil.rmtree(base, ignore_errors=True)
    base.mkdir(parents=True)
    log = rewrite_gps(inp.imageless, base / "drive.mcap", fn)
    ws = base / "ws"
    run = mapkit("build", log, "--out", ws)
    case.command = " ".join(map(str, run.args))
    case.seconds, case.stderr_tail = run.seconds, _tail(run)
    e = error_outcome(run, (str(log), "gps", "GPS"))
    if e is not None:
        case.outcome, case.detail = e
        return case
    ga = json.loads((ws / "sessions" / "drive" / "georef" / "gps_alignment.json").read_text())
    origin = json.loads((ws / "origin.json").read_text()).get("origin_wgs84") if (ws / "origin.json").is_file() else {}
    origin = origin or {}
    yaw = (ga.get("alignment") or {}).get("yaw_deg")
    told = [w for w in run.warnings if any(k in _normal(w, log) for k in ("GPS", "georeferenced", "fixes"))]
    if yaw is not None:
        near_null = abs(origin.get("lat_deg", 49.0)) < 1.0 and abs(origin.get("lon_deg", 8.4)) < 1.0
        said = f"; {told[0][:250]}" if told else ""
        if abs(yaw - 37.0) > 2.0 or near_null:  # a wrong georeference is wrong whatever was said
            case.outcome, case.detail = (
                "silent-wrong",
                f"georeferenced with yaw {yaw:.1f} deg (true 37), origin {origin}",
            )
        else:
            case.outcome, case.detail = "recovered", f"yaw {yaw:.1f} deg (true 37){said}"
        return case
    if told:
        case.outcome, case.detail = "recovered", f"not georeferenced, said so: {told[-1][:300]}"
    else:
        case.outcome, case.detail = "silent-wrong", "not georeferenced, no warning says so"
    return case


# --- SIGKILL --------------------------------------------------------------------------------------------


@dataclass
class KillPoint:
    name: str
    args: Callable[[Path], list]  # the command, given the workspace
    trigger: str  # a glob (relative to the workspace) whose first match says the stage runs
    outputs: list[str]  # stage folders (relative) whose markers' outputs must equal a clean run's
    prepare: Callable[[Path], None]  # makes the workspace the command starts from
    delay_s: float = 0.3


def kill_points(inp: Inputs) -> list[KillPoint]:
    assert inp.tiny_ws is not None
    clean = inp.work / "clean"
    mcap = inp.logs["mcap"]
    session = "sessions/" + mcap.stem
    stages = ["trajectory", "georef", "map", "imagedb"]

    def fresh(ws: Path) -> None:
        shutil.rmtree(ws, ignore_errors=True)

    def tiny_without(*parts: str) -> Callable[[Path], None]:
        def make(ws: Path) -> None:
            _copy(inp.tiny_ws, ws)
            for p in parts:
                shutil.rmtree(ws / p, ignore_errors=True)

        return make

    points = [
        KillPoint(
            f"build, during {st}",
            lambda ws: ["build", mcap, "--out", ws],
            f"{session}/{st}",
            [f"{session}/{s}" for s in stages],
            fresh,
        )
        for st in stages
    ]
    points += [
        KillPoint(
            "align", lambda ws: ["align", ws], "align", ["align"], tiny_without("align", "triplets", "indexes"), 1.0
        ),
        KillPoint(
            "triplets",
            lambda ws: ["triplets", ws, "-c", clean / "triplets.yaml"],
            "*triplets*",
            ["triplets"],
            tiny_without("triplets"),
            1.0,
        ),
        KillPoint(
            "index vlad",
            lambda ws: ["index", "vlad", ws, "-c", clean / "vlad.yaml"],
            "indexes/*vlad*",
            ["indexes/vlad"],
            tiny_without("indexes/vlad"),
            1.0,
        ),
        KillPoint(
            "index structure",
            lambda ws: ["index", "structure", ws, *STRUCTURE_SESSIONS],
            "indexes/*structure-nbld*",
            ["indexes/structure-nbld"],
            tiny_without("indexes/structure-nbld"),
            0.5,
        ),
    ]
    return points


def index_files(folder: Path) -> dict:
    """An index bundle's files and SHA-256 as its manifest records them (timings aside), else the folder's."""
    try:
        man = json.loads((folder / "manifest.json").read_text())
    except (OSError, ValueError):
        return {}
    files = man.get("files") or man.get("checksums") or {}
    if files:
        return {k: v for k, v in files.items() if "timings" not in k}
    return {k: v for k, v in listing(folder).items() if "timings" not in k and k != "manifest.json"}


def run_kill(inp: Inputs, kp: KillPoint, reference: Path | None) -> Case:
    """``kp``'s command killed, then run again; its outputs held against ``reference``, or (None) against a clean
    run of the same command from the same start, made now (with the code of this run: a reference made earlier
    would hold any change to mapkit since against the re-run)."""
    case = Case("SIGKILL", f"kill -9 {kp.name}, then re-run")
    clean_s = None
    if reference is None:
        reference = inp.work / "cases" / ("kill-ref-" + re.sub(r"\W+", "-", kp.name)) / "ws"
        shutil.rmtree(reference.parent, ignore_errors=True)
        reference.parent.mkdir(parents=True)
        kp.prepare(reference)
        clean_s = _must(mapkit(*kp.args(reference))).seconds
    ws = inp.work / "cases" / ("kill-" + re.sub(r"\W+", "-", kp.name)) / "ws"
    shutil.rmtree(ws.parent, ignore_errors=True)
    ws.parent.mkdir(parents=True)
    kp.prepare(ws)
    args = kp.args(ws)
    # the kill lands when the stage's folder appears, or half-way through a clean run's time if that comes first
    killed, ran = killed_at(args, ws, kp.trigger, kp.delay_s, None if clean_s is None else 0.5 * clean_s)
    run = mapkit(*args)
    case.command = "mapkit " + " ".join(map(str, args))
    case.seconds, case.stderr_tail = ran + run.seconds, _tail(run)
    where = f"killed {ran:.1f} s in" if killed else f"ended on its own after {ran:.1f} s before the kill"
    e = error_outcome(run, ())
    if e is not None:
        case.outcome = "traceback" if e[0] == "traceback" else "lost"
        case.detail = f"{where}; the re-run failed: {e[1]}"
        return case
    differ = []
    for rel in kp.outputs:
        got, want = _outputs(ws / rel), _outputs(reference / rel)
        if not want:
            raise RuntimeError(f"the clean run has no finished {rel}")
        differ += [f"{rel}/{k}" for k in sorted(set(got) | set(want)) if got.get(k) != want.get(k)]
    if differ:
        case.outcome, case.detail = "lost", f"{where}; the re-run's outputs differ from a clean run's: {differ[:6]}"
    else:
        n = sum(len(_outputs(ws / rel)) for rel in kp.outputs)
        case.outcome, case.detail = "recovered", f"{where}; re-run exit 0, {n} output files equal to a clean run's"
    return case


def _outputs(folder: Path) -> dict:
    return stage_outputs(folder) or index_files(folder)


# --- two writers ------------------------------------------------------------------------------------------


def writer_commands(inp: Inputs, ws: Path) -> list[tuple[str, list]]:
    assert inp.town is not None and inp.bundle is not None
    clean = inp.work / "clean"
    return [
        ("build", ["build", inp.logs["imageless"], "--out", ws]),
        ("align", ["align", ws]),
        ("triplets", ["triplets", ws, "-c", clean / "triplets.yaml"]),
        ("index vlad", ["index", "vlad", ws, "-c", clean / "vlad.yaml"]),
        ("index structure", ["index", "structure", ws, *STRUCTURE_SESSIONS]),
        ("localize into the workspace", ["localize", inp.bundle / "vlad", inp.logs["mcap"], "--out", ws / "loc"]),
        ("eval build", ["eval", "build", ws, "--truth", inp.town]),
        ("eval retrieval", ["eval", "retrieval", ws, ws / "indexes" / "vlad", "-q", "tiny-night_0"]),
        ("index export", ["index", "export", ws, "--out", ws / "export"]),
        ("export-crs", ["export-crs", ws, "--out", ws / "crs"]),
    ]


def run_writers(inp: Inputs, quick: bool) -> list[Case]:
    assert inp.tiny_ws is not None
    ws = _copy(inp.tiny_ws, inp.work / "cases" / "writers" / "ws")
    cases = []
    commands = writer_commands(inp, ws)
    with holding(ws) as pid:
        before = listing(ws)
        for name, args in commands[:2] if quick else commands:
            case = Case("two writers", f"{name} while another process writes")
            run = mapkit(*args)
            case.command = " ".join(map(str, run.args))
            case.seconds, case.stderr_tail = run.seconds, _tail(run)
            after = listing(ws)
            gone, altered, added = changed(before, after)
            e = error_outcome(run, (f"pid {pid}",))
            if gone or altered:
                case.outcome, case.detail = "lost", f"files gone {gone[:4]}, altered {altered[:4]}"
            elif e is None:
                case.outcome, case.detail = "silent-wrong", f"exit 0 beside the holder; wrote {added[:4]}"
            elif added and e[0] == "clear error":
                case.outcome, case.detail = "other", f"refused but wrote {added[:4]}"
            else:
                case.outcome, case.detail = e
            before = after
            cases.append(case)
    if not quick:  # a real first writer: a build running, a second build into the same workspace
        case = Case("two writers", "a second build while a build runs")
        ws2 = inp.work / "cases" / "writers" / "ws2"
        shutil.rmtree(ws2, ignore_errors=True)
        first = subprocess.Popen(
            [str(MAPKIT), "build", str(inp.logs["mcap"]), "--out", str(ws2)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        try:
            t0 = time.monotonic()
            while not (ws2 / "sessions").exists() and first.poll() is None and time.monotonic() - t0 < 300:
                time.sleep(0.05)
            run = mapkit("build", inp.logs["mcap"], "--out", ws2)
            case.command = " ".join(map(str, run.args))
            case.seconds, case.stderr_tail = run.seconds, _tail(run)
            e = error_outcome(run, (f"pid {first.pid}",))
            case.outcome, case.detail = e if e is not None else ("silent-wrong", "two builds ran into one workspace")
        finally:
            rc = first.wait()
        if rc != 0:
            case.outcome, case.detail = "lost", f"the first build ended with exit {rc} after the second was refused"
        cases.append(case)
    return cases


# --- full disk --------------------------------------------------------------------------------------------


def tmpfs_bytes(root: Path) -> int:
    """What the files under ``root`` take on a tmpfs: whole 4 KiB pages, one more per folder."""
    return sum(-(-p.stat().st_size // 4096) * 4096 if p.is_file() else 4096 for p in root.rglob("*"))


@contextlib.contextmanager
def tmpfs(at: Path, size_bytes: int) -> Iterator[Callable[[int], None] | None]:
    """A tmpfs of ``size_bytes`` mounted at ``at`` (None when mounting is not permitted); yields a function that
    grows it."""
    at.mkdir(parents=True, exist_ok=True)
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_bytes}", "tmpfs", str(at)], capture_output=True)
    if r.returncode != 0:
        yield None
        return
    try:
        yield lambda n: subprocess.run(["mount", "-o", f"remount,size={n}", str(at)], check=True)
    finally:
        subprocess.run(["umount", "-l", str(at)], capture_output=True)


def run_disk(inp: Inputs, quick: bool) -> list[Case]:
    assert inp.tiny_ws is not None
    clean = inp.work / "clean"
    specs = [
        ("build into a full disk", None, ("build", inp.logs["imageless"]), 200 * 1024),
        ("triplets onto a full disk", ("triplets",), ("triplets", "-c", clean / "triplets.yaml"), None),
        ("index vlad onto a full disk", ("indexes",), ("index", "vlad", "-c", clean / "vlad.yaml"), None),
    ]
    cases = []
    for name, drop, cmd, size in specs[:2] if quick else specs:
        case = Case("full disk", name)
        disk = inp.work / "cases" / ("disk-" + re.sub(r"\W+", "-", name))
        subprocess.run(["umount", "-l", str(disk)], capture_output=True)
        shutil.rmtree(disk, ignore_errors=True)
        if drop is None:
            need = size
        else:  # the workspace before the stage, and 150 kB to spare: the stage's outputs do not fit
            need = tmpfs_bytes(inp.tiny_ws) - sum(tmpfs_bytes(inp.tiny_ws / d) + 4096 for d in drop) + 150_000
        with tmpfs(disk, need) as grow:
            if grow is None:
                case.outcome, case.detail = "skipped", "mounting a tmpfs is not permitted (needs root)"
                cases.append(case)
                continue
            ws = disk / "ws"
            if drop is not None:
                shutil.copytree(inp.tiny_ws, ws, ignore=shutil.ignore_patterns(*drop), symlinks=True)
                args = [cmd[0], *([cmd[1]] if cmd[0] == "index" else []), ws, *cmd[(2 if cmd[0] == "index" else 1) :]]
            else:
                args = ["build", cmd[1], "--out", ws]
            before = listing(ws)
            run = mapkit(*args)
            case.command = " ".join(map(str, run.args))
            case.seconds, case.stderr_tail = run.seconds, _tail(run)
            e = error_outcome(run, ("No space left", "MB free"))
            gone, altered, _ = changed(before, listing(ws))
            if gone or altered:
                case.outcome, case.detail = "lost", f"files gone {gone[:4]}, altered {altered[:4]}"
            elif e is None:
                case.outcome, case.detail = "other", "the command fitted the disk: no fault was met"
            elif e[0] != "clear error":
                case.outcome, case.detail = e
            else:
                partial = [str(p.relative_to(ws)) for p in ws.rglob("*.partial")]
                grow(need * 4 + 8 * 2**20)
                again = mapkit(*args)
                case.seconds += again.seconds
                if partial:
                    case.outcome, case.detail = "other", f"{e[1]}; partial files left: {partial[:4]}"
                elif again.rc != 0:
                    case.outcome = "traceback" if again.traceback else "lost"
                    case.detail = f"{e[1]}; with room made the re-run failed: {(again.errors or [again.err[-300:]])[0]}"
                else:
                    case.outcome, case.detail = "clear error", f"{e[1]}; with room made the re-run finished"
        cases.append(case)
    return cases


# --- stale inputs -------------------------------------------------------------------------------------------


def run_stale(inp: Inputs, quick: bool) -> list[Case]:
    from test_build import _imageless_log

    assert inp.tiny_ws is not None
    cases = []
    base = inp.work / "cases" / "stale"
    shutil.rmtree(base, ignore_errors=True)
    base.mkdir(parents=True)

    # 1. a log replaced by another drive under the same name after its build
    case = Case("stale inputs", "log replaced after its build (another drive, yaw 80 deg)")
    log = _copy(inp.logs["imageless"], base / "replaced" / "drive.mcap")
    ws = base / "replaced" / "ws"
    _must(mapkit("build", log, "--out", ws))
    _imageless_log(log, yaw_deg=80.0)
    settle(log)
    run = mapkit("build", log, "--out", ws)
    case.command, case.seconds, case.stderr_tail = " ".join(map(str, run.args)), run.seconds, _tail(run)
    e = error_outcome(run, (str(log),))
    if e is not None:
        case.outcome, case.detail = e
    else:
        yaw = json.loads((ws / "sessions" / "drive" / "georef" / "gps_alignment.json").read_text())["alignment"][
            "yaw_deg"
        ]
        ok = abs(yaw - 80.0) < 1.0
        case.outcome = "recovered" if ok else "silent-wrong"
        case.detail = f"re-made: yaw {yaw:.1f} deg (the new drive's 80)" if ok else f"kept the old drive: yaw {yaw:.1f}"
    cases.append(case)

    # 2. points.ply truncated after the build, then align (a consumer) and build (its maker)
    tiny = inp.tiny_ws
    ply_rel = Path("sessions/tiny-rainy_0/map/points.ply")
    for name, args_of in [
        ("points.ply truncated, then align", lambda ws: ["align", ws]),
        ("points.ply truncated, then index structure", lambda ws: ["index", "structure", ws, *STRUCTURE_SESSIONS]),
        ("points.ply truncated, then build again", lambda ws: ["build", *tiny_logs(inp), "--out", ws]),
    ][: 1 if quick else 3]:
        case = Case("stale inputs", name)
        ws = _copy(tiny, base / re.sub(r"\W+", "-", name) / "ws")
        for d in ("align", "triplets", "indexes"):
            shutil.rmtree(ws / d, ignore_errors=True)
        good = (ws / ply_rel).read_bytes()
        (ws / ply_rel).write_bytes(good[: len(good) // 3])
        before = listing(ws)
        run = mapkit(*args_of(ws))
        case.command, case.seconds, case.stderr_tail = " ".join(map(str, run.args)), run.seconds, _tail(run)
        e = error_outcome(run, ("points.ply",))
        gone, altered, _ = changed(before, listing(ws))
        altered = [a for a in altered if a != str(ply_rel) and "timings" not in a and "metrics.json" not in a]
        if e is not None:
            case.outcome, case.detail = e
        elif args_of(ws)[0] == "build":
            # re-made: whole again and as its stage's marker records it (the bytes may differ from the first build's
            # when mapkit changed since: the marker is this build's own record)
            now = (ws / ply_rel).read_bytes()
            rec = stage_outputs(ws / ply_rel.parent).get(ply_rel.name) or {}
            ok = len(now) > len(good) // 3 and rec.get("sha256") == hashlib.sha256(now).hexdigest()
            case.outcome = "recovered" if ok else "silent-wrong"
            case.detail = "points.ply re-made, as its marker records it" if ok else "points.ply not re-made"
            case.detail += "; " + (next((w for w in run.warnings if "points.ply" in w), "no warning"))[:250]
        else:
            case.outcome, case.detail = "silent-wrong", "a truncated points.ply was taken for a result"
        if gone:
            case.outcome, case.detail = "lost", f"files gone: {gone[:4]}"
        cases.append(case)

    # 3. an image table edited (one image moved 30 m): index vlad, which reads it, refuses it naming the file; the
    # aligned table when align ran, the build's when it did not
    for name, rel, drop in [
        ("aligned images.csv edited, then index vlad", "align/sessions/tiny-rainy_0/images.csv", ("indexes",)),
        (
            "built images.csv edited, then index vlad (no align)",
            "sessions/tiny-rainy_0/imagedb/images.csv",
            ("indexes", "align", "triplets"),
        ),
    ][: 1 if quick else 2]:
        case = Case("stale inputs", name)
        ws = _copy(tiny, base / re.sub(r"\W+", "-", name) / "ws")
        for d in drop:
            shutil.rmtree(ws / d, ignore_errors=True)
        csv = ws / rel
        rows = csv.read_text().splitlines()
        cells = rows[5].split(",")
        cells[10] = f"{float(cells[10]) + 30.0:.4f}"
        rows[5] = ",".join(cells)
        csv.write_text("\n".join(rows) + "\n")
        run = mapkit("index", "vlad", ws, "-c", inp.work / "clean" / "vlad.yaml")
        case.command, case.seconds, case.stderr_tail = " ".join(map(str, run.args)), run.seconds, _tail(run)
        e = error_outcome(run, ("images.csv",))
        case.outcome, case.detail = e if e is not None else ("silent-wrong", f"an edited {rel} was indexed")
        cases.append(case)
    if quick:
        return cases

    # 4. an index edited in place (same size): a rebuild re-makes it, an export refuses it
    for name, args_of in [
        (
            "index.faiss edited, then index vlad",
            lambda ws: ["index", "vlad", ws, "-c", inp.work / "clean" / "vlad.yaml"],
        ),
        ("index.faiss edited, then index export", lambda ws: ["index", "export", ws, "--out", ws.parent / "export"]),
    ]:
        case = Case("stale inputs", name)
        ws = _copy(tiny, base / re.sub(r"\W+", "-", name) / "ws")
        faiss = ws / "indexes" / "vlad" / "index.faiss"
        good = faiss.read_bytes()
        bad = bytearray(good)
        bad[len(bad) // 2 : len(bad) // 2 + 16] = bytes(16)
        faiss.write_bytes(bytes(bad))
        run = mapkit(*args_of(ws))
        case.command, case.seconds, case.stderr_tail = " ".join(map(str, run.args)), run.seconds, _tail(run)
        e = error_outcome(run, ("index.faiss", "indexes/vlad"))
        if e is not None:
            case.outcome, case.detail = e
        elif args_of(ws)[1] == "vlad":
            now = faiss.read_bytes()
            listed = index_files(faiss.parent).get("index.faiss")
            listed_sha = listed.get("sha256") if isinstance(listed, dict) else listed
            ok = now != bytes(bad) and listed_sha == hashlib.sha256(now).hexdigest()
            case.outcome = "recovered" if ok else "silent-wrong"
            case.detail = "index.faiss rebuilt, as its manifest lists it" if ok else "the edited index was kept"
        else:
            case.outcome, case.detail = "silent-wrong", "an edited index was exported"
        cases.append(case)
    return cases


# --- damaged bundles ------------------------------------------------------------------------------------------


def bundle_damages() -> list[tuple[str, Callable[[Path], str], tuple[str, ...]]]:
    def changed_file(b: Path) -> str:
        p = b / "vlad" / "index.faiss"
        data = bytearray(p.read_bytes())
        data[len(data) // 2 : len(data) // 2 + 8] = b"\x00\x01" * 4
        p.write_bytes(bytes(data))
        return "index.faiss"

    def missing_file(b: Path) -> str:
        (b / "vlad" / "database.csv").unlink()
        return "database.csv"

    def fewer_indexes(b: Path) -> str:
        m = json.loads((b / "manifest.json").read_text())
        m["indexes"].pop("vlad")  # the VLAD index is still in the folder, unlisted
        (b / "manifest.json").write_text(json.dumps(m, indent=1))
        return "manifest.json"

    def unknown_version(b: Path) -> str:
        for p in (b / "manifest.json", b / "vlad" / "manifest.json"):
            m = json.loads(p.read_text())
            m["format_version"] = 99
            p.write_text(json.dumps(m, indent=1))
        return "manifest.json"

    return [
        ("a changed file (index.faiss)", changed_file, ("index.faiss",)),
        ("a missing file (database.csv)", missing_file, ("database.csv",)),
        ("manifest listing fewer indexes", fewer_indexes, ("manifest.json", "vlad")),
        ("unknown format version", unknown_version, ("manifest.json", "format_version")),
    ]


def run_bundles(inp: Inputs, quick: bool) -> list[Case]:
    assert inp.bundle is not None and inp.tiny_ws is not None
    cases = []
    damages = bundle_damages()
    for name, damage, names in damages[:2] if quick else damages:
        for cmd in ("localize", "eval retrieval"):
            case = Case("damaged bundles", f"{cmd}: {name}")
            base = inp.work / "cases" / ("bundle-" + re.sub(r"\W+", "-", f"{cmd}-{name}"))
            shutil.rmtree(base, ignore_errors=True)
            bundle = _copy(inp.bundle, base / "bundle")
            damage(bundle)  # an export, as a user deploys it; localize and eval retrieval take its VLAD index
            target = bundle / "vlad"
            if cmd == "localize":
                args = ["localize", target, inp.logs["mcap"], "--out", base / "loc"]
            else:
                ws = base / "ws"
                ws.mkdir()
                for f in ("origin.json", "build_config.yaml"):
                    shutil.copy2(inp.tiny_ws / f, ws / f)
                os.symlink(inp.tiny_ws / "sessions", ws / "sessions")  # read only: sessions are not written
                args = ["eval", "retrieval", ws, target, "-q", "tiny-night_0"]
            run = mapkit(*args)
            case.command, case.seconds, case.stderr_tail = " ".join(map(str, run.args)), run.seconds, _tail(run)
            e = error_outcome(run, names)
            if e is not None:
                case.outcome, case.detail = e
            elif name.startswith("manifest"):  # the VLAD index itself is intact: its outputs are right, not refused
                case.outcome = "other"
                case.detail = (
                    "exit 0: the export's manifest.json no longer lists vlad, but the command reads EXPORT/vlad alone "
                    "(intact, its own checksums pass) and never the export's manifest"
                )
            else:
                case.outcome, case.detail = "silent-wrong", f"a bundle with {name} was used"
            cases.append(case)
    return cases


# --- bad configs --------------------------------------------------------------------------------------------------


def config_faults(inp: Inputs) -> list[tuple[str, str, str, str]]:
    """(command, fault, YAML, field a clear error names)."""
    return [
        ("build", "wrong type", "trajectory:\n  kiss_icp:\n    voxel_size_m: big\n", "voxel_size_m"),
        ("build", "unknown field", "georef:\n  inlier_sigmaz: 3\n", "inlier_sigmaz"),
        ("build", "bad value", "imagedb:\n  min_spacing_m: -1\n", "min_spacing_m"),
        ("align", "wrong type", "icp:\n  voxel_sizes_m: coarse\n", "voxel_sizes_m"),
        ("align", "unknown field", "icpp:\n  voxel_sizes_m: [1.0]\n", "icpp"),
        ("align", "bad value", "icp:\n  voxel_sizes_m: [1.0, 0.0, 0.25]\n", "voxel_sizes_m"),
        ("triplets", "wrong type", "n_triplets: many\n", "n_triplets"),
        ("triplets", "unknown field", "n_triplet: 50\n", "n_triplet"),
        ("triplets", "bad value", "icp_voxel_sizes_m: [-0.3]\n", "icp_voxel_sizes_m"),
        ("index vlad", "wrong type", "vlad:\n  num_words: lots\n", "num_words"),
        ("index vlad", "unknown field", "vlad:\n  num_wordz: 64\n", "num_wordz"),
        ("index vlad", "bad value", "vlad:\n  num_words: -4\n", "num_words"),
        ("index structure", "wrong type", "keypoint_fraction: some\n", "keypoint_fraction"),
        ("index structure", "unknown field", "keypoint_fractions: 0.1\n", "keypoint_fractions"),
        ("index structure", "bad value", "keypoint_fraction: -0.5\n", "keypoint_fraction"),
    ]


def run_configs(inp: Inputs, quick: bool) -> list[Case]:
    assert inp.tiny_ws is not None
    cases = []
    faults = config_faults(inp)
    if quick:
        faults = [f for f in faults if f[1] == "unknown field"][:2] + [f for f in faults if f[1] == "bad value"][:1]
    for command, fault, text, fieldname in faults:
        case = Case("bad configs", f"{command}: {fault}")
        base = inp.work / "cases" / ("config-" + re.sub(r"\W+", "-", f"{command}-{fault}"))
        shutil.rmtree(base, ignore_errors=True)
        base.mkdir(parents=True)
        cfg = base / "config.yaml"
        cfg.write_text(text)
        if command == "build":
            ws = base / "ws"
            args = ["build", inp.logs["imageless"], "--out", ws, "-c", cfg]
        else:
            ws = _copy(inp.tiny_ws, base / "ws")
            drop = {"align": ("align", "triplets", "indexes"), "triplets": ("triplets",)}.get(command, ("indexes",))
            for d in drop:
                shutil.rmtree(ws / d, ignore_errors=True)
            extra = STRUCTURE_SESSIONS if command == "index structure" else ()
            args = [*command.split(), ws, *extra, "-c", cfg]
        before = listing(ws)
        run = mapkit(*args)
        case.command, case.seconds, case.stderr_tail = " ".join(map(str, run.args)), run.seconds, _tail(run)
        gone, altered, added = changed(before, listing(ws))
        e = error_outcome(run, (fieldname,))
        if gone or altered:
            case.outcome, case.detail = "lost", f"files gone {gone[:4]}, altered {altered[:4]}"
        elif e is None:
            told = [w for w in run.warnings if fieldname in w]
            case.outcome = "recovered" if told else "silent-wrong"
            case.detail = told[0][:300] if told else f"exit 0: the config was taken without a word ({fieldname})"
        elif added and e[0] == "clear error":
            case.outcome, case.detail = "other", f"{e[1][:200]}; but wrote {added[:4]}"
        else:
            case.outcome, case.detail = e
        cases.append(case)
    return cases


# --- the campaign ------------------------------------------------------------------------------------------------


def campaign(work: Path, quick: bool, seed: int, only: set[str] | None, log: Callable[[str], None]) -> list[Case]:
    rnd = random.Random(seed)
    t0 = time.monotonic()
    inp = prepare(work, log)
    shutil.rmtree(work / "baselines", ignore_errors=True)  # clean builds to compare with: made by this run's code
    log(f"clean inputs ready in {time.monotonic() - t0:.0f} s")
    # clean builds of the small logs, with their warnings, to compare a faulted build with
    cases: list[Case] = []

    def want(klass: str) -> bool:
        return only is None or klass in only

    def record(c: Case | list[Case]) -> None:
        for x in c if isinstance(c, list) else [c]:
            cases.append(x)
            log(f"  [{x.klass}] {x.name}: {x.outcome} ({x.seconds:.0f} s) {x.detail[:160]}")

    def attempt(klass: str, name: str, fn: Callable[[], Case | list[Case]]) -> None:
        """A case (or a class of them); an error of the campaign itself is recorded as not run, with the reason."""
        try:
            record(fn())
        except Exception as exc:  # noqa: BLE001 - a broken case must not cost the others
            record(Case(klass, name, outcome="skipped", detail=f"not run: the campaign failed ({exc!r})"[:400]))

    if want("damaged logs"):
        faults = log_faults()
        if quick:
            faults = [f for f in faults if f.kind in ("mcap", "folder")][:2] + [faults[8]]
        for f in faults:
            seeded = random.Random(rnd.getrandbits(64))
            attempt("damaged logs", f.name, lambda f=f, seeded=seeded: run_log_fault(inp, f, seeded))
    if want("GPS faults"):
        for name, fn in gps_faults()[: 2 if quick else None]:
            attempt("GPS faults", name, lambda name=name, fn=fn: run_gps_fault(inp, name, fn))
    if want("SIGKILL"):
        points = kill_points(inp)
        if quick:
            points = [points[1], points[4]]
        one = _baseline_with_warnings(inp, "mcap")
        for kp in points:
            ref = one if kp.name.startswith("build") else None
            attempt("SIGKILL", kp.name, lambda kp=kp, ref=ref: run_kill(inp, kp, ref))
    if want("two writers"):
        attempt("two writers", "all cases", lambda: run_writers(inp, quick))
    if want("full disk"):
        attempt("full disk", "all cases", lambda: run_disk(inp, quick))
    if want("stale inputs"):
        attempt("stale inputs", "all cases", lambda: run_stale(inp, quick))
    if want("damaged bundles"):
        attempt("damaged bundles", "all cases", lambda: run_bundles(inp, quick))
    if want("bad configs"):
        attempt("bad configs", "all cases", lambda: run_configs(inp, quick))
    return cases


def _baseline_with_warnings(inp: Inputs, kind: str) -> Path:
    """The clean build of reader ``kind``'s log, with its warnings kept beside it (a faulted build's warnings are
    compared with them)."""
    ws = inp.work / "baselines" / kind
    if not (ws / "metrics.json").is_file():
        shutil.rmtree(ws, ignore_errors=True)
        r = _must(mapkit("build", inp.logs[kind], "--out", ws, *inp.config_args(kind)))
        (ws.parent / f"{kind}.warnings").write_text("\n".join(r.warnings) + "\n")
    inp.baselines[kind] = ws
    return ws


def _published(case: Case, work: Path) -> dict:
    """A case as the record keeps it: the work folder written as $WORK, stderr only where the outcome breaks the
    promise."""
    d = {k: v.replace(str(work), "$WORK") if isinstance(v, str) else v for k, v in asdict(case).items()}
    d["seconds"] = round(case.seconds, 1)
    if case.outcome not in ("traceback", "silent-wrong", "lost", "other"):
        d.pop("stderr_tail")
    return d


def table(cases: list[Case]) -> str:
    cols = ("clear error", "recovered", "traceback", "silent-wrong", "lost", "other")
    head = "| class | cases | clear errors | recovered | tracebacks | silent-wrong | lost | other |"
    rows = [head, "|---|---|---|---|---|---|---|---|"]
    total: Counter = Counter()
    n_all = 0
    for klass in CLASSES:
        mine = [c for c in cases if c.klass == klass and c.outcome != "skipped"]
        skipped = [c for c in cases if c.klass == klass and c.outcome == "skipped"]
        if not mine and not skipped:
            continue
        counts = Counter(c.outcome for c in mine)
        total.update(counts)
        n_all += len(mine)
        label = klass + (f" (skipped: {skipped[0].detail})" if skipped and not mine else "")
        rows.append(f"| {label} | {len(mine)} | " + " | ".join(str(counts.get(o, 0)) for o in cols) + " |")
    rows.append(f"| all | {n_all} | " + " | ".join(str(total.get(o, 0)) for o in cols) + " |")
    return "\n".join(rows)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, help="write the record as JSON here (docs/figures.py collect fault-campaign)")
    ap.add_argument("--quick", action="store_true", help="a few cases per class (about 5 min)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--work",
        type=Path,
        default=Path("/tmp/mapkit-fault-campaign"),
        help="folder of the clean inputs and the cases (kept; a later run reuses the clean inputs)",
    )
    ap.add_argument("--only", action="append", choices=CLASSES, help="run only this class (repeatable)")
    args = ap.parse_args()
    if not MAPKIT.is_file():
        raise SystemExit(f"{MAPKIT} not found: the campaign runs the installed command line of this checkout")
    t0 = time.monotonic()

    def log(msg: str) -> None:
        print(f"[{time.monotonic() - t0:5.0f} s] {msg}", file=sys.stderr, flush=True)

    cases = campaign(args.work.resolve(), args.quick, args.seed, set(args.only) if args.only else None, log)
    seconds = time.monotonic() - t0
    print(f"fault campaign through the CLI: {'quick' if args.quick else 'full'}, seed {args.seed}, {seconds:.0f} s\n")
    print(table(cases))
    bad = [c for c in cases if c.outcome in ("traceback", "silent-wrong", "lost", "other")]
    for c in bad:
        print(f"\n{c.klass} / {c.name}: {c.outcome}\n  $ {c.command}\n  {c.detail}")
    for c in cases:
        if c.outcome == "skipped":
            print(f"\n{c.klass} / {c.name}: not run: {c.detail}")
    if args.out:
        command = "python3 bench/fault_campaign.py" + (" --quick" if args.quick else "") + f" --seed {args.seed}"
        record = {
            "command": command,
            "mode": "quick" if args.quick else "full",
            "seed": args.seed,
            "seconds": round(seconds),
            "outcomes": list(OUTCOMES),
            "classes": {
                k: {
                    "cases": sum(1 for c in cases if c.klass == k and c.outcome != "skipped"),
                    **{o: sum(1 for c in cases if c.klass == k and c.outcome == o) for o in OUTCOMES},
                    **(
                        {"skipped": next(c.detail for c in cases if c.klass == k and c.outcome == "skipped")}
                        if any(c.klass == k and c.outcome == "skipped" for c in cases)
                        else {}
                    ),
                }
                for k in CLASSES
                if any(c.klass == k for c in cases)
            },
            "cases": [_published(c, args.work.resolve()) for c in cases],
        }
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(record, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
