"""The presets and configs that ship with mapkit, wherever mapkit is installed.

Their one copy is ``configs/`` of the source tree (each value with a comment naming its source).
pyproject.toml installs that folder as the package ``mapkit.configs``: a wheel holds it as
``mapkit/configs/``, an editable install maps the package to ``configs/`` itself, and
:mod:`importlib.resources` finds it either way. Kinds are the folders of ``configs/``:

- ``synth``: town presets and overlays (``mapkit synth --preset NAME``, ``--config``);
- ``localize``: filter presets (``mapkit eval localize --config``);
- ``build``: ``mapkit build`` configs;
- ``""``: the top folder (``topics``).

Only the standard library is imported here.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from mapkit.core.errors import ConfigError

KINDS = ("synth", "localize", "build")


def configs_dir() -> Path:
    """The folder of the shipped configs (``mapkit/configs`` installed, ``configs/`` of a checkout)."""
    try:
        root = resources.files("mapkit.configs")
    except ModuleNotFoundError:  # an editable install made before configs/ was package data
        root = None
    if isinstance(root, Path) and root.is_dir():
        return root
    source = Path(__file__).resolve().parents[1] / "configs"
    if source.is_dir():
        return source
    raise ConfigError("mapkit's presets (the package mapkit.configs) are not installed as files: reinstall mapkit")


def _kind_dir(kind: str) -> Path:
    if kind and kind not in KINDS:
        raise ConfigError(f"unknown kind of preset {kind!r}; choose one of {', '.join(KINDS)}")
    return configs_dir() / kind if kind else configs_dir()


def preset_names(kind: str) -> list[str]:
    """The names of the shipped YAML files of a kind (``""``: the top folder), sorted."""
    return sorted(p.stem for p in _kind_dir(kind).iterdir() if p.suffix == ".yaml" and p.is_file())


def preset_path(kind: str, name: str) -> Path:
    """The file of a shipped preset: ``preset_path("localize", "odometry")`` -> ``.../localize/odometry.yaml``.

    ``name`` may carry the ``.yaml`` suffix. An unknown name raises a ``ConfigError`` listing the names there are.
    """
    stem = name[: -len(".yaml")] if name.endswith(".yaml") else name
    path = _kind_dir(kind) / f"{stem}.yaml"
    if "/" in stem or "\\" in stem or not path.is_file():
        where = f"{kind} " if kind else ""
        raise ConfigError(f"unknown {where}preset {name!r}; available: {', '.join(preset_names(kind)) or '(none)'}")
    return path
