"""The workspace write lock: a second writer is refused (or waits) with the holder named, a killed
holder leaves no stale lock, and one process may take it again inside itself."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from mapkit.core.lock import WorkspaceBusy, read_holder, workspace_lock
from mapkit.core.workspace import Workspace

HOLD = """
import sys, time
from pathlib import Path
from mapkit.core.lock import workspace_lock
with workspace_lock(sys.argv[1], command="mapkit build test-holder"):
    Path(sys.argv[2]).write_text("held")
    time.sleep(float(sys.argv[3]))
"""


def _hold(ws: Path, tmp_path: Path, seconds: float) -> subprocess.Popen:
    """A process that holds the workspace's lock for ``seconds`` (returned once it holds it)."""
    flag = tmp_path / f"held-{time.monotonic_ns()}"
    proc = subprocess.Popen([sys.executable, "-c", HOLD, str(ws), str(flag), str(seconds)])
    t0 = time.monotonic()
    while not flag.exists():
        assert proc.poll() is None, "the holder exited before taking the lock"
        assert time.monotonic() - t0 < 60, "the holder did not take the lock"
        time.sleep(0.05)
    return proc


@contextmanager
def _holder(ws: Path, tmp_path: Path, seconds: float) -> Iterator[subprocess.Popen]:
    """``_hold`` for a ``with`` block: the holder is killed at its end, whatever happened."""
    proc = _hold(ws, tmp_path, seconds)
    try:
        yield proc
    finally:
        proc.kill()
        proc.wait()


def test_second_writer_is_refused_naming_the_holder(tmp_path):
    ws = tmp_path / "ws"
    with _holder(ws, tmp_path, 30) as proc:
        with pytest.raises(WorkspaceBusy) as err, workspace_lock(ws, command="mapkit align"):
            pytest.fail("took a lock another process holds")
        msg = str(err.value)
        assert f"pid {proc.pid}" in msg and "mapkit build test-holder" in msg and str(ws) in msg
        assert read_holder(ws / ".lock")["pid"] == proc.pid


def test_waiter_gets_the_lock_when_the_holder_finishes(tmp_path):
    ws = tmp_path / "ws"
    with _holder(ws, tmp_path, 1.0) as proc, Workspace(ws).lock(command="waiter", wait_s=60):
        assert read_holder(ws / ".lock")["command"] == "waiter"
        assert proc.wait(timeout=30) == 0  # the holder released it by finishing (its exit may trail the release)


def test_killed_holder_leaves_no_stale_lock(tmp_path):
    ws = tmp_path / "ws"
    proc = _hold(ws, tmp_path, 60)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert (ws / ".lock").exists() and read_holder(ws / ".lock")["pid"] == proc.pid  # its record stays ...
    with workspace_lock(ws, command="after the kill"):  # ... but the kernel released its flock
        assert read_holder(ws / ".lock")["command"] == "after the kill"


def _another_process_takes_it(ws: Path) -> bool:
    """Whether a second process gets the workspace's lock at once (it is refused while this one holds it)."""
    code = "import sys\nfrom mapkit.core.lock import workspace_lock\nwith workspace_lock(sys.argv[1]): print('ok')"
    out = subprocess.run([sys.executable, "-c", code, str(ws)], capture_output=True, text=True)
    assert out.returncode == 0 and out.stdout.strip() == "ok" or "WorkspaceBusy" in out.stderr, out.stderr
    return out.returncode == 0


def test_reentrant_in_one_process_and_released_after(tmp_path):
    ws = tmp_path / "ws"
    with workspace_lock(ws, command="outer"):
        with workspace_lock(ws, command="inner"):
            assert read_holder(ws / ".lock")["command"] == "outer"
        # leaving the inner block keeps the lock, and the outer holder's record
        assert read_holder(ws / ".lock")["command"] == "outer"
        assert not _another_process_takes_it(ws)
    assert read_holder(ws / ".lock") == {}
    assert _another_process_takes_it(ws)  # released: another process takes it at once


