"""The library's entry points that write a workspace take its lock themselves.

Each public function that writes into a workspace is decorated with :func:`writes_workspace`: it
holds the workspace's write lock (:mod:`mapkit.core.lock`) for the whole call, so the CLI, the
pipelines, the benches and a user's own script are kept from each other alike. The lock is
re-entrant within a process, so an entry point that calls another takes it once.

A function whose output folder may lie inside a workspace (``mapkit localize``, ``mapkit train``)
locks the workspace that holds that folder, and nothing when none does.
"""

from __future__ import annotations

import functools
import inspect
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

from mapkit.core.lock import LOCK_NAME, workspace_lock
from mapkit.core.workspace import ORIGIN, SessionDirs, Workspace

F = TypeVar("F", bound=Callable[..., Any])

#: every function decorated with :func:`writes_workspace`, in the order they were imported
WRITERS: list[Callable[..., Any]] = []

_wait_s = 0.0


def set_lock_wait(seconds: float) -> None:
    """How long an entry point waits for another writer's lock before it refuses (``mapkit --wait``)."""
    global _wait_s
    _wait_s = max(0.0, float(seconds))


def lock_wait() -> float:
    return _wait_s


def is_workspace(folder: Path) -> bool:
    """Whether ``folder`` is a workspace that ``mapkit build`` wrote into (its origin or its build config)."""
    return (folder / ORIGIN).is_file() or Workspace(folder).build_config.is_file()


def enclosing_workspace(path: str | os.PathLike) -> Path | None:
    """The workspace that holds ``path`` (``path`` itself or a folder above it), None when none does."""
    p = Path(path).resolve()
    return next((d for d in (p, *p.parents) if is_workspace(d)), None)


def writes_workspace(
    arg: str = "workspace", *, creates: bool = False, within: bool = False, default: str = ""
) -> Callable[[F], F]:
    """Decorate an entry point that writes the workspace given as its argument ``arg`` (a path, a
    :class:`Workspace`, or with ``within`` a folder in one, such as a session's :class:`SessionDirs`).

    - ``creates``: the function makes the workspace when it does not exist (``build``), so the lock
      is taken on the new folder; otherwise a missing folder is left for the function to report;
    - ``within``: ``arg`` is an output folder; the lock is of the workspace that holds it, if any;
    - ``default``: when ``arg`` is None, the argument to use instead (an output that defaults to a
      folder of the workspace).
    """

    def wrap(fn: F) -> F:
        sig = inspect.signature(fn)
        if arg not in sig.parameters or (default and default not in sig.parameters):
            raise TypeError(f"{fn.__qualname__} has no argument {arg!r} (or {default!r}) to lock")

        def argument(bound: inspect.BoundArguments, name: str) -> Any:
            return bound.arguments.get(name, sig.parameters[name].default)

        def root_of(bound: inspect.BoundArguments) -> Path | None:
            value = argument(bound, arg)
            if value is None and default:
                value = argument(bound, default)
            if value is None or value is inspect.Parameter.empty:
                return None
            path = Path(value.root if isinstance(value, (Workspace, SessionDirs)) else value)
            if within:
                return enclosing_workspace(path)
            return path if creates or path.is_dir() else None

        @functools.wraps(fn)
        def run(*args: Any, **kwargs: Any) -> Any:
            root = root_of(sig.bind_partial(*args, **kwargs))
            if root is None:
                return fn(*args, **kwargs)
            new = not root.exists()
            try:
                with workspace_lock(root, wait_s=_wait_s):
                    return fn(*args, **kwargs)
            except BaseException:
                if new:  # a workspace refused before anything was written leaves no folder behind
                    _remove_if_only_the_lock(root)
                raise

        run.__mapkit_locks__ = arg  # type: ignore[attr-defined]
        WRITERS.append(run)
        return run  # type: ignore[return-value]

    return wrap


def _remove_if_only_the_lock(root: Path) -> None:
    try:
        if [p.name for p in root.iterdir()] == [LOCK_NAME]:
            (root / LOCK_NAME).unlink()
            root.rmdir()
    except OSError:
        pass  # another writer came in meanwhile: its folder stays
