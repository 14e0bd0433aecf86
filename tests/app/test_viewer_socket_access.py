"""Security round two (issue 24), findings 7 and 9: viewer sockets lose access on removal and
demotion, per-user socket cap, Content-Security-Policy, Secure cookies behind TLS.

Sockets here are real: the app (SQLite and PostgreSQL) is served by uvicorn on a loopback
port and the viewer is reached with the ``websockets`` client, like a browser would.
"""

from __future__ import annotations

import asyncio
import re
import time

import pytest

from app.serving import uvicorn_options
from tests.harness import ThreadServer

SOCKETS_OPENED = {"n": 0}  # the closing note's count
# a socket whose access ended closes within this many seconds of the answer to the request
# that ended it. The viewer re-checks every 0.25 s (1 s is the target on a quiet machine, see
# the printed figures); 2 s holds on a loaded 2-core runner, while the defect (a socket never
# closed, or closed only by a slow sweep) still fails: the drain waits 1 s longer than this.
CLOSE_LIMIT_S = 2.0


def Served(app) -> ThreadServer:  # noqa: ANN001, N802
    """The app served as ``occufly serve`` serves it (its uvicorn options), on a free port."""
    return ThreadServer(app, **uvicorn_options(app.state.ctx.settings))


def _token(env, name: str) -> str:  # noqa: ANN001
    return env.bearer(name)["Authorization"].split(" ", 1)[1]


async def _open(port: int, token: str, scene_id: int):  # noqa: ANN202
    import viser
    from websockets.asyncio.client import connect

    from tests.viewer.viewer_live import camera_message

    ws = await connect(f"ws://127.0.0.1:{port}/viewer",
                       subprotocols=[f"viser-v{viser.__version__}"],
                       additional_headers={"Cookie": f"occufly_session={token}; "
                                                     f"occufly_viewer_scene={scene_id}",
                                           "Origin": f"http://127.0.0.1:{port}"},
                       max_size=None, open_timeout=20)
    SOCKETS_OPENED["n"] += 1
    from websockets.exceptions import ConnectionClosed

    try:
        await ws.send(camera_message())
    except ConnectionClosed:  # refused at once (the caller reads close_code)
        pass
    return ws


async def _drain_until_closed(ws, limit_s: float) -> tuple[float | None, int]:  # noqa: ANN001
    """Seconds until the server closed ``ws`` (None: still open after limit_s), bytes read."""
    from websockets.exceptions import ConnectionClosed

    t0 = time.perf_counter()
    got = 0
    while time.perf_counter() - t0 < limit_s:
        try:
            m = await asyncio.wait_for(ws.recv(), timeout=max(0.05, limit_s -
                                                               (time.perf_counter() - t0)))
            got += len(m)
        except TimeoutError:
            return None, got
        except ConnectionClosed:
            return time.perf_counter() - t0, got
    return None, got


async def _wait_registered(app, n: int, timeout: float = 30.0) -> None:  # noqa: ANN001
    t0 = time.monotonic()
    while len([c for c in app.state.viewer.client_states() if c.scene_id]) < n:
        assert time.monotonic() - t0 < timeout, "viewer clients did not open their scene"
        await asyncio.sleep(0.05)


