"""The one error shape of the API: ``{"error": {"code": str, "message": str}}`` with the HTTP status.

:func:`error_response` is the only code that writes it (from :class:`occflownet.serve.schemas.ErrorResponse`, the
schema the OpenAPI document shows): the middlewares call it directly, everything inside the app raises
:class:`ApiError` (or lets the framework raise its own errors), and :func:`add_error_handlers` turns each into it.
Any other exception is a bug: :class:`InternalErrorMiddleware` logs it once, with its traceback, and answers 500
``internal`` (it does not let the exception go on to Starlette's and uvicorn's handlers, which would log it again).
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
         406: "not_acceptable", 408: "request_timeout", 413: "payload_too_large", 415: "unsupported_media_type",
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
    """ApiError answers as raised, the framework's HTTP errors (404, 405, ...) with the code of :data:`CODES`, its
    validation errors 422; anything else reaches :class:`InternalErrorMiddleware`."""

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


class InternalErrorMiddleware:
    """Pure ASGI middleware: an exception from the app is logged once (``occflownet.serve``, with its traceback)
    and answered 500 ``internal`` if nothing was sent yet (else the connection is left for the server to close);
    it goes no further."""

    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        started = False

        async def tracking_send(message):
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, receive, tracking_send)
        except Exception as exc:
            log.exception("unhandled error on %s %s", scope["method"], scope["path"])
            if not started:
                await error_response(500, "internal", f"internal error: {type(exc).__name__}")(scope, receive, send)
