#!/usr/bin/env bash
# Set-up of a fresh Debian machine with Python >= 3.10: one system library, then mapkit and every
# extra in a virtual environment of its own (no system site packages, so that nothing installed by
# hand elsewhere on the machine can make a run pass).
#
#   .venv/              the environment, in the checkout (git ignores it); enter it with
#                       `source .venv/bin/activate`, or call `.venv/bin/python` / `.venv/bin/mapkit`
#   MAPKIT_VENV=DIR     put the environment at DIR instead; .venv becomes a link to it (CI does this,
#                       with a new DIR outside the clone on every run)
#   PYTHON=python3.X    the interpreter the environment is made from (default python3)
#
# Idempotent: an environment made from the same pyproject.toml is checked in a few seconds and kept.
set -euo pipefail
cd "$(dirname "$0")/.."

PY=${PYTHON:-python3}
SUDO=""
if [ "$(id -u)" -ne 0 ] && command -v sudo >/dev/null 2>&1; then SUDO=sudo; fi
say() { echo "[setup] $*" >&2; }

if ! "$PY" -c 'import sys; sys.exit(sys.version_info < (3, 10))' 2>/dev/null; then
  say "error: $PY is missing or older than Python 3.10 (set PYTHON=python3.X)"; exit 2
fi

# open3d links against libusb-1.0 (Debian package libusb-1.0-0), absent on bare machines
if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  say "installing libusb-1.0-0 (needed by open3d)"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libusb-1.0-0 >/dev/null
fi

# where the environment lives
VENV=.venv
if [ -n "${MAPKIT_VENV:-}" ]; then
  mkdir -p "$(dirname "$MAPKIT_VENV")"
  if [ -e .venv ] && [ ! -L .venv ]; then
    say "error: MAPKIT_VENV is set but .venv is a real folder here; remove it or unset MAPKIT_VENV"; exit 2
  fi
  ln -sfn "$MAPKIT_VENV" .venv
  VENV=$MAPKIT_VENV
fi
if [ ! -x "$VENV/bin/python" ]; then
  say "creating the virtual environment $VENV (from $("$PY" --version 2>&1))"
  "$PY" -m venv "$VENV"
fi
VPY="$VENV/bin/python"
# --no-compile: pip would compile every module of every package (most of torch's, ray's and open3d's are
# never imported); scripts/warm_bytecode.py below compiles the ones mapkit imports
pip_install() { "$VPY" -m pip install --quiet --disable-pip-version-check --no-compile "$@"; }

# The environment is (re)filled when the project's dependencies changed since it was filled, or
# when a module is missing, or when the installed mapkit is not this checkout.
STAMP="$VENV/.mapkit-setup"
WANT="$(sha256sum pyproject.toml | cut -d' ' -f1) $(pwd -P)"
if [ "$(cat "$STAMP" 2>/dev/null)" != "$WANT" ] \
   || ! "$VPY" -I -c "import mapkit, open3d, pycolmap, cv2, kiss_icp, mcap_ros2, rosbags, pyproj, faiss, h5py, gtsam, PIL, pytest, hypothesis, torch, onnx, onnxruntime, ray, rerun, mkdocs, mkdocstrings" >/dev/null 2>&1 \
   || [ "$("$VPY" -I -c 'import mapkit, pathlib; print(pathlib.Path(mapkit.__file__).resolve().parents[1])' 2>/dev/null)" != "$(pwd -P)" ]; then
  t0=$(date +%s)
  # torch's CPU build first, pinned, so that the learning extra pulls no CUDA packages. On this kind
  # of machine `pip install torch==2.13.0` finds the CPU wheel on disk; elsewhere set
  # TORCH_INDEX=https://download.pytorch.org/whl/cpu (the Dockerfile does).
  if ! "$VPY" -I -c "import torch" >/dev/null 2>&1; then
    say "installing torch==2.13.0 (CPU build)"
    pip_install torch==2.13.0 ${TORCH_INDEX:+--index-url "$TORCH_INDEX"}
  fi
  say "installing mapkit (editable) with its extras learning, distributed, viewer, docs and test"
  # uv resolves and installs the same packages as pip from the same index, several times faster (it
  # downloads and unpacks in parallel); it ignores pip's configuration, so where it is missing or fails
  # (a private index set in pip.conf, say) pip does the install
  if ! { pip_install uv && "$VPY" -m uv pip install --quiet --python "$VPY" -e ".[test,learning,distributed,viewer,docs]"; }; then
    say "uv could not install the packages; installing with pip"
    pip_install -e ".[test,learning,distributed,viewer,docs]"
  fi
  # bytecode of what mapkit imports, written once: where PYTHONDONTWRITEBYTECODE is set, every process
  # would compile it again (about 3 s of each worker's start)
  "$VPY" scripts/warm_bytecode.py
  echo "$WANT" > "$STAMP"
  say "installed in $(( $(date +%s) - t0 )) s"
fi
# mapkit's own bytecode, for the modules changed since the last set-up (compileall writes it whatever
# PYTHONDONTWRITEBYTECODE says)
"$VPY" -m compileall -q mapkit >/dev/null
# the docs site serves Mermaid itself (docs/offline.py): fetched once from the npm registry, then offline
if ! "$VPY" docs/offline.py >/dev/null 2>&1; then
  say "warning: could not fetch Mermaid for the docs site (npm registry unreachable?); mkdocs build will try again"
fi
"$VPY" -c "import open3d, mapkit; print(f'[setup] ok: mapkit {mapkit.__version__}, open3d {open3d.__version__}, in $VENV')" >&2
