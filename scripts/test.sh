#!/usr/bin/env bash
# Install (as the quickstart does, plus the test extras) and run the whole test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh dev,ray  # the Ray engine tests run in CI; the quickstart installs only dev

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
PY="${PYTHON:-python3}"
"$PY" -m ruff check pipeline tests bench
"$PY" -m pytest -q "$@"
