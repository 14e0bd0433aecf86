"""Request body caps by route, enforced before the body is read (issue 24, finding 4).

An ASGI middleware: a request whose ``Content-Length`` exceeds its route's cap is answered
413 at once, without reading a byte of the body; a body without a length (chunked) is counted
as it streams in and refused with 413 as soon as it passes the cap (at most the cap plus one
chunk is ever held). The app behind it sees a client disconnect and its late response is
dropped.

Caps (``app.config.Settings``):

=================================================  ==========================================
``PUT /api/frames/{fid}/mask``,                    the frame's bound: 4 bytes per pixel (an
``PUT /api/frames/{fid}/reviewer-correction``      RGBA colour mask stored uncompressed) plus
                                                   64 KiB, at most ``max_upload_bytes``
``POST /api/scenes/{sid}/corrections``             12 bytes per point of the scene (a JSON id
                                                   list naming every point) plus 64 KiB, at
                                                   most ``max_selection_bytes``
``POST /api/scenes/{sid}/review-items``            ``max_selection_bytes`` (point id lists)
``POST /api/scenes/{sid}/masks/import``            ``max_import_upload_bytes`` (a zip of masks
                                                   painted in another tool, issue 26)
``POST /api/imports/upload``                       ``max_import_upload_bytes`` (the zip of a
                                                   project folder, streamed to disk)
anything else                                      ``max_json_bytes`` (1 MiB)
=================================================  ==========================================

Imports otherwise read their input from folders on the server (``OCCUFLY_IMPORT_ROOTS``);
the one upload of a project (``POST /api/imports/upload``) is written to disk as it arrives.
"""

from __future__ import annotations

import json
import logging
import re

from starlette.concurrency import run_in_threadpool

from app.scenes.models import Frame, Scene

log = logging.getLogger("occufly.bodylimit")

MASK_SLACK = 64 * 1024
BYTES_PER_MASK_PIXEL = 4
BYTES_PER_POINT_ID = 12

_MASK = re.compile(r"^/api/frames/(\d{1,10})/(?:mask|reviewer-correction)/?$")
_CORRECTIONS = re.compile(r"^/api/scenes/(\d{1,10})/corrections/?$")
_REVIEW_ITEMS = re.compile(r"^/api/scenes/\d{1,10}/review-items/?$")
_MASK_IMPORT = re.compile(r"^/api/scenes/\d{1,10}/masks/import/?$")  # issue 26: a zip of masks


def _too_large(limit: int, what: str) -> bytes:
    return json.dumps({"detail": f"request body too large: {what} accepts at most {limit} "
                                 f"bytes ({limit / 2**20:.2f} MiB)", "limit_bytes": limit}).encode()


class BodyLimitMiddleware:
    def __init__(self, app, get_ctx) -> None:  # noqa: ANN001
        self.app = app
        self.get_ctx = get_ctx

    async def limit_for(self, scope) -> tuple[int, str]:  # noqa: ANN001
        """(cap in bytes, what it applies to) for this request."""
        ctx = self.get_ctx()
        s = ctx.settings
        path = scope.get("path", "")
        method = scope.get("method", "GET")
        if method in ("PUT", "POST"):
            m = _MASK.match(path)
            if m:
                size = await run_in_threadpool(_frame_pixels, ctx, int(m.group(1)))
                if size is None:
                    return s.max_upload_bytes, "a mask upload"
                return (min(s.max_upload_bytes, BYTES_PER_MASK_PIXEL * size + MASK_SLACK),
                        "a mask of this frame")
            m = _CORRECTIONS.match(path)
            if m:
                n = await run_in_threadpool(_scene_points, ctx, int(m.group(1)))
                if n is None:
                    return s.max_json_bytes, "this request"
                return (min(s.max_selection_bytes, BYTES_PER_POINT_ID * n + MASK_SLACK),
                        "a correction of this scene")
            if _REVIEW_ITEMS.match(path):
                return s.max_selection_bytes, "a review item"
            if _MASK_IMPORT.match(path):
                return (s.max_import_upload_bytes,
                        "a mask archive upload (OCCUFLY_MAX_IMPORT_UPLOAD_MB)")
            if path.rstrip("/") == "/api/imports/upload":  # issue 28: app/scenes/imports.py
                return s.max_import_upload_bytes, "an import upload (OCCUFLY_MAX_IMPORT_UPLOAD_MB)"
        return s.max_json_bytes, "this request"

    async def __call__(self, scope, receive, send) -> None:  # noqa: ANN001
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = None
        for k, v in scope.get("headers", ()):
            if k == b"content-length":
                declared = v
                break
        if declared is not None and not declared.strip().isdigit():
            await _respond(send, 400, json.dumps(
                {"detail": "Content-Length is not a number"}).encode())
            return
        if declared is None and not _has_body(scope):
            await self.app(scope, receive, send)
            return
        limit, what = await self.limit_for(scope)
        if declared is not None and int(declared) > limit:
            await _respond(send, 413, _too_large(limit, what))
            return
        state = {"total": 0, "refused": False, "started": False}

        async def counted_receive():  # noqa: ANN202
            if state["refused"]:
                return {"type": "http.disconnect"}
            message = await receive()
            if message["type"] == "http.request":
                state["total"] += len(message.get("body", b""))
                if state["total"] > limit:
                    state["refused"] = True
                    if not state["started"]:
                        state["started"] = True
                        await _respond(send, 413, _too_large(limit, what))
                    return {"type": "http.disconnect"}
            return message

        async def guarded_send(message) -> None:  # noqa: ANN001
            if state["refused"]:
                return  # the 413 went out; what the app says after the disconnect goes nowhere
            if message["type"] == "http.response.start":
                state["started"] = True
            await send(message)

        try:
            await self.app(scope, counted_receive, guarded_send)
        except Exception:
            if state["refused"]:
                return  # the app failed on the cut-off body; the client has its 413
            raise


def _has_body(scope) -> bool:  # noqa: ANN001
    """A request without Content-Length has a body only when it is chunked."""
    for k, v in scope.get("headers", ()):
        if k == b"transfer-encoding" and b"chunked" in v.lower():
            return True
    return False


async def _respond(send, status: int, body: bytes) -> None:  # noqa: ANN001
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"),
                            (b"content-length", str(len(body)).encode()),
                            (b"connection", b"close")]})
    await send({"type": "http.response.body", "body": body})


def _frame_pixels(ctx, frame_id: int) -> int | None:  # noqa: ANN001
    """The frame's pixel count; None when it does not exist or the database cannot say (the
    route answers then; the general upload cap still holds -- never a 500 from here)."""
    try:
        with ctx.sessions() as s:
            f = s.get(Frame, frame_id)
            return None if f is None else int(f.width) * int(f.height)
    except Exception:  # noqa: BLE001 - middleware runs outside the app's error handlers
        log.warning("body limit: frame %s not read", frame_id, exc_info=True)
        return None


def _scene_points(ctx, scene_id: int) -> int | None:  # noqa: ANN001
    try:
        with ctx.sessions() as s:
            sc = s.get(Scene, scene_id)
            return None if sc is None or sc.n_points is None else int(sc.n_points)
    except Exception:  # noqa: BLE001 - as above
        log.warning("body limit: scene %s not read", scene_id, exc_info=True)
        return None
