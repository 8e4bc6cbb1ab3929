"""Keep OpenBLAS to one thread while open3d's ray casting owns the cores.

Embree's worker threads and OpenBLAS's both spin on a 2-core machine; a (300k x 3) @ (3 x 3)
product then takes 70 ms instead of 1 ms. ``single_thread_blas()`` sets the thread count of every
OpenBLAS that this process has loaded (numpy's and scipy's wheels bundle their own), the way
threadpoolctl does, and restores it afterwards. Elsewhere (MKL, Accelerate) it does nothing.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

from mapkit.core.blas import loaded_openblas, symbol

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


@contextmanager
def single_thread_blas() -> Iterator[None]:
    saved = []
    for lib in loaded_openblas():
        get, put = symbol(lib, _GETTERS), symbol(lib, _SETTERS)
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
