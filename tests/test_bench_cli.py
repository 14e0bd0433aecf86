"""Every benchmark's ``--help`` prints its options: a reviewer re-running a benchmark starts there
(bench_survey's help crashed on a ``%`` in an f-string help text, which argparse formats again)."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1] / "bench"

# One interpreter for all of them: each help is parsed in-process, its exit code and text checked.
_PROBE = r"""
import contextlib, io, json, runpy, sys
out = {}
for path in sys.argv[1:]:
    buf = io.StringIO()
    sys.argv = [path, "--help"]
    try:
        with contextlib.redirect_stdout(buf):
            runpy.run_path(path, run_name="__main__")
        out[path] = "returned without printing help"
    except SystemExit as e:
        out[path] = "ok" if e.code in (0, None) and "usage:" in buf.getvalue() else f"exit {e.code}"
    except Exception as e:
        out[path] = f"{type(e).__name__}: {e}"
sys.stdout.write(json.dumps(out) + "\n")
"""


def test_every_benchmark_prints_its_help():
    scripts = sorted(p for p in BENCH.glob("bench_*.py"))
    assert len(scripts) >= 20
    r = subprocess.run([sys.executable, "-c", _PROBE, *map(str, scripts)], capture_output=True,
                       text=True, timeout=300, cwd=BENCH.parent)
    assert r.returncode == 0, r.stderr[-2000:]
    res = json.loads(r.stdout.strip().splitlines()[-1])
    bad = {Path(k).name: v for k, v in res.items() if v != "ok"}
    assert not bad, bad
