#!/usr/bin/env bash
# Refresh the lock files requirements/{base,dev,ray,paper}.txt from pyproject.toml with `uv pip compile`.
#
#   bash scripts/lock.sh              # keep current pins where still valid (add/remove what pyproject changed)
#   bash scripts/lock.sh --upgrade    # move every package to its newest allowed version
#   bash scripts/lock.sh --upgrade-package duckdb   # (any extra argument goes to every `uv pip compile`)
#
# Each set is compiled under the pins of the one before (base -> dev -> ray -> paper), so any combination of
# lock files installs together (scripts/install.sh: `pip install -r dev.txt -r ray.txt`). torch is resolved
# against its CPU build (requirements/torch-cpu.txt); the script fails if a CUDA package slips in.
# Locks are for CPython 3.11 on Linux x86_64 (manylinux_2_28), the project's supported platform.
set -euo pipefail
cd "$(dirname "$0")/.."
UV="${UV:-$(command -v uv || echo "${PYTHON:-python3} -m uv")}"
FIND_LINKS="${PIP_FIND_LINKS:-/opt/wheels}"  # where the torch CPU wheel is (or set TORCH_INDEX_URL)
common=(--python-version 3.11 --python-platform x86_64-manylinux_2_28 --quiet
  --custom-compile-command "bash scripts/lock.sh" -c requirements/torch-cpu.txt)
[ -d "$FIND_LINKS" ] && common+=(--find-links "$FIND_LINKS")
[ -n "${TORCH_INDEX_URL:-}" ] && common+=(--extra-index-url "$TORCH_INDEX_URL" --index-strategy unsafe-best-match)

prev=""
for set in base dev ray paper; do
  extra=(); [ "$set" != base ] && extra=(--extra "$set")
  cons=(); [ -n "$prev" ] && cons=(-c "requirements/$prev.txt")
  echo "[lock] requirements/$set.txt"
  $UV pip compile pyproject.toml "${extra[@]}" "${cons[@]}" "${common[@]}" "$@" -o "requirements/$set.txt"
  # the lock names the release; pip picks the +cpu build of it (see requirements/torch-cpu.txt)
  sed -i -E 's/^torch==([0-9.]+)\+cpu$/torch==\1/' "requirements/$set.txt"
  if grep -E -i '^(nvidia-|triton|cuda-)' "requirements/$set.txt"; then
    echo "[lock] error: CUDA packages in requirements/$set.txt (torch must resolve to its CPU build)" >&2
    exit 1
  fi
  prev=$set
done
"${PYTHON:-python3}" scripts/check_lock.py pyproject  # every pyproject requirement is met by its lock
