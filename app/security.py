"""Request-level security: client addresses behind proxies, CSRF and same-origin checks, the
security headers and CSP, the session token of a request and the viewer socket's session watch.
Password hashing and tokens live in :mod:`app.credentials` (re-exported here)."""

from __future__ import annotations

import asyncio
import ipaddress
import logging
from urllib.parse import urlsplit

from starlette.concurrency import run_in_threadpool
from starlette.requests import HTTPConnection
from starlette.responses import JSONResponse

from app.credentials import (  # noqa: F401 - re-exported: security.configure, hash_password, ...
    configure,
    hash_password,
    lock_duration,
    new_token,
    token_digest,
    verify_password,
)
from app.users import service

log = logging.getLogger("occufly.security")


def _bearer(auth: str) -> str | None:
    """The token of an ``Authorization: Bearer <token>`` header (None: no bearer header)."""
    if auth.lower().startswith("bearer "):
        return auth[7:].strip() or None
    return None


def token_from(conn) -> str | None:  # noqa: ANN001 - Request or WebSocket
    """The session token of a request or socket: a bearer header, else the session cookie."""
    auth = conn.headers.get("authorization", "")
    if auth.lower().startswith("bearer "):
        return _bearer(auth)
    return conn.cookies.get(SESSION_COOKIE) or None


# ---- client address behind reverse proxies ---------------------------------------------------
def _networks(entries: list[str]) -> list:
    nets = []
    for e in entries:
        try:
            nets.append(ipaddress.ip_network(e, strict=False))
        except ValueError:
            continue
    return nets


def _in(addr: str, nets: list) -> bool:
    try:
        ip = ipaddress.ip_address(addr)
    except ValueError:
        return False
    return any(ip in n for n in nets)


def client_ip(peer: str | None, forwarded_for: str | None, trusted_proxies: list[str]) -> str:
    """The client's address: the TCP peer, unless the peer is a configured proxy; then the
    right-most ``X-Forwarded-For`` entry that is not itself a configured proxy (entries to its
    left were written by the client and prove nothing)."""
    peer = (peer or "unknown")[:64]
    nets = _networks(trusted_proxies)
    if not forwarded_for or not nets or not _in(peer, nets):
        return peer
    hops = [h.strip() for h in forwarded_for.split(",") if h.strip()]
    for hop in reversed(hops):
        if not _in(hop, nets):
            return hop[:64]
    return peer


# ---- cross-site request forgery --------------------------------------------------------------
UNSAFE_METHODS = frozenset({"POST", "PUT", "PATCH", "DELETE"})
SESSION_COOKIE = "occufly_session"


def _origin_of(url: str) -> str | None:
    try:
        parts = urlsplit(url)
    except ValueError:
        return None
    if not parts.scheme or not parts.netloc:
        return None
    return f"{parts.scheme.lower()}://{parts.netloc.lower()}"


def same_origin(origin_or_referer: str, host: str | None, allowed: list[str]) -> bool:
    """True when the Origin (or Referer) names this app's own host or a configured origin."""
    origin = _origin_of(origin_or_referer)
    if origin is None:
        return False
    if origin in {a.lower().rstrip("/") for a in allowed}:
        return True
    return bool(host) and origin.split("://", 1)[1] == host.lower()


def csrf_refusal(*, method: str, path: str, headers, cookies, allowed: list[str]) -> str | None:  # noqa: ANN001
    """Why a request must be refused as a possible cross-site forgery, or None.

    A state-changing request authenticated by the session cookie must carry an ``Origin`` --
    or, failing that, a ``Referer`` -- naming this app. Only a request with a Bearer token is
    not checked: it is judged by that token alone (:func:`token_from` never falls back to the
    cookie then), and another site cannot make a browser send one. Any other
    ``Authorization`` header -- e.g. ``Basic``, which a browser behind a basic-auth proxy adds
    by itself to a forged request -- leaves the cookie the credential and is checked (issue
    36). The login itself is refused only for a foreign Origin/Referer (login CSRF)."""
    if method.upper() not in UNSAFE_METHODS or _bearer(headers.get("authorization", "")):
        return None
    host = headers.get("host")
    source = headers.get("origin") or headers.get("referer")
    if source and source != "null":
        if same_origin(source, host, allowed):
            return None
        return f"cross-site request refused: origin {_origin_of(source) or source[:80]!r} is not this app"
    if path.rstrip("/") == "/api/auth/login" or SESSION_COOKIE not in cookies:
        return None
    return ("cookie-authenticated write without Origin or Referer refused (possible cross-site "
            "request); send the Origin header or use an Authorization: Bearer token")


# ---- response headers ------------------------------------------------------------------------
# Content-Security-Policy (issue 24, finding 9). The app's pages load only same-origin
# scripts (no inline script, no eval) and styles; images may be canvases' data:/blob: URLs.
APP_CSP = ("default-src 'self'; script-src 'self'; style-src 'self'; "
           "img-src 'self' data: blob:; font-src 'self'; connect-src 'self'; "
           "worker-src 'self'; object-src 'none'; base-uri 'none'; form-action 'self'; "
           "frame-ancestors 'self'")
