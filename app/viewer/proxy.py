"""Reverse proxy: the viser page and websocket under ``/viewer/``, for authorised users only.

- ``GET /viewer/`` and ``GET /viewer/{path}`` go to viser's HTTP server with httpx (cookies and
  ``Authorization`` are *not* forwarded). ``?scene=<id>`` on the page is remembered in the
  cookie ``occufly_viewer_scene`` (path ``/viewer``) because viser's client opens its
  websocket at the page URL without the query string.
- Each page load gets a new *view id* (cookie ``occufly_viewer_view``): viser's client
  reopens its socket by itself after a drop, with the same id, so the server puts that tab's
  selection, panel and camera back (:mod:`app.viewer.session_state`); a reload starts fresh.
- The websocket (``/viewer`` -- viser's client strips the trailing slash -- and ``/viewer/``)
  is accepted only after ``authorize``; the upstream connection carries a one-time ticket
  naming the user and scene (see :mod:`app.viewer.server`), then frames are pumped both ways.

Refusals: HTTP 401 without credentials, 403 with credentials that ``authorize`` rejects (or the
status of an ``HTTPException`` it raises); websockets are accepted and closed with code 1008.
"""

from __future__ import annotations

import asyncio
import inspect
import logging
import re
import secrets
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import httpx
from fastapi import FastAPI, HTTPException, Request, WebSocket
from fastapi.responses import JSONResponse, RedirectResponse, Response
from starlette.concurrency import run_in_threadpool
from starlette.websockets import WebSocketDisconnect
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed

from app.shared_limits import SocketCapReached
from app.viewer.client_page import ASSET_DIR, ClientLayoutError, client_assets
from app.viewer.server import ViewerService
from app.viewer.state import TICKET_HEADER

log = logging.getLogger(__name__)

SCENE_COOKIE = "occufly_viewer_scene"
FRAME_COOKIE = "occufly_viewer_frame"  # ?frame= of the page: the viewer flies to that camera
SUSPECT_COOKIE = "occufly_viewer_suspect"  # ?suspect= of the page: the viewer selects its points
VIEW_COOKIE = "occufly_viewer_view"  # one per page load: a reconnect restores that tab's state
_VIEW_ID = re.compile(r"^[A-Za-z0-9_-]{8,64}$")
_SUSPECT_KEY = re.compile(r"^[pr][0-9]{1,12}$")
SESSION_COOKIE = "occufly_session"
POLICY_VIOLATION = 1008
_CTRL = re.compile(r"[\x00-\x1f\x7f]")  # never in a file name viser serves


async def check_access(authorize: Callable[[Any], Any], conn: Request | WebSocket) -> int:
    """200 when ``authorize(conn)`` admits the caller, else 401 (no credentials) or 403."""
    try:
        if inspect.iscoroutinefunction(authorize):
            ok = await authorize(conn)
        else:
            ok = await run_in_threadpool(authorize, conn)
            if inspect.isawaitable(ok):
                ok = await ok
    except HTTPException as e:
        return int(e.status_code)
    if ok:
        return 200
    has_credentials = SESSION_COOKIE in conn.cookies or bool(conn.headers.get("authorization"))
    return 403 if has_credentials else 401


