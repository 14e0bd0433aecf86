#!/usr/bin/env bash
# Set everything up (including Chromium) and run the whole test suite.
# PostgreSQL tests need the server at OCCUFLY_TEST_POSTGRES_URL
# (default postgresql+psycopg://postgres@127.0.0.1:5432/test); they fail, not skip, without it.
#
# Two pytest processes run side by side on the two cores: the browser tests (tests/e2e,
# tests/viewer: mostly waiting on Chromium and live servers) and everything else. They share
# nothing: PostgreSQL tests use scratch databases of their own, servers take free ports.
# With arguments (a file, -k ...) one process runs exactly what was asked.
set -uo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh --test || exit 1

check() {  # pytest's exit code -> ours ("no tests collected" is a failure, not a pass)
  if [ "$1" = 5 ]; then
    echo "test: pytest collected no tests ($2) -- treating as failure" >&2
    return 1
  fi
  return "$1"
}

paths=0
for a in "$@"; do case "$a" in -*) ;; *) paths=1 ;; esac; done
if [ "$paths" = 1 ] || [ "${OCCUFLY_TEST_SERIAL:-0}" = 1 ]; then
  .venv/bin/python -m pytest -rs "$@"  # -rs: skipped tests say why (e.g. no vulnerability database)
  check $? "pytest $*"
  exit $?
fi

logs=$(mktemp -d)
.venv/bin/python -m pytest -rs "$@" tests/e2e tests/viewer > "$logs/browser.log" 2>&1 &
browser=$!
.venv/bin/python -m pytest -rs "$@" --ignore=tests/e2e --ignore=tests/viewer > "$logs/rest.log" 2>&1
rest_rc=$?
wait "$browser"
browser_rc=$?
echo "=== tests outside the browser (tests/e2e, tests/viewer excluded) ==="
cat "$logs/rest.log"
echo "=== browser tests (tests/e2e, tests/viewer) ==="
cat "$logs/browser.log"
rm -rf "$logs"
check "$rest_rc" "non-browser tests"; a=$?
check "$browser_rc" "browser tests"; b=$?
[ "$a" = 0 ] && [ "$b" = 0 ]
