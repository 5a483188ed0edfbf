#!/usr/bin/env bash
# Prove a built wheel outside the checkout: a brand-new venv with the locked base dependencies and the wheel
# (--no-deps), a drift check, then from an empty directory: onboard a copy of the sample library, one query,
# the audits and a SQL count, all through the `oscar` console command.
#
#   bash scripts/smoke_wheel.sh dist/oscar_pipeline-*.whl [WORKDIR]
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
whl="$(cd "$(dirname "$1")" && pwd)/$(basename "$1")"
work="${2:-$(mktemp -d "${TMPDIR:-/tmp}/oscar-wheel.XXXXXX")}"
mkdir -p "$work"
venv="$work/venv-wheel"
[ -e "$venv" ] && { echo "error: $venv exists; the smoke test needs a brand-new venv" >&2; exit 2; }
base="${BASE_PYTHON:-$(command -v python3.11 || command -v python3)}"
quiet() { "$@" 2> >(grep -v "is ignored: it is neither a file nor a directory" >&2); }

echo "[wheel] brand-new venv $venv, requirements/base.txt + $(basename "$whl")"
"$base" -m venv "$venv"
quiet "$venv/bin/python" -m pip install -q -r "$root/requirements/base.txt" ${TORCH_INDEX_URL:+--extra-index-url "$TORCH_INDEX_URL"}
quiet "$venv/bin/python" -m pip install -q --no-deps "$whl"
"$venv/bin/python" "$root/scripts/check_lock.py" env base
"$venv/bin/python" -m pip check

mkdir -p "$work/elsewhere"
cp -r "$root/data/sample_library" "$work/elsewhere/library"
cp "$root/data/queries/tabletop.jpg" "$work/elsewhere/photo.jpg"
cd "$work/elsewhere"
export PYTHONPATH=""  # nothing of the checkout may leak in
where="$("$venv/bin/python" -c 'import pipeline, pipeline.resources as r; print(pipeline.__file__, r.sql_root())')"
echo "[wheel] imports from: $where"
case "$where" in "$root"*|*" $root"*) echo "error: the checkout leaked into the wheel's venv" >&2; exit 1;; esac
oscar="$venv/bin/oscar"
"$oscar" --help >/dev/null
"$oscar" onboard library --store store --workers 1
out="$("$oscar" query --store store --image photo.jpg --box 318,200,408,450 --prompt "the yellow mustard bottle" --top 3)"
echo "$out"
echo "$out" | grep -Eq '^ +1  [0-9]{3}_' || { echo "error: the query returned no ranked model" >&2; exit 1; }
"$oscar" sql store --audit all
n="$("$oscar" sql store -c "SELECT count(*) AS n FROM meshes" --format csv | tail -1)"
[ "$n" = "4" ] || { echo "error: expected 4 meshes in the store, got '$n'" >&2; exit 1; }
echo "[wheel] ok: onboard, query, audits and SQL from $(basename "$whl") outside the checkout"
