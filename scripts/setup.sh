#!/usr/bin/env bash
# One-time set-up of a fresh Debian machine with Python >= 3.10: system library, package, test tools.
# Idempotent: a machine that already has everything is checked in a few seconds and left as it is.
set -euo pipefail
cd "$(dirname "$0")/.."

PY=${PYTHON:-python3}
SUDO=""
if [ "$(id -u)" -ne 0 ] && command -v sudo >/dev/null 2>&1; then SUDO=sudo; fi

# open3d links against libusb-1.0 (Debian package libusb-1.0-0), absent on bare machines
if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  echo "[setup] installing libusb-1.0-0 (needed by open3d)" >&2
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libusb-1.0-0 >/dev/null
fi

# torch for the 3D CNN (the `learning` extra): its CPU build, pinned, so that no CUDA packages are
# pulled. On this kind of machine `pip install torch==2.13.0` takes the CPU wheel from the local
# wheel folder; elsewhere set TORCH_INDEX=https://download.pytorch.org/whl/cpu (the Dockerfile does).
if ! "$PY" -I -c "import torch" >/dev/null 2>&1; then
  echo "[setup] installing torch==2.13.0 (CPU build)" >&2
  "$PY" -m pip install --quiet --disable-pip-version-check torch==2.13.0 ${TORCH_INDEX:+--index-url "$TORCH_INDEX"}
fi

# the package (editable, so that the checkout is what runs), its optional extras and the test runner
# -I (isolated): the installed mapkit, not ./mapkit of the current folder, must be this checkout
if ! "$PY" -I -c "import mapkit, open3d, pycolmap, cv2, kiss_icp, mcap_ros2, pyproj, faiss, pytest, torch, onnxruntime, ray" >/dev/null 2>&1 \
   || [ "$("$PY" -I -c 'import mapkit, pathlib; print(pathlib.Path(mapkit.__file__).resolve().parents[1])' 2>/dev/null)" != "$(pwd -P)" ]; then
  echo "[setup] installing mapkit, its extras (learning, distributed) and its dependencies with pip" >&2
  "$PY" -m pip install --quiet --disable-pip-version-check -e ".[test,learning,distributed]"
fi
"$PY" -c "import open3d, mapkit; print(f'[setup] ok: mapkit {mapkit.__version__}, open3d {open3d.__version__}')" >&2
