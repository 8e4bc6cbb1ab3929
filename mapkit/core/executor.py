"""One interface for per-item work: in this process, in a local process pool, or on Ray.

Per-frame and per-patch work (image encoding, semi-dense depth per keyframe, ICP of submap pairs,
patch description) goes through :meth:`Executor.map`::

    for result in executor.map(fn, items, shared=vocabulary, progress=True, desc="encode"):
        ...

- Results come back **in input order**, whichever executor ran them and however the items were
  chunked, so a caller that reduces them in that order gets bit-identical output from all of them.
  Any randomness in ``fn`` must come from the item (a per-item seed), never from worker state.
- ``shared`` is read-only state that every call needs (a vocabulary, the point clouds of a map).
  It is shipped **once per worker**: through a temporary file each process reads once, with one
  ``ray.put`` per ``map`` for Ray (each worker process deserialises it once and keeps it). With
  ``shared`` given, ``fn(shared, item)`` is called; without, ``fn(item)``.
- The first failing item in input order stops the map: the results before it are yielded, then a
  :class:`TaskError` names the item (its index and a short description) and carries the original
  exception as ``cause``. Errors raised while *producing* the items (``items`` may be a lazy
  generator) pass through unchanged, after the results of the items produced before them.
- ``items`` is consumed lazily, with at most a few chunks per worker in flight, so a streaming
  producer (the semi-dense frame window) keeps its memory bound.

Implementations: :class:`SerialExecutor` (in this process), :class:`ProcessExecutor` (spawned
processes, one BLAS/OpenMP thread each) and :class:`RayExecutor` (``pip install -e
".[distributed]"``; a running cluster's address or a local instance). :func:`make_executor` builds
one by name; :func:`use_executor` / :func:`set_default_executor` set the process-wide default that
:func:`get_executor` returns to callers that were not given one (the CLI sets it once per run).

With processes or Ray, ``fn`` must be importable by name (a module-level function, not a lambda or
closure), and on a Ray cluster mapkit must be installed on every node.
"""

from __future__ import annotations

import atexit
import contextlib
import itertools
import logging
import multiprocessing.context
import os
import pickle
import sys
import traceback
import uuid
from collections import deque
from collections.abc import Callable, Generator, Iterable, Iterator, Sequence
from typing import Any, Literal

from pydantic import Field

from mapkit.core.config import MapkitConfig, load_config
from mapkit.core.errors import ConfigError, MapkitError

ExecutorKind = Literal["local", "ray"]
_ONE_THREAD_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
_IN_FLIGHT_PER_WORKER = 2  # chunks queued per worker: one running, one ready to start
_RAY_CHUNKS_PER_WORKER = 4  # a Ray map is cut into about this many chunks per CPU (load balance vs. per-task overhead)
_RAY_MAX_CHUNK = 64
_LOOPBACK = "127.0.0.1"

_log = logging.getLogger(__name__)


class ExecutorConfig(MapkitConfig):
    """Where per-item work runs (``mapkit --executor/--workers/--ray-address``)."""

    kind: ExecutorKind = Field(
        "local", description="'local': this process (workers = 1) or a pool of spawned processes; 'ray': Ray."
    )
    workers: int | None = Field(
        None,
        ge=1,
        description="Processes (local) or CPUs of a local Ray instance. None = the cores available to this process; "
        "ignored when joining a running Ray cluster, whose size is its own.",
    )
    address: str | None = Field(
        None,
        description="Ray only: a running cluster ('auto' or 'HOST:PORT'); None = start a local instance for this run "
        "(on 127.0.0.1, whatever RAY_ADDRESS says).",
    )


class TaskError(MapkitError):
    """An item's call failed. ``index`` is its position in the input, ``item`` a short description
    of it, ``cause`` the original exception (rebuilt in this process when it ran elsewhere) and
    ``remote_traceback`` the worker's traceback text (empty when it ran here)."""

    def __init__(
        self,
        desc: str,
        index: int,
        item: str,
        cause: BaseException | None,
        cause_text: str,
        remote_traceback: str = "",
    ):
        self.index, self.item, self.cause, self.remote_traceback = index, item, cause, remote_traceback
        super().__init__(f"{desc or 'task'} failed on item {index} ({item}): {cause_text}")


# --------------------------------------------------------------------------- running one item (in any process)


class _NO_SHARED:  # noqa: N801 - a marker; a class, so that it keeps its identity through pickling
    """``map`` was given no shared state: call ``fn(item)``."""


