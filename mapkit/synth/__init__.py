"""Synthetic town generator (placeholder until the synthetic-town work lands)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

from ..errors import MapkitError


def synthesize(preset: str, out: Path, seed: Optional[int] = None, config: Optional[Path] = None,
               trajectory: Optional[Path] = None, overwrite: bool = False) -> Path:
    raise MapkitError("`mapkit synth` is not available yet (synthetic town)")
