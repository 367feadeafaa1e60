#!/usr/bin/env bash
# The ROS-free tests on Python 3.12 with numpy 1.26, as on a robot with ROS 2 Jazzy from apt (Ubuntu 24.04):
# builds .venv312 from requirements-runtime.txt plus the test packages of requirements.txt (without numpy 2,
# the ROS wheels and the build tools), then runs the test files that load no ROS module
# (scripts/ros_free_tests.py), less those marked ros or slow. Not part of `make test`.
#
# Python 3.12: $PSSNET_PYTHON312, else python3.12 on PATH, else one installed by pyenv or uv
# (`pyenv install 3.12` or `uv python install 3.12`).
# torch: PyPI's torch==2.13.0 for Python 3.12 is the CUDA build (~4 GB with its nvidia-* packages, downloaded
# once into pip's cache); it runs on the CPU. The CPU-only file on this project's machines is for Python 3.11.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
VENV=${PSSNET_VENV312:-$ROOT/.venv312}
STAMP=$VENV/.stamp-requirements

say() { echo "[test-py312] $*"; }

find_python() {
  local candidate
  for candidate in "${PSSNET_PYTHON312:-}" python3.12 "$(pyenv root 2>/dev/null)"/versions/3.12*/bin/python3.12 \
                   "$(uv python find 3.12 2>/dev/null)"; do
    [ -n "$candidate" ] || continue
    if "$candidate" -c 'import sys; assert sys.version_info[:2] == (3, 12)' 2>/dev/null; then
      command -v "$candidate" || echo "$candidate"
      return 0
    fi
  done
  return 1
}

if [ ! -x "$VENV/bin/python" ]; then
  PYTHON=$(find_python) || {
    echo "[test-py312] no Python 3.12 found: set PSSNET_PYTHON312, or install one (pyenv install 3.12," \
         "uv python install 3.12)" >&2
    exit 1
  }
  say "creating $VENV with $PYTHON"
  "$PYTHON" -m venv "$VENV"
fi

# The test packages of requirements.txt, without what an apt Jazzy robot has or must not get.
grep -v -E '^(numpy|ros-jazzy-|colcon|ruff|setuptools)' requirements.txt >"$VENV/requirements-test.txt"
digest=$(cat requirements-runtime.txt "$VENV/requirements-test.txt" | sha256sum | cut -c1-16)
if [ "$(cat "$STAMP" 2>/dev/null)" != "$digest" ]; then
  say "installing requirements-runtime.txt and the test packages (first time: several minutes, ~6 GB)"
  "$VENV/bin/pip" install -q --disable-pip-version-check -r requirements-runtime.txt -r "$VENV/requirements-test.txt"
  echo "$digest" >"$STAMP"
fi

"$VENV/bin/python" - <<'EOF'
import sys

import numpy
import torch

assert sys.version_info[:2] == (3, 12), sys.version
assert numpy.__version__.startswith("1.26."), numpy.__version__
print(f"[test-py312] Python {sys.version.split()[0]}, numpy {numpy.__version__}, torch {torch.__version__}")
EOF

mapfile -t files < <("$VENV/bin/python" scripts/ros_free_tests.py)
say "${#files[@]} ROS-free test files"
# The packages from their folders (this venv has no editable installs).
export PYTHONPATH=$ROOT/pssnet_core:$ROOT/pssnet_ros:$ROOT/pssnet_testing
exec "$VENV/bin/python" -m pytest -q -m "not slow and not ros" "$@" "${files[@]}"
