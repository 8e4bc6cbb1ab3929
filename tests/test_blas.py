"""One OpenBLAS kernel in the process: chosen by the CPU's flags, set before the libraries load, and in force in
numpy's, faiss's and OpenCV's copies alike."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from mapkit.core.blas import ENV, kernel_for, pin_openblas_kernel

AVX512 = {"avx512f", "avx512cd", "avx512bw", "avx512dq", "avx512vl"}


def test_the_widest_kernel_the_flags_allow():
    assert kernel_for({"sse2", "avx", "avx2", "fma", *AVX512, "amx_tile"}) == "SkylakeX"
    assert kernel_for({"avx", "avx2", "fma", "avx512f"}) == "Haswell"  # AVX-512F alone is not SkylakeX's set
    assert kernel_for({"avx", "avx2"}) == "Sandybridge"  # AVX2 without FMA
    assert kernel_for({"sse2", "sse4_2"}) is None


def test_a_kernel_the_user_named_is_kept_and_arm_is_left_alone():
    env = {ENV: "Zen"}
    assert pin_openblas_kernel(env, flags=AVX512 | {"avx2", "fma", "avx"}, machine="x86_64") == "Zen"
    assert env == {ENV: "Zen"}
    env = {}
    assert pin_openblas_kernel(env, flags={"avx2", "fma", "avx"}, machine="x86_64") == "Haswell"
    assert env == {ENV: "Haswell"}
    env = {}
    assert pin_openblas_kernel(env, flags={"asimd"}, machine="aarch64") is None
    assert env == {}


HERE = pin_openblas_kernel({})  # the kernel mapkit names on this machine (None: it names none)


@pytest.mark.skipif(HERE is None, reason="needs Linux on an x86-64 CPU with AVX (its flags in /proc/cpuinfo)")
def test_every_openblas_the_pipeline_loads_runs_the_pinned_kernel():
    """In a fresh interpreter without OPENBLAS_CORETYPE: import mapkit, then the libraries that bundle an OpenBLAS.
    Left to themselves, the older copies in faiss and OpenCV fall back to a generic kernel on CPUs newer than they
    are, while numpy's picks AVX-512."""
    code = (
        "import json, mapkit, numpy, scipy.linalg, faiss, cv2\n"
        "numpy.ones((64, 64)) @ numpy.ones((64, 64))\n"
        "from mapkit.core.blas import openblas_kernels\n"
        "print(json.dumps(openblas_kernels()))\n"
    )
    env = {k: v for k, v in os.environ.items() if k != ENV}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    kernels = json.loads(out.stdout)
    assert {"numpy", "faiss_cpu", "opencv_python_headless"} <= set(kernels)
    assert set(kernels.values()) == {HERE}, kernels
