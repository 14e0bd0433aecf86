#!/usr/bin/env bash
# Set everything up (including Chromium) and run the whole test suite.
# PostgreSQL tests need the server at OCCUFLY_TEST_POSTGRES_URL
# (default postgresql+psycopg://postgres@127.0.0.1:5432/test); they fail, not skip, without it.
#
# Two lanes of pytest run side by side on the two cores (see below). They share only the
# synthetic scene cache (OCCUFLY_TEST_CACHE): PostgreSQL tests use scratch databases of their
# own, servers take free ports.
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

# the synthetic scenes the tests share (tests/harness.py: generated once, by whichever process
# needs one first, under a file lock), removed at the end
OCCUFLY_TEST_CACHE=$(mktemp -d)
export OCCUFLY_TEST_CACHE
logs=$(mktemp -d)
trap 'rm -rf "$OCCUFLY_TEST_CACHE" "$logs"' EXIT

paths=0
for a in "$@"; do case "$a" in -*) ;; *) paths=1 ;; esac; done
if [ "$paths" = 1 ] || [ "${OCCUFLY_TEST_SERIAL:-0}" = 1 ]; then
  .venv/bin/python -m pytest -rs "$@"  # -rs: skipped tests say why (e.g. no vulnerability database)
  check $? "pytest $*"
  exit $?
fi

# Two lanes, one per core. The browser lane waits on Chromium and live servers much of the
# time, so it also takes the tests marked `slow` outside tests/e2e and tests/viewer (child
# processes, big scenes: tests/conftest.py lists why each is slow); the other lane runs the
# rest. Every test runs exactly once: the -m expressions are complements.
slow=$(.venv/bin/python -c 'from tests.conftest import SLOW; print(" ".join(SLOW))') || exit 1
(
  .venv/bin/python -m pytest -rs --durations=15 "$@" tests/e2e tests/viewer > "$logs/browser.log" 2>&1
  echo $? > "$logs/browser.rc"
  # shellcheck disable=SC2086  # $slow: paths, one word each
  .venv/bin/python -m pytest -rs --durations=15 "$@" -m slow $slow > "$logs/slow.log" 2>&1
  echo $? > "$logs/slow.rc"
) &
lane=$!
.venv/bin/python -m pytest -rs --durations=15 "$@" -m "not slow" --ignore=tests/e2e \
  --ignore=tests/viewer > "$logs/rest.log" 2>&1
rest_rc=$?
wait "$lane"
echo "=== tests outside the browser, not marked slow ==="
cat "$logs/rest.log"
echo "=== browser tests (tests/e2e, tests/viewer) ==="
cat "$logs/browser.log"
echo "=== tests outside the browser marked slow (run in the browser lane) ==="
cat "$logs/slow.log"
check "$rest_rc" "non-browser tests"; a=$?
check "$(cat "$logs/browser.rc")" "browser tests"; b=$?
check "$(cat "$logs/slow.rc")" "slow non-browser tests"; c=$?
[ "$a" = 0 ] && [ "$b" = 0 ] && [ "$c" = 0 ]
