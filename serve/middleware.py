"""ASGI middlewares of the app: the headers of every answer (outermost), request metrics and the optional API key.

Every answer, whatever wrote it (a route, an error handler, a middleware's refusal), carries
``X-Content-Type-Options: nosniff`` (:data:`EVERY_ANSWER`): browsers take each body as its declared media type.

API key: when ``OCCFLOWNET_API_KEY`` is set, every route except ``/healthz`` and ``/readyz`` (probes) and the
browser page's static files (``/``, ``/ui``, its script: no model data; the page sends the key itself) needs
``Authorization: Bearer <key>``; the comparison is ``hmac.compare_digest`` (constant time). Missing or wrong → 401.
"""
from __future__ import annotations

import hmac
import time

from occflownet.serve.errors import error_response
from occflownet.serve.metrics import Metrics
from occflownet.serve.routers.ui import PATHS as UI_PATHS

# the probes, and the browser page's static files (no model data; the page sends the key with its API calls)
PUBLIC_PATHS = ("/healthz", "/readyz", *UI_PATHS)
ROUTES = ("/healthz", "/readyz", "/metrics", "/v1/metadata", "/v1/occupancy", "/docs", "/redoc", "/openapi.json",
          *UI_PATHS)


EVERY_ANSWER = ((b"x-content-type-options", b"nosniff"),)


class HeadersMiddleware:
    """Adds :data:`EVERY_ANSWER`'s headers to each response that does not set them itself."""

    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)

        async def send_with_headers(message):
            if message["type"] == "http.response.start":
                headers = list(message.get("headers", []))
                present = {key.lower() for key, _ in headers}
                headers += [(key, value) for key, value in EVERY_ANSWER if key not in present]
                message = {**message, "headers": headers}
            await send(message)

        await self.app(scope, receive, send_with_headers)


def route_label(path: str) -> str:
    """Metric label for a path: the known route, or "other" (keeps label cardinality bounded)."""
    return path if path in ROUTES else "other"


class MetricsMiddleware:
    """Counts every HTTP request by route/method/status, its duration and the number in flight."""

    def __init__(self, app, metrics: Metrics):
        self.app = app
        self.metrics = metrics

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        status = 500
        t0 = time.perf_counter()
        self.metrics.request_started()

        async def tracking_send(message):
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, tracking_send)
        finally:
            self.metrics.request_finished(route_label(scope["path"]), scope["method"], status,
                                          time.perf_counter() - t0)


class ApiKeyMiddleware:
    """401 unless ``Authorization: Bearer <api_key>`` (for every path but the probes)."""

    def __init__(self, app, api_key: str):
        self.app = app
        self.expected = b"Bearer " + api_key.encode("utf-8")

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http" or scope["path"] in PUBLIC_PATHS:
            return await self.app(scope, receive, send)
        given = b""
        for key, value in scope["headers"]:
            if key == b"authorization":
                given = value
                break
        if not hmac.compare_digest(given, self.expected):
            response = error_response(401, "unauthorized", "missing or wrong API key: send Authorization: Bearer "
                                      "<key>", headers={"WWW-Authenticate": "Bearer"})
            return await response(scope, receive, send)
        return await self.app(scope, receive, send)
