#!/usr/bin/env bash
# Set up everything OccuFly Studio needs on a fresh Debian machine, idempotently:
#   system packages (apt, as root), a virtual environment at .venv/ with the package installed
#   in editable mode, and -- with --test -- Debian's Chromium for the browser tests.
# Usage: scripts/setup.sh [--test]
set -euo pipefail
cd "$(dirname "$0")/.."

want_test=0
[ "${1:-}" = "--test" ] && want_test=1

# --- system packages ----------------------------------------------------------------------
pkgs=(libusb-1.0-0 libgl1 libgomp1)               # Open3D's shared-library needs
# nginx: tests/app/test_serving.py runs deploy/nginx.conf (TLS) in front of the app
[ "$want_test" = 1 ] && pkgs+=(chromium fonts-dejavu-core nginx)
missing=()
for p in "${pkgs[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ "${#missing[@]}" -gt 0 ]; then
  echo "setup: installing system packages: ${missing[*]}" >&2
  SUDO=""
  [ "$(id -u)" = 0 ] || SUDO="sudo"
  $SUDO apt-get update -q >/dev/null
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -q --no-install-recommends "${missing[@]}" >/dev/null
fi

# --- Python 3.11+ and the virtual environment --------------------------------------------
PY=""
for cand in python3.11 python3.12 python3.13 python3; do
  if command -v "$cand" >/dev/null 2>&1 && "$cand" -c 'import sys; sys.exit(sys.version_info < (3, 11))' 2>/dev/null; then
    PY="$cand"; break
  fi
done
[ -n "$PY" ] || { echo "setup: Python 3.11 or newer is required" >&2; exit 1; }
if [ ! -x .venv/bin/python ]; then
  echo "setup: creating .venv with $($PY --version)" >&2
  "$PY" -m venv .venv
fi

# Reinstall only when the package definition or the locks changed (stamp = their hash + extras).
# --test adds the `torch` extra (CPU torch==2.13.0) so the occufly.datasets.torch tests run.
# `masks` (Datumaro, pycocotools, the Label Studio codec) is for the app's mask import/export.
extras="dev,masks"
[ "$want_test" = 1 ] && extras="dev,masks,torch"
# The dependencies come from the hash-pinned locks (scripts/lock.sh writes them): pip refuses
# any file whose sha256 the lock does not list. The package itself is then installed on top;
# a requirement of pyproject.toml the lock does not pin yet (someone added one without running
# scripts/lock.sh) is installed unpinned with a warning, and tests/test_lock.py fails on it.
locks=(-r requirements.lock)
[ "$want_test" = 1 ] && locks+=(-r requirements-torch.lock)
stamp=.venv/.occufly-installed
want="$(cat pyproject.toml requirements.lock requirements-torch.lock | sha256sum | cut -d' ' -f1)-$extras"
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ] || [ ! -x .venv/bin/occufly ]; then
  echo "setup: installing Python packages into .venv from requirements.lock (first run takes a minute)" >&2
  .venv/bin/python -m pip install -q --require-hashes "${locks[@]}"
  .venv/bin/python -m pip install -q --no-deps -e .
  if ! .venv/bin/python scripts/lock_check.py "$extras"; then
    echo "setup: WARNING requirements.lock is stale (pyproject.toml needs packages it does not" \
         "pin); installing them unpinned -- run scripts/lock.sh and commit the locks" >&2
    .venv/bin/python -m pip install -q -e ".[$extras]"
  fi
  echo "$want" > "$stamp"
fi
