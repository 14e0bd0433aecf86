"""The /viewer/ proxy: refusals, the page, the websocket with tickets, direct access refused."""

from __future__ import annotations

import asyncio
import time

import numpy as np
import pytest
import viser
from fastapi import FastAPI, HTTPException
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect
from viewer_fixtures import COUNTS
from viewer_live import (
    ANNOTATOR,
    REVIEWER,
    FakeSettings,
    LiveServer,
    camera_message,
    fake_client,
    make_app,
)

from app import viewer
from app.viewer import server as vserver
from app.viewer import state as vstate

PROTO = f"viser-v{viser.__version__}"


@pytest.fixture
def client(tiny):
    app = make_app(tiny.ws.parent)
    with TestClient(app) as c:  # runs the lifespan: viser starts in the background
        yield c
    assert not app.state.viewer.running  # and stops with the app


def test_http_refusals(client):
    r = client.get("/viewer/")
    assert r.status_code == 401 and "log in" in r.json()["detail"]
    r = client.get("/viewer/some/asset.js")
    assert r.status_code == 401
    r = client.get("/viewer/", headers={"Authorization": f"Bearer {ANNOTATOR}"})
    assert r.status_code == 403
    client.cookies.set("occufly_session", ANNOTATOR)
    r = client.get("/viewer/")
    assert r.status_code == 403 and "reviewers" in r.json()["detail"]
    assert client.app.state.viewer.client_states() == []  # nothing reached viser


def test_http_exception_from_authorize_is_passed_through(tmp_path):
    def authorize(conn):
        raise HTTPException(status_code=403, detail="nope")

    app = FastAPI()
    viewer.mount(app, settings=FakeSettings(tmp_path), authorize=authorize)
    assert TestClient(app).get("/viewer/").status_code == 403


def test_websocket_refused_with_1008(client):
    with pytest.raises(WebSocketDisconnect) as e:
        with client.websocket_connect("/viewer", subprotocols=[PROTO]) as ws:
            ws.receive_bytes()
    assert e.value.code == 1008
    client.cookies.set("occufly_session", ANNOTATOR)
    with pytest.raises(WebSocketDisconnect) as e:
        with client.websocket_connect("/viewer/", subprotocols=[PROTO]) as ws:
            ws.receive_bytes()
    assert e.value.code == 1008


def test_page_for_reviewer_and_scene_cookie(client):
    r = client.get("/viewer", params={"scene": "tiny"}, follow_redirects=False)
    assert r.status_code == 307 and r.headers["location"] == "/viewer/?scene=tiny"
    client.cookies.set("occufly_session", REVIEWER)
    r = client.get("/viewer/?scene=tiny")
    assert r.status_code == 200
    assert r.headers["content-type"].startswith("text/html")
    assert "<canvas" in r.text or "viser" in r.text.lower()
    assert "occufly_viewer_scene=tiny" in r.headers["set-cookie"]
    assert "Path=/viewer" in r.headers["set-cookie"]
    svc = client.app.state.viewer
    assert svc.running and svc.server.get_host() == "127.0.0.1"


def test_proxied_socket_sends_float32_cloud_and_direct_socket_is_refused(tiny):
    """Through the proxy a reviewer's socket gets every point as float32 (>= 12 bytes each);
    the same viser port reached directly (no ticket) gets a 1008 close and no scene."""

    app = make_app(tiny.ws.parent)
    n = sum(COUNTS.values())
    with LiveServer(app) as srv:
        svc = app.state.viewer

        # the client's state, read while its socket is still open (a close drops it)
        got = asyncio.run(fake_client(
            f"ws://127.0.0.1:{srv.port}/viewer",
            {"Cookie": f"occufly_session={REVIEWER}; occufly_viewer_scene=tiny"},
            while_open=svc.client_states))
        proxied, states = got["bytes"], got["open"]
        assert len(states) == 1 and states[0].scene_id == "tiny"
        assert states[0].user == {"username": "rita", "role": "reviewer"}
        assert states[0].sent_points == n
        assert proxied >= n * (12 + 3)  # float32 xyz + uint8 rgb per point, at least
        d = asyncio.run(fake_client(f"ws://127.0.0.1:{svc.port}/", {}))
        direct, code = d["bytes"], d["close_code"]
        assert code == 1008
        assert direct < n * 12
        time.sleep(0.3)
        assert all(s.scene_id == "tiny" for s in svc.client_states())  # no ticketless client


