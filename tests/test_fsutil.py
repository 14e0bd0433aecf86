"""Atomic output folders: a killed run leaves nothing that outlives it."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from occufly.fsutil import atomic_directory, remove_stale_partials


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def test_a_killed_runs_partial_folder_is_removed_by_the_next_run(tmp_path):
    ws = tmp_path / "ws"
    dead = tmp_path / f".ws.{_dead_pid()}-abc123.partial"
    dead_old = tmp_path / f".ws.old-{_dead_pid()}"
    for d in (dead, dead_old):
        d.mkdir()
        (d / "points.npy").write_bytes(b"x" * 1000)
    live_proc = subprocess.Popen(["sleep", "30"])
    try:
        live = tmp_path / f".ws.{live_proc.pid}-def456.partial"
        live.mkdir()
        other = tmp_path / f".other.{_dead_pid()}-abc.partial"  # another target's: not ours
        other.mkdir()
        with atomic_directory(ws) as tmp:
            assert f".ws.{os.getpid()}-" in tmp.name
            (tmp / "scene.json").write_text("{}")
        assert (ws / "scene.json").is_file()
        assert not dead.exists() and not dead_old.exists()
        assert live.is_dir(), "a live process's work in progress must stay"
        assert other.is_dir()
        assert remove_stale_partials(tmp_path / "other") == [other.absolute()]
    finally:
        live_proc.kill()
        live_proc.wait()


@pytest.mark.parametrize("command", ["synth", "import"])
def test_sigterm_unwinds_a_command_and_leaves_no_partial_output(tmp_path, command, request):
    """A command stopped by SIGTERM (a job runner, `kill`) mid-way: exit 130, no ``.partial``
    folder, the target not created."""
    if command == "import":
        src = request.getfixturevalue("synth_tiny")  # generated once per run (read-only)
        work = tmp_path / "work"
        work.mkdir()
        out = work / "ws"
        argv = ["import", str(src), "-w", str(out)]
    else:
        work = tmp_path
        out = work / "scene"
        argv = ["synth", str(out), "--preset", "tiny"]
    proc = subprocess.Popen([sys.executable, "-m", "occufly.cli", *argv],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    t0 = time.monotonic()
    partial = []
    while time.monotonic() - t0 < 60 and proc.poll() is None:
        partial = [p for p in work.iterdir() if p.name.endswith(".partial")]
        if partial and any(partial[0].rglob("*")):
            break
        time.sleep(0.005)
    if proc.poll() is not None:
        pytest.fail(f"{command} ended (rc {proc.returncode}) before a partial folder was seen")
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err.decode()
    assert b"interrupted" in err
    assert not out.exists()
    assert [p.name for p in work.iterdir()] == []
