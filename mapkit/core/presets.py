"""The presets and configs that ship with mapkit, wherever mapkit is installed.

Their one copy is ``configs/`` of the source tree (each value with a comment naming its source).
pyproject.toml installs that folder as the package ``mapkit.configs``: a wheel holds it as
``mapkit/configs/``, an editable install maps the package to ``configs/`` itself; a plain
checkout on ``sys.path`` has it beside the package. Kinds are the folders of ``configs/``:

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
    """The folder of the shipped configs that belong to *this* mapkit.

    Looked up beside the imported package first, so that a checkout run as a script (its
    ``pipelines/main.py`` puts it first on ``sys.path``) reads its own ``configs/`` even when
    another checkout is installed in editable mode: ``mapkit/configs`` in a wheel's layout, then
    ``configs/`` of the source tree that holds this package. :mod:`importlib.resources` is the
    last resort (an installed layout this code does not know)."""
    package = Path(__file__).resolve().parents[1]  # .../mapkit
    for candidate in (package / "configs", package.parent / "configs"):
        if (candidate / "synth").is_dir():
            return candidate
    try:
        root = resources.files("mapkit.configs")
    except ModuleNotFoundError:
        root = None
    if isinstance(root, Path) and root.is_dir():
        return root
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
