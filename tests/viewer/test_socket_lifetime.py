"""Issue 40, defect 4: the /viewer/ socket outlives the server's body idle timeout.

Root cause: ``app.serving.TimedH11Protocol`` armed its request-body idle timer on the websocket
upgrade request (h11 still reports the client in ``SEND_BODY`` when uvicorn hands the
connection to the websocket protocol) and nothing cancelled it, so every viewer socket was
closed ``OCCUFLY_BODY_IDLE_TIMEOUT_S`` after it opened (30 s by default: Chromium reopened it
at 1.1, 31.1, 61.2, 91.2 s). Here the timeout is 1 s and the socket is held for 4 s with
traffic both ways: the old code closed it at ~1 s (``closed_for_idle_body`` counted it). A
request body that stalls on the same server is still closed after ~1 s (slow-loris guard).
"""

from __future__ import annotations

import asyncio
import socket
import time

import viser
from viewer_live import REVIEWER, LiveServer, camera_message, make_app

from app.serving import TimedH11Protocol

IDLE_S = 1.0
HOLD_S = 4.0


async def _hold(url: str, headers: dict) -> dict:
    from websockets.asyncio.client import connect

    out = {"frames": 0, "closed_after": None, "pongs": 0}
    t0 = time.perf_counter()
    async with connect(url, subprotocols=[f"viser-v{viser.__version__}"],
                       additional_headers=headers, max_size=None, ping_interval=None) as ws:
        await ws.send(camera_message())
        try:
            while time.perf_counter() - t0 < HOLD_S:
                try:
                    await asyncio.wait_for(ws.recv(), timeout=0.25)
                    out["frames"] += 1
                except TimeoutError:
                    # a live socket: the browser keeps reporting its camera, pings pass
                    await ws.send(camera_message(position=(0.0, 1.0, 50.0)))
                    await asyncio.wait_for(await ws.ping(), timeout=2.0)
                    out["pongs"] += 1
        except Exception:  # noqa: BLE001 - the server closed it
            out["closed_after"] = time.perf_counter() - t0
        out["close_code"] = ws.close_code
    return out


def test_viewer_socket_outlives_body_idle_timeout_and_stalled_bodies_still_close(
        tiny, monkeypatch):
    monkeypatch.setenv("OCCUFLY_BODY_IDLE_TIMEOUT_S", str(IDLE_S))
    app = make_app(tiny.ws.parent)
    with LiveServer(app) as srv:
        before = TimedH11Protocol.closed_for_idle_body
        got = asyncio.run(_hold(f"ws://127.0.0.1:{srv.port}/viewer",
                                {"Cookie": f"occufly_session={REVIEWER}; "
                                           "occufly_viewer_scene=tiny"}))
        assert got["closed_after"] is None, (
            f"the viewer socket was closed after {got['closed_after']:.1f} s (body idle "
            f"timeout {IDLE_S} s; idle-body closes {TimedH11Protocol.closed_for_idle_body - before})")
        assert got["frames"] > 0 and got["pongs"] >= 2, got
        assert TimedH11Protocol.closed_for_idle_body == before

        # the guard the timer exists for: a body that stops moving is still cut
        s = socket.create_connection(("127.0.0.1", srv.port))
        s.sendall(b"GET /api/ping HTTP/1.1\r\nHost: x\r\nContent-Length: 100\r\n\r\n{")
        s.settimeout(IDLE_S + 5)
        t0 = time.perf_counter()
        data = b""
        try:
            while chunk := s.recv(4096):
                data += chunk
        except (ConnectionResetError, TimeoutError):
            pass
        waited = time.perf_counter() - t0
        s.close()
        assert IDLE_S - 0.3 <= waited <= IDLE_S + 3.0, waited
        assert TimedH11Protocol.closed_for_idle_body == before + 1