def test_second_cli_writer_refuses_with_one_line_and_writes_nothing(tmp_path, capsys):
    """Two commands into one workspace (two builds at once): the second exits 2 with the
    holder named and touches nothing; with --wait it runs once the first is done."""
    from mapkit.cli import main

    ws = tmp_path / "ws"
    with _holder(ws, tmp_path, 30) as proc:
        before = sorted(p.name for p in ws.iterdir())
        assert main(["build", str(tmp_path / "no-such.mcap"), "--out", str(ws)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and f"pid {proc.pid}" in err[0] and "being written" in err[0]
        assert sorted(p.name for p in ws.iterdir()) == before  # no build_config.yaml, no sessions/
    with _holder(
        ws, tmp_path, 1.0
    ) as proc:  # waiting: the lock is taken after the holder ends, then the build reports its own error
        assert main(["--wait", "60", "build", str(tmp_path / "no-such.mcap"), "--out", str(ws)]) == 2
        assert "no-such.mcap: no such" in capsys.readouterr().err
        assert proc.wait(timeout=30) == 0


# --- the library takes the lock itself --------------------------------------------------------------


def _all_writers() -> list:
    """Every entry point registered by ``writes_workspace``, once every module that defines one is imported."""
    import importlib
    import pkgutil

    import mapkit
    from mapkit.core.writers import WRITERS

    for info in pkgutil.walk_packages(mapkit.__path__, "mapkit."):
        if info.name != "mapkit.__main__":
            importlib.import_module(info.name)

    return list(WRITERS)


def _a_workspace(root: Path) -> Path:
    root.mkdir(parents=True)
    Workspace(root).build_config.write_text("{}\n")
    return root


def _listing(root: Path) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*") if p.name != ".lock")


def test_every_library_writer_refuses_while_another_process_writes(tmp_path):
    """Through the Python API, as a user's script calls it: every entry point that writes into a workspace
    refuses with the holder named while another process holds the workspace, and writes nothing."""
    from mapkit.core.writers import enclosing_workspace

    ws = _a_workspace(tmp_path / "ws")
    writers = _all_writers()
    assert len(writers) >= 16
    with _holder(ws, tmp_path, 60) as proc:
        before = _listing(ws)
        for fn in writers:
            arg = fn.__mapkit_locks__
            target = ws / "out" if arg == "out" else ws  # an output folder inside the workspace
            with pytest.raises(WorkspaceBusy, match=f"pid {proc.pid}"):
                fn(**{arg: target})
            assert _listing(ws) == before, fn.__qualname__
    assert enclosing_workspace(ws / "a" / "b") == ws.resolve() and enclosing_workspace(tmp_path) is None


def test_an_output_outside_any_workspace_takes_no_lock(tmp_path):
    """`mapkit localize` and `mapkit train` lock only the workspace their output lies in: elsewhere they run."""
    from mapkit.learning.train import train_cnn

    ws = _a_workspace(tmp_path / "ws")
    with _holder(ws, tmp_path, 60), pytest.raises(Exception) as err:
        train_cnn(tmp_path / "no-dataset", tmp_path / "model")
    assert not isinstance(err.value, WorkspaceBusy)


def test_mapkit_localize_into_a_workspace_being_built_is_refused(tmp_path, capsys):
    from mapkit.cli import main

    ws = _a_workspace(tmp_path / "ws")
    with _holder(ws, tmp_path, 60) as proc:
        before = _listing(ws)
        code = main(["localize", str(tmp_path / "bundle"), str(tmp_path / "drive.mcap"), "--out", str(ws / "loc")])
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(err) == 1 and f"pid {proc.pid}" in err[0]
        assert _listing(ws) == before


def test_every_cli_write_goes_through_a_locking_entry_point():
    """Structural: each library function a writing CLI command calls with the workspace it writes is a registered
    writer, so the lock does not depend on the CLI."""
    import ast
    import importlib
    import inspect

    import mapkit.cli

    _all_writers()
    tree = ast.parse(Path(mapkit.cli.__file__).read_text())
    called = set()
    for cmd in tree.body:
        if not isinstance(cmd, ast.FunctionDef):
            continue
        locks = [
            d.args[0].value
            for d in cmd.decorator_list
            if isinstance(d, ast.Call)
            and getattr(d.func, "id", "") == "_writes"
            and isinstance(d.args[0], ast.Constant)
        ]
        if not locks:
            continue
        imported = {
            a.asname or a.name: (node.module, a.name)
            for node in ast.walk(cmd)
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("mapkit.")
            for a in node.names
        }
        for node in ast.walk(cmd):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in imported:
                names = {a.id for a in [*node.args, *(k.value for k in node.keywords)] if isinstance(a, ast.Name)}
                module, name = imported[node.func.id]
                fn = getattr(importlib.import_module(module), name)
                if locks[0] in names and inspect.isfunction(fn):
                    called.add(fn)
    assert len(called) >= 10
    unlocked = sorted(f"{fn.__module__}.{fn.__name__}" for fn in called if not hasattr(fn, "__mapkit_locks__"))
    assert unlocked == []


def test_a_session_builder_on_a_held_workspace_refuses_before_it_empties_a_stage(tmp_path):
    """SessionBuilder is public: run while another process writes the workspace, it refuses with the holder named,
    and a stage it would re-make (its marker gone) is not emptied first."""
    import warnings

    from test_build import _imageless_log

    from mapkit.core.errors import InputWarning
    from mapkit.core.runio import DONE_MARKER
    from mapkit.mapping.build import BuildConfig, SessionBuilder, build

    log = _imageless_log(tmp_path / "drive.mcap")
    os.utime(log, (time.time() - 3600,) * 2)  # a log that finished being written
    ws = tmp_path / "ws"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputWarning)  # the image stages are skipped: this log has no camera
        build([log], ws, progress=False)
    (Workspace(ws).session("drive").trajectory / DONE_MARKER).unlink()
    with _holder(ws, tmp_path, 60) as proc:
        before = _listing(ws)
        with pytest.raises(WorkspaceBusy, match=f"pid {proc.pid}"), warnings.catch_warnings():
            warnings.simplefilter("ignore", InputWarning)
            SessionBuilder(log, ws, BuildConfig(), progress=False).run()
        assert _listing(ws) == before


def test_a_worker_writes_under_its_parents_lock_only_with_its_token(tmp_path):
    """A worker process that the holder started adopts the holder's lock by its token (build's sessions on a pool);
    a process with another token, or none, is refused as any second writer is."""
    from mapkit.core.lock import lock_token

    ws = _a_workspace(tmp_path / "ws")
    worker = (
        "import sys\n"
        "from mapkit.core.lock import adopted_lock, workspace_lock\n"
        "token = sys.argv[2] or None\n"
        "with adopted_lock(sys.argv[1], token), workspace_lock(sys.argv[1]):\n"
        "    print('wrote')\n"
    )
    with workspace_lock(ws, command="mapkit build parent"):
        token = lock_token(ws)
        assert token is not None and read_holder(ws / ".lock")["token"] == token
        runs = {
            t: subprocess.run([sys.executable, "-c", worker, str(ws), t], capture_output=True, text=True, timeout=60)
            for t in (token, "0" * 16, "")
        }
    assert runs[token].returncode == 0 and runs[token].stdout.strip() == "wrote"
    for t in ("0" * 16, ""):
        assert runs[t].returncode != 0 and "WorkspaceBusy" in runs[t].stderr and "mapkit build parent" in runs[t].stderr
    assert lock_token(ws) is None  # released: the token is gone with the lock
