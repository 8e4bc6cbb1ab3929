"""An installed mapkit carries its presets: configs/ of the source tree is the package data mapkit.configs.

A wheel is built (offline, from a copy of the sources so that the checkout gets no build/ or
egg-info) and checked to hold every file of configs/ and every module of mapkit; unzipped, it is
imported by a Python that cannot see the checkout, which loads every preset and config through
mapkit.core.presets and runs `mapkit synth --help`. An editable build must map mapkit.configs to configs/.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

from mapkit.core.errors import ConfigError
from mapkit.core.presets import KINDS, preset_names, preset_path

ROOT = Path(__file__).resolve().parents[1]
SKIP = shutil.ignore_patterns("__pycache__", "*.pyc")


def _files(folder: Path) -> set[str]:
    return {
        p.relative_to(folder).as_posix()
        for p in folder.rglob("*")
        if p.is_file() and "__pycache__" not in p.parts and p.suffix != ".pyc"
    }


def _installed_python(code: str, path: list[Path], cwd: Path, *args: str) -> subprocess.CompletedProcess:
    """``code`` run by a Python without site (no .pth: the venv's editable mapkit stays out) on ``path``
    and the environment's site-packages (numpy, pydantic, ...), with ``cwd`` outside the checkout."""
    libs = dict.fromkeys([sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]])
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([*map(str, path), *libs]), PYTHONDONTWRITEBYTECODE="1")
    return subprocess.run(
        [sys.executable, "-S", "-c", code, *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=300
    )


@pytest.fixture(scope="module")
def sources(tmp_path_factory) -> Path:
    """What a build reads: pyproject.toml, README.md, mapkit/ and configs/."""
    src = tmp_path_factory.mktemp("pkg") / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, src / name)
    for name in ("mapkit", "configs"):
        shutil.copytree(ROOT / name, src / name, ignore=SKIP)
    return src


@pytest.fixture(scope="module")
def wheel(sources) -> Path:
    out = sources.parent / "dist"
    env = dict(os.environ, PIP_NO_INDEX="1", PIP_DISABLE_PIP_VERSION_CHECK="1")
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "--no-deps",
            "--no-build-isolation",
            "--no-index",
            "-w",
            str(out),
            str(sources),
        ],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    (whl,) = out.glob("mapkit-*.whl")
    return whl