def test_viewer_socket_closes_within_a_second_on_removal_and_demotion(world):
    """Finding 7: removal from the scene and demotion to annotator close the viewer socket
    within 1 s (before: only deactivation/password reset did; a removed reviewer's socket kept
    receiving the scene's label updates). A reviewer who stays a member keeps theirs."""
    env, hdr, scene, _frames = world
    sid = scene["id"]
    admin = hdr["admin"]
    r = env.client.post("/api/users", json={"username": "reviewer2", "password":
                                            "correct-horse-battery", "role": "reviewer"},
                        headers=admin)
    assert r.status_code == 201, r.text
    env.add_members(sid, ["reviewer2"], admin)
    users = {u["username"]: u["id"] for u in env.client.get("/api/users", headers=admin).json()}
    tok_rev, tok_rev2 = _token(env, "reviewer"), _token(env, "reviewer2")

    async def run() -> dict:
        out = {}
        with Served(env.app) as srv:
            a = await _open(srv.port, tok_rev, sid)
            b = await _open(srv.port, tok_rev2, sid)
            await _wait_registered(env.app, 2)
            await asyncio.sleep(0.3)
            # removal from the scene: reviewer's socket closes, reviewer2's stays
            t0 = time.perf_counter()
            r = await asyncio.to_thread(env.client.delete,
                                        f"/api/scenes/{sid}/members/{users['reviewer']}",
                                        headers=admin)
            assert r.status_code == 204, r.text
            out["removal_request_s"] = time.perf_counter() - t0
            closed, _ = await _drain_until_closed(a, CLOSE_LIMIT_S + 1.0)
            out["removed_s"] = closed  # from the answer to the request
            out["removed_code"] = a.close_code
            out["kept_open"], _ = await _drain_until_closed(b, 1.5)
            # demotion (reviewer -> annotator): the remaining socket closes
            t0 = time.perf_counter()
            r = await asyncio.to_thread(env.client.patch, f"/api/users/{users['reviewer2']}",
                                        json={"role": "annotator"}, headers=admin)
            assert r.status_code == 200, r.text
            out["demotion_request_s"] = time.perf_counter() - t0
            closed, _ = await _drain_until_closed(b, CLOSE_LIMIT_S + 1.0)
            out["demoted_s"] = closed
            out["demoted_code"] = b.close_code
            # a removed reviewer who reconnects is refused at once
            c = await _open(srv.port, tok_rev, sid)
            out["again_s"], _ = await _drain_until_closed(c, 3.0)
            out["again_code"] = c.close_code
        return out

    out = asyncio.run(run())
    assert out["removed_s"] is not None and out["removed_s"] <= CLOSE_LIMIT_S, out
    assert out["removed_code"] == 1008, out
    assert out["kept_open"] is None, out  # None: still open after 1.5 s
    assert out["demoted_s"] is not None and out["demoted_s"] <= CLOSE_LIMIT_S, out
    assert out["demoted_code"] == 1008, out
    assert out["again_s"] is not None and out["again_code"] == 1008, out
    print(f"closed after removal {out['removed_s']:.2f} s, after demotion "
          f"{out['demoted_s']:.2f} s")


def test_admin_demoted_to_reviewer_loses_a_scene_they_are_not_member_of(world):
    env, hdr, scene, _frames = world
    admin = hdr["admin"]
    r = env.client.post("/api/users", json={"username": "admin2", "password":
                                            "correct-horse-battery", "role": "admin"},
                        headers=admin)
    assert r.status_code == 201, r.text
    uid = r.json()["id"]
    tok = _token(env, "admin2")

    async def run():  # noqa: ANN202
        with Served(env.app) as srv:
            a = await _open(srv.port, tok, scene["id"])
            await _wait_registered(env.app, 1)
            r = await asyncio.to_thread(env.client.patch, f"/api/users/{uid}",
                                        json={"role": "reviewer"}, headers=admin)
            assert r.status_code == 200, r.text
            return await _drain_until_closed(a, CLOSE_LIMIT_S + 1.0)

    closed_s, _ = asyncio.run(run())
    assert closed_s is not None and closed_s <= CLOSE_LIMIT_S, closed_s


def test_viewer_sockets_per_user_are_capped(world):
    """Finding 9: at most OCCUFLY_VIEWER_SOCKETS_PER_USER (here 2) open viewer sockets per user;
    the next is closed 1008 with the reason; closing one frees a place; other users unaffected."""
    import dataclasses

    env, hdr, scene, _frames = world
    env.app.state.viewer.max_sockets_per_user = 2
    env.app.state.ctx.settings = dataclasses.replace(env.settings, viewer_sockets_per_user=2)
    tok = _token(env, "reviewer")
    tok_admin = _token(env, "admin")

    async def run() -> dict:
        with Served(env.app) as srv:
            a = await _open(srv.port, tok, scene["id"])
            b = await _open(srv.port, tok, scene["id"])
            await _wait_registered(env.app, 2)
            c = await _open(srv.port, tok, scene["id"])
            c_closed, _ = await _drain_until_closed(c, 3.0)
            d = await _open(srv.port, tok_admin, scene["id"])  # another user: fine
            d_open, _ = await _drain_until_closed(d, 1.0)
            await a.close()
            await asyncio.sleep(0.5)
            e = await _open(srv.port, tok, scene["id"])
            e_open, _ = await _drain_until_closed(e, 1.0)
            for w in (b, d, e):
                await w.close()
            return {"c_closed": c_closed, "c_code": c.close_code, "c_reason": c.close_reason,
                    "d_open": d_open, "e_open": e_open}

    out = asyncio.run(run())
    assert out["c_closed"] is not None and out["c_code"] == 1008, out
    assert "too many 3D viewer windows" in out["c_reason"], out
    assert out["d_open"] is None and out["e_open"] is None, out


