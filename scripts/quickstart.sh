#!/usr/bin/env bash
# The main job on the bundled sample data, offline profile: install, onboard data/sample_library into
# data/store, then answer one query. Re-running it is incremental (the second onboarding does no work).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh dev
PY="${PYTHON:-python3}"
"$PY" -m pipeline.onboard data/sample_library --store data/store
if [ -f data/queries/sample_queries.jsonl ] && "$PY" -c "import pipeline.query" 2>/dev/null; then
  "$PY" -m pipeline.query --store data/store --image data/queries/mustard_view.png \
    --mask data/queries/mustard_view_mask.png --prompt "the yellow mustard bottle" --top 3
fi