class _Failure:
    """A failed call as a value: travels back from a worker, where exceptions may not unpickle."""

    def __init__(self, exc: BaseException, remote: bool):
        self.text = f"{type(exc).__name__}: {exc}"
        self.traceback = "".join(traceback.format_exception(exc)) if remote else ""
        self.exc: BaseException | None = exc
        if remote:
            # rebuilt without calling __init__ (InputError's signature is not its args); dropped if
            # its class or state cannot travel
            self.exc = None
            self.rebuild: tuple[type[BaseException], tuple[Any, ...], dict[str, Any]] | None = (
                type(exc),
                exc.args,
                dict(getattr(exc, "__dict__", {})),
            )
            try:
                pickle.loads(pickle.dumps(self.rebuild))
            except Exception:  # noqa: BLE001 - whatever the exception holds, the text still travels
                self.rebuild = None

    def exception(self) -> BaseException | None:
        rebuild = getattr(self, "rebuild", None)
        if self.exc is None and rebuild is not None:
            cls, args, state = rebuild
            try:
                exc = cls.__new__(cls, *args)
                exc.args = args
                exc.__dict__.update(state)
                if sys.version_info >= (3, 11):  # exceptions have notes from Python 3.11 on
                    exc.add_note(f"raised in a worker:\n{self.traceback}")
            except Exception:  # noqa: BLE001 - the text names it anyway
                return None
            self.exc = exc
        return self.exc


def _run_items(fn: Callable, items: Sequence, shared: Any, remote: bool) -> list:
    """``fn`` over a chunk of items; stops at the first failure, which ends the list as a _Failure."""
    out: list = []
    for item in items:
        try:
            out.append(fn(item) if shared is _NO_SHARED else fn(shared, item))
        except Exception as exc:  # noqa: BLE001 - reported to the caller with the item named
            out.append(_Failure(exc, remote))
            break
    return out


def _describe(item: Any, limit: int = 100) -> str:
    text = repr(item)
    return text if len(text) <= limit else text[: limit - 3] + "..."


# --------------------------------------------------------------------------- the interface


class Executor:
    """Runs ``fn`` over items; see the module docstring for the contract every implementation keeps."""

    kind: str = "serial"
    #: tasks run in the calling process (nothing is pickled): callers may pass cached objects
    in_process: bool = True

    @property
    def workers(self) -> int:
        return 1

    def map(
        self,
        fn: Callable,
        items: Iterable,
        *,
        shared: Any = None,
        progress: bool = False,
        desc: str = "",
        unit: str = "item",
        label: Callable[[Any], str] | None = None,
        chunksize: int | None = None,
    ) -> Generator[Any, None, None]:
        """Results of ``fn(item)`` (or ``fn(shared, item)``) in the order of ``items``.

        ``label(item)`` describes a failed item in the :class:`TaskError` (default: its repr,
        shortened). ``chunksize`` items travel per task (default: the executor's choice).
        """
        total = len(items) if hasattr(items, "__len__") else None  # type: ignore[arg-type]
        return self._ordered(
            fn,
            iter(items),
            total,
            _NO_SHARED if shared is None else shared,
            progress,
            desc,
            unit,
            label or _describe,
            chunksize,
        )

    def _ordered(
        self, fn, it: Iterator, total, shared, progress, desc, unit, label, chunksize
    ) -> Generator[Any, None, None]:
        raise NotImplementedError

    def close(self) -> None:
        """Release workers or the cluster connection (the executor may not be used afterwards)."""

    def __enter__(self) -> Executor:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"{type(self).__name__}(workers={self.workers})"


def _raise_failure(f: _Failure, desc: str, index: int, item: Any, label: Callable) -> None:
    exc = f.exception()
    raise TaskError(desc, index, label(item), exc, f.text, f.traceback) from exc


