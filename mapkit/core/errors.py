"""Errors and warnings that reach users as one clear line.

Library code raises these instead of printing or exiting; the CLI turns a ``MapkitError`` into a
single line on stderr and a non-zero exit code.
"""

from __future__ import annotations

from pathlib import Path


class MapkitError(Exception):
    """Base class of every error mapkit reports to a user (never a bug)."""


class InputError(MapkitError):
    """Bad input: names the file and, where known, the field, topic or row that is wrong."""

    def __init__(self, path: str | Path | None, what: str, *, field: str | None = None):
        self.path = None if path is None else Path(path)
        self.field = field
        self.what = what
        where = "" if self.path is None else f"{self.path}"
        if field:
            where = f"{where} [{field}]" if where else f"[{field}]"
        super().__init__(f"{where}: {what}" if where else what)


class ConfigError(MapkitError):
    """A configuration file or value is invalid."""


class InputWarning(UserWarning):
    """Input that was usable in part: says what was skipped and where."""
