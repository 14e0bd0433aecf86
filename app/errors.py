"""Domain exceptions and the one place that maps them (and OccuflyError) to HTTP responses.

Services raise these; routes never build error responses themselves. Anything else that
escapes is a bug and gives a 500.
"""

from __future__ import annotations

import errno
import math

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from sqlalchemy.exc import OperationalError

from occufly.errors import InputFormatError, MaskError, OccuflyError, TaxonomyError, WorkspaceError


class DomainError(Exception):
    status_code = 400

    def __init__(self, detail: str, **extra) -> None:
        super().__init__(detail)
        self.detail = detail
        self.extra = extra


class NotAuthenticated(DomainError):
    status_code = 401


class Forbidden(DomainError):
    status_code = 403


class NotFound(DomainError):
    status_code = 404


class Conflict(DomainError):
    status_code = 409


class StaleVersion(Conflict):
    """If-Match did not name the frame's current mask version."""


class PayloadTooLarge(DomainError):
    status_code = 413


class Invalid(DomainError):
    status_code = 422


class InsufficientStorage(DomainError):
    """A storage quota would be passed, or the server's disk is full (nothing was written)."""
    status_code = 507


class TooManyAttempts(DomainError):
    status_code = 429


class PreconditionRequired(DomainError):
    status_code = 428


DISK_FULL_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT})
DISK_FULL = ("the server's disk is full: nothing was written (every write is atomic); an "
             "admin must free space, then try again")


def db_disk_full(exc: BaseException) -> bool:
    """A database error that says the disk is full (SQLite SQLITE_FULL, PostgreSQL 53100)."""
    orig = getattr(exc, "orig", exc)
    return (getattr(orig, "sqlstate", None) == "53100"
            or "database or disk is full" in str(orig)
            or getattr(orig, "sqlite_errorcode", None) == 13)


def _status_for_occufly(exc: OccuflyError) -> int:
    if isinstance(exc, (MaskError, TaxonomyError, InputFormatError)):
        return 422
    if isinstance(exc, WorkspaceError):
        return 409
    return 400


#: the longest error message an answer carries (issue 36: a 422 that showed a user's value
#: whole answered 796 MB); the messages name what was wrong well within this
MAX_DETAIL_CHARS = 8000


def bounded(detail: str) -> str:
    detail = str(detail)
    if len(detail) <= MAX_DETAIL_CHARS:
        return detail
    return detail[:MAX_DETAIL_CHARS - 60] + f" ... ({len(detail)} characters, cut)"


def install(app: FastAPI) -> None:
    @app.exception_handler(DomainError)
    async def _domain(_request: Request, exc: DomainError) -> JSONResponse:
        headers = {}
        if isinstance(exc, TooManyAttempts) and "retry_after" in exc.extra:
            headers["Retry-After"] = str(exc.extra["retry_after"])
        if isinstance(exc, NotAuthenticated):
            headers["WWW-Authenticate"] = "Bearer"
        return JSONResponse({"detail": bounded(exc.detail), **exc.extra},
                            status_code=exc.status_code, headers=headers)

    @app.exception_handler(OccuflyError)
    async def _occufly(_request: Request, exc: OccuflyError) -> JSONResponse:
        return JSONResponse({"detail": bounded(str(exc))}, status_code=_status_for_occufly(exc))

    @app.exception_handler(OSError)
    async def _os_error(_request: Request, exc: OSError) -> JSONResponse:
        if exc.errno in DISK_FULL_ERRNOS:
            return JSONResponse({"detail": DISK_FULL}, status_code=507)
        raise exc  # anything else is a bug: a 500 with its traceback in the log

    @app.exception_handler(OperationalError)
    async def _db_error(_request: Request, exc: OperationalError) -> JSONResponse:
        if db_disk_full(exc):
            return JSONResponse({"detail": DISK_FULL}, status_code=507)
        return JSONResponse({"detail": "the database is unavailable right now; nothing was "
                                       "written, try again"}, status_code=503,
                            headers={"Retry-After": "5"})

    @app.exception_handler(RequestValidationError)
    async def _validation(_request: Request, exc: RequestValidationError) -> JSONResponse:
        return JSONResponse(validation_body(exc.errors()), status_code=422)


MAX_ECHO = 200  # characters of a bad input value echoed back in a 422


def validation_body(errors: list) -> dict:
    """The 422 body for pydantic errors: one readable ``detail`` line plus ``errors`` (loc, msg,
    type and a JSON-safe, truncated echo of the bad input: NaN/Infinity become strings, bytes
    and long values are cut), so any input at all gives a 422 and never a 500."""
    parts = []
    for e in errors:
        loc = ".".join(str(x) for x in e.get("loc", ()) if x != "body")
        msg = _plain(e.get("msg"))
        parts.append(f"{loc}: {msg}" if loc else str(msg))
    return {"detail": "; ".join(parts)[:4000] or "invalid request",
            "errors": [_plain({k: v for k, v in e.items() if k in ("loc", "msg", "type", "input")})
                       for e in errors[:50]]}


def _plain(obj, depth: int = 0):  # noqa: ANN001, ANN202 - JSON-safe copy of validation details
    if depth > 4:
        return "..."
    if isinstance(obj, dict):
        return {str(k)[:MAX_ECHO]: _plain(v, depth + 1) for k, v in list(obj.items())[:20]}
    if isinstance(obj, (list, tuple)):
        return [_plain(v, depth + 1) for v in list(obj)[:20]]
    if isinstance(obj, bool) or obj is None:
        return obj
    if isinstance(obj, int):
        return obj if abs(obj) < 2**53 else str(obj)[:MAX_ECHO]
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else str(obj)
    if isinstance(obj, (bytes, bytearray)):
        return bytes(obj[:MAX_ECHO]).decode("utf-8", "replace")
    return str(obj).replace("\x00", "\\x00")[:MAX_ECHO]