class SerialExecutor(Executor):
    """Every call in this process, one after the other; OpenBLAS held to one thread meanwhile.

    One BLAS thread because the per-item products are small and, on a loaded machine, BLAS threads
    spinning against other work made VLAD encoding 4.6x slower (0.41 vs 0.09 s per half-resolution
    KITTI frame, measured); and so that a worker process and this one compute alike.
    """

    def __init__(self, single_thread_blas: bool = True):
        self.single_thread_blas = single_thread_blas

    def _ordered(
        self, fn, it: Iterator, total, shared, progress, desc, unit, label, chunksize
    ) -> Generator[Any, None, None]:
        from mapkit.core.runio import progress_bar
        from mapkit.core.threads import single_thread_blas

        bar = progress_bar(total, progress, desc, unit)
        with contextlib.ExitStack() as stack:
            stack.callback(bar.close)
            if self.single_thread_blas:
                stack.enter_context(single_thread_blas())
            for index in itertools.count():
                try:
                    item = next(it)
                except StopIteration:
                    return
                (r,) = _run_items(fn, (item,), shared, remote=False)
                if isinstance(r, _Failure):
                    _raise_failure(r, desc, index, item, label)
                del item  # a streaming producer's memory bound must not count the previous item
                bar.update(1)
                yield r


class _Pending:
    """A submitted chunk: its first item's index, its items (to name a failure) and a handle."""

    __slots__ = ("start", "items", "handle")

    def __init__(self, start: int, items: list, handle: Any):
        self.start, self.items, self.handle = start, items, handle


