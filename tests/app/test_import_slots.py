"""Issue 36 (part B, item 5): "at most 2 mask imports read at once" holds across API
processes. The slots are flock-ed files under the data dir; another process holding both
makes this server answer 429 with Retry-After, and a slot frees when its holder exits (even
killed). Threads of one process are bounded by the same slots. SQLite and PostgreSQL."""

from __future__ import annotations

import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from app.annotations.interchange import MAX_CONCURRENT_IMPORTS, import_slot
from app.errors import TooManyAttempts
from occufly.io import mask_interchange
from tests.app.conftest import H, W, make_tiny_scene

REPO = Path(__file__).resolve().parents[2]
HOLDER = """
import sys
from contextlib import ExitStack
from app.annotations.interchange import import_slot
with ExitStack() as st:
    held = [st.enter_context(import_slot(sys.argv[1])) for _ in range(int(sys.argv[2]))]
    print("held", held, flush=True)
    sys.stdin.readline()
"""


def _holder(data_dir: Path, n: int) -> subprocess.Popen:
    p = subprocess.Popen([sys.executable, "-c", HOLDER, str(data_dir), str(n)],
                         stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=REPO)
    line = p.stdout.readline()
    assert line.startswith("held"), line
    return p


def _archive(tmp: Path) -> bytes:
    sc = make_tiny_scene()
    mask = np.zeros((H, W), np.uint8)
    mask[: H // 2] = 6
    out = tmp / "m.zip"
    mask_interchange.write_masks(out, "png", {0: mask}, sc.frames, sc.taxonomy)
    return out.read_bytes()


def _post(env, sid, hdr, data):  # noqa: ANN001, ANN202
    return env.client.post(f"/api/scenes/{sid}/masks/import", headers=hdr,
                           data={"format": "png"}, files={"archive": ("m.zip", data)})


def test_another_process_holding_every_slot_makes_this_server_answer_429(world, tmp_path):
    env, hdr, scene, _frames = world
    data = _archive(tmp_path)
    other = _holder(env.settings.data_dir, MAX_CONCURRENT_IMPORTS)  # "another API process"
    try:
        r = _post(env, scene["id"], hdr["admin"], data)
        assert r.status_code == 429, r.text
        assert r.headers["Retry-After"] == "5"
        assert "2 mask imports are being read" in r.json()["detail"]
    finally:
        other.kill()  # killed, not closed: the kernel drops its locks
        other.wait()
    r = _post(env, scene["id"], hdr["admin"], data)
    assert r.status_code == 200 and r.json()["frames_imported"] == 1, r.text


def test_one_slot_held_elsewhere_leaves_one_here(world, tmp_path):
    env, hdr, scene, _frames = world
    other = _holder(env.settings.data_dir, 1)
    try:
        with import_slot(env.settings.data_dir) as mine:
            assert mine == 1
            with pytest.raises(TooManyAttempts):
                with import_slot(env.settings.data_dir):
                    pass
    finally:
        other.stdin.close()
        other.wait()


def test_threads_share_the_host_wide_slots(tmp_path):
    held, refused = [], []
    go, done = threading.Event(), threading.Event()

    def one() -> None:
        try:
            with import_slot(tmp_path) as i:
                held.append(i)
                go.wait(10)
        except TooManyAttempts:
            refused.append(1)
        finally:
            done.set()

    threads = [threading.Thread(target=one) for _ in range(2)]
    for t in threads:
        t.start()
    deadline = threading.Event()
    for _ in range(100):
        if len(held) == 2:
            break
        deadline.wait(0.05)
    assert sorted(held) == [0, 1]
    with pytest.raises(TooManyAttempts) as ei:
        with import_slot(tmp_path):
            pass
    assert ei.value.extra["retry_after"] == 5
    go.set()
    for t in threads:
        t.join()
    with import_slot(tmp_path) as i:  # freed
        assert i == 0
    assert not refused
