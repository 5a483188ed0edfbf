#!/usr/bin/env bash
# Install into the venv (as the quickstart does, plus the ray set for the Ray engine tests), then run ruff
# and the test suite. Extra arguments go to pytest (bash scripts/test.sh tests/test_store.py -x).
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/venv.sh
bash scripts/install.sh dev,ray

# --- test-only Debian packages (i11): headless Chromium for the web-page test (tests/test_serve_browser.py,
# which skips without them). Set OSCAR_TEST_APT="" to skip this step.
OSCAR_TEST_APT="${OSCAR_TEST_APT-chromium chromium-driver}"
if [ -n "$OSCAR_TEST_APT" ] && ! command -v chromedriver >/dev/null; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && command -v sudo >/dev/null && SUDO="sudo"
  echo "[test] Debian packages: $OSCAR_TEST_APT"
  $SUDO apt-get update -qq
  # shellcheck disable=SC2086  # a space-separated package list
  $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends $OSCAR_TEST_APT >/dev/null
fi
# --- end of test-only Debian packages
"$PY" -m ruff check pipeline tests bench scripts setup.py
rc=0
"$PY" -m pytest -q "$@" || rc=$?
if [ "$rc" -eq 5 ]; then
  echo "error: pytest collected no tests (exit code 5)" >&2
  exit 1
fi
exit "$rc"
