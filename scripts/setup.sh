#!/usr/bin/env bash
# Set up jaxslam on a fresh Debian/Ubuntu machine with Python 3.11.
#   bash scripts/setup.sh          # the product: jaxslam + fast sparse solvers
#   bash scripts/setup.sh dev      # + test/bench tools (pytest, gtsam oracle, ruff, mypy)
# System packages (needs root or sudo): SuiteSparse headers to build CHOLMOD's binding,
# OpenBLAS for CHOLMOD's dense kernels. Skipped with a warning where apt is unavailable;
# jaxslam then falls back to MKL PARDISO or SciPy's SuperLU.
set -euo pipefail
cd "$(dirname "$0")/.."
extras="fast"
if [ "${1:-}" = "dev" ]; then extras="fast,dev"; fi
SUDO=""
if [ "$(id -u)" != 0 ] && command -v sudo >/dev/null; then SUDO="sudo"; fi
if command -v apt-get >/dev/null && { [ "$(id -u)" = 0 ] || [ -n "$SUDO" ]; }; then
  need=""
  for p in libsuitesparse-dev libopenblas0-pthread libusb-1.0-0; do
    dpkg -s "$p" >/dev/null 2>&1 || need="$need $p"
  done
  if [ -n "$need" ]; then
    echo "setup: apt-get install$need" >&2
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq $need >/dev/null
  fi
else
  echo "setup: warning: no apt-get/root: skipping SuiteSparse and OpenBLAS" >&2
  extras="${extras/fast/mkl}"
fi
python3 -m pip install -q --disable-pip-version-check -e ".[${extras}]" 2>&1 | grep -v -e "^WARNING: Running pip as" -e "is ignored: it is neither" || true
python3 -c "import jaxslam, jaxslam.solvers as s; print('setup: jaxslam', jaxslam.__version__, '- linear solvers:', ', '.join(s.available_linear_solvers()))"
