"""The package's imports point one way: from the CLI and pipelines down to ``core``, never back.

Every ``import`` of a mapkit module is read from the source with ``ast``, including the ones made
inside functions, and each module is given the rung of its subpackage. A module may import from
its own rung or any rung below it; an import from a rung above is a backward edge and fails the
test with the file and line. Separately, the module graph must have no cycles.
"""

from __future__ import annotations

import ast
import re
from collections import defaultdict
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "mapkit"
#: a string naming a class for a lazy import (``"mapkit.io.kitti:KittiRaw"``)
REGISTRY = re.compile(r"mapkit(\.\w+)+:\w+")

#: subpackage (or top-level module) -> rung; equal rungs may import each other's modules
RUNGS: dict[str, int] = {
    "__init__": 0,
    "core": 0,
    "io": 1,
    "synth": 2,
    "mapping": 3,
    "multisession": 4,
    "places": 5,
    "retrieval": 5,
    "learning": 6,
    "localization": 6,
    "deploy": 6,
    "evaluation": 7,
    "report": 8,
    "pipelines": 9,
    "cli": 10,
    "__main__": 10,
}
#: rungs that share a level but must not import each other (siblings stay independent)
SIBLINGS = [{"places", "retrieval"}, {"learning", "localization", "deploy"}]


def module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def imports_of(path: Path, root: Path) -> list[tuple[str, int]]:
    """Absolute names of every mapkit module ``path`` imports (top level or lazily), with the line."""
    me = module_name(path, root)
    package = me if path.name == "__init__.py" else me.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and REGISTRY.fullmatch(node.value):
            # "mapkit.places.triplets:TripletConfig": a lazy registry entry imports that module as surely
            out.append((node.value.split(":")[0], node.lineno))
        elif isinstance(node, ast.Import):
            out += [(a.name, node.lineno) for a in node.names if a.name.split(".")[0] == "mapkit"]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] != "mapkit":
                continue
            for a in node.names:  # ``from mapkit.places import patches`` imports the module mapkit.places.patches
                sub = f"{target}.{a.name}"
                out.append((sub if _is_module(sub, root) else target, node.lineno))
    return out


def _is_module(name: str, root: Path) -> bool:
    rel = Path(*name.split(".")[1:])
    return (root / rel).with_suffix(".py").exists() or (root / rel / "__init__.py").exists()


def rung_key(name: str) -> str:
    parts = name.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def backward_edges(root: Path) -> list[str]:
    bad = []
    for path in sorted(root.rglob("*.py")):
        me = module_name(path, root)
        mine = rung_key(me)
        for target, line in imports_of(path, root):
            theirs = rung_key(target)
            if mine == theirs or theirs == "__init__":
                continue
            if RUNGS[theirs] > RUNGS[mine]:
                bad.append(
                    f"{path.relative_to(root.parent)}:{line}: {mine} (rung {RUNGS[mine]}) imports {target} (rung "
                    f"{RUNGS[theirs]})"
                )
            elif any({mine, theirs} <= group for group in SIBLINGS):
                bad.append(f"{path.relative_to(root.parent)}:{line}: sibling {mine} imports {target}")
    return bad


def cycles(root: Path) -> list[list[str]]:
    graph: dict[str, set[str]] = defaultdict(set)
    for path in root.rglob("*.py"):
        me = module_name(path, root)
        graph[me] |= {
            t
            for t, _ in imports_of(path, root)
            if t != me and _is_module(t, root) and not (root / Path(*t.split(".")[1:]) / "__init__.py").exists()
        }
    # Tarjan's strongly connected components; a component of more than one module is a cycle
    index, low, stack, on, found = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in list(graph):
        if v not in index:
            visit(v)
    return found


def test_every_subpackage_has_a_rung():
    kinds = {p.name for p in PACKAGE.iterdir() if (p / "__init__.py").exists()} | {p.stem for p in PACKAGE.glob("*.py")}
    assert kinds <= set(RUNGS), f"give these a rung in RUNGS: {sorted(kinds - set(RUNGS))}"


def test_imports_point_down():
    bad = backward_edges(PACKAGE)
    assert not bad, "backward imports:\n" + "\n".join(bad)


def test_no_import_cycles():
    found = cycles(PACKAGE)
    assert not found, f"import cycles: {found}"


def test_the_checks_catch_a_backward_edge_and_a_cycle(tmp_path):
    """The walker itself: a probe package with one backward import, one lazy one and a cycle."""
    root = tmp_path / "mapkit"
    for sub in ("core", "mapping", "report"):
        (root / sub).mkdir(parents=True)
        (root / sub / "__init__.py").write_text("")
    (root / "__init__.py").write_text("")
    (root / "core" / "a.py").write_text("def f():\n    from mapkit.report import b\n")
    (root / "report" / "b.py").write_text("from ..mapping import c\n")
    (root / "mapping" / "c.py").write_text("from mapkit.mapping.d import x\n")
    (root / "mapping" / "d.py").write_text("import mapkit.mapping.c\nx = 1\n")
    (root / "mapping" / "e.py").write_text("MODELS = {'b': 'mapkit.report.b:Model'}\n")
    bad = backward_edges(root)
    assert len(bad) == 2 and "core/a.py:2" in bad[0] and "mapkit.report.b" in bad[0]
    assert "mapping/e.py:1" in bad[1] and "mapkit.report.b" in bad[1]
    assert cycles(root) == [["mapkit.mapping.c", "mapkit.mapping.d"]]


@pytest.mark.parametrize("name", ["mapkit.core.workspace"])
def test_layout_modules_exist(name):
    assert _is_module(name, PACKAGE)


#: a per-line suppression of a linter finding, and whether a reason follows its codes
NOQA = re.compile(r"#\s*noqa(?::\s*[A-Z]+[0-9]+(?:\s*,\s*[A-Z]+[0-9]+)*)?(?P<reason>.*)$")


def _noqa_without_reason(text: str) -> list[int]:
    return [i for i, line in enumerate(text.splitlines(), 1) if (m := NOQA.search(line)) and not m["reason"].strip()]


def test_every_noqa_says_why():
    """A linter finding is silenced on its line only, and the line says why (no blanket ignores either)."""
    root = PACKAGE.parent
    bare = {
        str(p.relative_to(root)): lines
        for d in ("mapkit", "tests", "bench", "pipelines", "docs")
        for p in sorted((root / d).rglob("*.py"))
        if (lines := _noqa_without_reason(p.read_text()))
    }
    assert bare == {}
    assert _noqa_without_reason("x = 1  # noqa: E731\ny = 2  # noqa\nz = 3  # noqa: E731 (why)\n") == [1, 2]