# Swagger UI (/docs): same scripts rule; its React components set inline styles
DOCS_CSP = APP_CSP.replace("style-src 'self'", "style-src 'self' 'unsafe-inline'")
# The 3D viewer (viser's client, unpacked by app.viewer.client_page so no inline script
# runs): WebAssembly (zstd and mesh decoders), workers from blob: URLs (inlined worker
# sources), <style> elements its UI library injects, and data: icons/fonts/WebAssembly.
VIEWER_CSP = ("default-src 'self'; script-src 'self' 'wasm-unsafe-eval'; "
              "worker-src 'self' blob:; style-src 'self' 'unsafe-inline'; "
              "img-src 'self' data: blob:; font-src 'self' data:; connect-src 'self' data:; "
              "object-src 'none'; base-uri 'none'; form-action 'self'; frame-ancestors 'self'")


def csp_for(path: str) -> bytes:
    if path == "/viewer" or path.startswith("/viewer/"):
        return VIEWER_CSP.encode()
    if path == "/docs" or path.startswith("/docs-assets"):
        return DOCS_CSP.encode()
    return APP_CSP.encode()


SECURITY_HEADERS = (
    (b"x-frame-options", b"SAMEORIGIN"),
    (b"x-content-type-options", b"nosniff"),
    (b"referrer-policy", b"same-origin"),
)


class SecurityMiddleware:
    """ASGI middleware: security headers on every response, the CSRF check on unsafe methods
    and on websocket upgrades (Origin), and websockets closed (1008) once the session that
    opened them ends (logout, expiry, deactivation), re-checked every ``session_check_s``."""

    def __init__(self, app, get_ctx) -> None:  # noqa: ANN001
        self.app = app
        self.get_ctx = get_ctx

    async def __call__(self, scope, receive, send) -> None:  # noqa: ANN001
        if scope["type"] == "http":
            await self._http(scope, receive, send)
        elif scope["type"] == "websocket":
            await self._websocket(scope, receive, send)
        else:
            await self.app(scope, receive, send)

    async def _http(self, scope, receive, send) -> None:  # noqa: ANN001
        conn = HTTPConnection(scope)
        settings = self.get_ctx().settings
        why = csrf_refusal(method=scope["method"], path=scope["path"], headers=conn.headers,
                           cookies=conn.cookies, allowed=settings.allowed_origins)

        async def send_with_headers(message) -> None:  # noqa: ANN001
            if message["type"] == "http.response.start":
                present = {k.lower() for k, _v in message.get("headers", [])}
                message = dict(message)
                message["headers"] = list(message.get("headers", [])) + [
                    (k, v) for k, v in SECURITY_HEADERS if k not in present]
                if b"content-security-policy" not in present:
                    message["headers"].append((b"content-security-policy",
                                               csp_for(scope["path"])))
            await send(message)

        if why is not None:
            await JSONResponse({"detail": why}, status_code=403)(scope, receive, send_with_headers)
            return
        await self.app(scope, receive, send_with_headers)

    async def _websocket(self, scope, receive, send) -> None:  # noqa: ANN001

        conn = HTTPConnection(scope)
        ctx = self.get_ctx()
        origin = conn.headers.get("origin")
        if origin and not same_origin(origin, conn.headers.get("host"),
                                      ctx.settings.allowed_origins):
            await send({"type": "websocket.close", "code": 1008,
                        "reason": "cross-site websocket refused"})
            return

        token = token_from(conn)
        if not token:
            await self.app(scope, receive, send)
            return
        ended = asyncio.Event()
        lock = asyncio.Lock()
        state = {"accepted": False, "closed": False}

        def session_alive() -> bool:
            with ctx.sessions() as s:
                return service.user_for_token(session=s, settings=ctx.settings,
                                              token=token) is not None

        async def watch() -> None:
            failures = 0
            while not state["closed"]:
                await asyncio.sleep(ctx.settings.session_check_s)
                if state["closed"]:
                    return
                try:
                    alive = await run_in_threadpool(session_alive)
                    failures = 0
                except Exception:  # noqa: BLE001 - one database hiccup is not a logout ...
                    failures += 1
                    log.warning("viewer socket: session check failed", exc_info=True)
                    if failures < 5:
                        continue
                    alive = False  # ... but a session that cannot be verified ends
                if not alive:
                    async with lock:
                        if not state["closed"]:
                            state["closed"] = True
                            try:
                                await send({"type": "websocket.close", "code": 1008,
                                            "reason": "session ended"})
                            except Exception:  # noqa: BLE001
                                pass
                    ended.set()
                    return

        async def guarded_send(message) -> None:  # noqa: ANN001
            async with lock:
                if state["closed"]:
                    return  # the session ended: the app's late frames go nowhere
                if message["type"] == "websocket.accept":
                    state["accepted"] = True
                elif message["type"] == "websocket.close":
                    state["closed"] = True
                await send(message)

        async def guarded_receive():  # noqa: ANN202
            if ended.is_set():
                return {"type": "websocket.disconnect", "code": 1008}
            recv = asyncio.ensure_future(receive())
            stop = asyncio.ensure_future(ended.wait())
            done, _ = await asyncio.wait({recv, stop}, return_when=asyncio.FIRST_COMPLETED)
            if recv in done:
                stop.cancel()
                return recv.result()
            recv.cancel()
            return {"type": "websocket.disconnect", "code": 1008}

        watcher = asyncio.ensure_future(watch())
        try:
            await self.app(scope, guarded_receive, guarded_send)
        finally:
            state["closed"] = True
            watcher.cancel()