def add_routes(app: FastAPI, service: ViewerService, *, authorize: Callable[[Any], Any],
               identify: Callable[[Any], Any] | None = None, prefix: str = "/viewer") -> None:
    """Register the proxy routes on ``app``."""
    prefix = prefix.rstrip("/")
    def refusal(status: int) -> JSONResponse:
        detail = ("log in to open the 3D viewer" if status == 401
                  else "the 3D viewer is for reviewers and admins")
        return JSONResponse({"detail": detail}, status_code=status)

    async def page(request: Request, path: str = "") -> Response:
        status = await check_access(authorize, request)
        if status != 200:
            return refusal(status)
        if not service.running:  # the page's socket follows at once
            await run_in_threadpool(service.start)
        if path in ("", "index.html") or path.startswith(f"{ASSET_DIR}/"):
            # viser's client unpacked so no inline script runs (app/viewer/client_page.py)
            try:
                assets = await run_in_threadpool(client_assets)
            except ClientLayoutError as e:
                return JSONResponse({"detail": f"3D viewer client unavailable: {e}"},
                                    status_code=502)
            if path.startswith(f"{ASSET_DIR}/"):
                name = path[len(ASSET_DIR) + 1:]
                if name not in assets.files:
                    return JSONResponse({"detail": f"no viewer asset {name!r}"}, status_code=404)
                body, ctype = assets.files[name]
                return Response(body, media_type=ctype, headers={
                    "Cache-Control": "private, max-age=86400", "X-Content-Type-Options": "nosniff"})
            resp = Response(assets.page, media_type="text/html; charset=utf-8",
                            headers={"Cache-Control": "no-cache",
                                     "X-Content-Type-Options": "nosniff"})
            _remember_scene(resp, request, prefix)
            resp.set_cookie(VIEW_COOKIE, secrets.token_urlsafe(12), path=prefix, httponly=True,
                            samesite="lax", secure=request.url.scheme == "https")
            return resp
        if _CTRL.search(path) or ".." in path.split("/"):
            # a NUL or other control character (``main.js%00.png``), or a dot-dot segment, names
            # nothing viser serves: 404 here instead of a 500 from the URL parser (issue 24)
            return JSONResponse({"detail": "no such viewer file"}, status_code=404)
        url = f"http://127.0.0.1:{service.port}/{path}"
        headers = {}
        if "accept-encoding" in request.headers:
            headers["accept-encoding"] = request.headers["accept-encoding"]
        try:  # forward the raw (possibly gzip-encoded) body unchanged; no pooled
            # connection is kept open to viser (page loads are rare, shutdown stays fast)
            async with httpx.AsyncClient(timeout=30.0) as client:
                up = await client.send(client.build_request("GET", url, headers=headers),
                                       stream=True)
                try:
                    body = b"".join([chunk async for chunk in up.aiter_raw()])
                finally:
                    await up.aclose()
        except httpx.InvalidURL:
            return JSONResponse({"detail": "no such viewer file"}, status_code=404)
        except httpx.HTTPError as e:
            return JSONResponse({"detail": f"3D viewer is not reachable: {e}"}, status_code=502)
        keep = {k: v for k, v in up.headers.items()
                if k.lower() in ("content-type", "content-encoding", "cache-control", "etag")}
        keep["X-Content-Type-Options"] = "nosniff"
        return Response(body, status_code=up.status_code, headers=keep)

    async def redirect(request: Request) -> Response:
        q = request.url.query
        return RedirectResponse(f"{prefix}/" + (f"?{q}" if q else ""), status_code=307)

    async def socket(websocket: WebSocket) -> None:
        status = await check_access(authorize, websocket)
        if status != 200:
            await websocket.accept()
            await websocket.close(code=POLICY_VIOLATION,
                                  reason="not logged in" if status == 401 else "forbidden")
            return
        if not service.running:
            await run_in_threadpool(service.start)
        user = None
        if identify is not None:
            user = identify(websocket)
            if inspect.isawaitable(user):
                user = await user
        else:
            user = getattr(websocket.state, "user", None)
        key = _user_name(user)
        cap = service.max_sockets_per_user
        try:
            lease = await _claim_socket(service, key, cap)
        except SocketCapReached:
            # each viewer socket holds its own copy of the scene in viser (tens of MB)
            await websocket.accept()
            await websocket.close(code=POLICY_VIOLATION,
                                  reason=f"too many 3D viewer windows open (at most {cap} per "
                                         "user); close one")
            return
        scene_id = websocket.cookies.get(SCENE_COOKIE) or websocket.query_params.get("scene")
        view = websocket.cookies.get(VIEW_COOKIE)
        ticket = service.issue_ticket(user, scene_id, websocket.cookies.get(FRAME_COOKIE),
                                      suspect=websocket.cookies.get(SUSPECT_COOKIE),
                                      view=view if view and _VIEW_ID.match(view) else None)
        stats = {"opened": time.perf_counter(), "bytes": 0, "frames": 0, "last": None,
                 "log": deque(maxlen=256)}  # (perf_counter, cumulative bytes) per frame
        service.proxy_stats.append(stats)
        try:
            await pump(websocket, f"ws://127.0.0.1:{service.port}/", ticket, stats)
        finally:
            await _release_socket(service, key, lease)

    app.add_api_route(f"{prefix}/", page, methods=["GET"], include_in_schema=False)
    app.add_api_route(f"{prefix}/{{path:path}}", page, methods=["GET"], include_in_schema=False)
    app.add_api_route(prefix, redirect, methods=["GET"], include_in_schema=False)
    app.add_api_websocket_route(prefix, socket)
    app.add_api_websocket_route(f"{prefix}/", socket)


