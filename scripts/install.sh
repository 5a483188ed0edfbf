#!/usr/bin/env bash
# Install OSCAR into a virtual environment from the lock files, on a fresh Debian/Ubuntu machine:
#
#   bash scripts/install.sh [SETS]     SETS: comma-separated lock sets of requirements/ (default: dev);
#                                      base is in every set: dev = base + pytest/ruff/httpx, ray, paper
#
# 1. Debian packages for headless EGL rendering (Mesa), with sudo when not root, if missing.
# 2. The venv (VENV=DIR, default .venv in the checkout; or PYTHON=an existing venv's python), created with
#    BASE_PYTHON (default python3.11, else python3). Never the system interpreter.
# 3. `pip install -r requirements/<set>.txt` (exact pins), then the project itself with --no-deps
#    (editable, so the checkout's code runs), then a drift check: the venv holds exactly the locked pins.
# A second run with the same locks, pyproject.toml and sets does nothing (a stamp in the venv), in seconds.
# TORCH_INDEX_URL: PyTorch's CPU index, where torch 2.13.0+cpu is not in PIP_FIND_LINKS (docs/install.md).
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/venv.sh
IFS=',' read -r -a sets <<< "${1:-dev}"
for s in "${sets[@]}"; do
  [ -f "requirements/$s.txt" ] || { echo "error: no lock set '$s' (requirements/$s.txt)" >&2; exit 2; }
done

if [ ! -x "$PY" ]; then
  [ -n "${PYTHON:-}" ] && { echo "error: PYTHON=$PYTHON is not an executable python" >&2; exit 2; }
  base="${BASE_PYTHON:-$(command -v python3.11 || command -v python3)}"
  echo "[install] new virtual environment $VENV ($("$base" -V 2>&1))"
  "$base" -m venv "$VENV"
fi
if ! "$PY" -c 'import sys; sys.exit(sys.prefix == sys.base_prefix)'; then
  echo "error: $PY is not a virtual environment; OSCAR never installs into a system interpreter" \
    "(use VENV=DIR, or PYTHON=the python of a venv)" >&2
  exit 2
fi
pyver="$("$PY" -c 'import sys; print(f"{sys.version_info[0]}.{sys.version_info[1]}")')"
if [ "$pyver" != "3.11" ]; then
  echo "error: the lock files are for CPython 3.11, $PY is $pyver (BASE_PYTHON=python3.11 or VENV=...)" >&2
  exit 2
fi

if ! ldconfig -p 2>/dev/null | grep -q "libEGL_mesa.so" || ! ldconfig -p | grep -q "libGL.so.1"; then
  echo "[install] Debian packages for headless EGL rendering"
  SUDO=""; [ "$(id -u)" -ne 0 ] && command -v sudo >/dev/null && SUDO="sudo"
  $SUDO apt-get update -qq
  $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
    libegl1 libegl-mesa0 libgl1 libgl1-mesa-dri libgles2 >/dev/null
fi

# The stamp: one key over everything that decides what gets installed, and the sets installed under it.
key="$(cat requirements/*.txt pyproject.toml setup.py | sha256sum | cut -c1-16) $pyver $PWD"
stamp="$VENV/.oscar-install"
have_key=""; have_sets=""
[ -f "$stamp" ] && { have_key="$(sed -n 1p "$stamp")"; have_sets="$(sed -n 2p "$stamp")"; }
todo=()
for s in "${sets[@]}"; do [[ ",$have_sets," == *",$s,"* ]] || todo+=("$s"); done
if [ "$have_key" == "$key" ] && [ ${#todo[@]} -eq 0 ]; then
  echo "[install] $VENV is up to date (sets ${have_sets}; locks unchanged)"
  exit 0
fi

# keep the sets this venv already has, so that alternating quickstart (dev) and test (dev,ray) stays fast
all=("${sets[@]}")
for s in ${have_sets//,/ }; do [[ " ${all[*]} " == *" $s "* ]] || all+=("$s"); done
reqs=(); for s in "${all[@]}"; do reqs+=(-r "requirements/$s.txt"); done
# pip warns once per package about extra indexes that lack it (e.g. local mirrors): noise, not a problem
quiet() { "$@" 2> >(grep -v "is ignored: it is neither a file nor a directory" >&2); }
rm -f "$stamp"
echo "[install] requirements/{$(IFS=,; echo "${all[*]}")}.txt into $VENV"
quiet "$PY" -m pip install -q "${reqs[@]}" ${TORCH_INDEX_URL:+--extra-index-url "$TORCH_INDEX_URL"}
echo "[install] oscar-pipeline (editable, --no-deps)"
quiet "$PY" -m pip install -q --no-deps --no-build-isolation -e .
"$PY" scripts/check_lock.py sync "${all[@]}"  # remove what a refreshed lock dropped; fail on any drift
printf '%s\n%s\n' "$key" "$(IFS=,; echo "${all[*]}")" > "$stamp"
echo "[install] done: $PY"
