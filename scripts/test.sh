#!/usr/bin/env bash
# Set everything up (including Chromium) and run the whole test suite.
# PostgreSQL tests need the server at OCCUFLY_TEST_POSTGRES_URL
# (default postgresql+psycopg://postgres@127.0.0.1:5432/test); they fail, not skip, without it.
set -uo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh --test || exit 1
.venv/bin/python -m pytest -rs "$@"  # -rs: skipped tests say why (e.g. no vulnerability database)
rc=$?
if [ "$rc" = 5 ]; then
  echo "test: pytest collected no tests -- treating as failure" >&2
  exit 1
fi
exit "$rc"
