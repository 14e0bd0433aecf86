"""Shared fixtures' helpers: a live uvicorn app with the viewer mounted, a test authorize."""

from __future__ import annotations

import socket
import threading
import time
from pathlib import Path

import uvicorn
from fastapi import FastAPI, Request

from app import viewer

REVIEWER = "reviewer-token"
ANNOTATOR = "annotator-token"
CHROMIUM_ARGS = [
    "--no-sandbox", "--disable-gpu", "--disable-background-networking",
    "--disable-component-update", "--no-first-run", "--disable-sync",
    "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
]


class FakeSettings:
    def __init__(self, data_dir: Path, viewer_max_points: int = 2_000_000) -> None:
        self.data_dir = Path(data_dir)
        self.viewer_max_points = viewer_max_points


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


def make_app(data_dir: Path, **kw) -> FastAPI:
    app = FastAPI()

    @app.get("/api/ping")
    def ping(request: Request) -> dict:
        return {"ok": True}

    viewer.mount(app, settings=FakeSettings(data_dir), authorize=test_authorize, **kw)
    return app


class LiveServer:
    """uvicorn on a free loopback port in a thread (lifespan on, so viser starts with it)."""

    def __init__(self, app: FastAPI) -> None:
        self.app = app
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        cfg = uvicorn.Config(app, log_level="warning", lifespan="on", ws_max_size=64 << 20)
        self.server = uvicorn.Server(cfg)
        self.thread = threading.Thread(target=self.server.run, kwargs={"sockets": [self.sock]},
                                       daemon=True)

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def __enter__(self) -> LiveServer:
        self.thread.start()
        t0 = time.time()
        while not self.server.started:
            if time.time() - t0 > 30:
                raise RuntimeError("uvicorn did not start")
            time.sleep(0.02)
        return self

    def __exit__(self, *exc) -> None:
        self.server.should_exit = True
        self.thread.join(timeout=15)
        self.sock.close()
