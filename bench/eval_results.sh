#!/usr/bin/env bash
# Reproduce every number in docs/results.md (offline profile, CPU only; about 25 min on 2 idle cores,
# hours on a machine shared with other jobs: docs/results.md says which steps its numbers come from).
#   bash bench/eval_results.sh [WORK_DIR]     (default WORK_DIR: /tmp/oscar_eval_results)
# Reports land in WORK_DIR/report_*/ (report.html, report.md, metrics.json, plots/, gallery/); each report
# names its metric set (`paper`: the reference scripts' definitions, the default; `standard`: textbook).
set -euo pipefail
cd "$(dirname "$0")/.."
W=${1:-/tmp/oscar_eval_results}
DATA=${OSCAR_SHARED_DATA:-../shared/data}
mkdir -p "$W"
step() { echo "== $(date -u +%H:%M:%S) $*"; }

# 1. the 78 YCB meshes, offline profile (attributes prompt style)
step onboard ycb
python -m pipeline.onboard "$DATA/ycb" --store "$W/ycb_store" --no-progress

# 2. 390 synthetic queries: 5 novel views per mesh, backgrounds incl. crops of the real photos
step synth 390
python -m pipeline.evaluate synth --store "$W/ycb_store" --out "$W/ycb_synth" --per-mesh 5 --seed 0 \
  --photo-dir "$DATA/photos" --no-progress

# 3. paper metric set: all metrics + tau (0.10..0.95), fallback top-k (5..40), mode and ROI sweeps
step report_ycb paper
python -m pipeline.evaluate --store "$W/ycb_store" --queries "$W/ycb_synth/queries.jsonl" \
  --out "$W/report_ycb" --taus 0.10:0.95:0.05 --no-progress

# 3b. the same queries in the standard (textbook) metric set: base setting, modes and ROI variants
step report_ycb_standard
python -m pipeline.evaluate --store "$W/ycb_store" --queries "$W/ycb_synth/queries.jsonl" \
  --out "$W/report_ycb_standard" --metrics standard --taus 0.5 --top-ks 10 --no-progress

# 3c. the fallback counted in meshes instead of captions (two-stage, segm), over the taus where it fires
step report_ycb_fallback_meshes
python -m pipeline.evaluate --store "$W/ycb_store" --queries "$W/ycb_synth/queries.jsonl" \
  --out "$W/report_ycb_fallback_meshes" --fallback-unit meshes --taus 0.50:0.95:0.05 --top-ks 5,10,15 \
  --modes two-stage --rois segm --no-progress

# 3d. one query per mesh (every 5th line: each mesh's first query), base setting, in both metric sets
step report_ycb78
awk 'NR % 5 == 1' "$W/ycb_synth/queries.jsonl" > "$W/ycb_synth/queries_1per_mesh.jsonl"
for m in paper standard; do
  python -m pipeline.evaluate --store "$W/ycb_store" --queries "$W/ycb_synth/queries_1per_mesh.jsonl" \
    --out "$W/report_ycb78_$m" --metrics "$m" --no-sweeps --no-progress
done

# 4. prompt styles: one store per style, each started as a copy of the attributes store (renders reused),
#    on a second, smaller synthetic set (1 view per mesh, seed 1); the offline captioner ignores the prompt
step prompt styles
python -m pipeline.evaluate synth --store "$W/ycb_store" --out "$W/ycb_synth_1" --per-mesh 1 --seed 1 \
  --photo-dir "$DATA/photos" --no-progress
python -m pipeline.evaluate --store "$W/ycb_store" --queries "$W/ycb_synth_1/queries.jsonl" \
  --out "$W/report_styles" --no-sweeps --style-store "attributes=$W/ycb_store" \
  --onboard-styles blind,comma,caption --library "$DATA/ycb" --styles-dir "$W/styles" --no-progress

# 5. the real BBQ-sauce photo against the HOPE mesh + the 78 YCB meshes (box and mask drawn by hand):
#    a copy of the YCB store with the HOPE library onboarded into it (the same as onboarding both folders)
step bbq
rm -rf "$W/hope_ycb_store"
cp -r "$W/ycb_store" "$W/hope_ycb_store" && rm -rf "$W/hope_ycb_store/_lock" "$W/hope_ycb_store/_cache"
python -m pipeline.onboard "$DATA/hope" --store "$W/hope_ycb_store" --no-progress
python -m pipeline.evaluate --store "$W/hope_ycb_store" --queries data/queries/bbq_sauce.jsonl \
  --out "$W/report_bbq" --taus 0.10:0.95:0.05 --no-progress

# 6. 22 objects in the five real PoseCNN demo photos (boxes drawn by hand, no masks) against the YCB meshes
step photos
python -m pipeline.evaluate --store "$W/ycb_store" --queries data/queries/ycb_photos.jsonl \
  --out "$W/report_photos" --taus 0.10:0.95:0.05 --no-progress
python -m pipeline.evaluate --store "$W/ycb_store" --queries data/queries/ycb_photos.jsonl \
  --out "$W/report_photos_standard" --metrics standard --no-sweeps --no-progress
step done
