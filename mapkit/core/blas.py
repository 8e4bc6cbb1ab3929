"""One OpenBLAS kernel for every library in the process, chosen by what the CPU can run.

numpy, scipy, faiss and OpenCV each bundle their own OpenBLAS, and each picks its kernels by the CPU
when it loads. The copies bundled with faiss and OpenCV are older than numpy's and do not know the
newest CPUs: on a Sapphire Rapids Xeon they fall back to their generic SSE3 kernel (``Prescott``)
while numpy's picks AVX-512 (``SkylakeX``). A product summed by another kernel differs in its last
bits, and where a result breaks ties on them (the k-means assignments of the VLAD vocabulary) the
figures move: the demo's VLAD index, and every retrieval and localization figure after it, differ
between two Xeons running the same code.

So before any of them loads, :func:`pin_openblas_kernel` names the kernel for all of them: the
widest of ``SkylakeX`` (AVX-512), ``Haswell`` (AVX2 and FMA) and ``Sandybridge`` (AVX) that this CPU
runs. Machines of the same class then compute the same bits. An ``OPENBLAS_CORETYPE`` the user set
is kept. ``mapkit`` calls it on import; where numpy was imported first, numpy's OpenBLAS has chosen
already and only the libraries loaded later (and worker processes) follow. :func:`openblas_kernels`
says what each loaded library runs, for a run's record.
"""

from __future__ import annotations

import ctypes
import os
import platform
from collections.abc import Iterable, MutableMapping
from pathlib import Path

#: the kernels mapkit names, widest first, with the CPU flags (/proc/cpuinfo) each needs
KERNELS: tuple[tuple[str, frozenset[str]], ...] = (
    ("SkylakeX", frozenset({"avx512f", "avx512cd", "avx512bw", "avx512dq", "avx512vl"})),
    ("Haswell", frozenset({"avx2", "fma"})),
    ("Sandybridge", frozenset({"avx"})),
)
ENV = "OPENBLAS_CORETYPE"
_CORENAME = ("scipy_openblas_get_corename64_", "scipy_openblas_get_corename", "openblas_get_corename")


def cpu_flags() -> frozenset[str]:
    """The CPU's feature flags as Linux states them (those the kernel lets programs use); empty elsewhere."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("flags"):
                    return frozenset(line.split(":", 1)[1].split())
    except OSError:
        pass
    return frozenset()


def kernel_for(flags: Iterable[str]) -> str | None:
    """The widest kernel of :data:`KERNELS` a CPU with ``flags`` runs; None below AVX."""
    have = set(flags)
    return next((name for name, need in KERNELS if need <= have), None)


def pin_openblas_kernel(
    environ: MutableMapping[str, str] | None = None, flags: Iterable[str] | None = None, machine: str | None = None
) -> str | None:
    """Set ``OPENBLAS_CORETYPE`` in ``environ`` (this process's environment) to :func:`kernel_for` this CPU,
    unless it is set already; returns the kernel in force (None: OpenBLAS chooses, as on ARM)."""
    env = os.environ if environ is None else environ
    if env.get(ENV):
        return env[ENV]
    if (machine or platform.machine()).lower() not in ("x86_64", "amd64"):
        return None
    kernel = kernel_for(cpu_flags() if flags is None else flags)
    if kernel is not None:
        env[ENV] = kernel
    return kernel


def loaded_openblas() -> list[ctypes.CDLL]:
    """Every OpenBLAS library loaded in this process (numpy's, scipy's, faiss's and OpenCV's wheels bundle their
    own), found in ``/proc/self/maps``; empty on a non-Linux OS."""
    paths = set()
    try:
        with open("/proc/self/maps") as f:
            for line in f:
                path = line.rsplit(None, 1)[-1]
                if "openblas" in path.lower() and (path.endswith(".so") or ".so." in path):
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


def symbol(lib: ctypes.CDLL, names: Iterable[str]):
    """The first of ``names`` that ``lib`` exports (OpenBLAS builds prefix and suffix their symbols), or None."""
    return next((getattr(lib, n) for n in names if hasattr(lib, n)), None)


def openblas_kernels() -> dict[str, str]:
    """The kernel each OpenBLAS loaded in this process runs, by the package that bundles it
    (``{"numpy": "SkylakeX", "faiss_cpu": "SkylakeX", ...}``); empty where none is loaded or on a non-Linux OS."""
    out: dict[str, str] = {}
    for lib in loaded_openblas():
        fn = symbol(lib, _CORENAME)
        if fn is None:
            continue
        fn.restype = ctypes.c_char_p
        path = Path(lib._name)
        out[path.parent.name.removesuffix(".libs") or path.name] = (fn() or b"").decode(errors="replace")
    return out