class _ChunkedExecutor(Executor):
    """Ordered, bounded, lazily fed chunk submission shared by the process pool and Ray."""

    in_process = False

    def _default_chunksize(self, total: int | None) -> int:
        return 1

    def _start(self, fn, shared, n_chunks: int | None) -> Any:
        raise NotImplementedError

    def _submit(self, state, fn, chunk: list, shared) -> Any:
        raise NotImplementedError

    def _result(self, state, handle) -> list:
        raise NotImplementedError

    def _stop(self, state, pending: deque, failed: bool) -> None:
        raise NotImplementedError

    def _ordered(
        self, fn, it: Iterator, total, shared, progress, desc, unit, label, chunksize
    ) -> Generator[Any, None, None]:
        from mapkit.core.runio import progress_bar

        try:
            pickle.dumps(fn)
        except Exception as exc:  # noqa: BLE001 (pickling can raise any exception type; each means the same)
            raise ConfigError(
                f"{desc or 'map'}: {fn!r} cannot be sent to worker processes ({exc}); use a module-level function"
            ) from None
        size = max(1, int(chunksize or self._default_chunksize(total)))
        try:
            first = next(it)  # no workers for nothing (an error here has no results before it)
        except StopIteration:
            return
        it = itertools.chain([first], it)
        del first
        n_chunks = None if total is None else -(-total // size)
        bar = progress_bar(total, progress, desc, unit)
        state = self._start(fn, shared, n_chunks)
        pending: deque[_Pending] = deque()
        failed = True
        exhausted = False
        produce_error: BaseException | None = None
        index = 0
        try:
            while True:
                # keep the workers fed; an error of the producer waits until the results before it are out
                while not exhausted and produce_error is None and len(pending) < _IN_FLIGHT_PER_WORKER * self.workers:
                    chunk: list = []
                    try:
                        while len(chunk) < size:
                            chunk.append(next(it))
                    except StopIteration:
                        exhausted = True
                    except Exception as exc:  # noqa: BLE001 - re-raised below, in order
                        produce_error = exc
                    if chunk:
                        pending.append(_Pending(index, chunk, self._submit(state, fn, chunk, shared)))
                        index += len(chunk)
                    del chunk
                if not pending:
                    break
                head = pending.popleft()
                results = self._result(state, head)
                if len(results) != len(head.items) and not isinstance(results[-1], _Failure):
                    raise MapkitError(
                        f"{desc or 'map'}: a worker returned {len(results)} results for {len(head.items)} items"
                    )
                for k, r in enumerate(results):
                    if isinstance(r, _Failure):
                        _raise_failure(r, desc, head.start + k, head.items[k], label)
                    bar.update(1)
                    yield r
                del head, results
            failed = False
        finally:
            # a consumer that stops right after the last result (zip with a list of the same
            # length) leaves nothing in flight: the workers are let go, not terminated
            self._stop(state, pending, failed and not (exhausted and not pending))
            bar.close()
        if produce_error is not None:
            raise produce_error


# --------------------------------------------------------------------------- local processes

_WORKER_SHARED: dict[str, Any] = {}


def exit_with_parent(poll_s: float = 0.5) -> None:
    """End this worker process as soon as its parent is gone (killed: no pool shutdown reaches the workers), instead
    of letting it finish its task and write into a run that was stopped. A daemon thread compares the parent's pid
    every ``poll_s`` seconds."""
    import threading
    import time

    parent = os.getppid()

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(poll_s)
        os._exit(1)

    threading.Thread(target=watch, name="mapkit-parent-watch", daemon=True).start()


def _process_init() -> None:
    import cv2

    exit_with_parent()
    cv2.setNumThreads(1)
    _WORKER_SHARED.clear()


def _process_chunk(fn: Callable, items: list, token: str | None, path: str | None) -> list:
    """A chunk of a map in a worker: the map's ``shared`` is read from its file once per worker (by the map's token)
    and replaces the previous map's (a kept pool's workers serve map after map)."""
    if token is None:
        return _run_items(fn, items, _NO_SHARED, remote=True)
    if _WORKER_SHARED.get("token") != token:
        _WORKER_SHARED.clear()
        with open(path, "rb") as f:  # type: ignore[arg-type]
            _WORKER_SHARED["value"] = pickle.load(f)
        _WORKER_SHARED["token"] = token
    return _run_items(fn, items, _WORKER_SHARED["value"], remote=True)


@contextlib.contextmanager
def _one_thread_env() -> Iterator[None]:
    """Spawned workers inherit the environment: one BLAS/OpenMP thread each (set before they import numpy)."""
    saved = {n: os.environ.get(n) for n in _ONE_THREAD_ENV}
    os.environ.update(_ONE_THREAD_ENV)
    try:
        yield
    finally:
        for n, v in saved.items():
            if v is None:
                os.environ.pop(n, None)
            else:
                os.environ[n] = v


class _OneThreadSpawnProcess(multiprocessing.context.SpawnProcess):
    """A spawned process started in the one-thread environment (the pool starts its workers as work arrives)."""

    def start(self) -> None:
        with _one_thread_env():
            super().start()


class _OneThreadSpawnContext(multiprocessing.context.SpawnContext):
    Process = _OneThreadSpawnProcess


class ProcessExecutor(_ChunkedExecutor):
    """A pool of ``workers`` spawned processes, one BLAS/OpenMP/OpenCV thread each.

    Spawned, not forked: a fork of a process that holds OpenMP, open3d or faiss threads can
    deadlock. Each map's ``shared`` travels through a temporary file, read once per worker (which
    keeps it until its next map). By default the pool lives for one ``map``: nothing outlives the
    call. With ``keep_pool``, the executor's owner (:func:`use_executor`,
    :func:`set_default_executor`, the CLI) keeps one pool for every map until :meth:`close`: a worker
    spawns and imports once per run instead of once per map (about a second each). It is a
    ``concurrent.futures.ProcessPoolExecutor``: a map abandoned half-way kills its workers (a kept
    pool is then started afresh by the next map), and that pool notices dead workers, where
    ``multiprocessing.Pool.terminate`` waits forever for a queue lock that a worker killed in the
    middle of sending its result still holds.
    """

    kind = "process"

    def __init__(self, workers: int = 2, keep_pool: bool = False):
        if workers < 1:
            raise ConfigError(f"workers must be >= 1, got {workers}")
        self._workers = int(workers)
        self.keep_pool = bool(keep_pool)
        self._pool: Any = None

    @property
    def workers(self) -> int:
        return self._workers

    def _start(self, fn, shared, n_chunks):
        from concurrent.futures import ProcessPoolExecutor

        pool = self._pool
        if pool is None:
            n = self._workers if n_chunks is None or self.keep_pool else max(1, min(self._workers, n_chunks))
            pool = ProcessPoolExecutor(n, mp_context=_OneThreadSpawnContext(), initializer=_process_init)
            if self.keep_pool:
                self._pool = pool
        if shared is _NO_SHARED:
            return pool, None, None
        import tempfile

        fd, path = tempfile.mkstemp(prefix="mapkit-shared-", suffix=".pkl")
        with os.fdopen(fd, "wb") as f:
            pickle.dump(shared, f, protocol=pickle.HIGHEST_PROTOCOL)
        return pool, uuid.uuid4().hex, path

    def _submit(self, state, fn, chunk, shared):
        pool, token, path = state
        return pool.submit(_process_chunk, fn, chunk, token, path)

    def _result(self, state, head):
        return head.handle.result()

    def _stop(self, state, pending, failed):
        pool, _, path = state
        try:
            if failed:  # what is in flight is not waited for: its workers are killed (SIGKILL: no handler runs)
                for proc in list((pool._processes or {}).values()):
                    proc.kill()
                pool.shutdown(wait=True, cancel_futures=True)
                if pool is self._pool:
                    self._pool = None  # the next map starts a fresh one
            elif pool is not self._pool:
                pool.shutdown(wait=True)
        finally:
            if path is not None:
                with contextlib.suppress(OSError):
                    os.unlink(path)

    def close(self) -> None:
        """Let a kept pool's workers go (a later map starts a new one)."""
        pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=True)


