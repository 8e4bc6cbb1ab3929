"""Keep OpenBLAS to one thread while open3d's ray casting owns the cores.

Embree's worker threads and OpenBLAS's both spin on a 2-core machine; a (300k x 3) @ (3 x 3)
product then takes 70 ms instead of 1 ms. ``single_thread_blas()`` sets the thread count of every
OpenBLAS that this process has loaded (numpy's and scipy's wheels bundle their own), the way
threadpoolctl does, and restores it afterwards. Elsewhere (MKL, Accelerate) it does nothing.
"""

from __future__ import annotations

import ctypes
from collections.abc import Iterator
from contextlib import contextmanager

_SETTERS = (
    "scipy_openblas_set_num_threads64_",
    "scipy_openblas_set_num_threads",
    "openblas_set_num_threads64_",
    "openblas_set_num_threads",
)
_GETTERS = (
    "scipy_openblas_get_num_threads64_",
    "scipy_openblas_get_num_threads",
    "openblas_get_num_threads64_",
    "openblas_get_num_threads",
)


def _openblas_libs() -> list[ctypes.CDLL]:
    paths = set()
    try:
        with open("/proc/self/maps") as f:
            for line in f:
                path = line.rsplit(None, 1)[-1]
                if "openblas" in path.lower() and path.endswith(".so") or ".so." in path and "openblas" in path.lower():
                    paths.add(path)
    except OSError:
        return []
    libs = []
    for p in sorted(paths):
        try:
            libs.append(ctypes.CDLL(p))
        except OSError:
            continue
    return libs


def _fn(lib: ctypes.CDLL, names: tuple[str, ...]):
    for n in names:
        f = getattr(lib, n, None)
        if f is not None:
            return f
    return None


@contextmanager
def single_thread_blas() -> Iterator[None]:
    saved = []
    for lib in _openblas_libs():
        get, put = _fn(lib, _GETTERS), _fn(lib, _SETTERS)
        if get is None or put is None:
            continue
        try:
            saved.append((put, int(get())))
            put(1)
        except Exception:  # noqa: BLE001 - a foreign library must never break rendering
            continue
    try:
        yield
    finally:
        for put, n in saved:
            put(n)
