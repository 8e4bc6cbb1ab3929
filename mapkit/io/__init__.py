"""Readers and writers. ``open_log`` picks a reader from an explicit name or from the path.

Readers are imported lazily from an explicit name-to-class map, so a missing optional
dependency of one reader never breaks the others.
"""

from __future__ import annotations

from pathlib import Path

from mapkit.core.errors import InputError
from mapkit.core.registry import load_entry
from mapkit.io.base import DriveLog

#: reader name -> "module:Class"; each class has ``detect(path) -> bool``
READERS: dict[str, str] = {
    "mcap": "mapkit.io.mcap_log:McapLog",  # a .mcap file or a rosbag2 folder with mcap storage
    "rosbag": "mapkit.io.rosbag:RosbagLog",  # a ROS 1 .bag file or a rosbag2 folder with sqlite3 storage
    "kitti-odometry": "mapkit.io.kitti:KittiOdometry",
    "kitti-raw": "mapkit.io.kitti:KittiRaw",
    "robotcar": "mapkit.io.robotcar:RobotCar",
    "folder": "mapkit.io.folder:FolderLog",
    "photos": "mapkit.io.photos:PhotoFolder",
}


def reader_class(name: str) -> type[DriveLog]:
    if name not in READERS:
        raise InputError(None, f"unknown log format {name!r}; known: {', '.join(READERS)}", field="format")
    return load_entry(READERS[name])


def _rosbag2_reader(folder: Path) -> str:
    """``rosbag`` for a rosbag2 folder with sqlite3 storage, ``mcap`` otherwise (McapLog explains other storage)."""
    from mapkit.io.mcap_log import rosbag2_metadata

    info = rosbag2_metadata(folder)
    storage = str(info.get("storage_identifier") or "").strip().lower()
    if not storage:  # old bags may leave it out: the storage files' suffix tells
        rel = info.get("relative_file_paths")
        files = [str(p) for p in rel] if isinstance(rel, list) and rel else [p.name for p in folder.iterdir()]
        storage = "sqlite3" if any(f.endswith(".db3") for f in files) else "mcap"
    return "rosbag" if storage == "sqlite3" else "mcap"


def guess_format(path: str | Path) -> str:
    path = Path(path)
    if not path.exists():
        raise InputError(path, "no such file or folder")
    if path.is_file():
        from mapkit.io.mcap_log import ROSBAG2_METADATA, is_mcap, is_rosbag2

        if path.suffix == ".bag":
            return "rosbag"
        if path.name == ROSBAG2_METADATA and is_rosbag2(path.parent):
            return _rosbag2_reader(path.parent)
        if (
            is_mcap(path) or path.suffix == ".mcap"
        ):  # McapLog reads a file whose leading magic is damaged, or says why not
            return "mcap"
        raise InputError(
            path,
            "is a file but not an MCAP log or a ROS 1 .bag (folders are read as rosbag2, KITTI, RobotCar, "
            "photo or generic layouts)",
        )
    from mapkit.io.mcap_log import is_rosbag2

    if is_rosbag2(path):
        return _rosbag2_reader(path)
    for name in ("kitti-odometry", "kitti-raw", "robotcar", "folder", "photos"):
        try:
            cls = reader_class(name)
        except (ImportError, AttributeError):
            continue
        if cls.detect(path):
            return name
    raise InputError(
        path,
        "folder layout not recognised as a rosbag2 bag (metadata.yaml), KITTI odometry, KITTI raw, Oxford RobotCar, "
        "a geotagged photo folder or a generic image folder (a ROS 1 bag is a .bag file: give the file)",
    )


def open_log(path: str | Path, format: str | None = None, **kwargs) -> DriveLog:
    """Open a drive log with the named reader, or the one whose layout matches ``path``."""
    name = format or guess_format(path)
    return reader_class(name)(path, **kwargs)


__all__ = ["DriveLog", "READERS", "open_log", "guess_format", "reader_class"]