# --------------------------------------------------------------------------- Ray

_RAY_SHARED: dict[str, Any] = {}


def _ray_chunk(fn: Callable, items: list, token: str | None, shared_box: list | None) -> list:
    """Runs in a Ray worker: ``shared`` is fetched from the object store once per worker process."""
    if not _RAY_SHARED.get("configured"):  # BLAS and OpenMP: one thread by the job's environment (see RayExecutor)
        import cv2

        cv2.setNumThreads(1)
        _RAY_SHARED["configured"] = True
    shared: Any
    if token is None:
        shared = _NO_SHARED
    elif _RAY_SHARED.get("token") == token:
        shared = _RAY_SHARED["value"]
    else:
        import ray

        assert shared_box is not None  # _start gives a box with every token
        shared = ray.get(shared_box[0])
        _RAY_SHARED.update(token=token, value=shared)  # only the latest: a finished map's state is let go
    return _run_items(fn, items, shared, remote=True)


class RayExecutor(_ChunkedExecutor):
    """Ray tasks: a running cluster (``address``) or a local instance of ``workers`` CPUs.

    Ray is imported and started at construction. Without ``address`` a fresh instance is always
    started (``ray.init(address="local")``): neither ``RAY_ADDRESS`` nor the cluster a ``ray start``
    left recorded in Ray's temp folder is joined, and the instance is bound to the loopback
    interface (GCS, raylet, object manager, workers and agents listen on 127.0.0.1 only; no
    dashboard). Items travel in chunks (about four per CPU, at most 64 items each) so that the
    per-task overhead (a few ms) is amortised; ``shared`` is put into the object store once per
    ``map``. A local instance started here is shut down by ``close``; a cluster that was already
    running is only disconnected from.
    """

    kind = "ray"

    def __init__(self, workers: int | None = None, address: str | None = None):
        try:
            import ray
        except ImportError:
            raise MapkitError('the Ray executor needs Ray: pip install -e ".[distributed]"') from None
        self._ray = ray
        self._owns = False
        runtime_env = {"env_vars": dict(_ONE_THREAD_ENV)}
        if not ray.is_initialized():
            kwargs: dict[str, Any] = dict(
                runtime_env=runtime_env, include_dashboard=False, log_to_driver=False, configure_logging=False
            )
            if address:
                ray.init(address=address, **kwargs)
            else:
                # the driver's import path, so that workers find what it finds (a checkout, tests)
                env = dict(runtime_env["env_vars"], PYTHONPATH=os.pathsep.join(p for p in _import_path() if p))
                with _ray_loopback_only():
                    ray.init(
                        address="local",
                        num_cpus=workers,
                        _node_ip_address=_LOOPBACK,
                        **dict(kwargs, runtime_env={"env_vars": env}),
                    )
            self._owns = True
        cpus = int(ray.cluster_resources().get("CPU", 1))
        self._workers = max(1, cpus)
        self._remote = ray.remote(num_cpus=1)(_ray_chunk)

    @property
    def workers(self) -> int:
        return self._workers

    def _default_chunksize(self, total):
        if total is None:
            return 1
        return max(1, min(_RAY_MAX_CHUNK, total // (_RAY_CHUNKS_PER_WORKER * self._workers)))

    def _start(self, fn, shared, n_chunks):
        if shared is _NO_SHARED:
            return None, None
        return uuid.uuid4().hex, [self._ray.put(shared)]

    def _submit(self, state, fn, chunk, shared):
        token, box = state
        return self._remote.remote(fn, chunk, token, box)

    def _result(self, state, head):
        try:
            return self._ray.get(head.handle)
        except self._ray.exceptions.RayError as exc:
            end = head.start + len(head.items) - 1
            raise MapkitError(f"Ray lost the task of items {head.start}..{end}: {type(exc).__name__}: {exc}") from exc

    def _stop(self, state, pending, failed):
        if failed:
            for p in pending:
                with contextlib.suppress(Exception):
                    self._ray.cancel(p.handle)

    def close(self) -> None:
        if self._owns and self._ray.is_initialized():
            self._ray.shutdown()
        self._owns = False


@contextlib.contextmanager
def _ray_loopback_only() -> Iterator[None]:
    """While a local Ray instance starts: nothing it launches joins ``RAY_ADDRESS``, and it binds to 127.0.0.1.

    Ray's servers listen on the node's IP, but on Linux Ray turns a loopback node IP into the machine's
    routable address unless its cluster support is off (``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0``, the
    default on Windows and macOS). It is switched off in this process (Ray reads the flag from
    ``ray._private.ray_constants`` when it resolves the address) and in the environment the Ray
    processes inherit, then restored.
    """
    from ray._private import ray_constants

    saved_env = {k: os.environ.get(k) for k in ("RAY_ADDRESS", "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER")}
    if saved_env["RAY_ADDRESS"]:
        _log.warning(
            "RAY_ADDRESS=%s is ignored: the local Ray executor starts its own instance "
            "(pass --ray-address to join a running cluster)",
            saved_env["RAY_ADDRESS"],
        )
    saved_flag = getattr(ray_constants, "ENABLE_RAY_CLUSTER", None)
    os.environ.pop("RAY_ADDRESS", None)
    os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"
    ray_constants.ENABLE_RAY_CLUSTER = False
    try:
        yield
    finally:
        if saved_flag is None:
            del ray_constants.ENABLE_RAY_CLUSTER
        else:
            ray_constants.ENABLE_RAY_CLUSTER = saved_flag
        for k, v in saved_env.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _import_path() -> list[str]:
    import sys

    return [os.path.abspath(p or os.getcwd()) for p in sys.path if os.path.isdir(p or os.getcwd())]


# --------------------------------------------------------------------------- choosing one


def available_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def make_executor(kind: str = "local", workers: int | None = None, address: str | None = None) -> Executor:
    """An executor by name: ``"local"`` (``workers`` = 1: this process; more: a process pool kept for every map
    until :meth:`Executor.close`; None: one process per available core) or ``"ray"`` (``address`` of a running
    cluster, or a local instance of ``workers`` CPUs). Its caller closes it."""
    cfg = load_config(ExecutorConfig, None, {"kind": kind, "workers": workers, "address": address})
    if cfg.kind == "ray":
        return RayExecutor(cfg.workers, cfg.address)
    if cfg.address:
        raise ConfigError("an address is for the Ray executor (--executor ray)")
    n = cfg.workers or available_cores()
    return SERIAL if n <= 1 else ProcessExecutor(n, keep_pool=True)  # its maker closes it


SERIAL = SerialExecutor()
_default: Executor | None = None
_owned_default: Executor | None = None


def get_executor(workers: int | None = None) -> Executor:
    """The executor for a caller that was given none: the process-wide one when it was set
    (:func:`use_executor`, :func:`set_default_executor`), else a local one of ``workers``
    (a stage's ``workers`` setting; None or 1 = this process)."""
    if _default is not None:
        return _default
    return SERIAL if not workers or workers <= 1 else ProcessExecutor(workers)


@contextlib.contextmanager
def use_executor(
    executor: Executor | str = "local", workers: int | None = None, address: str | None = None
) -> Iterator[Executor]:
    """The process-wide default executor for a while: an executor, or one made by name (and then
    closed on exit). The previous default comes back afterwards."""
    global _default
    if isinstance(executor, Executor):
        made, ex = False, executor
    else:
        made, ex = True, make_executor(executor, workers, address)
    before, _default = _default, ex
    try:
        yield ex
    finally:
        _default = before
        if made:
            ex.close()


def set_default_executor(kind: str = "local", workers: int | None = None, address: str | None = None) -> Executor:
    """Set the process-wide default executor for the rest of the run (the CLI's ``--executor``,
    ``--workers``, ``--ray-address``); the one this replaces, if made here, is closed, and the
    last one is closed at exit."""
    global _default, _owned_default
    ex = make_executor(kind, workers, address)
    if _owned_default is not None:
        _owned_default.close()
    _default = _owned_default = ex
    return ex


def default_executor() -> Executor | None:
    """The process-wide default when one was set (:func:`use_executor`, :func:`set_default_executor`), else None."""
    return _default


@atexit.register
def _close_default() -> None:
    if _owned_default is not None:
        _owned_default.close()


__all__ = [
    "Executor",
    "ExecutorConfig",
    "SerialExecutor",
    "ProcessExecutor",
    "RayExecutor",
    "TaskError",
    "SERIAL",
    "make_executor",
    "get_executor",
    "default_executor",
    "use_executor",
    "set_default_executor",
    "available_cores",
]