def _remember_scene(resp: Response, request: Request, prefix: str) -> None:
    """?scene= (and ?frame=) of the page in cookies: viser's client opens its websocket at the
    page URL without the query string. ``Secure`` when the request came over TLS."""
    secure = request.url.scheme == "https"
    scene = request.query_params.get("scene")
    if scene is None:
        return
    resp.set_cookie(SCENE_COOKIE, scene, path=prefix, httponly=True, samesite="lax",
                    secure=secure)
    frame = request.query_params.get("frame")
    if frame and len(frame) <= 200 and frame.replace("_", "").replace("-", "")\
            .replace(".", "").isalnum():
        resp.set_cookie(FRAME_COOKIE, frame, path=prefix, httponly=True, samesite="lax",
                        secure=secure)
    else:  # a page without ?frame= must not fly to the last one
        resp.delete_cookie(FRAME_COOKIE, path=prefix)
    suspect = request.query_params.get("suspect")
    if suspect and _SUSPECT_KEY.match(suspect):
        resp.set_cookie(SUSPECT_COOKIE, suspect, path=prefix, httponly=True, samesite="lax",
                        secure=secure)
    else:  # nor select the last page's suspect
        resp.delete_cookie(SUSPECT_COOKIE, path=prefix)


async def _claim_socket(service: ViewerService, key: str | None, cap: int | None) -> int | None:
    """Count a new socket of user ``key`` against ``cap``: in the database when the service
    has :class:`~app.shared_limits.SocketLeases` (the cap holds across API processes; the
    lease id is returned), else in this process. :class:`SocketCapReached` when it is full."""
    if key is None:
        return None
    leases = service.socket_leases
    if cap is not None and leases is not None:
        lease = await run_in_threadpool(leases.claim, key, cap)
    else:
        if cap is not None and service.open_sockets.get(key, 0) >= cap:
            raise SocketCapReached(service.open_sockets[key], cap)
        lease = None
    service.open_sockets[key] = service.open_sockets.get(key, 0) + 1
    return lease


async def _release_socket(service: ViewerService, key: str | None, lease: int | None) -> None:
    if key is None:
        return
    service.open_sockets[key] -= 1
    if service.open_sockets[key] <= 0:
        del service.open_sockets[key]
    if lease is not None and service.socket_leases is not None:
        try:
            await run_in_threadpool(service.socket_leases.release, lease)
        except Exception:  # noqa: BLE001 - the row's lease runs out by itself
            log.warning("viewer proxy: releasing socket %s failed", lease, exc_info=True)


def _user_name(user: Any) -> str | None:
    name = user.get("username") if isinstance(user, dict) else getattr(user, "username", None)
    return str(name) if name else None


async def pump(websocket: WebSocket, upstream_url: str, ticket: str,
               stats: dict | None = None) -> None:
    """Connect upstream with the ticket, accept the browser, forward frames both ways.

    ``stats`` (optional) is updated with bytes/frames sent to the browser and the
    ``time.perf_counter()`` of the last frame (the benchmark reads it)."""
    stats = stats if stats is not None else {"bytes": 0, "frames": 0, "last": None}
    protocols = list(websocket.scope.get("subprotocols") or [])
    try:
        upstream = await connect(upstream_url, subprotocols=protocols or None,
                                 additional_headers={TICKET_HEADER: ticket}, max_size=None,
                                 compression=None, open_timeout=10, ping_interval=None)
    except (TimeoutError, OSError, Exception) as e:  # noqa: BLE001
        log.warning("viewer proxy: upstream connect failed: %s", e)
        await websocket.accept()
        await websocket.close(code=1011, reason="3D viewer is not reachable")
        return
    await websocket.accept(subprotocol=upstream.subprotocol)

    async def browser_to_viser() -> None:
        while True:
            msg = await websocket.receive()
            if msg["type"] == "websocket.disconnect":
                return
            if msg.get("bytes") is not None:
                await upstream.send(msg["bytes"])
            elif msg.get("text") is not None:
                await upstream.send(msg["text"])

    async def viser_to_browser() -> None:
        async for m in upstream:
            if isinstance(m, bytes):
                await websocket.send_bytes(m)
            else:
                await websocket.send_text(m)
            stats["bytes"] += len(m)
            stats["frames"] += 1
            stats["last"] = time.perf_counter()
            if "log" in stats:
                stats["log"].append((stats["last"], stats["bytes"]))

    tasks = [asyncio.create_task(browser_to_viser()), asyncio.create_task(viser_to_browser())]
    try:
        await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        await upstream.close()
        code = upstream.close_code or 1000
        try:
            await websocket.close(code=code if code != 1006 else 1011)
        except (RuntimeError, WebSocketDisconnect, ConnectionClosed):
            pass
