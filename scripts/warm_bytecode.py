"""Write the bytecode of every module that mapkit and its tests import, once, at set-up.

Python caches a module's compiled bytecode beside it the first time it is imported, unless
``PYTHONDONTWRITEBYTECODE`` is set, as on many CI machines and container images. There, every new
process (each worker of a stage, each ``mapkit`` command) compiles numpy, scipy, open3d and mapkit
again from source: about 3 s of each process's start on a 2-core machine, a third of the tiny chain's
CPU time. This script imports what mapkit's and the tests' sources name, with the cache on for
itself only; later processes read the bytecode whatever the variable says. The names come from the
sources themselves (every ``import`` statement), so that a new dependency needs no list kept here.

    .venv/bin/python scripts/warm_bytecode.py     # scripts/setup.sh runs it after installing
"""

from __future__ import annotations

import sys

sys.dont_write_bytecode = False  # before any import below: this process writes what it compiles

import ast  # noqa: E402
import importlib  # noqa: E402
import warnings  # noqa: E402
from concurrent.futures import ProcessPoolExecutor  # noqa: E402
from multiprocessing import get_context  # noqa: E402
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
#: imported in a process of their own (the largest): the two processes take about the same time
HEAVY = ("torch", "ray", "onnxruntime", "onnx", "rerun")


def imported_modules(folders: list[Path]) -> list[str]:
    """Every module an ``import`` statement of the Python files under ``folders`` names (relative imports aside)."""
    names: set[str] = set()
    for folder in folders:
        for path in sorted(folder.rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_bytes(), filename=str(path))):
                if isinstance(node, ast.Import):
                    names.update(a.name for a in node.names)
                elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                    names.add(node.module)
    return sorted(names)


def _import_all(names: list[str]) -> int:
    sys.dont_write_bytecode = False  # a spawned process starts from the environment again
    warnings.simplefilter("ignore")
    done = 0
    for name in names:
        try:
            importlib.import_module(name)
            done += 1
        except Exception:  # noqa: BLE001 - an optional module that is absent, or one of the tests' own: skipped
            pass
    return done


def main() -> int:
    names = [n for n in imported_modules([ROOT / "mapkit", ROOT / "tests", ROOT / "pipelines"]) if n != "__future__"]
    heavy = [n for n in names if n.split(".")[0] in HEAVY]
    rest = [n for n in names if n.split(".")[0] not in HEAVY]
    with ProcessPoolExecutor(2, mp_context=get_context("spawn")) as pool:
        done = sum(pool.map(_import_all, [heavy, rest]))
    print(f"[setup] bytecode written for {done} of {len(names)} imported modules", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
