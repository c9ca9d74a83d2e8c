"""The one error shape of the API: ``{"error": {"code": str, "message": str}}`` with the HTTP status.

:func:`error_response` is the only code that writes it (from :class:`occflownet.serve.schemas.ErrorResponse`, the
schema the OpenAPI document shows): the middlewares call it directly, everything inside the app raises
:class:`ApiError` (or lets the framework raise its own errors), and :func:`add_error_handlers` turns each into it.
"""
from __future__ import annotations

import logging

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.responses import Response

from occflownet.serve.schemas import ErrorBody, ErrorResponse

log = logging.getLogger("occflownet.serve")

# HTTP status → default error code, for errors raised by the framework (404, 405, ...).
CODES = {400: "bad_request", 401: "unauthorized", 404: "not_found", 405: "method_not_allowed",
         406: "not_acceptable", 413: "payload_too_large", 415: "unsupported_media_type",
         422: "unprocessable", 500: "internal", 503: "unavailable"}


class ApiError(Exception):
    """Raised anywhere in request handling; turned into the JSON error response by the app's handler."""

    def __init__(self, status: int, code: str, message: str, headers: dict[str, str] | None = None):
        super().__init__(message)
        self.status = status
        self.code = code
        self.message = message
        self.headers = headers or {}


def error_response(status: int, code: str, message: str, headers: dict[str, str] | None = None) -> Response:
    body = ErrorResponse(error=ErrorBody(code=code, message=message)).model_dump_json()
    return Response(body, status_code=status, media_type="application/json", headers=headers)


def add_error_handlers(app: FastAPI) -> None:
    """Every exception that leaves a route answers in the error shape: ApiError as raised, the framework's HTTP
    errors (404, 405, ...) with the code of :data:`CODES`, anything else 500 ``internal`` (logged)."""

    @app.exception_handler(ApiError)
    async def api_error(request: Request, exc: ApiError):
        return error_response(exc.status, exc.code, exc.message, exc.headers)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException):
        return error_response(exc.status_code, CODES.get(exc.status_code, "error"), str(exc.detail),
                              getattr(exc, "headers", None))

    @app.exception_handler(RequestValidationError)
    async def validation_error(request: Request, exc: RequestValidationError):
        return error_response(422, "unprocessable", str(exc.errors()))

    @app.exception_handler(Exception)
    async def internal_error(request: Request, exc: Exception):
        log.exception("unhandled error on %s %s", request.method, request.url.path)
        return error_response(500, "internal", f"internal error: {type(exc).__name__}")
