"""Run-folder plumbing: atomic writes, finished-stage markers, resolved configs and metrics.

A stage writes into its output folder and, last of all, a ``.done`` marker holding its identity:
the :func:`stage_hash` of its name, the version of its algorithm (``stage_version``, a constant
beside the stage's code) and the resolved configuration it depends on, every field with its
default; the identity of its inputs (``inputs``: a log's fingerprint, the :func:`stage_digest` of
the upstream stages it read); and the size and SHA-256 of its outputs (``outputs``). A folder
without the marker (an interrupted run) is never taken for a finished one; a marker with another
hash (another config, a changed default, another version) or other inputs means the stage reruns,
and so does a marker without an input record where the stage has inputs; an output that no longer
matches its record is re-made by its own stage (:func:`is_done` with ``verify``) or refused by the
stage that loads it (:func:`verify_file`). A marker of an older mapkit (no ``stage_version``) is
migrated once (:func:`is_done` with ``legacy_hash``): when its hash is the older rule's hash of
today's config and its inputs and outputs still match, it is rewritten with today's hash, with a
warning, and the stage is reused; otherwise the stage runs again.

Wall-clock figures (how long a stage took, how fast it went) are a record of one run, not a result:
they go into the stage folder's ``timings.json`` (:func:`write_timings`), never into ``metrics.json``
nor into any file a marker records, so that the same inputs give byte-identical results.

Writes are verified before the rename that publishes them (:func:`atomic_path`), and an OS error
while writing (a full disk above all) becomes one :class:`WriteError` line naming the path and the
free space.
"""

from __future__ import annotations

import errno
import hashlib
import json
import logging
import os
import shutil
import tempfile
import warnings
import zipfile
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from mapkit.core.errors import InputError, InputWarning, MapkitError
from mapkit.core.fingerprint import check_file, record_files, sha256_file  # noqa: F401  (sha256_file: re-exported, stages import it from here)

if TYPE_CHECKING:
    from mapkit.core.geodesy import LocalFrame

logger = logging.getLogger(__name__)

DONE_MARKER = ".done"
#: a stage folder's run record: wall-clock figures of the run that made it (never hashed, never compared)
TIMINGS = "timings.json"
_UMASK = os.umask(0)
os.umask(_UMASK)
# errors of the storage, not of the program: reported as one line
# (a full disk, a quota, a read-only mount, a failing device)
WRITE_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS, errno.EIO}


class WriteError(MapkitError, OSError):
    """An output could not be written (disk full, quota, read-only, I/O error); nothing was renamed into place.
    An ``OSError`` too, as what it replaces was."""


def write_error(path: Path, exc: OSError) -> WriteError:
    """The one line for an OS error while writing ``path``: the error and the free space where it was written."""
    where = path.parent
    while not where.exists() and where != where.parent:
        where = where.parent
    try:
        free = f"{shutil.disk_usage(where).free / 1e6:.1f} MB free on {where}"
    except OSError:
        free = "free space unknown"
    return WriteError(
        f"{path}: could not be written ({exc.strerror or exc}; {free}); nothing was renamed into place: "
        "make room (or fix the mount) and re-run the command, which resumes"
    )


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it is checked (:func:`_check_written`)
    and replaces ``path`` in one rename. An OS error of the storage while writing is a :class:`WriteError`."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".partial", dir=path.parent)
        os.close(fd)
    except OSError as exc:
        if exc.errno in WRITE_ERRNOS:
            raise write_error(path, exc) from None
        raise
    tmp_path = Path(tmp)
    try:
        os.chmod(tmp_path, 0o666 & ~_UMASK)  # mkstemp makes 0600; outputs get the usual permissions
        yield tmp_path
        _check_written(tmp_path, path)
        os.replace(tmp_path, path)
    except OSError as exc:
        tmp_path.unlink(missing_ok=True)
        if exc.errno in WRITE_ERRNOS:
            raise write_error(path, exc) from None
        raise
    except BaseException:
        tmp_path.unlink(missing_ok=True)
        raise


