"""Security round three (issue 36), carried over from round two: a request body must keep up a
minimum average rate (app/serving.py). A body dribbled a byte every 0.5 s re-arms the body
idle timer with each byte, so before this it stayed open as long as the body caps allowed.

The app is served by uvicorn with the options of ``occufly serve`` (a thread of this process;
the timers read their environment variables when they are armed) and reached with raw sockets.
"""

from __future__ import annotations

import json
import selectors
import socket
import time

import pytest

from app.serving import TimedH11Protocol, uvicorn_options
from tests.app.conftest import PASSWORD
from tests.harness import ThreadServer

MIN_RATE = 100  # bytes/s
GRACE_S = 2.0
N_DRIBBLE = 20


@pytest.fixture
def served(env, monkeypatch):
    monkeypatch.setenv("OCCUFLY_BODY_MIN_RATE_BPS", str(MIN_RATE))
    monkeypatch.setenv("OCCUFLY_BODY_RATE_GRACE_S", str(GRACE_S))
    monkeypatch.setenv("OCCUFLY_BODY_IDLE_TIMEOUT_S", "30")  # only the rate may cut them
    with ThreadServer(env.app, **uvicorn_options(env.settings)) as srv:
        yield srv


def _head(port: int, length: int) -> bytes:
    return (f"POST /api/auth/login HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n"
            f"Content-Type: application/json\r\nContent-Length: {length}\r\n\r\n").encode()


def _dribble(socks: list[socket.socket], limit_s: float) -> list[float | None]:
    """Send one body byte on every open socket each 0.5 s; seconds from the first byte until
    the server closed each one (None: still open at limit_s)."""
    sel = selectors.DefaultSelector()
    for i, s in enumerate(socks):
        s.setblocking(False)
        sel.register(s, selectors.EVENT_READ, i)
    closed: dict[int, float] = {}
    t0 = time.perf_counter()
    next_drip = t0
    while len(closed) < len(socks) and time.perf_counter() - t0 < limit_s:
        if time.perf_counter() >= next_drip:
            next_drip += 0.5
            for i, s in enumerate(socks):
                if i not in closed:
                    try:
                        s.send(b" ")
                    except OSError:
                        closed[i] = time.perf_counter() - t0
                        sel.unregister(s)
        for key, _ev in sel.select(timeout=0.05):
            try:
                data = key.fileobj.recv(4096)
            except (ConnectionResetError, BlockingIOError) as e:
                data = b"" if isinstance(e, ConnectionResetError) else None
            if data == b"":
                closed[key.data] = time.perf_counter() - t0
                sel.unregister(key.fileobj)
    sel.close()
    return [closed.get(i) for i in range(len(socks))]


@pytest.mark.parametrize("env", ["sqlite"], indirect=True)  # no database work here
def test_a_body_dribbled_a_byte_at_a_time_is_cut(served):
    """20 connections each announcing a 1,000-byte body and sending one byte every 0.5 s
    (2 bytes/s, the minimum 100 bytes/s after a 2 s grace): every one is closed ~2 s after
    its first body byte, and the server keeps answering meanwhile."""
    import httpx

    before = TimedH11Protocol.closed_for_slow_body
    socks = [socket.create_connection(("127.0.0.1", served.port)) for _ in range(N_DRIBBLE)]
    for s in socks:
        s.sendall(_head(served.port, 1000))
    t = _dribble(socks, limit_s=15.0)
    assert httpx.get(f"{served.url}/api/health", timeout=5).status_code == 200
    for s in socks:
        s.close()
    still_open = [i for i, x in enumerate(t) if x is None]
    assert not still_open, f"{len(still_open)} dribbling connections still open after 15 s"
    assert GRACE_S - 0.5 <= min(t) and max(t) <= GRACE_S + 3.0, t
    assert TimedH11Protocol.closed_for_slow_body - before == N_DRIBBLE
    print(f"\n{N_DRIBBLE} bodies dribbled at 2 B/s closed {min(t):.2f}-{max(t):.2f} s after "
          f"their first byte (minimum {MIN_RATE} B/s after {GRACE_S} s)")


@pytest.mark.parametrize("env", ["sqlite"], indirect=True)
def test_a_slow_but_steady_upload_passes(served):
    """A 1,500-byte login body sent at ~300 bytes/s (3x the minimum) over 5 s -- longer than
    the grace -- is answered 200: the minimum cuts dribbles, not slow links."""
    body = json.dumps({"username": "reviewer", "password": PASSWORD}).encode()
    body += b" " * (1500 - len(body))
    s = socket.create_connection(("127.0.0.1", served.port))
    s.settimeout(20)
    s.sendall(_head(served.port, len(body)))
    t0 = time.perf_counter()
    for i in range(0, len(body), 30):  # 30 bytes every 0.1 s
        s.sendall(body[i:i + 30])
        time.sleep(0.1)
    answer = s.recv(65536)
    took = time.perf_counter() - t0
    s.close()
    assert answer.startswith(b"HTTP/1.1 200"), answer[:200]
    assert took > GRACE_S + 1, took
