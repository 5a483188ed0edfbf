#!/usr/bin/env bash
# The main job on the bundled sample data, offline profile: install into a venv from the lock (.venv, or
# VENV=DIR / PYTHON=venv python), onboard data/sample_library into data/store, then answer one query.
# A second run reuses the venv and the store: the install step and the onboarding are no-ops.
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/venv.sh
bash scripts/install.sh dev
"$PY" -m pipeline.onboard data/sample_library --store data/store
# a real tabletop photo; the offline profile has no detector, so the object is given by its box
"$PY" -m pipeline.query --store data/store --image data/queries/tabletop.jpg --box 318,200,408,450 \
  --prompt "the yellow mustard bottle" --top 3
