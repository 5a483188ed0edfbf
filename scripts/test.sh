#!/usr/bin/env bash
# Install (as the quickstart does, plus the test extras) and run the whole test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh dev,ray  # the Ray engine tests run in CI; the quickstart installs only dev
PY="${PYTHON:-python3}"
"$PY" -m ruff check pipeline tests bench
"$PY" -m pytest -q "$@"
