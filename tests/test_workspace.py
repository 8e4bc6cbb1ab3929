"""The workspace layout: one owner of every path, the frame read or refused clearly, and the
choice between a session's built and aligned products made in one place."""

from __future__ import annotations

import ast
import json
from pathlib import Path

import numpy as np
import pytest

from mapkit.core.errors import InputError
from mapkit.core.geodesy import LocalFrame
from mapkit.core.workspace import Workspace

PACKAGE = Path(__file__).resolve().parents[1] / "mapkit"


def _touch(path: Path, text: str = "") -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def test_frame_round_trip_and_clear_errors(tmp_path):
    ws = Workspace(tmp_path)
    assert ws.frame() is None
    with pytest.raises(InputError) as e:
        ws.require_frame()
    assert "origin.json" in str(e.value)
    frame = LocalFrame(48.1, 11.5, 520.0)
    _touch(ws.origin, json.dumps(frame.to_dict()))
    back = ws.require_frame()
    assert np.allclose(back.to_frame(frame), np.eye(4), atol=1e-9)
    ws.origin.write_text("{not json")
    with pytest.raises(InputError) as e:
        ws.frame()
    assert "origin.json" in str(e.value)


def test_sessions_by_finished_stage(tmp_path):
    ws = Workspace(tmp_path)
    assert ws.session_names() == []
    _touch(ws.session("b").imagedb / ".done")
    _touch(ws.session("b").images_csv, "id\n")
    _touch(ws.session("a").map / "points.ply")  # a map folder without its marker is not finished
    assert ws.session_names() == ["a", "b"]
    assert ws.session_names("imagedb") == ["b"]
    assert ws.session_names("map") == []
    assert ws.sessions_with_images() == ["b"]
    assert ws.session("a").gps_alignment == tmp_path / "sessions" / "a" / "georef" / "gps_alignment.json"


def test_aligned_products_only_when_align_finished(tmp_path):
    ws = Workspace(tmp_path)
    _touch(ws.session("s").map / "observations.npz")
    _touch(ws.aligned("s").map / "observations.npz")
    _touch(ws.session("s").images_csv)
    _touch(ws.aligned("s").images_csv)
    # align wrote the session's files but did not finish: the built products are used
    assert ws.aligned_sessions() == []
    assert ws.session_map("s") == (ws.session("s").map, "build")
    assert ws.session_images_csv("s") == ws.session("s").images_csv
    _touch(ws.align_done, json.dumps({"sessions": ["s"], "config_hash": "x"}))
    assert ws.aligned_sessions() == ["s"]
    assert ws.session_map("s") == (ws.aligned("s").map, "align")
    assert ws.session_map("s", prefer_aligned=False) == (ws.session("s").map, "build")
    assert ws.session_images_csv("s") == ws.aligned("s").images_csv
    assert ws.sessions_with_maps() == ["s"]
    ws.align_done.write_text("[1, 2")  # a torn marker is not a finished alignment
    assert ws.aligned_sessions() == []
    with pytest.raises(InputError) as e:
        ws.session_map("missing")
    assert "missing" in str(e.value)


def test_workspace_accepts_itself_and_paths():
    a = Workspace("/x/ws")
    assert Workspace(a) == a and Workspace(Path("/x/ws")) == a
    assert a.structure_index("m2dp") == Path("/x/ws/indexes/structure-m2dp")
    assert a.vlad_index == Path("/x/ws/indexes/vlad")


# Names of the workspace's own folders and files: joining one of them onto a path anywhere but in
# core/workspace.py spells the layout a second time.
LAYOUT_NAMES = {"sessions", "align", "origin.json", "indexes", "georef", "imagedb", "build_config.yaml", "tiles"}


def _layout_joins(path: Path, root: Path = PACKAGE.parent) -> list[str]:
    """Joins of a layout name onto a path; a stage's own output folder that happens to share a
    name (``out / "indexes"`` inside eval/places) says so with ``# own output folder``."""
    found = []
    lines = path.read_text().splitlines()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Div):
            for side in (node.left, node.right):
                if (
                    isinstance(side, ast.Constant)
                    and side.value in LAYOUT_NAMES
                    and "# own output folder" not in lines[node.lineno - 1]
                ):
                    found.append(f"{path.relative_to(root)}:{node.lineno}: / {side.value!r}")
    return found


def test_no_module_but_the_workspace_spells_its_layout():
    """The synthetic town (synth/) has a layout of its own and readers (io/) read the logs' own layouts."""
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE)
        if rel.parts[0] in ("synth", "io") or rel == Path("core/workspace.py"):
            continue
        found += _layout_joins(path)
    assert not found, "workspace paths built outside mapkit/core/workspace.py:\n" + "\n".join(found)


def test_the_layout_check_sees_a_hand_built_path(tmp_path):
    probe = tmp_path / "probe.py"
    probe.write_text("def f(ws, name):\n    return ws / 'sessions' / name / 'map'\n\nx = 'sessions'\n")
    assert _layout_joins(probe, tmp_path) == ["probe.py:2: / 'sessions'"]