def test_the_wheel_holds_every_file_of_configs_and_every_module(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    configs = _files(ROOT / "configs")
    assert "synth/tiny.yaml" in configs and "localize/paper.yaml" in configs
    missing = sorted(f for f in configs if f"mapkit/configs/{f}" not in names)
    assert not missing, f"configs/ files not in the wheel (pyproject.toml: packages / package-data): {missing}"
    modules = {f for f in _files(ROOT / "mapkit") if f.endswith(".py")}
    missing = sorted(f for f in modules if f"mapkit/{f}" not in names)
    assert not missing, f"modules not in the wheel (a subpackage missing from pyproject.toml's packages?): {missing}"


INSTALLED = r"""
import json, sys
from pathlib import Path
import mapkit
from mapkit.core import presets
from mapkit.cli import config_model
from mapkit.core.config import load_config
from mapkit.synth.config import PRESETS, load_config as load_synth

site = Path(sys.argv[1]).resolve()
assert Path(mapkit.__file__).resolve().is_relative_to(site), mapkit.__file__
assert presets.configs_dir().resolve() == site / "mapkit" / "configs", presets.configs_dir()
loaded = {}
for kind in presets.KINDS + ("",):
    for name in presets.preset_names(kind):
        path = presets.preset_path(kind, name)
        if kind == "synth":  # the presets, and overlays named after the preset they go over
            cfg = load_synth(name) if name in PRESETS else load_synth(name.split("-")[0], config=path)
        else:
            cfg = load_config(config_model(kind or name), path)
        loaded[f"{kind}/{name}"] = type(cfg).__name__
print(json.dumps(loaded))
"""


def test_an_installed_wheel_loads_every_preset_without_the_checkout(wheel, tmp_path):
    site, cwd = tmp_path / "site", tmp_path / "elsewhere"
    cwd.mkdir()
    zipfile.ZipFile(wheel).extractall(site)
    r = _installed_python(INSTALLED, [site], cwd, str(site))
    assert r.returncode == 0, r.stderr[-3000:]
    loaded = json.loads(r.stdout.strip().splitlines()[-1])
    expected = {f"{kind}/{name}" for kind in KINDS + ("",) for name in preset_names(kind)}
    assert set(loaded) == expected and len(expected) == len(_files(ROOT / "configs")) - 1  # all but __init__.py
    assert loaded["synth/tiny"] == "SynthConfig" and loaded["localize/paper"] == "LocalizeConfig"
    assert loaded["build/mcvl-database"] == "BuildConfig" and loaded["/topics"] == "TopicConfig"
    cli = "import sys; from mapkit.cli import main; sys.argv = ['mapkit', 'synth', '--help']; main()"
    r = _installed_python(cli, [site], cwd)
    assert r.returncode == 0 and "--preset" in r.stdout, r.stdout[-2000:] + r.stderr[-2000:]


EDITABLE = r"""
import importlib.util, site, sys
from pathlib import Path
sys.path.insert(0, sys.argv[1])  # before site-packages, which has the venv's own finder module of that name
site.addsitedir(sys.argv[1])  # runs the editable wheel's .pth: it installs the wheel's import finder
import mapkit
from mapkit.core.presets import configs_dir, preset_path
src = Path(sys.argv[2]).resolve()
assert Path(mapkit.__file__).resolve() == src / "mapkit" / "__init__.py", mapkit.__file__
spec = importlib.util.find_spec("mapkit.configs")
assert spec is not None and Path(spec.origin).resolve() == src / "configs" / "__init__.py", spec
assert configs_dir().resolve() == src / "configs"
assert preset_path("synth", "tiny").resolve() == src / "configs" / "synth" / "tiny.yaml"
print("ok")
"""


def test_an_editable_install_maps_mapkit_configs_to_the_configs_folder(sources, tmp_path):
    build = "import sys; from setuptools import build_meta; print(build_meta.build_editable(sys.argv[1]))"
    r = subprocess.run(
        [sys.executable, "-c", build, str(tmp_path / "ed")], cwd=sources, capture_output=True, text=True, timeout=300
    )
    assert r.returncode == 0, r.stderr[-3000:]
    (whl,) = (tmp_path / "ed").glob("*.whl")
    zipfile.ZipFile(whl).extractall(tmp_path / "site")
    r = _installed_python(EDITABLE, [], tmp_path, str(tmp_path / "site"), str(sources))
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr[-3000:]


def test_an_unknown_preset_lists_the_names_there_are():
    with pytest.raises(ConfigError, match="available: odometry, odometry-multihypothesis, paper"):
        preset_path("localize", "odometri")
    with pytest.raises(ConfigError, match="synth, localize, build"):
        preset_path("nope", "tiny")
    assert preset_path("synth", "tiny.yaml") == preset_path("synth", "tiny")
    assert preset_path("synth", "tiny").read_text().startswith("#")


def test_a_checkout_reads_its_own_configs_even_with_another_installed(tmp_path):
    """pipelines/main.py runs a checkout's mapkit whatever is installed: its presets too. A copy of
    the package and configs elsewhere, first on sys.path, must read the copy's configs/, not the
    editable install's (which importlib.resources would find)."""

    copy = tmp_path / "checkout"
    shutil.copytree(ROOT / "mapkit", copy / "mapkit", ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copytree(ROOT / "configs", copy / "configs")
    (copy / "configs" / "synth" / "probe.yaml").write_text("seed: 1\n")
    code = (
        "import sys; sys.path.insert(0, sys.argv[1]); import mapkit; "
        "from mapkit.core.presets import configs_dir, preset_path; "
        "print(mapkit.__file__); print(configs_dir()); print(preset_path('synth', 'probe'))"
    )
    r = subprocess.run([sys.executable, "-c", code, str(copy)], capture_output=True, text=True, cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    module, configs, probe = r.stdout.split()
    assert Path(module).resolve().is_relative_to(copy.resolve())
    assert Path(configs).resolve() == (copy / "configs").resolve() and Path(probe).is_file()