def test_content_security_policy_on_every_page(world):
    """Finding 9: script-src 'self' (no inline script, no eval) on the app's pages, the API,
    the API docs and the viewer; the viewer adds only WebAssembly/blob workers."""
    env, hdr, scene, _frames = world
    rev = env.login("reviewer")
    for path in ("/", "/index.html", "/js/main.js", "/api/health", "/docs",
                 "/api/does-not-exist", f"/viewer/?scene={scene['id']}"):
        r = rev.get(path)
        csp = r.headers.get("content-security-policy", "")
        d = dict(part.strip().split(" ", 1) for part in csp.split(";") if part.strip())
        script = d.get("script-src", "")
        assert script.split()[0] == "'self'", (path, csp)
        assert "'unsafe-inline'" not in script and "'unsafe-eval'" not in script, (path, csp)
        assert d.get("object-src") == "'none'" and "frame-ancestors" in d, (path, csp)
        if path.startswith("/viewer"):
            assert script == "'self' 'wasm-unsafe-eval'", csp
    # the viewer page itself has no inline script left: every <script> has a same-origin src
    page = rev.get(f"/viewer/?scene={scene['id']}")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    scripts = re.findall(r"<script\b([^>]*)>(.*?)</script>", page.text, flags=re.S)
    assert scripts, page.text[:500]
    for attrs, body in scripts:
        assert re.search(r'\ssrc="\./__occufly/', attrs) and not body.strip(), attrs
    assert "data-p=" not in page.text
    # its assets: the app's module, the loader, the WebAssembly decoder, the stylesheet
    for name, ctype in (("loader.js", "text/javascript"), ("client.js", "text/javascript"),
                        ("zstd.wasm", "application/wasm"), ("client.css", "text/css")):
        r = rev.get(f"/viewer/__occufly/{name}")
        assert r.status_code == 200 and r.headers["content-type"].startswith(ctype), name
    assert rev.get("/viewer/__occufly/zstd.wasm").content[:4] == b"\0asm"
    assert env.client.get("/viewer/__occufly/client.js").status_code == 401  # not logged in
    # the app's own HTML pages carry no inline script either
    html = rev.get("/").text + rev.get("/docs").text
    for attrs, body in re.findall(r"<script\b([^>]*)>(.*?)</script>", html, flags=re.S):
        assert "src=" in attrs and not body.strip(), attrs


def test_session_cookie_is_secure_behind_tls_only(env):
    """Finding 9: the session cookie (and the viewer's scene cookie) carry ``Secure`` when the
    request came over TLS -- directly, or via a trusted proxy's X-Forwarded-Proto with
    ``--proxy-headers`` (tests/app/test_serving.py) -- and not over plain HTTP."""
    from fastapi.testclient import TestClient

    body = {"username": "reviewer", "password": "correct-horse-battery"}
    tls = TestClient(env.app, base_url="https://testserver")
    r = tls.post("/api/auth/login", json=body)
    assert r.status_code == 200 and "secure" in r.headers["set-cookie"].lower(), r.headers
    plain = TestClient(env.app, base_url="http://testserver")
    r = plain.post("/api/auth/login", json=body)
    assert r.status_code == 200 and "secure" not in r.headers["set-cookie"].lower()
    adm = TestClient(env.app, base_url="https://testserver")
    assert adm.post("/api/auth/login", json={**body, "username": "admin"}).status_code == 200
    r = adm.get("/viewer/?scene=1")
    assert r.status_code == 200, r.text
    assert "occufly_viewer_scene=1" in r.headers["set-cookie"]
    assert "secure" in r.headers["set-cookie"].lower()


@pytest.fixture(autouse=True, scope="module")
def _report_counts():
    yield
    print(f"\nviewer sockets opened: {SOCKETS_OPENED['n']}")