def _check_written(tmp: Path, path: Path) -> None:
    """Read back what the formats allow cheaply before it is renamed into place: every member of a
    ``.npz`` (CRC-checked), a ``.json`` parsed, an HDF5 file opened. A short or damaged write
    (a writer that reported success on a full disk) is a :class:`WriteError` instead of a finished file."""
    suffix = path.suffix.lower()
    try:
        if suffix == ".npz":
            with zipfile.ZipFile(tmp) as z:
                bad = z.testzip()
            if bad is not None:
                raise ValueError(f"member {bad} fails its CRC")
        elif suffix == ".json":
            json.loads(tmp.read_bytes())
        elif suffix in (".h5", ".hdf5"):
            import h5py

            with h5py.File(tmp, "r"):
                pass
    except (ValueError, zipfile.BadZipFile, OSError) as exc:
        raise WriteError(
            f"{path}: the file written does not read back ({exc}; {tmp.stat().st_size} bytes on disk); "
            "not renamed into place (a full disk?)"
        ) from None


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    """``data`` at ``path``, atomically, its size checked on disk before the rename."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
            size = os.fstat(f.fileno()).st_size
        if size != len(data):
            raise WriteError(f"{path}: wrote {size} of {len(data)} bytes; not renamed into place (a full disk?)")
    return Path(path)


def atomic_write_ply(
    path: str | Path,
    points: np.ndarray,
    colors: np.ndarray | None = None,
    frame: LocalFrame | None = None,
    crs_epsg: int | None = None,
    comments: Sequence[str] = (),
) -> Path:
    """A binary little-endian PLY point cloud (float64 x, y, z; optional RGB in [0, 1], stored as
    uchar), written atomically: the file only appears, under its name, complete.

    The header states the frame of the coordinates (:func:`mapkit.core.geodesy.ply_crs_comments`):
    ``frame`` is the workspace's :class:`~mapkit.core.geodesy.LocalFrame` (or None: unspecified) and
    ``crs_epsg`` the EPSG code the points are in, or None for the local ENU frame of ``frame``.
    ``comments`` are extra header comment lines. Coordinates are float64 without an offset, so
    UTM or ECEF coordinates keep sub-micrometre precision and every PLY reader (open3d, PDAL,
    CloudCompare, which offers its own global shift on import) gets them as they are.
    """
    from mapkit.core.geodesy import ply_crs_comments

    path = Path(path)
    pts = np.asarray(points, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        pts = pts.reshape(-1, 3)
    n = len(pts)
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    if colors is not None:
        col = np.asarray(colors, np.float64)
        if col.shape != (n, 3):
            raise ValueError(f"{path}: colors of shape {col.shape} for {n} points")
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    rec = np.empty(n, np.dtype(fields))
    rec["x"], rec["y"], rec["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    if colors is not None:
        c8 = np.clip(np.rint(col * 255.0), 0, 255).astype(np.uint8)
        rec["red"], rec["green"], rec["blue"] = c8[:, 0], c8[:, 1], c8[:, 2]
    lines = ["ply", "format binary_little_endian 1.0", "comment generator mapkit"]
    for c in [*ply_crs_comments(frame, crs_epsg), *comments]:
        if "\n" in c or "\r" in c:
            raise ValueError(f"{path}: a PLY header comment cannot span lines: {c!r}")
        lines.append(f"comment {c}")
    lines.append(f"element vertex {n}")
    lines += [f"property {'double' if t == '<f8' else 'uchar'} {name}" for name, t in fields]
    lines.append("end_header")
    header = ("\n".join(lines) + "\n").encode("ascii")
    body = rec.tobytes()
    expected = len(header) + n * rec.dtype.itemsize
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(header)
            f.write(body)
            f.flush()
            os.fsync(f.fileno())
            size = os.fstat(f.fileno()).st_size
        if size != expected:
            raise WriteError(
                f"{path}: wrote {size} bytes, expected {expected} ({n} points); not renamed into place (a full disk?)"
            )
    return path


def atomic_write_text(path: str | Path, text: str) -> Path:
    return atomic_write_bytes(path, text.encode())


def _json_default(o: Any):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, Path):
        return str(o)
    if hasattr(o, "model_dump"):
        return o.model_dump(mode="json")
    raise TypeError(f"{type(o).__name__} is not JSON serialisable")


def to_json(obj: Any) -> str:
    return json.dumps(obj, indent=2, sort_keys=False, default=_json_default) + "\n"


def write_json(path: str | Path, obj: Any) -> Path:
    return atomic_write_text(path, to_json(obj))


def write_timings(folder: str | Path, **figures: Any) -> Path:
    """Add wall-clock ``figures`` (seconds, rates) to the run record ``folder/timings.json``; floats
    are rounded to the millisecond. Returns its path."""
    path = Path(folder) / TIMINGS
    record = read_timings(folder)
    record.update({k: round(v, 3) if isinstance(v, float) else v for k, v in figures.items()})
    return write_json(path, record)


def read_timings(folder: str | Path) -> dict:
    """The run record of a stage folder (:func:`write_timings`); empty when there is none."""
    try:
        record = json.loads((Path(folder) / TIMINGS).read_text())
    except (OSError, ValueError):
        return {}
    return record if isinstance(record, dict) else {}


def config_hash(obj: Any) -> str:
    """Stable short hash of a configuration (any JSON-serialisable object or pydantic model)."""
    text = json.dumps(json.loads(to_json(obj)), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def read_marker(folder: str | Path) -> dict | None:
    """The ``.done`` record of a stage folder, None when there is none (or it does not parse: not finished)."""
    try:
        record = json.loads((Path(folder) / DONE_MARKER).read_text())
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) else None


def stage_hash(stage: str, version: int, config: Any) -> str:
    """The hash a stage's marker holds: of the stage's name, the version of its algorithm and ``config``,
    the resolved configuration it depends on (every field, defaults included), so that another config, a
    changed default or a bumped version makes the stage run again."""
    return config_hash({"stage": stage, "version": version, "config": config})


def is_done(
    folder: str | Path,
    cfg_hash: str | None = None,
    *,
    inputs: dict | None = None,
    verify: bool = False,
    legacy_hash: str | None = None,
    version: int | None = None,
) -> bool:
    """Whether ``folder`` holds a finished stage made with ``cfg_hash`` from ``inputs``.

    ``inputs`` are compared with the marker's record of them; a marker that records none is not trusted
    (the stage runs again, the reason logged). With ``verify``, every output the marker recorded must
    still have its size and SHA-256; a stage whose inputs or outputs changed is not finished (the reason
    is logged, or warned for changed outputs).

    ``legacy_hash`` (with ``version``) is the older rule's hash of today's config: a marker without a
    ``stage_version`` that holds it, and whose inputs and outputs still match, is rewritten with
    ``cfg_hash`` and ``version`` (one warning) and the stage is finished. Such a marker was made by the
    stage's first algorithm: at a later ``version`` the stage runs again."""
    folder = Path(folder)
    record = read_marker(folder)
    if record is None:
        return False
    legacy = False
    if cfg_hash is not None and record.get("config_hash") != cfg_hash:
        if legacy_hash is None or "stage_version" in record or record.get("config_hash") != legacy_hash:
            return False
        if version is None:
            raise ValueError("is_done: legacy_hash needs the stage's version")
        if version != 1:  # made before the stage's algorithm changed
            return False
        legacy = True
    if inputs is not None:
        if "inputs" not in record:
            logger.info("%s: its marker records no inputs to compare; the stage runs again", folder)
            return False
        if record["inputs"] != json.loads(to_json(inputs)):
            changed = sorted(
                k
                for k in set(inputs) | set(record["inputs"])
                if json.loads(to_json(inputs.get(k))) != record["inputs"].get(k)
            )
            logger.info("%s: inputs changed (%s); the stage runs again", folder, ", ".join(changed))
            return False
    if verify or legacy:
        for rel, rec in (record.get("outputs") or {}).items():
            why = check_file(folder / rel, rec)
            if why is not None:
                warnings.warn(f"{folder / rel} {why}; its stage runs again", InputWarning, stacklevel=2)
                return False
    if legacy:
        _migrate_marker(folder, record, str(cfg_hash), 1)
    return True


