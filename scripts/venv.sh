# Sourced by install.sh, quickstart.sh and test.sh: which virtual environment to use.
#   VENV=DIR     the venv (default: .venv in the checkout), created by install.sh when missing
#   PYTHON=PATH  the python of an existing virtual environment, used as is (VENV is then ignored)
# Sets VENV and PY (the venv's python). Nothing is ever installed into a system interpreter.
OSCAR_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
if [ -n "${PYTHON:-}" ]; then
  PY="$PYTHON"
  VENV="$("$PY" -c 'import sys; print(sys.prefix)')"
else
  VENV="${VENV:-$OSCAR_ROOT/.venv}"
  PY="$VENV/bin/python"
fi
export VENV PY
