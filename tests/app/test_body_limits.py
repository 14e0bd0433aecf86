"""Issue 24, finding 4: request bodies are capped by route before they are read (413)."""
from __future__ import annotations

import os
import socket
import threading
import time

import numpy as np
import psutil
import pytest

from tests.app.conftest import H, W, mask_png, png
from tests.harness import ProcessServer


def test_login_body_over_the_json_cap_is_413(env):
    """A 200 MB body to the public login: 413 naming the cap (before: read whole, then 422)."""
    big = b"{" + b" " * (200 << 20) + b"}"
    r = env.client.post("/api/auth/login", content=big,
                        headers={"content-type": "application/json"})
    assert r.status_code == 413, r.status_code
    assert "at most 1048576 bytes" in r.json()["detail"]
    del big
    # a body the cap allows still logs in
    ok = env.client.post("/api/auth/login", json={"username": "admin",
                                                  "password": "correct-horse-battery"})
    assert ok.status_code == 200


def test_mask_body_capped_by_the_frame_size(world):
    """The mask routes take at most 4 bytes per pixel of the frame + 64 KiB: a 1 MiB upload
    limit does not let a 64x48 frame take 1 MiB."""
    env, hdr, scene, frames = world
    r = env.client.post(f"/api/scenes/{scene['id']}/next", headers=hdr["annotator"])
    fid = r.json()["id"]
    cap = 4 * W * H + 64 * 1024
    body = png(np.zeros((H, W), np.uint8)) + b"\x00" * (cap + 1)
    r = env.client.put(f"/api/frames/{fid}/mask", content=body,
                       headers={**hdr["annotator"], "content-type": "image/png",
                                "If-Match": '"none"'})
    assert r.status_code == 413, (r.status_code, r.text)
    assert f"at most {cap} bytes" in r.json()["detail"]
    r = env.client.put(f"/api/frames/{fid}/mask", content=mask_png(),
                       headers={**hdr["annotator"], "content-type": "image/png",
                                "If-Match": '"none"'})
    assert r.status_code == 200, r.text




# ---- against a real server process (its memory is measured, not the test's) -----------------
@pytest.fixture
def live_server(tmp_path):
    env = {**os.environ, "OCCUFLY_DATA_DIR": str(tmp_path / "data"), "OCCUFLY_ENV": "development",
           "OCCUFLY_LIFTING": "off", "OCCUFLY_JOB_PROCESSES": "0",
           "OCCUFLY_ARGON2_MEMORY_KIB": "1024", "OCCUFLY_ARGON2_TIME_COST": "1"}
    with ProcessServer(env, tmp_path / "server.log", start_timeout=60) as server:
        yield server.port, psutil.Process(server.pid)


def _send_body(port: int, size: int, *, chunked: bool, peak: dict) -> tuple[bytes, int]:
    """POST /api/auth/login with ``size`` bytes of body; returns (status line, bytes sent
    before the server closed or the body was done)."""
    c = socket.create_connection(("127.0.0.1", port), timeout=30)
    head = b"POST /api/auth/login HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
    head += b"Transfer-Encoding: chunked\r\n\r\n" if chunked else f"Content-Length: {size}\r\n\r\n".encode()
    c.sendall(head)
    piece = b" " * (1 << 20)
    sent = 0
    try:
        while sent < size:
            c.sendall((b"100000\r\n" + piece + b"\r\n") if chunked else piece)
            sent += len(piece)
    except OSError:
        pass  # the server answered and closed: the rest is never read
    if chunked and sent >= size:
        try:
            c.sendall(b"0\r\n\r\n")
        except OSError:
            pass
    try:
        status = c.recv(64).split(b"\r\n")[0]
    except OSError:
        status = b""
    c.close()
    return status, sent


def test_200mb_login_body_does_not_raise_server_memory(live_server):
    """Finding 4 as reported: 200 MB to the public login raised the server by 535 MB; four
    concurrent 80 MB bodies took it from 0.66 to 2.3 GB. Now: 413, and the server's resident
    memory grows by less than 40 MB over all of it (Content-Length and chunked)."""
    port, server = live_server
    base = server.memory_info().rss
    peak = {"rss": base}
    stop = threading.Event()

    def watch() -> None:
        while not stop.is_set():
            peak["rss"] = max(peak["rss"], server.memory_info().rss)
            time.sleep(0.02)

    w = threading.Thread(target=watch)
    w.start()
    try:
        status, _sent = _send_body(port, 200 << 20, chunked=False, peak=peak)
        assert b"413" in status, status
        status, sent = _send_body(port, 200 << 20, chunked=True, peak=peak)
        assert b"413" in status, status
        results = []
        ts = [threading.Thread(target=lambda: results.append(
            _send_body(port, 80 << 20, chunked=True, peak=peak))) for _ in range(4)]
        for t in ts:
            t.start()
        for t in ts:
            t.join()
        assert [b"413" in s for s, _ in results] == [True] * 4, results
    finally:
        stop.set()
        w.join()
    grew = peak["rss"] - base
    print(f"server RSS {base / 2**20:.0f} MB -> peak {peak['rss'] / 2**20:.0f} MB "
          f"(+{grew / 2**20:.1f} MB) over 200 MB + 200 MB chunked + 4 x 80 MB chunked")
    assert grew < 40 << 20, grew


def test_mask_route_with_an_id_beyond_int32_is_422_not_500(world):
    """The cap's frame lookup must not fail on ids the database cannot hold (PostgreSQL
    raises for > 2**31-1): the route answers 422 as for any bad id."""
    env, hdr, _scene, _frames = world
    from fastapi.testclient import TestClient

    c = TestClient(env.app, raise_server_exceptions=False)
    for fid in ("9999999999", "2147483648"):
        r = c.put(f"/api/frames/{fid}/mask", content=mask_png(),
                  headers={**hdr["annotator"], "content-type": "image/png", "If-Match": '"none"'})
        assert r.status_code == 422, (fid, r.status_code, r.text[:200])
        r = c.post(f"/api/scenes/{fid}/corrections", json={"point_ids": [1]},
                   headers=hdr["reviewer"])
        assert r.status_code == 422, (fid, r.status_code, r.text[:200])
