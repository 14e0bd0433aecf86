#!/usr/bin/env bash
# README screenshots, made on the demo with headless Chromium so they stay current:
# docs/screenshots/{annotator,annotator_grabcut,annotator_scissors,reviewer,admin[,admin_effort],viewer,grid_preview}.png
#
#   scripts/screenshots.sh                 # the small demo scene (synthesized once, cached)
#   PRESET=tiny scripts/screenshots.sh     # quicker, for a look at the pages
#
# Env: PRESET (small), PORT (9450), OUT (docs/screenshots), CACHE (/tmp/occufly-screenshots:
# the synthetic scene is kept there between runs). Needs .venv (scripts/setup.sh --test).
set -euo pipefail
cd "$(dirname "$0")/.."
PRESET=${PRESET:-small}
PORT=${PORT:-9450}
OUT=${OUT:-docs/screenshots}
CACHE=${CACHE:-/tmp/occufly-screenshots}
PY=.venv/bin/python
[ -x .venv/bin/occufly ] || { echo "screenshots: .venv is missing; run scripts/setup.sh --test first" >&2; exit 2; }
[ -x /usr/bin/chromium ] || { echo "screenshots: /usr/bin/chromium is missing; run scripts/setup.sh --test first" >&2; exit 2; }

SRC="$CACHE/imports/synthetic_${PRESET}_0"
mkdir -p "$CACHE/imports"
if [ ! -f "$SRC/truth/point_labels.npy" ]; then
  echo "screenshots: synthesizing the $PRESET scene into $SRC (once)" >&2
  .venv/bin/occufly synth "$SRC" --preset "$PRESET" --seed 0 --force >/dev/null
fi
DATA=$(mktemp -d /tmp/occufly-screenshots-data.XXXXXX)
LOG="$DATA/demo.log"
OCCUFLY_DATA_DIR="$DATA" OCCUFLY_IMPORT_ROOTS="$CACHE/imports" OCCUFLY_FILL_DEBOUNCE_S=0.5 \
  .venv/bin/occufly demo --source "$SRC" --dev --port "$PORT" >"$LOG" 2>&1 &
DEMO=$!
cleanup() { kill "$DEMO" 2>/dev/null || true; wait "$DEMO" 2>/dev/null || true; rm -rf "$DATA"; }
trap cleanup EXIT
for _ in $(seq 1 900); do
  grep -q "open http" "$LOG" && curl -fsS "http://127.0.0.1:$PORT/api/health" >/dev/null 2>&1 && break
  kill -0 "$DEMO" 2>/dev/null || { cat "$LOG" >&2; echo "screenshots: the demo stopped" >&2; exit 1; }
  sleep 1
done
grep -q "open http" "$LOG" || { cat "$LOG" >&2; echo "screenshots: the demo did not start" >&2; exit 1; }
"$PY" scripts/screenshots.py --url "http://127.0.0.1:$PORT" --source "$SRC" \
  --workspace "$DATA/scenes/$(basename "$SRC")" --out "$OUT"
