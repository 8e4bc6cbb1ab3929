"""Typed configuration: pydantic models with written-out defaults, loaded from YAML.

Each stage declares its model here or in its own module; ``mapkit.cli.CONFIGS`` names it so that
``mapkit config defaults NAME`` prints it. Defaults that come from a paper say so in the field's
description. Unknown keys are errors (a typo must not silently fall back to a default).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from mapkit.core.errors import ConfigError, InputError
from mapkit.core.types import StreamKind

M = TypeVar("M", bound="MapkitConfig")


class MapkitConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class TopicConfig(MapkitConfig):
    """Which streams of a log to use. ``None`` = detect by message type (every stream of that kind)."""

    images: list[str] | None = Field(None, description="Camera image topics; all image streams if unset.")
    camera_info: list[str] | None = Field(None, description="CameraInfo topics; all if unset.")
    gps: str | None = Field(None, description="NavSatFix topic; the only GPS stream if unset.")
    lidar: str | None = Field(None, description="PointCloud2 topic; the only LiDAR stream if unset.")
    imu: str | None = Field(None, description="Imu topic; the only IMU stream if unset.")
    poses: str | None = Field(None, description="Ground-truth/INS pose topic; the only pose stream if unset.")


def load_config(model: type[M], path: M | str | Path | None = None, overrides: dict[str, Any] | None = None) -> M:
    """Defaults of ``model``, overlaid by a YAML file (or a config already resolved) and then by ``overrides``."""
    data: dict[str, Any] = {}
    if isinstance(path, model):
        if not overrides:
            return path
        data, path = path.model_dump(), None
    elif path is not None:
        # mypy cannot narrow by ``isinstance(path, model)`` with ``model: type[M]``: path is a str or Path here
        path = Path(path)  # type: ignore[arg-type]
        if not path.is_file():
            raise ConfigError(f"{path}: no such config file")
        try:
            loaded = yaml.safe_load(path.read_text()) or {}
        except yaml.YAMLError as exc:
            raise ConfigError(f"{path}: not valid YAML ({exc})") from None
        if not isinstance(loaded, dict):
            raise ConfigError(f"{path}: expected a mapping at the top level, found {type(loaded).__name__}")
        data = loaded
    if overrides:
        data = deep_merge(data, overrides)
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        field = ".".join(str(p) for p in err["loc"]) or "(top level)"
        where = f"{path}: " if path is not None else ""
        raise ConfigError(f"{where}field {field}: {err['msg']}") from None


def dump_config(cfg: MapkitConfig) -> str:
    """YAML of a resolved config, as written next to every result."""
    return yaml.safe_dump(cfg.model_dump(mode="json"), sort_keys=False)


def defaults_yaml(model: type[MapkitConfig]) -> str:
    """The defaults with each field's description as a comment (for ``mapkit config defaults``)."""
    lines: list[str] = []
    _commented(model, model(), lines, 0)
    return "\n".join(lines) + "\n"


def _commented(model: type[MapkitConfig], value: MapkitConfig, lines: list[str], indent: int) -> None:
    pad = "  " * indent
    for name, field in model.model_fields.items():
        v = getattr(value, name)
        if field.description:
            lines.append(f"{pad}# {field.description}")
        if isinstance(v, MapkitConfig):
            lines.append(f"{pad}{name}:")
            _commented(type(v), v, lines, indent + 1)
        else:
            dumped = yaml.safe_dump(
                {name: v.value if hasattr(v, "value") else v}, default_flow_style=True, sort_keys=False
            ).strip()
            lines.append(f"{pad}{dumped.strip('{}')}")


def deep_merge(base: dict, override: dict) -> dict:
    """``override`` over ``base``: mappings merge key by key, everything else (lists too) replaces."""
    out = dict(base)
    for k, v in override.items():
        out[k] = deep_merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def resolve_topics(log, cfg: TopicConfig) -> dict[StreamKind, list[str]]:
    """The topics to use per kind: named ones are checked to exist, the rest detected by type.

    Where a single stream is expected (GPS, LiDAR, IMU, poses) and the log has several, the
    choice must be made in the config; mapkit does not guess.
    """
    streams = log.streams()
    by_kind: dict[StreamKind, list[str]] = {}
    for s in streams:
        by_kind.setdefault(s.kind, []).append(s.topic)
    known = {s.topic: s.kind for s in streams}

    def check(topic: str, kind: StreamKind, field: str) -> str:
        if topic not in known:
            raise InputError(log.path, f"topic {topic!r} (config topics.{field}) is not in this log", field=field)
        if known[topic] != kind:
            raise InputError(
                log.path,
                f"topic {topic!r} (config topics.{field}) carries {known[topic].value}, not {kind.value}",
                field=field,
            )
        return topic

    out: dict[StreamKind, list[str]] = {}
    for kind, field in ((StreamKind.IMAGE, "images"), (StreamKind.CAMERA_INFO, "camera_info")):
        chosen = getattr(cfg, field)
        out[kind] = [check(t, kind, field) for t in chosen] if chosen is not None else by_kind.get(kind, [])
    for kind, field in (
        (StreamKind.GPS, "gps"),
        (StreamKind.LIDAR, "lidar"),
        (StreamKind.IMU, "imu"),
        (StreamKind.POSE, "poses"),
    ):
        chosen = getattr(cfg, field)
        if chosen is not None:
            out[kind] = [check(chosen, kind, field)]
        else:
            candidates = by_kind.get(kind, [])
            if len(candidates) > 1:
                raise InputError(
                    log.path,
                    f"{len(candidates)} {kind.value} streams ({', '.join(candidates)}): choose one with topics.{field}",
                    field=field,
                )
            out[kind] = candidates
    out[StreamKind.TF] = by_kind.get(StreamKind.TF, [])
    return out