def _migrate_marker(folder: Path, record: dict, cfg_hash: str, version: int) -> None:
    """Rewrite the marker of an older mapkit with today's hash and the stage's version. Its hash is kept as
    ``legacy_config_hash``, which :func:`stage_digest` reads, so that the downstream stages' input records
    still match."""
    write_json(
        folder / DONE_MARKER,
        {
            **record,
            "config_hash": cfg_hash,
            "stage_version": version,
            "legacy_config_hash": record.get("legacy_config_hash", record.get("config_hash")),
        },
    )
    warnings.warn(
        f"{folder}: finished by an older mapkit (its marker holds no stage version); its config, inputs and "
        f"outputs still match, so it is reused and its marker migrated to stage version {version}",
        InputWarning,
        stacklevel=3,
    )


def mark_done(
    folder: str | Path,
    cfg_hash: str,
    *,
    version: int | None = None,
    inputs: dict | None = None,
    outputs: bool | Sequence[str] = (),
    **info: Any,
) -> None:
    """Finish a stage: its marker records ``cfg_hash`` (a :func:`stage_hash`), the stage's ``version``,
    ``inputs`` (JSON) and the size and SHA-256 of ``outputs`` (paths relative to ``folder``, a folder
    standing for its files; True: every file in it)."""
    folder = Path(folder)
    record: dict[str, Any] = {"config_hash": cfg_hash}
    if version is not None:
        record["stage_version"] = version
    if inputs is not None:
        record["inputs"] = inputs
    if outputs:
        record["outputs"] = record_files(folder, ["."] if outputs is True else list(outputs))
    write_json(folder / DONE_MARKER, {**record, **info})


