"""Shared fixtures' helpers: a live uvicorn app with the viewer mounted, a test authorize."""

from __future__ import annotations

from pathlib import Path

from fastapi import FastAPI, Request

from app import viewer
from app.serving import uvicorn_options
from tests.harness import ThreadServer

REVIEWER = "reviewer-token"
ANNOTATOR = "annotator-token"
CHROMIUM_ARGS = [
    "--no-sandbox", "--disable-gpu", "--disable-background-networking",
    "--disable-component-update", "--no-first-run", "--disable-sync",
    "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
]


class FakeSettings:
    def __init__(self, data_dir: Path, viewer_max_points: int = 2_000_000,
                 viewer_preview_points: int = 150_000) -> None:
        self.data_dir = Path(data_dir)
        self.viewer_max_points = viewer_max_points
        self.viewer_preview_points = viewer_preview_points


def test_authorize(conn) -> bool:  # noqa: ANN001 - Request or WebSocket
    """A logged-in reviewer has cookie occufly_session=reviewer-token (or the bearer)."""
    token = conn.cookies.get("occufly_session")
    auth = conn.headers.get("authorization", "")
    if auth.lower().startswith("bearer "):
        token = auth[7:]
    if token == REVIEWER:
        conn.state.user = {"username": "rita", "role": "reviewer"}
        return True
    return False


test_authorize.__test__ = False  # not a pytest test


def make_app(data_dir: Path, *, preview_points: int = 150_000, **kw) -> FastAPI:
    app = FastAPI()

    @app.get("/api/ping")
    def ping(request: Request) -> dict:
        return {"ok": True}

    viewer.mount(app, settings=FakeSettings(data_dir, viewer_preview_points=preview_points),
                 authorize=test_authorize, **kw)
    return app


class LiveServer(ThreadServer):
    """The suite's live server (tests.harness.ThreadServer: uvicorn in a thread on a free
    loopback port, lifespan on, so viser starts with it)."""

    def __init__(self, app: FastAPI) -> None:
        # served as `occufly serve` serves the app (app.serving: its h11 protocol with the
        # header and body timeouts, no permessage-deflate on the viewer socket): a test
        # server without them never saw the body timer cut the viewer socket (issue 40)
        super().__init__(app, ws_max_size=64 << 20, **uvicorn_options(None))


def camera_message(position=(0.0, 0.0, 50.0), look_at=(0.0, 0.0, 0.0)) -> bytes:
    """What viser's browser client sends first: its camera (a client counts as connected
    only after this). msgpack of the message's serializable dict."""
    import msgspec
    from viser._messages import ViewerCameraMessage

    msg = ViewerCameraMessage(wxyz=(1.0, 0.0, 0.0, 0.0), position=tuple(position), fov=1.0,
                              near=0.01, far=1000.0, image_height=600, image_width=800,
                              look_at=tuple(look_at), up_direction=(0.0, 0.0, 1.0))
    return msgspec.msgpack.encode(msg.as_serializable_dict())


async def fake_client(url: str, headers: dict, *, quiet_s: float = 1.0,
                      max_s: float = 60.0, min_bytes: int = 0, while_open=None) -> dict:
    """Connect like viser's client, send the camera, read until ``quiet_s`` of silence
    (once at least ``min_bytes`` arrived; silence before that is waited out up to ``max_s``).

    ``while_open()``, if given, runs after the reading, before the socket closes (the server
    drops a client's state once it sees the close); its result is returned as ``"open"``.
    Returns bytes, frames, seconds from connect to the last frame, and the close code."""
    import asyncio
    import time

    import viser
    from websockets.asyncio.client import connect

    out = {"bytes": 0, "frames": 0, "last_s": None, "close_code": None}
    t0 = time.perf_counter()
    async with connect(url, subprotocols=[f"viser-v{viser.__version__}"],
                       additional_headers=headers, max_size=None) as ws:
        await ws.send(camera_message())
        try:
            while time.perf_counter() - t0 < max_s:
                try:
                    m = await asyncio.wait_for(ws.recv(), timeout=quiet_s)
                except TimeoutError:
                    if out["bytes"] >= min_bytes:
                        break
                    continue
                out["bytes"] += len(m)
                out["frames"] += 1
                out["last_s"] = time.perf_counter() - t0
        except (TimeoutError, Exception):  # noqa: BLE001 - silence or close ends it
            pass
        if while_open is not None:
            out["open"] = while_open()
        out["close_code"] = ws.close_code
    return out
