"""Defect 12 of issue 17: ``occufly demo`` shows each step as it happens (not after ~90 s of
silence): numbered start lines, progress, each step's time, then the logins."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.e2e
REPO = Path(__file__).resolve().parents[2]


def test_demo_prints_each_step_with_its_time_while_it_runs(live, tmp_path):
    root = live.app.state.ctx.settings.import_roots[0]
    source = next(p for p in sorted(root.iterdir()) if p.is_dir())
    env = {**os.environ, "OCCUFLY_DATA_DIR": str(tmp_path / "data"),
           "OCCUFLY_IMPORT_ROOTS": str(root), "PYTHONUNBUFFERED": ""}
    env.pop("OCCUFLY_DATABASE_URL", None)
    exe = Path(sys.executable).with_name("occufly")
    t0 = time.monotonic()
    proc = subprocess.Popen([str(exe), "demo", "--source", str(source), "--no-serve"], cwd=tmp_path,
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    lines: list[tuple[float, str]] = []
    for line in proc.stderr:  # read as the lines arrive
        lines.append((time.monotonic() - t0, line.rstrip("\n")))
    assert proc.wait(timeout=300) == 0, "\n".join(t for _, t in lines)
    text = [t for _, t in lines]
    starts = [i for i, t in enumerate(text) if re.match(r"\[\d/3\] .* \.\.\.$", t)]
    dones = [i for i, t in enumerate(text) if re.match(r"\[\d/3\] .*: done in \d+\.\d s$", t)]
    assert len(starts) == 3 and len(dones) == 3, text
    assert [text[i][:5] for i in starts] == ["[1/3]", "[2/3]", "[3/3]"]
    assert any("importing" in text[i] for i in starts) and any("selecting" in text[i] for i in starts)
    # each step's start line was on stderr before the step ended (not buffered to the end)
    t_first, t_last = lines[starts[0]][0], lines[-1][0]
    assert t_last - t_first > 1.0, lines
    imp = next(i for i in starts if "importing" in text[i])
    imp_done = next(i for i in dones if "importing" in text[i])
    assert lines[imp_done][0] - lines[imp][0] > 0.5
    # then the logins
    tail = "\n".join(text[dones[-1]:])
    for role in ("admin", "reviewer", "annotator"):
        assert re.search(rf"{role}\s+password \S+", tail), tail