def marker_hash(record: dict) -> str | None:
    """The config hash a marker's stage was made with, as its downstream stages identify it: the older hash a
    migrated marker keeps (:func:`is_done` with ``legacy_hash``), else its own."""
    return record.get("legacy_config_hash", record.get("config_hash"))


def stage_digest(folder: str | Path) -> str | None:
    """What a downstream stage records of an upstream one: a hash of its marker's output record (of
    its config hash and inputs for a marker without one), so that a re-made upstream output
    invalidates what was made from it. A migrated marker (:func:`is_done` with ``legacy_hash``)
    gives the digest it gave before. None when the stage has not finished."""
    record = read_marker(folder)
    if record is None:
        return None
    return config_hash(
        {
            "config_hash": marker_hash(record),
            "inputs": record.get("inputs"),
            "outputs": record.get("outputs"),
        }
    )


def verify_file(path: str | Path, rerun: str) -> None:
    """Refuse a stage output that differs from what its stage recorded: one ``InputError`` naming
    the file and the command to re-run (``rerun``). The record is the nearest ``.done`` marker
    above ``path``; a marker without output records (an older workspace) checks nothing."""
    path = Path(path)
    for folder in path.parents:
        record = read_marker(folder)
        if record is None:
            continue
        rec = (record.get("outputs") or {}).get(path.relative_to(folder).as_posix())
        if rec is not None:
            why = check_file(path, rec)
            if why is not None:
                raise InputError(path, f"{why}: re-run {rerun} to write it again", field="sha256")
        return


def reset_stage(folder: str | Path) -> Path:
    """Empty a stage folder whose previous run did not finish (or must be redone)."""
    folder = Path(folder)
    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    return folder


def progress_bar(total: int | None, enabled: bool | None, desc: str, unit: str, leave: bool = True):
    """The one progress bar of mapkit: tqdm on stderr for long work (``update``/``close``).

    ``enabled``: shown or silent; None shows it when stderr is a terminal (so logs and CI output
    stay free of redraws)."""
    import sys

    from tqdm import tqdm

    if enabled is None:
        enabled = sys.stderr.isatty()
    return tqdm(total=total, desc=desc, unit=unit, leave=leave, disable=not enabled, file=sys.stderr)
