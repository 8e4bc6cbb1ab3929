"""``mapkit index export``: a workspace's indexes as one deployable folder.

The export holds one self-describing sub-folder per index (VLAD, structure NBLD / M2DP / CNN),
each the index's own bundle with its own manifest and checksums, the workspace's reference model when
it has a finished one (``reference_model/``: the COLMAP model, its features database and settings, what
the 6-DoF localizer reads, with a manifest of checksums like an index's), and a top-level
``manifest.json`` that says what is there: the export's format version, per index its kind,
format version, parameters, the CRS and origin of its poses, its source sessions, and the sha256
of its manifest (which in turn checksums each of its files). Files are copied, never hard-linked:
an edit of the export must not reach the workspace's index (the kernel shares blocks where the
file system can reflink).

:func:`load_bundle` is the deployment-side entry point: it refuses an unknown export format
version, checks every index's manifest against the top-level one, verifies every file's
checksum, and returns the loaded indexes by name.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from mapkit import __version__
from mapkit.core.bundle import EXPORT_KIND, MANIFEST, building, copy_file, load_manifest, read_manifest, write_manifest
from mapkit.core.errors import InputError
from mapkit.core.runio import atomic_write_text, read_marker, sha256_file, write_json
from mapkit.core.workspace import Workspace
from mapkit.core.writers import writes_workspace
from mapkit.deploy.benchmark import MODEL_FOLDER

FORMAT_VERSION = 1
KIND = EXPORT_KIND

#: the index kinds an export holds, as their manifests name them
_VLAD, _STRUCTURE, _MODEL = "mapkit VLAD index", "mapkit structure index", "mapkit reference model"
#: the files of a reference model (``mapkit model``) that the 6-DoF localizer reads, and its record
_MODEL_FILES = ("sfm", "database.db", "config.yaml", "metrics.json")
MODEL_FORMAT_VERSION = 1


def _loader(kind: str):
    """The ``load(path, verify)`` of an index kind (it checks the kind's own format version), or None."""
    if kind == _VLAD:
        from mapkit.retrieval.index_vlad import VladIndex

        return VladIndex.load
    if kind == _STRUCTURE:
        from mapkit.places.index_structure import StructureIndex

        return StructureIndex.load
    if kind == _MODEL:
        return load_model_bundle
    return None


def load_model_bundle(path: str | Path, verify: bool = True) -> Path:
    """An exported reference model (``BUNDLE/reference_model``) after checking its manifest and (``verify``) every
    file's checksum: its folder, what :class:`mapkit.localization.sixdof.SixDofLocalizer` and ``mapkit localize
    --refine 6dof --model`` take."""
    read_manifest(Path(path), "reference model", MODEL_FORMAT_VERSION, ("database.db", "config.yaml"), verify)
    return Path(path)


def _model_entry(name: str, src: Path, origin: dict | None) -> dict:
    metrics = json.loads((src / "metrics.json").read_text())
    cfg = yaml.safe_load((src / "config.yaml").read_text()) or {}
    return {
        "path": name,
        "kind": _MODEL,
        "descriptor": "sift",
        "format_version": MODEL_FORMAT_VERSION,
        "parameters": {k: v for k, v in cfg.items() if k != "sessions"},
        "crs": origin,
        "source_sessions": sorted(cfg.get("sessions") or []),
        "entries": metrics.get("points"),
        "images": metrics.get("images"),
    }


def _copy_model(src: Path, dst: Path) -> None:
    for part in _MODEL_FILES:
        f = src / part
        for g in sorted(f.rglob("*")) if f.is_dir() else [f]:
            if g.is_file():
                copy_file(g, dst / g.relative_to(src))
    write_manifest(dst, {"format_version": MODEL_FORMAT_VERSION, "kind": _MODEL, "mapkit_version": __version__})


def find_indexes(workspace: str | Path | Workspace) -> dict[str, Path]:
    """Finished index bundles under ``WORKSPACE/indexes`` (``vlad``, ``structure-nbld``, ...), by folder name."""
    root = Workspace(workspace).indexes_dir
    found = {}
    if root.is_dir():
        for p in sorted(root.iterdir()):
            if p.is_dir() and not p.name.startswith(".") and (p / MANIFEST).is_file():
                found[p.name] = p
    return found


def _index_entry(name: str, src: Path, origin: dict | None) -> dict:
    m = json.loads((src / MANIFEST).read_text())
    kind = m.get("kind")
    load = _loader(kind)
    if load is None:
        raise InputError(src / MANIFEST, f"unknown index kind {kind!r}", field="kind")
    load(src, verify=True)  # a broken or unknown-version index is not exported
    cfg = m.get("config", {})
    if kind == _VLAD:
        sessions = sorted(n for n, s in (m.get("sessions") or {}).items() if s.get("database"))
        frame = m.get("frame") or origin
        params = {"vlad": cfg.get("vlad"), "index": m.get("index")}
        entries = (m.get("index") or {}).get("ntotal")
    else:
        sessions = list(m.get("session_names") or [])
        frame = origin
        params = {
            k: cfg.get(k) for k in ("kind", "keypoint_fraction", "pca_dim", "nbld", "m2dp", "cnn_model") if k in cfg
        }
        entries = (m.get("counts") or {}).get("entries")
    return {
        "path": name,
        "kind": kind,
        "descriptor": "vlad" if kind == _VLAD else m.get("descriptor"),
        "format_version": m.get("format_version"),
        "parameters": params,
        "crs": frame,
        "source_sessions": sessions,
        "entries": entries,
        "manifest_sha256": sha256_file(src / MANIFEST),
    }


@writes_workspace("workspace")
def export_bundles(workspace: str | Path, out: str | Path, names: Sequence[str] | None = None) -> Path:
    """Copy the finished indexes of ``workspace`` into ``out`` with a top-level manifest; returns ``out``.
    ``names`` selects folders of ``WORKSPACE/indexes`` (default all, and the finished reference model).
    The export is built beside ``out`` and renamed into place, so ``out`` is always whole."""
    ws, out = Workspace(workspace), Path(out)
    found = find_indexes(ws)
    if names:
        missing = [n for n in names if n not in found]
        if missing:
            raise InputError(ws.indexes_dir, f"no finished index named {missing}; found {sorted(found)}")
        found = {n: found[n] for n in names}
    if not found:
        raise InputError(
            ws.indexes_dir, "no finished index to export (run `mapkit index vlad` or `mapkit index structure` first)"
        )
    origin = (
        json.loads(ws.origin.read_text()) if ws.origin.is_file() else None
    )  # as written: the export states it verbatim
    entries = {name: _index_entry(name, src, origin) for name, src in found.items()}
    model = ws.root / MODEL_FOLDER
    with_model = not names and read_marker(model) is not None
    if with_model:
        entries[MODEL_FOLDER] = _model_entry(MODEL_FOLDER, model, origin)
    with building(out) as tmp:
        for name, src in found.items():
            for f in sorted(src.rglob("*")):
                if f.is_file():
                    copy_file(f, tmp / name / f.relative_to(src))
        if with_model:
            _copy_model(model, tmp / MODEL_FOLDER)
            entries[MODEL_FOLDER]["manifest_sha256"] = sha256_file(tmp / MODEL_FOLDER / MANIFEST)
        manifest = {
            "format_version": FORMAT_VERSION,
            "kind": KIND,
            "mapkit_version": __version__,
            "source_workspace": str(ws.root.resolve()),
            "crs": origin,
            "indexes": entries,
        }
        atomic_write_text(tmp / "README.txt", _readme(entries))
        write_json(tmp / MANIFEST, manifest)
    return out


def _readme(entries: dict) -> str:
    lines = [
        "mapkit deployment bundle",
        "",
        "Load and verify everything in Python:",
        "",
        "    from mapkit.deploy.export import load_bundle",
        "    bundle = load_bundle('THIS_FOLDER')   # bundle['vlad'], bundle['structure-nbld'], ...",
        "",
        "A reference_model/ folder (when listed) is what `mapkit localize --refine 6dof --model` takes.",
        "",
        "Indexes:",
    ]
    for name, e in entries.items():
        lines.append(
            f"  {name}: {e['kind']} ({e['descriptor']}), {e['entries']} entries, sessions "
            f"{', '.join(e['source_sessions'])}"
        )
    return "\n".join(lines) + "\n"


@dataclass
class Bundle:
    """A loaded deployment bundle: its manifest and the indexes by name."""

    path: Path
    manifest: dict
    indexes: dict[str, Any]

    def __getitem__(self, name: str):
        return self.indexes[name]


def load_bundle(path: str | Path, verify: bool = True) -> Bundle:
    """Load every index of an export after checking the export's format version, that each
    index's manifest is the one the export lists (sha256), and (``verify``) every file's checksum."""
    path = Path(path)
    mpath = path / MANIFEST
    top = load_manifest(path, KIND, FORMAT_VERSION)
    if top.get("kind") != KIND:
        raise InputError(mpath, f"not a {KIND}", field="kind")
    indexes = {}
    for name, e in (top.get("indexes") or {}).items():
        sub = path / e.get("path", name)
        if not (sub / MANIFEST).is_file():
            raise InputError(sub, f"index {name!r} listed in {mpath} is missing")
        if sha256_file(sub / MANIFEST) != e.get("manifest_sha256"):
            raise InputError(
                sub / MANIFEST, f"index {name!r} differs from the one the export lists", field="manifest_sha256"
            )
        load = _loader(e.get("kind"))
        if load is None:
            raise InputError(mpath, f"index {name!r} has unknown kind {e.get('kind')!r}", field="kind")
        indexes[name] = load(sub, verify=verify)
    listed = {(path / e.get("path", name)).resolve() for name, e in (top.get("indexes") or {}).items()}
    unlisted = sorted(d.name for d in path.iterdir() if (d / MANIFEST).is_file() and d.resolve() not in listed)
    if unlisted:  # an export and its manifest that disagree: edited, or two exports mixed in one folder
        raise InputError(
            mpath,
            f"lists {len(listed)} index(es) but the folder holds others: {unlisted}; export it again",
            field="indexes",
        )
    return Bundle(path, top, indexes)


__all__ = ["FORMAT_VERSION", "KIND", "Bundle", "export_bundles", "find_indexes", "load_bundle"]
