"""Domain exceptions and the one place that maps them (and OccuflyError) to HTTP responses.

Services raise these; routes never build error responses themselves. Anything else that
escapes is a bug and gives a 500.
"""

from __future__ import annotations

from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse

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


class TooManyAttempts(DomainError):
    status_code = 429


class PreconditionRequired(DomainError):
    status_code = 428


def _status_for_occufly(exc: OccuflyError) -> int:
    if isinstance(exc, (MaskError, TaxonomyError, InputFormatError)):
        return 422
    if isinstance(exc, WorkspaceError):
        return 409
    return 400


def install(app: FastAPI) -> None:
    @app.exception_handler(DomainError)
    async def _domain(_request: Request, exc: DomainError) -> JSONResponse:
        headers = {}
        if isinstance(exc, TooManyAttempts) and "retry_after" in exc.extra:
            headers["Retry-After"] = str(exc.extra["retry_after"])
        if isinstance(exc, NotAuthenticated):
            headers["WWW-Authenticate"] = "Bearer"
        return JSONResponse({"detail": exc.detail, **exc.extra}, status_code=exc.status_code,
                            headers=headers)

    @app.exception_handler(OccuflyError)
    async def _occufly(_request: Request, exc: OccuflyError) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, status_code=_status_for_occufly(exc))
