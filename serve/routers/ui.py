"""The browser page: ``GET /ui`` (``GET /`` redirects to it) and its one script, ``GET /ui/occflownet-web.js``.

The page (``occflownet/viewer/assets/page.html``) is a client of the API like any other: it sends the chosen images
to ``POST /v1/occupancy`` and shows the answer (top-down picture, 3D view, latencies) or the API's own error
message. Nothing here bypasses a limit or a check, and the page's Content-Security-Policy lets it load and call
nothing but this server. Page and script are static files of the package (no model data), so they are served
without the API key; the page sends the key the user types with its API calls. ``OCCFLOWNET_UI=0`` leaves these
routes out (404), for deployments that want the API only.
"""
from __future__ import annotations

from fastapi import APIRouter
from starlette.responses import RedirectResponse, Response

from occflownet.viewer import BUNDLE, PAGE

SCRIPT_PATH = "/ui/occflownet-web.js"
PATHS = ("/", "/ui", SCRIPT_PATH)
POLICY = ("default-src 'none'; script-src 'self'; style-src 'self' 'unsafe-inline'; img-src 'self' data: blob:; "
          "connect-src 'self'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'")
_HEADERS = {"Content-Security-Policy": POLICY, "Cache-Control": "no-cache"}  # nosniff: on every answer


def make_router() -> APIRouter:
    """The routes, with the page and the script read once (the script is ~0.6 MB)."""
    page, script = PAGE.read_bytes(), BUNDLE.read_bytes()
    router = APIRouter(include_in_schema=False)

    @router.get("/")
    async def root() -> Response:
        return RedirectResponse("/ui", status_code=307)

    @router.get("/ui")
    async def ui_page() -> Response:
        return Response(page, media_type="text/html; charset=utf-8", headers=_HEADERS)

    @router.get(SCRIPT_PATH)
    async def ui_script() -> Response:
        return Response(script, media_type="text/javascript; charset=utf-8", headers=_HEADERS)

    return router
