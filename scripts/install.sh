#!/usr/bin/env bash
# Install everything OSCAR needs on a fresh Debian/Ubuntu machine: headless EGL (Mesa) for rendering,
# a CPU-sized PyTorch, and the package itself with the given extras (default: dev).
set -euo pipefail
cd "$(dirname "$0")/.."
extras="${1:-dev}"
SUDO=""; [ "$(id -u)" -ne 0 ] && command -v sudo >/dev/null && SUDO="sudo"

if ! ldconfig -p 2>/dev/null | grep -q "libEGL_mesa.so" || ! ldconfig -p | grep -q "libGL.so.1"; then
  echo "[install] Debian packages for headless EGL rendering"
  $SUDO apt-get update -qq
  $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
    libegl1 libegl-mesa0 libgl1 libgl1-mesa-dri libgles2 >/dev/null
fi

PY="${PYTHON:-python3}"
if ! "$PY" -c "import torch" 2>/dev/null; then
  echo "[install] torch (CPU build)"
  # Pinned so pip takes the local CPU wheel; elsewhere use the CPU index of PyTorch to avoid CUDA wheels.
  "$PY" -m pip install -q "torch==2.13.0" ${TORCH_INDEX_URL:+--index-url "$TORCH_INDEX_URL"}
fi
echo "[install] oscar-pipeline[$extras]"
"$PY" -m pip install -q -e ".[$extras]"
