"""The one error shape of the API: ``{"error": {"code": str, "message": str}}`` with the HTTP status."""
from __future__ import annotations

import json

from starlette.responses import Response


class ApiError(Exception):
    """Raised anywhere in request handling; turned into the JSON error response by the app's handler."""

    def __init__(self, status: int, code: str, message: str, headers: dict[str, str] | None = None):
        super().__init__(message)
        self.status = status
        self.code = code
        self.message = message
        self.headers = headers or {}


def error_response(status: int, code: str, message: str, headers: dict[str, str] | None = None) -> Response:
    body = json.dumps({"error": {"code": code, "message": message}}).encode("utf-8")
    return Response(body, status_code=status, media_type="application/json", headers=headers)


# HTTP status → default error code, for errors raised by the framework (404, 405, ...).
CODES = {400: "bad_request", 401: "unauthorized", 404: "not_found", 405: "method_not_allowed",
         406: "not_acceptable", 413: "payload_too_large", 415: "unsupported_media_type",
         422: "unprocessable", 500: "internal", 503: "unavailable"}