def test_tickets_are_single_use_and_expire(tiny, monkeypatch):
    svc = vserver.ViewerService(scenes=vstate.default_scenes(tiny.ws.parent))
    tok = svc.issue_ticket("u", "tiny")
    t = svc.redeem_ticket(tok)
    assert t is not None and t.user == "u" and t.scene_id == "tiny"
    assert svc.redeem_ticket(tok) is None  # single use
    assert svc.redeem_ticket("forged") is None
    monkeypatch.setattr(vserver, "TICKET_TTL_S", -1.0)
    assert svc.redeem_ticket(svc.issue_ticket("v", None)) is None  # expired


def test_viewer_refuses_non_loopback_host(tiny):
    with pytest.raises(ValueError, match="loopback"):
        vserver.ViewerService(scenes=vstate.default_scenes(tiny.ws.parent), host="0.0.0.0")


def test_default_scenes_finds_workspaces(tiny):
    table = vstate.default_scenes(tiny.ws.parent)()
    assert list(table) == ["tiny"] and table["tiny"][1] == tiny.ws
    assert np.isfinite(len(table))


def test_refresh_resends_only_the_affected_classes(tiny):
    """Three grass points become vehicle: refresh() re-sends grass + vehicle (655 points),
    not the 1000-point cloud, to the open viewer."""
    from websockets.asyncio.client import connect

    from occufly.fsutil import atomic_save_npy

    app = make_app(tiny.ws.parent)
    with LiveServer(app) as srv:
        svc = app.state.viewer
        headers = {"Cookie": f"occufly_session={REVIEWER}; occufly_viewer_scene=tiny"}

        async def drain(ws, quiet: float) -> int:
            got = 0
            try:
                while True:
                    got += len(await asyncio.wait_for(ws.recv(), timeout=quiet))
            except TimeoutError:
                return got

        async def run() -> tuple[int, int]:
            async with connect(f"ws://127.0.0.1:{srv.port}/viewer", subprotocols=[PROTO],
                               additional_headers=headers, max_size=None) as ws:
                await ws.send(camera_message())
                first = await drain(ws, 1.0)
                labels = tiny.labels.copy()
                labels[np.flatnonzero(labels == 6)[:3]] = 13
                atomic_save_npy(tiny.ws / "lifting" / "labels.npy", labels)
                svc.refresh("tiny")
                second = await drain(ws, 1.5)
                st = svc.client_states()[0]
                return first, second, len(st.point_nodes[13].point_ids), st.class_boxes[13].label

        first, second, n_vehicle, box_label = asyncio.run(run())
        n = sum(COUNTS.values())
        assert first >= 15 * n
        assert 15 * (597 + 58) <= second < 15 * n  # only grass and vehicle went again
        assert n_vehicle == 58 and box_label == "vehicle (58)"


def test_large_scene_gets_a_preview_first_then_the_full_lod(tiny):
    app = make_app(tiny.ws.parent, preview_points=100)  # 1000 points > 4 x 100: preview
    n = sum(COUNTS.values())
    with LiveServer(app) as srv:
        svc = app.state.viewer
        r = asyncio.run(fake_client(
            f"ws://127.0.0.1:{srv.port}/viewer",
            {"Cookie": f"occufly_session={REVIEWER}; occufly_viewer_scene=tiny"},
            min_bytes=15 * (n + 100)))
        assert r["bytes"] >= 15 * (n + 100)  # the preview's 100 points, then all 1000
        assert r["bytes"] < 15 * (2 * n)
        assert svc.preview_points == 100
