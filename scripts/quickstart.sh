#!/usr/bin/env bash
# The main job on the bundled sample data, offline profile: install, onboard data/sample_library into
# data/store, then answer one query. Re-running it is incremental (the second onboarding does no work).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh dev
PY="${PYTHON:-python3}"
"$PY" -m pipeline.onboard data/sample_library --store data/store
# a real tabletop photo; the offline profile has no detector, so the object is given by its box
"$PY" -m pipeline.query --store data/store --image data/queries/tabletop.jpg --box 318,200,408,450 \
  --prompt "the yellow mustard bottle" --top 3
