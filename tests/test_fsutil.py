"""Atomic output folders: a killed run leaves nothing that outlives it."""

from __future__ import annotations

import io
import os
import signal
import subprocess
import sys
import time
import zipfile

import numpy as np
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


def test_load_npz_reads_stored_members_directly_and_anything_else_through_np_load(tmp_path,
                                                                                  monkeypatch):
    """load_npz: the arrays of np.savez equal to np.load's (several dtypes, a 2-D Fortran
    array, an empty one, a long name), no file left open; a compressed archive, a pickled
    object array, a member whose header lies about its size and a file that is no archive go
    through np.load (equal arrays, or np.load's refusal)."""
    from occufly.fsutil import load_npz

    rng = np.random.default_rng(2)
    arrays = {"point_ids": np.sort(rng.integers(0, 1 << 40, 5000)),
              "cols": rng.integers(-1, 20, 5000).astype(np.int8),
              "w": np.asfortranarray(rng.random((30, 7)).astype(np.float32)),
              "empty": np.zeros((0, 3), np.uint16), "x" * 200: np.arange(3, dtype=np.uint16)}
    p = tmp_path / "v.npz"
    np.savez(p, **arrays)
    fds = len(os.listdir("/proc/self/fd"))
    with monkeypatch.context() as m:  # read directly: np.load is not called
        m.setattr(np, "load", lambda *a, **k: pytest.fail("np.load used for a stored archive"))
        got = load_npz(p)
    assert len(os.listdir("/proc/self/fd")) == fds  # nothing held open
    assert sorted(got) == sorted(arrays)
    for k, a in arrays.items():
        assert type(got[k]) is np.ndarray and got[k].dtype == a.dtype and got[k].shape == a.shape
        assert np.array_equal(got[k], a)
    assert got["w"].flags.f_contiguous
    # mmap=True: read-only maps of the same arrays; the files close when they are dropped
    mapped = load_npz(p, mmap=True)
    assert all(np.array_equal(mapped[k], a) for k, a in arrays.items())
    assert isinstance(mapped["point_ids"].base, np.memmap) and not mapped["cols"].flags.writeable
    assert len(os.listdir("/proc/self/fd")) > fds
    del mapped
    assert len(os.listdir("/proc/self/fd")) == fds
    buf = io.BytesIO()
    np.savez(buf, point_ids=np.zeros(5000, np.int64))
    # compressed: read whole, the same arrays
    c = tmp_path / "c.npz"
    np.savez_compressed(c, **arrays)
    gc = load_npz(c)
    assert sorted(gc) == sorted(arrays) and all(np.array_equal(gc[k], a) for k, a in arrays.items())
    # an object array is never unpickled
    o = tmp_path / "o.npz"
    np.savez(o, bad=np.array([{"a": 1}], dtype=object))
    with pytest.raises(ValueError, match="allow_pickle"):
        load_npz(o)
    # a header claiming more elements than the member holds: not read past it
    raw = bytearray(buf.getvalue())
    at = raw.index(b"'shape': (5000,)")
    raw[at:at + 16] = b"'shape': (9000,)"
    lie = tmp_path / "lie.npz"
    lie.write_bytes(bytes(raw))
    with pytest.raises((ValueError, OSError, zipfile.BadZipFile)):
        load_npz(lie)
    # not an archive at all
    (tmp_path / "junk.npz").write_bytes(b"PK\x03\x04 not a zip")
    with pytest.raises((ValueError, OSError, zipfile.BadZipFile)):
        load_npz(tmp_path / "junk.npz")
