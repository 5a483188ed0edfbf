#!/usr/bin/env bash
# Install into the venv (as the quickstart does, plus the ray set for the Ray engine tests), then run ruff
# and the test suite. Extra arguments go to pytest (bash scripts/test.sh tests/test_store.py -x).
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/venv.sh
bash scripts/install.sh dev,ray
"$PY" -m ruff check pipeline tests bench scripts setup.py
rc=0
"$PY" -m pytest -q "$@" || rc=$?
if [ "$rc" -eq 5 ]; then
  echo "error: pytest collected no tests (exit code 5)" >&2
  exit 1
fi
exit "$rc"
