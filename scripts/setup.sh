#!/usr/bin/env bash
# One-shot set-up on a fresh machine: system packages, virtual environment, pinned install.
# Idempotent: re-running only installs what is missing.  Used by `make test` and `make demo`.
set -euo pipefail
cd "$(dirname "$0")/.."

VENV=${VENV:-.venv}
PYTHON=${PYTHON:-python3.11}
command -v "$PYTHON" >/dev/null 2>&1 || PYTHON=python3

# System libraries: open3d needs libusb; VTK (pyvista off-screen pictures) needs GL/EGL; gmsh needs libGLU/Xrender/Xcursor/Xft/Xinerama.
APT_PKGS="libusb-1.0-0 libgl1 libegl1 libglu1-mesa libxrender1 libxcursor1 libxft2 libxinerama1 libxi6 libgomp1"
missing=""
for p in $APT_PKGS; do
  dpkg -s "$p" >/dev/null 2>&1 || missing="$missing $p"
done
if [ -n "$missing" ]; then
  echo "[setup] installing system packages:$missing"
  SUDO=""; [ "$(id -u)" -ne 0 ] && command -v sudo >/dev/null 2>&1 && SUDO="sudo"
  export DEBIAN_FRONTEND=noninteractive
  $SUDO apt-get install -y -q $missing >/dev/null 2>&1 || { $SUDO apt-get update -q >/dev/null && $SUDO apt-get install -y -q $missing >/dev/null; }
fi

if [ ! -x "$VENV/bin/python" ]; then
  echo "[setup] creating $VENV with $($PYTHON --version)"
  "$PYTHON" -m venv "$VENV"
fi
"$VENV/bin/python" -m pip install -q --upgrade pip 2>&1 | grep -v "^WARNING: Location" || true
# torch first and exactly pinned: the CPU wheel on disk; anything else would fetch CUDA packages
"$VENV/bin/python" -m pip install -q "torch==2.13.0" 2>&1 | grep -v "^WARNING: Location" || true
# every other package at the exact version the project was last tested with (constraints.txt), so a fresh
# machine meshes a part as this one does; pyproject.toml keeps the ranges the code supports
"$VENV/bin/python" -m pip install -q -c constraints.txt -e ".[dev]" 2>&1 | grep -v "^WARNING: Location" || true
"$VENV/bin/python" -c "import torch, open3d, gmsh, trimesh, meshio, pyvista, prefect, dask; print('[setup] ok: torch', torch.__version__, '| prefect', prefect.__version__)"
