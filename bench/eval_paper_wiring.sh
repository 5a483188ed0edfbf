#!/usr/bin/env bash
# Wiring check of the evaluator on the PAPER profile without real weights: tiny randomly initialised
# LLaVA / CLIP / DINOv2 (built by tests/tiny_models.py, saved to disk) replace the hub models through
# --model overrides. The numbers it prints are meaningless; it shows that onboarding, synthetic queries,
# the CLIP-image stage 1, the DINOv2 stage 2, sweeps and the report all run on the paper code path.
#   bash bench/eval_paper_wiring.sh [WORK_DIR]
set -euo pipefail
cd "$(dirname "$0")/.."
W=${1:-/tmp/oscar_eval_paper_wiring}
mkdir -p "$W"
python - "$W" <<'PY'
import sys
from pathlib import Path

sys.path.insert(0, "tests")
import tiny_models
from test_eval_synth import make_toy_library

w = Path(sys.argv[1])
make_toy_library(w / "lib")
tiny_models.build_clip(w / "clip")
tiny_models.build_dinov2(w / "dinov2")
tiny_models.build_llava(w / "llava")
PY
M=(--model "captioner=$W/llava" --model "text_encoder=$W/clip" --model "clip_image_encoder=$W/clip"
   --model "view_encoder=$W/dinov2")
python -m pipeline.onboard "$W/lib" --store "$W/store" --profile paper "${M[@]}" --workers 0 --no-progress
python -m pipeline.evaluate synth --store "$W/store" --out "$W/queries" --per-mesh 2 --size 200x150 --no-progress
python -m pipeline.evaluate --store "$W/store" --queries "$W/queries/queries.jsonl" --out "$W/report" \
  --profile paper "${M[@]}" --taus 0.1,0.37,0.9 --top-ks 1,10 --no-progress
