"""Deployable bundles: a folder with a ``manifest.json`` that lists every other file's sha256.

Shared by the VLAD and structure indexes. A bundle is built in ``.<name>.partial-<pid>-<rand>``
beside its destination and renamed into place last, so a folder at the destination is always a
finished bundle; partial folders of processes that are gone are removed by the next build.
"""

from __future__ import annotations

import json
import os
import shutil
import uuid
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

from mapkit import __version__
from mapkit.core.errors import InputError
from mapkit.core.runio import TIMINGS, WRITE_ERRNOS, sha256_file, write_error, write_json

MANIFEST = "manifest.json"
#: the ``kind`` of an export's top manifest (:mod:`mapkit.deploy.export`): several indexes in one folder
EXPORT_KIND = "mapkit deployment bundle"


def write_manifest(folder: Path, manifest: dict) -> None:
    """Checksum every file of the bundle but the manifest and the run record (``timings.json``: how
    long the build took, which differs from run to run), then write the manifest (last)."""
    files = {}
    for p in sorted(folder.rglob("*")):
        if p.is_file() and p.name not in (MANIFEST, TIMINGS) and not p.name.endswith(".partial"):
            files[p.relative_to(folder).as_posix()] = {"sha256": sha256_file(p), "bytes": p.stat().st_size}
    manifest["files"] = files
    write_json(folder / MANIFEST, manifest)


def load_manifest(path: Path, what: str, format_version: int) -> dict:
    """The manifest of the bundle at ``path`` after checking that it is JSON of ``format_version``
    (one ``InputError`` naming the file and field otherwise); no file is checked."""
    mpath = path / MANIFEST
    if not mpath.is_file():
        raise InputError(path, f"not a {what} (no {MANIFEST})")
    try:
        manifest = json.loads(mpath.read_text())
    except json.JSONDecodeError as exc:
        raise InputError(mpath, f"not valid JSON ({exc})") from None
    version = manifest.get("format_version") if isinstance(manifest, dict) else None
    if version != format_version:
        raise InputError(
            mpath,
            f"unknown bundle format version {version!r}; this mapkit {__version__} reads version {format_version}",
            field="format_version",
        )
    return manifest


def read_manifest(path: Path, what: str, format_version: int, required: Iterable[str], verify: bool = True) -> dict:
    """The manifest of the bundle at ``path``, after checking its format version, that it lists
    ``required`` files, that every listed file is there and (``verify``) has its sha256.
    Each failure is one ``InputError`` naming the file and field."""
    mpath = path / MANIFEST
    manifest = load_manifest(path, f"{what} bundle", format_version)
    files = manifest.get("files")
    if manifest.get("kind") == EXPORT_KIND:  # the export's top folder, not one of its indexes
        names = sorted(manifest.get("indexes") or {})
        raise InputError(mpath, f"is an export of {len(names)} index(es) {names}: pass one of its index folders")
    if not isinstance(files, dict):
        raise InputError(mpath, "no file list", field="files")
    _check_enclosing_export(path)
    for rel in required:
        if rel not in files:
            raise InputError(mpath, f"the file list lacks {rel}", field="files")
    for rel, info in files.items():
        p = path / rel
        if not p.is_file():
            raise InputError(p, "missing from the bundle (listed in its manifest)")
        if verify and sha256_file(p) != info.get("sha256"):
            raise InputError(p, "checksum mismatch: the file changed since the bundle was written", field="sha256")
    return manifest


def _check_enclosing_export(path: Path) -> None:
    """An index inside an export (``mapkit index export``) must be one its export lists, with the manifest it
    lists: an export whose manifest was edited, or an index copied into another export, is refused."""
    top = path.parent / MANIFEST
    try:
        export = json.loads(top.read_text())
    except (OSError, json.JSONDecodeError):
        return  # not inside an export (or its manifest is not one: then it is not an export's)
    if not isinstance(export, dict) or export.get("kind") != EXPORT_KIND:
        return
    listed = {(path.parent / e.get("path", n)).resolve(): n for n, e in (export.get("indexes") or {}).items()}
    name = listed.get(path.resolve())
    if name is None:
        raise InputError(
            top, f"does not list the index {path.name!r} its folder holds; export it again", field="indexes"
        )
    if sha256_file(path / MANIFEST) != export["indexes"][name].get("manifest_sha256"):
        raise InputError(path / MANIFEST, f"index {name!r} differs from the one {top} lists", field="manifest_sha256")


def is_finished(out: Path, build_hash: str, format_version: int) -> bool:
    """A bundle at ``out`` built from the same inputs, whose files all have their sizes and SHA-256
    (an edited file, even of the same size, makes it unfinished and the next build replaces it)."""
    try:
        m = json.loads((out / MANIFEST).read_text())
    except (OSError, json.JSONDecodeError):
        return False
    if m.get("format_version") != format_version or m.get("build_hash") != build_hash:
        return False
    files = m.get("files") or {}
    return all(
        (out / f).is_file()
        and (out / f).stat().st_size == info.get("bytes")
        and sha256_file(out / f) == info.get("sha256")
        for f, info in files.items()
    )


@contextmanager
def building(out: Path) -> Iterator[Path]:
    """A fresh partial folder beside ``out`` that replaces ``out`` in one rename when the block
    succeeds, and is removed when it fails."""
    out.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_partials(out)
    tmp = out.parent / f".{out.name}.partial-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    tmp.mkdir()
    try:
        yield tmp
        replace_dir(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def replace_dir(tmp: Path, out: Path) -> None:
    """Move the finished bundle ``tmp`` to ``out``, replacing any bundle there."""
    if out.exists():
        old = out.parent / f".{out.name}.old-{os.getpid()}-{uuid.uuid4().hex[:8]}"
        os.rename(out, old)
        os.rename(tmp, out)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.rename(tmp, out)


def remove_stale_partials(out: Path) -> None:
    """Remove the partial folders of interrupted builds (their process is gone) beside ``out``."""
    for p in out.parent.glob(f".{out.name}.partial-*"):
        try:
            pid = int(p.name.rsplit(".partial-", 1)[1].split("-")[0])
        except ValueError:
            continue
        if p.is_dir() and (pid == os.getpid() or not pid_alive(pid)):
            shutil.rmtree(p, ignore_errors=True)
    for p in out.parent.glob(f".{out.name}.old-*"):
        shutil.rmtree(p, ignore_errors=True)


def pid_alive(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except (ProcessLookupError, OverflowError):
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    return True


def copy_file(src: Path, dst: Path) -> None:
    """Copy ``src`` to ``dst``, never a hard link: a link would let an edit of one bundle corrupt
    the other (an exported bundle's file was the workspace index's). ``shutil.copy2`` copies in the
    kernel (``copy_file_range``/``sendfile``), which shares the blocks where the file system can
    (reflinks on XFS, Btrfs); a full disk is one :class:`~mapkit.core.runio.WriteError` line."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    try:
        shutil.copy2(src, dst)
    except OSError as exc:
        if exc.errno in WRITE_ERRNOS:
            raise write_error(dst, exc) from None
        raise
