"""A COLMAP database (``database.db``: images, keypoints, descriptors, verified pairs) read without changing it.

COLMAP's own ``Database.open`` switches the SQLite file to write-ahead logging and rewrites its header each time it
opens it, even to read. A reference model's database is a checksummed file of a deployment bundle and of a
benchmark export, and a localizer only reads it: reading it through COLMAP would make the bundle fail its own
checksum the next time it is loaded. Here the file is opened read-only and immutable (no lock, no journal, no
shared-memory file beside it), and its tables are read as COLMAP's schema lays them out: ``keypoints`` rows of
float32 (x, y and the affine shape), ``descriptors`` rows of uint8, ``two_view_geometries`` rows of inlier matches.
"""

from __future__ import annotations

import sqlite3
import threading
from pathlib import Path

import numpy as np

from mapkit.core.errors import InputError


class ColmapDatabase:
    """Read-only access to a COLMAP database file; a missing, damaged or foreign file is one
    :class:`~mapkit.core.errors.InputError` naming it (field ``database``). Any thread may read through one
    instance: its reads take turns on the one connection."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        if not self.path.is_file():  # sqlite would create an empty database
            raise InputError(self.path, "no such file: the reference model's features are missing", field="database")
        self._con: sqlite3.Connection | None = None
        self._lock = threading.Lock()
        try:
            self._con = sqlite3.connect(
                f"{self.path.resolve().as_uri()}?mode=ro&immutable=1", uri=True, check_same_thread=False
            )
            self._names = {int(i): str(n) for i, n in self._con.execute("SELECT image_id, name FROM images")}
            self._con.execute("SELECT image_id, rows, cols, data FROM keypoints LIMIT 1").fetchall()
            self._con.execute("SELECT image_id, rows, cols, data FROM descriptors LIMIT 1").fetchall()
        except sqlite3.Error as exc:
            self.close()
            raise InputError(self.path, f"not a readable COLMAP database: {exc}", field="database") from None

    def close(self) -> None:
        if self._con is not None:
            self._con.close()
            self._con = None

    def __enter__(self) -> ColmapDatabase:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def image_names(self) -> dict[int, str]:
        """Image names by image id."""
        return dict(self._names)

    def _rows(self, table: str, image_id: int, dtype: type, cols: int | None = None) -> np.ndarray:
        assert self._con is not None, "the database is closed"
        with self._lock:
            row = self._con.execute(
                f"SELECT rows, cols, data FROM {table} WHERE image_id = ?", (int(image_id),)
            ).fetchone()
        if row is None:
            return np.zeros((0, cols or 0), dtype)
        rows, ncols, data = int(row[0]), int(row[1]), row[2] or b""
        arr: np.ndarray = np.frombuffer(data, dtype)
        if arr.size != rows * ncols or (cols is not None and ncols != cols):
            raise InputError(
                self.path, f"image {image_id}: {table} of {rows} x {ncols} in {len(data)} bytes", field="database"
            )
        return arr.reshape(rows, ncols)

    def keypoints(self, image_id: int) -> np.ndarray:
        """(N, 2..6) float32: x, y in COLMAP's pixel convention, then the affine shape where stored."""
        return self._rows("keypoints", image_id, np.float32)

    def descriptors(self, image_id: int) -> np.ndarray:
        """(N, 128) uint8 SIFT descriptors (RootSIFT as COLMAP stores them)."""
        return np.ascontiguousarray(self._rows("descriptors", image_id, np.uint8, 128))

    def num_rows(self, table: str, image_id: int) -> int:
        """How many keypoints (``table="keypoints"``) or descriptors an image has (0 without any)."""
        if table not in ("keypoints", "descriptors"):
            raise ValueError(table)
        assert self._con is not None, "the database is closed"
        with self._lock:
            row = self._con.execute(f"SELECT rows FROM {table} WHERE image_id = ?", (int(image_id),)).fetchone()
        return 0 if row is None else int(row[0])

    def num_verified_pairs(self) -> int:
        """Image pairs with at least one inlier match after geometric verification."""
        assert self._con is not None, "the database is closed"
        with self._lock:
            return int(self._con.execute("SELECT COUNT(*) FROM two_view_geometries WHERE rows > 0").fetchone()[0])
