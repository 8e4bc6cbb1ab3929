"""Registries that name their entries as ``"package.module:Name"`` strings, imported on first use.

The CLI's configurations and the readers are registered this way, so that ``mapkit --help`` stays
fast and a missing optional dependency of one entry never breaks the others.
"""

from __future__ import annotations

import importlib
from typing import Any


def load_entry(spec: str) -> Any:
    """The object ``spec`` (``"package.module:Name"``) names, its module imported now."""
    module, name = spec.split(":")
    return getattr(importlib.import_module(module), name)
