"""An advisory lock that lets one writer at a time into a workspace.

Every command that writes a workspace holds ``WORKSPACE/.lock`` for its whole run: an exclusive
``flock`` on that file (released by the kernel when the process dies, so a killed run never leaves
a stale lock), whose text names the holder (pid, host, command, start time) for the message the
next writer sees. A second writer refuses at once with that message, or waits up to ``wait_s``.

The lock is re-entrant within a process (a pipeline that calls ``build`` and then ``align`` takes
it once; threads of one process share it). A worker process that a holder starts (``build``'s
sessions on a process pool or Ray) is not given the flock; it works under its parent's lock by
:func:`adopted_lock` with the holder's token (:func:`lock_token`), which the lock file records, so
the library's own entry points called inside the worker find the lock held. It is advisory: it
keeps mapkit's writers from each other, not an editor.
"""

from __future__ import annotations

import errno
import fcntl
import json
import os
import secrets
import socket
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from mapkit.core.errors import MapkitError

LOCK_NAME = ".lock"

_held: dict[Path, tuple[int, int]] = {}  # resolved lock path -> (fd, depth), this process only
_tokens: dict[Path, str] = {}  # resolved lock path -> the token this process's holder wrote
_adopted: dict[Path, int] = {}  # resolved lock path -> depth, locks a worker works under for its parent
_guard = threading.Lock()


class WorkspaceBusy(MapkitError):
    """Another process is writing the workspace."""

    def __init__(self, lock_path: Path, holder: dict, waited_s: float):
        self.lock_path = lock_path
        self.holder = holder
        who = describe_holder(holder)
        waited = f" after waiting {waited_s:.0f} s" if waited_s > 0 else ""
        super().__init__(
            f"{lock_path.parent}: the workspace is being written by {who}{waited}; "
            "wait for it to finish (or pass --wait SECONDS), then run again"
        )


def describe_holder(holder: dict) -> str:
    if not holder:
        return "another process (no holder recorded)"
    cmd = holder.get("command") or "?"
    return f"pid {holder.get('pid', '?')} on {holder.get('host', '?')} ({cmd}), since {holder.get('started', '?')}"


def read_holder(lock_path: Path) -> dict:
    """What the current holder wrote into the lock file ({} when empty or unreadable)."""
    try:
        return json.loads(lock_path.read_text() or "{}")
    except (OSError, ValueError):
        return {}


def _command_line() -> str:
    argv = [Path(sys.argv[0]).name, *sys.argv[1:]] if sys.argv and sys.argv[0] else []
    return " ".join(argv)[:300]


@contextmanager
def workspace_lock(
    root: str | os.PathLike, command: str | None = None, wait_s: float = 0.0, poll_s: float = 0.2
) -> Iterator[Path]:
    """Hold the workspace's write lock for the ``with`` block (the folder is created if need be).

    Raises :class:`WorkspaceBusy` naming the holder when another process holds it for longer
    than ``wait_s`` seconds.
    """
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    path = (root / LOCK_NAME).resolve()
    with _guard:
        if path in _held:  # re-entrant in this process
            fd, depth = _held[path]
            _held[path] = (fd, depth + 1)
            reentered = True
        else:
            reentered = False
        adopted = path in _adopted
    if reentered:
        try:
            yield path
        finally:
            _release(path)
        return
    if adopted:  # a worker under its parent's lock
        yield path
        return
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    t0 = time.monotonic()
    try:
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except OSError as exc:
                if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                    raise
                waited = time.monotonic() - t0
                if waited >= wait_s:
                    raise WorkspaceBusy(path, read_holder(path), waited) from None
                time.sleep(min(poll_s, max(wait_s - waited, 0.01)))
        token = secrets.token_hex(8)
        holder = {
            "pid": os.getpid(),
            "token": token,
            "host": socket.gethostname(),
            "command": command or _command_line(),
            "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        }
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(holder).encode(), 0)
    except BaseException:
        os.close(fd)
        raise
    with _guard:
        _held[path] = (fd, 1)
        _tokens[path] = token
    try:
        yield path
    finally:
        _release(path)


def lock_token(root: str | os.PathLike) -> str | None:
    """The token of the lock this process holds on workspace ``root`` (None when it holds none): what a
    worker it starts needs for :func:`adopted_lock`."""
    path = (Path(root) / LOCK_NAME).resolve()
    with _guard:
        return _tokens.get(path) if path in _held else None


@contextmanager
def adopted_lock(root: str | os.PathLike, token: str | None) -> Iterator[None]:
    """In a worker process: work under the lock that the process which started it holds on ``root`` (its
    ``token``, from :func:`lock_token`), so that entry points called here find it held. Without a token
    (the parent held no lock) nothing is adopted. Raises :class:`WorkspaceBusy` when the lock file no
    longer names that token: the parent's lock is gone, and writing now would race another writer."""
    if token is None:
        yield
        return
    path = (Path(root) / LOCK_NAME).resolve()
    holder = read_holder(path)
    if holder.get("token") != token:
        raise WorkspaceBusy(path, holder, 0.0)
    with _guard:
        _adopted[path] = _adopted.get(path, 0) + 1
    try:
        yield
    finally:
        with _guard:
            _adopted[path] -= 1
            if not _adopted[path]:
                del _adopted[path]


def _release(path: Path) -> None:
    with _guard:
        fd, depth = _held[path]
        if depth > 1:
            _held[path] = (fd, depth - 1)
            return
        del _held[path]
        _tokens.pop(path, None)
    try:
        os.ftruncate(fd, 0)  # the file stays (removing it would race a waiter that opened it)
    finally:
        os.close(fd)  # closing the last descriptor releases the flock
